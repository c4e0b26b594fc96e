"""Embree ray transport: the `TransportMatrix`, its builder, the matrix-free `TransportOperator`, `render` and the reference renderer."""

from ._build import DEFAULT_PIXEL_SAMPLES as DEFAULT_PIXEL_SAMPLES
from ._build import DEFAULT_SAMPLES as DEFAULT_SAMPLES
from ._build import transport_matrix as transport_matrix
from ._embree import RayCaster as RayCaster
from ._matrix import TransportMatrix as TransportMatrix
from ._matrix import render as render
from ._memory import parse_memory as parse_memory
from ._operator import TransportOperator as TransportOperator
from ._operator import transport_operator as transport_operator
from ._sharding import row_mesh as row_mesh
from ._sharding import shard as shard
from ._sharding import transport_matrix_sharded as transport_matrix_sharded
from ._reference import reference_render as reference_render
from ._point_lights import DistantLightRows as DistantLightRows
from ._point_lights import depth_map as depth_map
from ._point_lights import render_point_lights as render_point_lights
