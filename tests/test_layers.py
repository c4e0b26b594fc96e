"""The package's layers (docs/architecture.md): no import cycle, so the top-level imports work in any order."""

import subprocess
import sys
from pathlib import Path

import pytest

import hiddenjax

INIT = Path(hiddenjax.__file__)

# Imports `hiddenjax/__init__.py` with its package imports in the given order, in a fresh interpreter.
PROGRAM = """
import importlib.util, sys
init, order = sys.argv[1], sys.argv[2]
lines = open(init).read().splitlines()
imports = [l for l in lines if l.startswith("from .") or l.startswith("from . ")]
rest = [l for l in lines if l not in imports]
imports = imports[::-1] if order == "reversed" else sorted(imports, key=lambda l: hash(l) % 97)
spec = importlib.util.spec_from_file_location("hiddenjax", init, submodule_search_locations=[init.rsplit("/", 1)[0]])
module = importlib.util.module_from_spec(spec)
sys.modules["hiddenjax"] = module
exec(compile("\\n".join(rest + imports), init, "exec"), module.__dict__)
assert module.solve_illumination and module.shadows.fit_lights and module.solvers.ProjectedNewton
print("ok")
"""


@pytest.mark.parametrize("order", ["reversed", "shuffled"])
def test_top_level_imports_work_in_any_order(order):
    proc = subprocess.run([sys.executable, "-c", PROGRAM, str(INIT), order], capture_output=True, text=True,
                          timeout=120, env={"PYTHONHASHSEED": "1", "JAX_PLATFORMS": "cpu", "PATH": ""})
    assert proc.returncode == 0 and proc.stdout.strip() == "ok", proc.stderr[-2000:]


def test_image_io_imports_nothing_else_of_the_package():
    """The bottom layer: importing `hiddenjax.io`'s modules pulls in no other hiddenjax package."""
    program = ("import sys, importlib.util; from pathlib import Path; root = Path(sys.argv[1]).parent\n"
               "import types; pkg = types.ModuleType('hiddenjax'); pkg.__path__ = [str(root)]; sys.modules['hiddenjax'] = pkg\n"
               "import hiddenjax.io\n"
               "print(sorted(m for m in sys.modules if m.startswith('hiddenjax.') and not m.startswith('hiddenjax.io')))")
    proc = subprocess.run([sys.executable, "-c", program, str(INIT)], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout.strip() == "[]"
