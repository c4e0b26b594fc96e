"""Scene description: environment grid, camera, surfaces, fixtures and set-ups."""

from ._camera import Camera as Camera
from ._fixtures import FIXTURES as FIXTURES
from ._fixtures import coded_aperture as coded_aperture
from ._fixtures import fixture as fixture
from ._fixtures import ground_plane as ground_plane
from ._fixtures import PRIMITIVES as PRIMITIVES
from ._fixtures import mura_pattern as mura_pattern
from ._fixtures import primitive as primitive
from ._fixtures import sphere as sphere
from ._fixtures import teapot as teapot
from ._gloss import Gloss as Gloss
from ._gloss import check_gloss as check_gloss
from ._grid import EnvGrid as EnvGrid
from ._grid import direction as direction
from ._grid import direction_to_angles as direction_to_angles
from ._grid import rotate_azimuth as rotate_azimuth
from ._measured import MeasuredReflectance as MeasuredReflectance
from ._setups import Setup as Setup
from ._setups import box_on_floor as box_on_floor
from ._setups import doorways as doorways
from ._setups import object_on_plane as object_on_plane
from ._setups import wood_texture as wood_texture
from ._sky import procedural_sky as procedural_sky
from ._surface import Scene as Scene
from ._surface import Surface as Surface
from ._surface import load_mesh as load_mesh
