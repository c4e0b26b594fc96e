"""Frames of a real corner's floor -> the network's input, and a hidden object tracked over a video.

A camera in the visible corridor films the floor near the corner (thesis 3.2.4). Each frame
minus a background without the object (`y_f - b`) is the differential image of eq. 3.1's inputs;
`network_frames` turns the camera's frames (any size, grey or RGB) into the square grey images
the network was trained on: the `crop` square of each frame (default: the central square),
area-averaged to `size x size`, mirrored when the hidden corridor opens to the image's right
(the training scenes have it on the left). `track` averages `window` consecutive differences
(noise falls as `1/sqrt(window)`) and locates the object in each, in fixed-size batches (one
compiled program for any video length).
"""

from typing import NamedTuple

import cv2
import numpy as np

from .._jit import host_array
from ._evaluate import _localize_batch
from ._labels import PolarGrid, position_to_polar
from ._network import CornerNet


class Track(NamedTuple):
    """One estimate per window: `frame (K,)` the index of its last frame, `position (K, 2)` (x, z)
    metres in the corner frame, `polar (K, 2)` (theta rad, rho m), `cov (K, 2, 2)` m^2 (the fitted
    Gaussian's, thesis' Sigma_0), `heatmap (K, T, R)` cell probabilities."""

    frame: np.ndarray
    position: np.ndarray
    polar: np.ndarray
    cov: np.ndarray
    heatmap: np.ndarray


def square_crop(height: int, width: int, crop=None) -> tuple[int, int, int]:
    """`(x0, y0, side)` of the square the network sees: `crop` checked against the frame, or the central square."""
    if crop is None:
        side = min(height, width)
        return (width - side) // 2, (height - side) // 2, side
    x0, y0, side = (int(v) for v in crop)
    if side < 8 or x0 < 0 or y0 < 0 or x0 + side > width or y0 + side > height:
        raise ValueError(f"crop (x0, y0, side) = {tuple(crop)} is not a square of at least 8 pixels inside the "
                         f"{width}x{height} frames")
    return x0, y0, side


def network_frames(frames, size: int, *, crop=None, mirror: bool = False) -> np.ndarray:
    """`(N, size, size)` float32: frames `(N, H, W)` or `(N, H, W, 3)` cropped, area-averaged, mirrored (module docstring)."""
    frames = np.asarray(frames, np.float32)
    if frames.ndim == 4 and frames.shape[-1] == 3:
        frames = frames.mean(-1)
    if frames.ndim != 3:
        raise ValueError(f"expected frames (N, H, W) or (N, H, W, 3), got shape {frames.shape}")
    x0, y0, side = square_crop(*frames.shape[1:], crop)
    out = np.stack([cv2.resize(f[y0:y0 + side, x0:x0 + side], (size, size), interpolation=cv2.INTER_AREA)
                    for f in frames]).astype(np.float32)
    return out[:, :, ::-1].copy() if mirror else out


def window_means(differences, window: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """`(means (N - window + 1, H, W), last_frame (N - window + 1,))`: sliding means of `window` differences."""
    d = np.asarray(differences, np.float64)
    if not 1 <= window <= len(d):
        raise ValueError(f"window must be between 1 and the number of frames ({len(d)}), got {window}")
    c = np.concatenate([np.zeros((1,) + d.shape[1:]), np.cumsum(d, 0)])
    return ((c[window:] - c[:-window]) / window).astype(np.float32), np.arange(window - 1, len(d))


def track(model: CornerNet, differences, *, window: int = 1, grid: PolarGrid = PolarGrid(), batch: int = 64,
          progress=None) -> Track:
    """Locate the hidden object in each window of differential frames `(N, size, size)` (`network_frames`).

    Frames go through the network in batches of `batch` (the last one padded), so a video of any
    length runs one compiled program. `progress(done, total)` is called after each batch.
    """
    means, last = window_means(differences, window)
    if not np.all(np.isfinite(means)):
        raise ValueError("the differential frames hold NaN or infinite values")
    parts = []
    for i in range(0, len(means), batch):
        chunk = means[i:i + batch]
        padded = np.concatenate([chunk, np.repeat(chunk[-1:], batch - len(chunk), 0)]) if len(chunk) < batch else chunk
        pos, cov, heat = _localize_batch(model, host_array(padded, np.float32), grid)
        parts.append((np.asarray(pos)[:len(chunk)], np.asarray(cov)[:len(chunk)], np.asarray(heat)[:len(chunk)]))
        if progress is not None:
            progress(min(i + batch, len(means)), len(means))
    pos, cov, heat = (np.concatenate(p).astype(np.float64) for p in zip(*parts))
    return Track(last, pos, np.asarray(position_to_polar(pos)), cov, heat)


def draw_track(path, result: Track, grid: PolarGrid = PolarGrid(), difference=None, title: str = "") -> None:
    """A PNG: the mean heat map on the floor plan (x, z) with the track and 1-sigma ellipses, beside the
    (first) differential frame the network saw. Written atomically."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Ellipse

    from ..io import atomic_path

    panels = 1 if difference is None else 2
    fig, axes = plt.subplots(1, panels, figsize=(5.2 * panels, 4.6), squeeze=False)
    ax = axes[0, 0]
    heat = np.mean(result.heatmap, 0)
    th = np.linspace(0, grid.theta_max, grid.n_theta + 1)
    rh = np.linspace(0, grid.rho_max, grid.n_rho + 1)
    TH, RH = np.meshgrid(th, rh, indexing="ij")
    ax.pcolormesh(RH * np.cos(TH), RH * np.sin(TH), heat, cmap="inferno", shading="flat")
    ax.plot([0, grid.rho_max], [0, 0], "w-", lw=3)  # the occluding wall's face
    pos = result.position
    if len(pos) > 1:
        ax.plot(pos[:, 0], pos[:, 1], "-", color="c", lw=1, alpha=0.8)
    ax.scatter(pos[:, 0], pos[:, 1], c=result.frame, cmap="cool", s=14, zorder=3)
    for p, c in zip(pos[:: max(1, len(pos) // 12)], result.cov[:: max(1, len(pos) // 12)]):
        w, V = np.linalg.eigh(c)
        ax.add_patch(Ellipse(p, *(2 * np.sqrt(np.maximum(w, 0))), angle=np.degrees(np.arctan2(V[1, 1], V[0, 1])),
                             fill=False, color="c", lw=1))
    ax.set_aspect("equal")
    ax.set_xlim(-0.02, grid.rho_max)
    ax.set_ylim(-0.02, grid.rho_max)
    ax.set_xlabel("x along the hidden corridor (m)")
    ax.set_ylabel("z from the occluding wall (m)")
    ax.set_title(title or f"{len(pos)} estimate(s): mean heat map, track, 1-sigma")
    if difference is not None:
        d = np.asarray(difference)
        lim = float(np.percentile(np.abs(d), 99.5)) or 1.0
        axes[0, 1].imshow(d, cmap="RdBu_r", vmin=-lim, vmax=lim)
        axes[0, 1].set_title("frame minus background (network input)")
        axes[0, 1].axis("off")
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=90, format="png")
    plt.close(fig)
