"""Designing the object camera (thesis 6.3): printable occluders optimized for the lowest reconstruction error.

A parameterized shape (`HeightField`, `Boxes`, `Cylinders`, `Voxels`), a stage and an objective (`Objective`: A-optimal,
D-optimal and expected error over skies of the Gaussian posterior, or the default solve's
reconstruction error over skies) make a `DesignProblem`;
`design_occluder` minimizes it through the differentiable soft transport, and `DesignProblem.score`
checks a mesh, designed or not, with Embree's hard visibility.
"""

from ._unions import Boxes as Boxes
from ._unions import Cylinders as Cylinders
from ._heightfield import HeightField as HeightField
from ._voxels import Voxels as Voxels
from ._objectives import KINDS as KINDS
from ._objectives import Objective as Objective
from ._optimize import Design as Design
from ._optimize import DesignProblem as DesignProblem
from ._optimize import design_occluder as design_occluder
from ._optimize import stage as stage
from ._compare import reconstruction_study as reconstruction_study
