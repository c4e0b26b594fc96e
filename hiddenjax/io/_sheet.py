"""Contact sheets: labelled panels side by side in one PNG."""

import cv2
import numpy as np

from ._files import atomic_path
from ._images import colormap, tonemap, write_png


def panel(image, kind: str = "radiance", white: float | None = None) -> np.ndarray:
    """One panel as uint8 RGB: `kind` is 'radiance' (tone mapped), 'map' (inferno) or 'signed'.

    NaN marks "no data" (e.g. pixels outside a transport matrix's mask) and is drawn grey.
    """
    a = np.asarray(image, dtype=np.float64)
    missing = np.isnan(a) if a.ndim == 2 else np.any(np.isnan(a), axis=-1)
    a = np.nan_to_num(a, nan=0.0)
    if kind == "radiance":
        rgb = tonemap(a, white=white)
        rgb = np.repeat(rgb[..., None], 3, -1) if rgb.ndim == 2 else rgb
    elif kind in ("map", "signed"):
        rgb = colormap(a, signed=kind == "signed", limit=white)
    else:
        raise ValueError(f"panel kind must be 'radiance', 'map' or 'signed', got {kind!r}")
    rgb[missing] = 128
    return rgb


def write_map(path, array, signed: bool = False, limit: float | None = None, gamma: float = 1.0) -> None:
    """Write a scalar map (leverage, uncertainty, saliency, Cook's distance) as a false-colour PNG.

    `signed` uses blue-white-red around zero (saliency, gain images), otherwise inferno; `limit`
    is the value drawn at full colour (default the 99th percentile of `|array|`); `gamma < 1`
    compresses the range (`|v|^gamma`, sign kept; the thesis draws Cook's distance with 0.5).
    NaN (no data) is drawn grey.
    """
    a = np.asarray(array, dtype=np.float64)
    if a.ndim != 2:
        raise ValueError(f"expected a map (H, W), got shape {a.shape}")
    a = np.sign(a) * np.abs(a) ** gamma  # NaN stays NaN: `panel` draws it grey
    write_png(path, panel(a, "signed" if signed else "map", None if limit is None else limit**gamma))


def contact_sheet(path, panels, height: int = 256, columns: int | None = None) -> np.ndarray:
    """Write labelled panels to a PNG and return the sheet (uint8 RGB).

    `panels` is a sequence of `(title, image)` or `(title, image, kind)` or
    `(title, image, kind, white)`; every panel is resized (nearest neighbour, so pixels stay
    visible) to `height` rows and the sheet has `columns` panels per row (default: all).
    A title may have several lines (`"\n"`); every title bar is as tall as the tallest.
    """
    if not panels:
        raise ValueError("contact_sheet needs at least one panel")
    lines = max(len(str(spec[0]).split("\n")) for spec in panels)
    tiles = []
    for spec in panels:
        title, image, *rest = spec
        rgb = panel(image, *rest)
        width = max(1, round(rgb.shape[1] * height / rgb.shape[0]))
        rgb = cv2.resize(rgb, (width, height), interpolation=cv2.INTER_NEAREST)
        bar = np.full((6 + 18 * lines, width, 3), 255, np.uint8)
        for k, line in enumerate(str(title).split("\n")):
            cv2.putText(bar, line, (4, 17 + 18 * k), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
        tiles.append(np.concatenate([bar, rgb], axis=0))
    columns = columns or len(tiles)
    rows = []
    for start in range(0, len(tiles), columns):
        row = tiles[start : start + columns]
        row = sum(([t, np.full((t.shape[0], 6, 3), 255, np.uint8)] for t in row), [])[:-1]
        rows.append(np.concatenate(row, axis=1))
    width = max(r.shape[1] for r in rows)
    rows = [np.pad(r, ((0, 6), (0, width - r.shape[1]), (0, 0)), constant_values=255) for r in rows]
    sheet = np.concatenate(rows, axis=0)
    write_png(path, sheet)
    return sheet


def write_plot(path, curves: dict, xlabel: str = "", ylabel: str = "", log: bool = False, title: str = "") -> None:
    """A line plot (PNG, matplotlib's Agg backend) of `curves = {label: (x, y)}`, written atomically.

    `log` puts the y axis on a log scale.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if not curves:
        raise ValueError("write_plot needs at least one curve")
    fig, ax = plt.subplots(figsize=(6, 3.5))
    for label, (x, y) in curves.items():
        ax.plot(np.asarray(x), np.asarray(y), label=label)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    if log:
        ax.set_yscale("log")
    if title:
        ax.set_title(title, fontsize=9)
    ax.legend(fontsize=7)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110)
    plt.close(fig)
