"""hiddenjax: find and use hidden cues (shadows, subtle changes) in ordinary photographs.

Everything public is re-exported here; implementation modules are private.

Precision: on GPUs JAX computes float32 matrix products in TensorFloat32 by default (10-bit
mantissa), which moves camera projections by hundredths of a pixel and breaks the normal
equations of the solvers. Importing hiddenjax therefore sets `jax_default_matmul_precision` to
"float32" unless it was already chosen (by `JAX_DEFAULT_MATMUL_PRECISION` or `jax.config`);
code that wants TF32 back for its own work can use `with jax.default_matmul_precision("tensorfloat32")`.

Compiled programs: `hj.enable_compilation_cache()` keeps them on disk in the user's cache folder,
so a later process loads them instead of compiling (the `hiddenjax` command, the examples and the
benchmarks call it; importing hiddenjax does not).
"""

import jax as _jax

if _jax.config.jax_default_matmul_precision is None:
    _jax.config.update("jax_default_matmul_precision", "float32")

from . import corners as corners
from . import cues as cues
from . import design as design
from . import io as io
from . import metrics as metrics
from . import photo as photo
from . import scene as scenes
from . import shadows as shadows
from . import solvers as solvers
from ._compilation_cache import compilation_cache_dir as compilation_cache_dir
from ._compilation_cache import default_cache_dir as default_cache_dir
from ._compilation_cache import enable_compilation_cache as enable_compilation_cache
from ._jit import COMPILER_OPTIONS as COMPILER_OPTIONS
from ._scene_file import SceneFile as SceneFile
from ._scene_file import load_scene as load_scene
from .scene import Camera as Camera
from .scene import EnvGrid as EnvGrid
from .scene import Scene as Scene
from .scene import Surface as Surface
from .solvers import solve_illumination as solve_illumination
from .transport import TransportMatrix as TransportMatrix
from .transport import depth_map as depth_map
from .transport import reference_render as reference_render
from .transport import render as render
from .transport import render_point_lights as render_point_lights
from .transport import transport_matrix as transport_matrix
from .transport import transport_operator as transport_operator

__version__ = "0.1.0"
