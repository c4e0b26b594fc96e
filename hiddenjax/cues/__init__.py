"""Discovering hidden cues (thesis ch. 6): which pixels carry the information, and how well an object sees.

Relative regularization weights throughout (docs/conventions.md, "Regularization weights"). Pure JAX, jit-compatible.
"""

from ._linear import LinearCues as LinearCues
from ._linear import cooks_distance as cooks_distance
from ._linear import effective_rank as effective_rank
from ._linear import gain_images as gain_images
from ._linear import leverage as leverage
from ._linear import uncertainty as uncertainty
from ._saliency import saliency as saliency
