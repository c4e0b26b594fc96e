"""Solvers for the illumination, albedo and scene parameters: pure JAX, jit and vmap."""

from ._illumination import DEFAULT_RIDGE as DEFAULT_RIDGE
from ._illumination import DEFAULT_SMOOTH as DEFAULT_SMOOTH
from ._illumination import DampedNewton as DampedNewton
from ._illumination import IlluminationOperator as IlluminationOperator
from ._illumination import IlluminationSolution as IlluminationSolution
from ._illumination import ProjectedNewton as ProjectedNewton
from ._illumination import normal_matrix as normal_matrix
from ._illumination import prior_matrix as prior_matrix
from ._illumination import regularization_weights as regularization_weights
from ._illumination import solve_illumination as solve_illumination
from ._albedo import AlbedoIlluminationSolution as AlbedoIlluminationSolution
from ._albedo import solve_albedo_illumination as solve_albedo_illumination
from ._adam import AdamSolution as AdamSolution
from ._adam import solve_illumination_adam as solve_illumination_adam
from ._adam import AdamProblem as AdamProblem
from ._weights import choose_weights as choose_weights
from ._scene_params import SceneParams as SceneParams
from ._scene_params import SceneUncertainty as SceneUncertainty
from ._scene_model import SceneModel as SceneModel
from ._robust import GaussNewtonStep as GaussNewtonStep
from ._robust import SceneSolution as SceneSolution
from ._robust import gauss_newton_step as gauss_newton_step
from ._robust import jacobian_gram as jacobian_gram
from ._robust import model_average as model_average
from ._robust import solve_scene_illumination as solve_scene_illumination
from ._robust import taylor_operator as taylor_operator
