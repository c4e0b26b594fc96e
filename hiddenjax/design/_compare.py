"""Checking designs against other occluders on the same stage: hard-visibility objective and a reconstruction study.

The design is optimized through the soft transport; these checks use Embree's hard visibility
(`transport_matrix`) and photos from the independent reference renderer (`reference_render`,
a path tracer over the full-resolution panorama), never `A x`.
"""

import numpy as np
import trimesh

from ..metrics import env_errors
from ..scene import EnvGrid
from ..solvers import IlluminationOperator, hdr_prior
from ..transport import reference_render, transport_matrix
from ._optimize import stage


def reconstruction_study(meshes: dict[str, trimesh.Trimesh], panoramas: dict[str, np.ndarray], grid: EnvGrid, *,
                         footprint: float = 0.1, width: int = 64, height: int = 64, elevation: float = 90.0,
                         prior=None, samples: int = 128, pixel_samples: int = 2, seed: int = 1) -> tuple[dict, dict]:
    """Reconstruct every panorama with every occluder and score it (`hj.metrics.env_errors`, upper hemisphere).

    Each mesh stands on the plane of `stage` (scaled to `footprint`); the photo is
    `reference_render` of the panorama (`samples` paths per pixel sample), the solve
    `IlluminationOperator.build(T, prior)` on the Embree matrix (`prior` None: `hdr_prior(adapt=0.0)`,
    the prior designs are optimized with), the truth the panorama
    area-averaged onto `grid`. **Returns** `(scores, estimates)`: `scores[mesh][panorama]` the
    errors, with a `"mean"` entry per mesh holding each error's mean over the panoramas;
    `estimates[mesh][panorama]` the recovered map `(H, W, 3)`.
    """
    if not meshes or not panoramas:
        raise ValueError("reconstruction_study needs at least one mesh and one panorama")
    out, maps = {}, {}
    for name, mesh in meshes.items():
        setup = stage(mesh, footprint, width=width, height=height, elevation=elevation)
        T = transport_matrix(setup.scene, setup.camera, grid, progress=False)
        op = IlluminationOperator.build(T, prior=hdr_prior(adapt=0.0) if prior is None else prior)
        runs, maps[name] = {}, {}
        for sky, pano in panoramas.items():
            photo = reference_render(setup.scene, setup.camera, pano, samples=samples, pixel_samples=pixel_samples,
                                     seed=seed)
            sol = op.solve(photo, throw=False)
            maps[name][sky] = np.asarray(sol.env)
            runs[sky] = env_errors(maps[name][sky], grid.downsample(pano))
        runs["mean"] = {k: float(np.mean([r[k] for r in runs.values()])) for k in next(iter(runs.values()))}
        out[name] = runs
    return out, maps
