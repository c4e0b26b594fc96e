"""`hiddenjax render`: the image `A x` of a map."""


import numpy as np

from .. import io
from ..transport import render
from ._common import IMAGE_HELP, _env_on_grid, _load_matrix, _output, photo_options


def add_parsers(sub) -> None:
    """This module's subcommand(s) of `hiddenjax`."""
    p = sub.add_parser("render", help="render the image A x of an env map",
                       description="Render A x; ENV is on the matrix's grid or a full-resolution lat-long panorama.")
    p.add_argument("matrix", help="transport matrix .npz")
    p.add_argument("env", help="env map: " + IMAGE_HELP)
    p.add_argument("-o", "--output", required=True, help="output image, .exr, .hdr or .png")
    photo_options(p)
    p.set_defaults(run=render_image)


def render_image(args) -> dict:
    """`hiddenjax render`: the image `A x` of an env map."""
    out = _output(args.output, (".exr", ".hdr", ".png"))
    T = _load_matrix(args.matrix)
    env = io.read_image(args.env, srgb=args.srgb)
    image = np.asarray(render(T, _env_on_grid(env, T.grid, args.env)))
    io.write_image(out, image)
    print(f"wrote {out}: {image.shape[1]}x{image.shape[0]} image")
    return dict(shape=list(image.shape))
