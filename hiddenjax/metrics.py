"""Environment-map error metrics, one definition everywhere (docs/conventions.md, "Metrics")."""

import numpy as np
from skimage.metrics import structural_similarity


def env_errors(est, truth, region: str = "upper") -> dict:
    """Errors of an estimated env map against the truth, `(H, W)` or `(H, W, C)`.

    **Returns:** a dict with `rmse` (of `est` as given), `scale` `s = <est, truth>/<est, est>`
    (least-squares fit), `relrmse = ||s est - truth|| / ||truth||`, `ssim` (scikit-image SSIM on
    linear values, `data_range = max - min` of the truth) and `ssim_tm` (SSIM after the tone map
    `t(v) = v / (1 + v)` of `v = map / mean(truth)`, same data-range rule). `region` is "upper"
    (rows `0 .. H/2 - 1`, the upper hemisphere) or "all".
    """
    est, truth = np.asarray(est, dtype=np.float64), np.asarray(truth, dtype=np.float64)
    if est.shape != truth.shape or est.ndim not in (2, 3):
        raise ValueError(f"est and truth must be env maps of one shape (H, W[, C]); got {est.shape}, {truth.shape}")
    if not (np.all(np.isfinite(est)) and np.all(np.isfinite(truth))):
        raise ValueError("env maps must be finite")
    if region == "upper":
        est, truth = est[: est.shape[0] // 2], truth[: truth.shape[0] // 2]
    elif region != "all":
        raise ValueError(f"region must be 'upper' or 'all', got {region!r}")
    norm_truth = np.linalg.norm(truth)
    if norm_truth == 0:
        raise ValueError("the true map is zero over the region: relative errors are undefined")
    denom = np.sum(est * est)
    scale = float(np.sum(est * truth) / denom) if denom > 0 else 0.0
    mean = truth.mean()
    tm = lambda m: (m / mean) / (1 + np.maximum(m / mean, 0))
    return dict(
        rmse=float(np.sqrt(np.mean((est - truth) ** 2))),
        scale=scale,
        relrmse=float(np.linalg.norm(scale * est - truth) / norm_truth),
        ssim=_ssim(est, truth),
        ssim_tm=_ssim(tm(est), tm(truth)),
    )


def _ssim(a, b):
    data_range = float(b.max() - b.min()) or 1.0
    win = min(7, *(d if d % 2 else d - 1 for d in b.shape[:2]))
    if win < 3:
        raise ValueError(f"env map region {b.shape[:2]} is too small for SSIM (needs 3x3 or more)")
    return float(structural_similarity(a, b, data_range=data_range, win_size=win,
                                       channel_axis=-1 if b.ndim == 3 else None))
