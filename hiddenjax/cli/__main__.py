"""`python -m hiddenjax.cli`: the `hiddenjax` command."""

import sys

from . import main

sys.exit(main())
