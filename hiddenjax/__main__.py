"""`python -m hiddenjax` runs the `hiddenjax` command."""

import sys

from .cli import main

sys.exit(main())
