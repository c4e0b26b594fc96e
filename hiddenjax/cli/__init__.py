"""The `hiddenjax` command: build a transport matrix, solve for the light, render, map the cues, demo.

    hiddenjax transport SCENE.toml -o A.npz
    hiddenjax solve A.npz photo.exr -o env.exr [--png env.png] [--prior hdr|l2|tv|sunsky] [--smooth S] [--ridge R]
                    [--signed]
    hiddenjax render A.npz env.exr -o image.exr
    hiddenjax cues A.npz [--image photo.exr] -o cues/
    hiddenjax lights SCENE.toml photo.exr -o lights.json [--count N] [--init X Y Z ...] [--reach M]
                     [--within M] [--reference table.exr] [--shading smooth|none] [--clearance M] [--width W]
                     [--no-polish] [--png fit.png]
    hiddenjax demo [--quick] [--out DIR]
    hiddenjax board -o board.png [--pdf board.pdf] [--squares C R] [--square M] [--marker M] [--dpi D]
                    [--chessboard]
    hiddenjax calibrate board.toml photo... -o camera.toml [--sheet check.png]
    hiddenjax reconstruct board.toml photo... --object MESH --at X Z [--yaw DEG] [--size M]
                          (--intrinsics camera.toml | --fov DEG) [--times T...] [--plate PHOTO...]
                          [--gloss ROUGHNESS|auto] -o out/
    hiddenjax probe photo... --mask MASK (--sphere | --object MESH --intrinsics camera.toml) [--linear]
                    [--times T...] -o out/
    hiddenjax video A.npz clip.mp4 -o maps/ [--background median|first] [--video maps.mp4]
    hiddenjax corner (clip.mp4 | folder/ | frame.png...) -o out/ [--corner corner.toml] [--class L|T|table]
                     [--setting fixed-lamp|random-lamp] [--background median|first|IMAGE] [--window N]
                     [--crop X0 Y0 SIDE] [--mirror] [--refine] [--every N] [--max-frames N] [--linear]
    hiddenjax design -o out/ [--quick] [--objective a_optimal|d_optimal|expected_error|reconstruction]
                     [--shape heightfield|boxes|cylinders|voxels] [--count K] [--cells N]
                     [--temperature START END] [--steps N] [--footprint M] [--height M] [--controls G]
                     [--seed S] [--grid H W] [--skies PANORAMA...] [--rotations N] [--resample N]

Exit status 0 on success, 1 when the input is bad (one line on stderr says what and how to fix
it; no output file is left behind), 2 for a malformed command line.
"""

import argparse
import os
import sys
import warnings

from .. import __version__
from .._compilation_cache import enable_compilation_cache
from . import _board, _corner, _cues, _demo, _design, _lights, _probe, _reconstruct, _render, _solve, _transport, _video
from ._common import IMAGE_HELP, _Parser, _runtime_message
from ._demo import demo as demo

COMMANDS = (_transport, _solve, _render, _cues, _lights, _demo, _design, _board, _reconstruct, _probe, _video, _corner)


def _parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="hiddenjax", description=__doc__.split("\n\n")[0],
                     epilog="Images: " + IMAGE_HELP + ". Run `hiddenjax COMMAND --help` for each command.")
    parser.add_argument("--version", action="version", version=f"hiddenjax {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser, metavar="COMMAND")
    for module in COMMANDS:
        module.add_parsers(sub)
    return parser


def main(argv=None) -> int:
    """Entry point of the `hiddenjax` console script; returns the exit status."""
    parser = _parser()
    args = parser.parse_args(argv)

    def show(message, category, *_):  # one line on stderr, as the errors are
        print(f"hiddenjax {args.command}: warning: {' '.join(str(message).split())}", file=sys.stderr)

    try:
        with warnings.catch_warnings():
            warnings.showwarning = show
            warnings.simplefilter("always", UserWarning)
            enable_compilation_cache()  # before the first program: compiled once per machine (HIDDENJAX_CACHE=off)
            args.run(args)
    except (ValueError, OSError) as e:
        message = " ".join(str(e).split())  # one line
        print(f"hiddenjax {args.command}: error: {message}", file=sys.stderr)
        return 1
    except (RuntimeError, MemoryError) as e:  # raised inside compiled code (EquinoxRuntimeError, XLA's errors)
        if os.environ.get("HIDDENJAX_DEBUG"):
            raise
        print(f"hiddenjax {args.command}: error: {_runtime_message(e)} (HIDDENJAX_DEBUG=1 shows the traceback)",
              file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"hiddenjax {args.command}: interrupted", file=sys.stderr)
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
