"""Hidden objects around corners (thesis ch. 3): randomized scenes, differential rendering, polar labels,
the localization CNN and its training, Gaussian read-out, variational refinement and saliency."""

from ._scenes import RHO_MAX as RHO_MAX
from ._scenes import SCENE_CLASSES as SCENE_CLASSES
from ._scenes import CornerScene as CornerScene
from ._scenes import HiddenObject as HiddenObject
from ._scenes import object_visible as object_visible
from ._scenes import random_corner_scene as random_corner_scene
from ._render import DifferentialRenderer as DifferentialRenderer
from ._render import render_full as render_full
from ._render import temporal_difference as temporal_difference
from ._labels import GaussianFit as GaussianFit
from ._labels import PolarGrid as PolarGrid
from ._labels import fit_gaussian as fit_gaussian
from ._labels import localization_errors as localization_errors
from ._labels import locate as locate
from ._labels import polar_to_position as polar_to_position
from ._labels import position_to_polar as position_to_polar
from ._dataset import CornerDataset as CornerDataset
from ._dataset import generate_dataset as generate_dataset
from ._dataset import render_sample as render_sample
from ._network import CornerNet as CornerNet
from ._network import heatmap_loss as heatmap_loss
from ._network import instance_normalize as instance_normalize
from ._network import predict_heatmap as predict_heatmap
from ._training import TrainConfig as TrainConfig
from ._training import TrainingLog as TrainingLog
from ._training import load_checkpoint as load_checkpoint
from ._training import save_checkpoint as save_checkpoint
from ._training import train as train
from ._evaluate import Localization as Localization
from ._evaluate import error_table as error_table
from ._evaluate import localize as localize
from ._evaluate import location_saliency as location_saliency
from ._refine import refine_location as refine_location
from ._refine import rendering_loss as rendering_loss
from ._refine import scale_free_loss as scale_free_loss
