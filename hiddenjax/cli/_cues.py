"""`hiddenjax cues`: leverage, uncertainty and Cook's distance maps (thesis ch. 6)."""

from pathlib import Path

from ..solvers import DEFAULT_RIDGE
from ._common import IMAGE_HELP, _load_matrix, _load_photo, _write_cues, photo_options


def add_parsers(sub) -> None:
    """This module's subcommand(s) of `hiddenjax`."""
    p = sub.add_parser("cues", help="leverage, uncertainty and Cook's distance maps (thesis ch. 6)",
                       description="Which pixels carry the information: leverage (eq. 6.2) and the env-map "
                                   "uncertainty; with --image also Cook's distance (eq. 6.1). EXR values and PNG pictures.")
    p.add_argument("matrix", help="transport matrix .npz")
    p.add_argument("--image", help="a photo, for Cook's distance: " + IMAGE_HELP)
    p.add_argument("-o", "--output", default="cues", help="output folder (default ./cues)")
    p.add_argument("--ridge", type=float, default=DEFAULT_RIDGE, help=f"ridge weight (default {DEFAULT_RIDGE})")
    photo_options(p)
    p.set_defaults(run=cues)


def cues(args) -> dict:
    """`hiddenjax cues`: leverage, uncertainty and (with a photo) Cook's distance maps (thesis ch. 6)."""
    out = Path(args.output)
    if out.exists() and not out.is_dir():
        raise ValueError(f"output {out} exists and is not a folder")
    T = _load_matrix(args.matrix)
    image = _load_photo(args.image, T, args.srgb) if args.image else None
    return _write_cues(out, T, image, args.ridge)[0]
