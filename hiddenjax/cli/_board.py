"""`hiddenjax board` and `hiddenjax calibrate`: the printed board (ChArUco or a plain chessboard) and the
camera's intrinsics."""

from pathlib import Path

from .. import io
from .. import photo as _photo
from ._common import IMAGE_HELP, _output


def add_parsers(sub) -> None:
    """This module's subcommand(s) of `hiddenjax`."""
    p = sub.add_parser("board", help="write a printable ChArUco calibration board (PNG, PDF) and its board.toml",
                       description="A ChArUco board (OpenCV's CharucoBoard, default layout) at its true size: print it "
                                   "at 100%%, glue it flat, measure a square. The .toml beside the PNG describes it for "
                                   "`hiddenjax calibrate` and `board_pose`.")
    p.add_argument("-o", "--output", required=True, help="output .png (the board at --dpi)")
    p.add_argument("--pdf", help="also a one-page PDF that prints the board at its true size")
    p.add_argument("--toml", help="board description (default: the PNG's name with .toml)")
    p.add_argument("--squares", type=int, nargs=2, default=(10, 7), metavar=("COLS", "ROWS"),
                   help="chessboard squares (default 10 7)")
    p.add_argument("--square", type=float, default=0.025, help="square side in metres (default 0.025: fits A4)")
    p.add_argument("--marker", type=float, default=0.019, help="marker side in metres (default 0.019)")
    p.add_argument("--dictionary", default="4X4_50", help="ArUco dictionary (default 4X4_50)")
    p.add_argument("--dpi", type=float, default=300.0, help="dots per inch (default 300)")
    p.add_argument("--chessboard", action="store_true",
                   help="a plain chessboard of --squares squares instead (no markers; for calibration only: its "
                        "pose has no marked corner)")
    p.set_defaults(run=board)
    p = sub.add_parser("calibrate", help="camera intrinsics from photos of the board",
                       description="Focal lengths, principal point and lens distortion (OpenCV) from 3 or more photos "
                                   "of the printed board taken from different angles with one camera setting. The "
                                   "board is a ChArUco board or a plain chessboard (a board file with kind = "
                                   "\"chessboard\", inner = [cols, rows] inner corners and square in metres).")
    p.add_argument("board", help="board description (.toml from `hiddenjax board`, or a chessboard's)")
    p.add_argument("photos", nargs="+", help="photos of the board: " + IMAGE_HELP)
    p.add_argument("-o", "--output", required=True, help="output camera .toml")
    p.add_argument("--sheet", help="also a PNG contact sheet of the corners found in each photo")
    p.set_defaults(run=calibrate)


def board(args) -> None:
    png = _output(args.output, (".png",))
    pdf = None if args.pdf is None else _output(args.pdf, (".pdf",))
    toml = png.with_suffix(".toml") if args.toml is None else _output(args.toml, (".toml",))
    if args.chessboard:
        b = _photo.Chessboard(inner=(args.squares[0] - 1, args.squares[1] - 1), square=args.square)
    else:
        b = _photo.Board(squares=tuple(args.squares), square=args.square, marker=args.marker, dictionary=args.dictionary)
    image = b.image(dpi=args.dpi)
    io.write_png(png, image)
    if pdf is not None:
        _photo.write_board_pdf(pdf, b.image(dpi=args.dpi, margin=0.01), dpi=args.dpi)
    b.save(toml)
    W, D = b.size
    print(f"wrote {png}" + (f", {pdf}" if pdf else "") + f" and {toml}: {W * 100:g} x {D * 100:g} cm "
          f"at {args.dpi:g} dpi; print at 100% (no scaling) and measure one square: it must be {b.square * 1000:g} mm")


def calibrate(args) -> None:
    out = _output(args.output, (".toml",))
    sheet = None if args.sheet is None else _output(args.sheet, (".png",))
    b = _photo.load_board(args.board)
    images = [_photo.read_board_photo(p) for p in args.photos]
    intr = _photo.calibrate(b, images, names=args.photos)
    if sheet is not None:
        _write_detections(sheet, b, images, args.photos)
    intr.save(out)
    print(f"wrote {out}: fx {intr.focal[0]:.2f} px, fy {intr.focal[1]:.2f} px, principal point "
          f"({intr.K[0, 2]:.1f}, {intr.K[1, 2]:.1f}), RMS reprojection error {intr.rms:.3f} px from {intr.views} photos")


def _write_detections(path, b, images, names) -> None:
    panels = []
    for image, name in zip(images, names):
        d = _photo.detect(b, image)
        drawn = _photo.draw_detection(image, d) / 255.0
        panels.append((f"{Path(name).name}: {len(d.ids)} corners", drawn**2.2, "radiance", 1.0))
    io.contact_sheet(path, panels, height=360, columns=min(len(panels), 4))
