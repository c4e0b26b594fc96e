"""Calibration boards placed in the world plane y = 0: OpenCV's `CharucoBoard` and a plain chessboard.

World placement (docs/conventions.md, "Real captures"). OpenCV's board frame has `x_b` along the
printed rows to the right, `y_b` down the printed columns and `z_b = x_b x y_b` into the paper,
with the origin at the board's top-left corner. The world frame puts the board's centre at the
origin, its printed side facing +y (up):

    x_w = x_b - W/2,    y_w = -z_b,    z_w = y_b - D/2,

`W = cols * square`, `D = rows * square`. So the board's top edge (as printed) is at
`z_w = -D/2`, and a camera at `+z`, above the table, sees the board the right way up.

A plain chessboard has no marked corner: its frame follows the order in which OpenCV's detector
lists the inner corners, so its pose is defined up to a half-turn about the board's normal (use a
ChArUco board where the world's orientation matters; calibration does not need it).
"""

from pathlib import Path

import cv2
import equinox as eqx
import numpy as np

from ..io import atomic_path, read_toml, write_text

MM_PER_INCH = 25.4
# Board frame -> world frame rotation (x_w, y_w, z_w) = BOARD_TO_WORLD @ (x_b, y_b, z_b) - centre.
BOARD_TO_WORLD = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])


def _dictionary(name: str):
    key = "DICT_" + str(name).upper()
    if not hasattr(cv2.aruco, key):
        known = sorted(k[5:] for k in dir(cv2.aruco) if k.startswith("DICT_") and "X" in k)
        raise ValueError(f"unknown ArUco dictionary {name!r}; use one of {', '.join(known)}")
    return cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, key))


class _PlanarBoard(eqx.Module):
    """What every printed board shares: `squares = (cols, rows)` squares of side `square` metres,
    centred at the world origin in the plane y = 0 (module docstring)."""

    @property
    def size(self) -> tuple[float, float]:
        """`(W, D)`: the board's extent in metres along world x and z."""
        cols, rows = _pair(self.squares)
        return cols * self.square, rows * self.square

    def to_world(self, points_board) -> np.ndarray:
        """Board-frame points `(..., 3)` (OpenCV's, metres) -> world points `(..., 3)`."""
        W, D = self.size
        p = np.asarray(points_board, dtype=np.float64) - np.array([W / 2, D / 2, 0.0])
        return p @ BOARD_TO_WORLD.T

    def corners(self) -> np.ndarray:
        """World positions `(K, 3)` of the chessboard's inner corners, in OpenCV's id order."""
        return self.to_world(self.board_points())

    def image(self, dpi: float = 300.0, margin: float = 0.0) -> np.ndarray:
        """The printable board, uint8 `(H, W)` at `dpi` dots per inch (true size when printed at 100%).

        `margin` metres of white are added on every side.
        """
        if not (np.isfinite(dpi) and dpi > 0):
            raise ValueError(f"dpi must be positive, got {dpi}")
        W, D = self.size
        px = dpi / (MM_PER_INCH / 1000.0)  # pixels per metre
        width, height = int(round(W * px)), int(round(D * px))
        if min(width, height) < 4 * max(self.squares):
            raise ValueError(f"dpi {dpi} gives {width} x {height} pixels, too few for the board's squares; "
                             f"raise the dpi")
        board = self._pattern(width, height, px)
        m = int(round(margin * px))
        return np.pad(board, m, constant_values=255) if m else board

    def texture(self, pixels_per_metre: float = 4000.0) -> np.ndarray:
        """Reflectance-free board pattern as float `(H, W)` in `{0, 1}` covering exactly `size` (for renderers)."""
        return self.image(dpi=pixels_per_metre * MM_PER_INCH / 1000.0).astype(np.float32) / 255.0

    def save(self, path) -> None:
        """Write the board's description as TOML (`load_board` reads it back)."""
        write_text(path, self.toml())


class Board(_PlanarBoard):
    """A ChArUco board: `squares = (cols, rows)` chessboard squares of side `square` metres,
    ArUco markers of side `marker` metres in the white squares, from `dictionary` (e.g. "4X4_50").

    It is OpenCV's `cv2.aruco.CharucoBoard((cols, rows), square, marker, dictionary)` with OpenCV's
    default (non-legacy) layout, so a board printed by any OpenCV tool with these parameters works.
    It lies in the world plane y = 0, printed side up, centre at the origin (module docstring).
    """

    squares: tuple[int, int] = eqx.field(static=True)
    square: float = eqx.field(static=True)
    marker: float = eqx.field(static=True)
    dictionary: str = eqx.field(static=True, default="4X4_50")

    def __check_init__(self):
        cols, rows = _pair(self.squares)
        if cols < 3 or rows < 3:
            raise ValueError(f"a ChArUco board needs at least 3 x 3 squares, got squares={self.squares}")
        if not (np.isfinite(self.square) and self.square > 0):
            raise ValueError(f"square must be a positive length in metres, got {self.square}")
        if not (np.isfinite(self.marker) and 0 < self.marker < self.square):
            raise ValueError(
                f"marker must be positive and smaller than the square ({self.square} m), got {self.marker}; "
                f"OpenCV's boards use about 0.75 * square"
            )
        size = _dictionary(self.dictionary).bytesList.shape[0]
        if cols * rows // 2 > size:
            raise ValueError(
                f"a {cols} x {rows} board needs {cols * rows // 2} markers but dictionary "
                f"{self.dictionary} has {size}; choose a larger one (e.g. 4X4_100 or 5X5_250)"
            )

    def opencv(self):
        """The `cv2.aruco.CharucoBoard` with these parameters."""
        board = cv2.aruco.CharucoBoard(
            tuple(int(v) for v in self.squares), float(self.square), float(self.marker), _dictionary(self.dictionary)
        )
        board.setLegacyPattern(False)
        return board

    def board_points(self) -> np.ndarray:
        """The inner corners `(K, 3)` in OpenCV's board frame (metres), in id order."""
        return np.asarray(self.opencv().getChessboardCorners(), dtype=np.float64)

    def _pattern(self, width: int, height: int, px: float) -> np.ndarray:
        """The board's `(height, width)` uint8 pattern at `px` pixels per metre."""
        # OpenCV draws squares on whole pixels; draw them whole at the next integer square size and
        # box-filter down, so every square edge lands at its true position (grey where it cuts a pixel).
        n = int(np.ceil(self.square * px - 1e-6))
        cols, rows = _pair(self.squares)
        board = self.opencv().generateImage((cols * n, rows * n), marginSize=0, borderBits=1)
        if board.shape != (height, width):
            board = cv2.resize(board, (width, height), interpolation=cv2.INTER_AREA)
        return board

    # ---- files ------------------------------------------------------------------------------
    def toml(self) -> str:
        cols, rows = _pair(self.squares)
        return (
            "# ChArUco board (OpenCV CharucoBoard, default layout); lengths in metres.\n"
            "# World frame: board centre at the origin, printed side up (+y); see the docs' conventions.\n"
            "[board]\n"
            f"squares = [{cols}, {rows}]  # columns, rows\n"
            f"square = {self.square!r}\n"
            f"marker = {self.marker!r}\n"
            f'dictionary = "{self.dictionary}"\n'
        )

    @classmethod
    def load(cls, path) -> "Board":
        """Read a ChArUco board file written by `save` (or by `hiddenjax board`); `load_board` reads either kind."""
        table = _board_table(path)
        if table.get("kind", "charuco") != "charuco":
            raise ValueError(f"{path} describes a {table['kind']!r} board, not a ChArUco one; read it with load_board")
        unknown = set(table) - {"kind", "squares", "square", "marker", "dictionary"}
        if unknown:
            raise ValueError(f"{path}: unknown key(s) {sorted(unknown)} in [board]")
        missing = {"squares", "square", "marker"} - set(table)
        if missing:
            raise ValueError(f"{path}: [board] needs {sorted(missing)}")
        return cls(
            squares=_pair(table["squares"]),
            square=float(table["square"]),
            marker=float(table["marker"]),
            dictionary=str(table.get("dictionary", "4X4_50")),
        )


class Chessboard(_PlanarBoard):
    """A plain chessboard with `inner = (cols, rows)` inner corners (OpenCV's pattern size; `(cols + 1)
    x (rows + 1)` squares) of side `square` metres, in the world plane y = 0, centre at the origin.

    Found by OpenCV's chessboard detectors (`calibration.detect`), which need the whole pattern in
    view; its frame is defined up to a half-turn (module docstring). A ChArUco board is
    also a chessboard: its inner corners are found this way too.
    """

    inner: tuple[int, int] = eqx.field(static=True)
    square: float = eqx.field(static=True)

    def __check_init__(self):
        cols, rows = _pair(self.inner)
        if cols < 2 or rows < 2:
            raise ValueError(f"a chessboard needs at least 2 x 2 inner corners, got inner={self.inner}")
        if not (np.isfinite(self.square) and self.square > 0):
            raise ValueError(f"square must be a positive length in metres, got {self.square}")

    @property
    def squares(self) -> tuple[int, int]:
        cols, rows = _pair(self.inner)
        return cols + 1, rows + 1

    def board_points(self) -> np.ndarray:
        """The inner corners `(K, 3)` in the board frame (origin at the outer top-left corner), row by row."""
        cols, rows = _pair(self.inner)
        j, i = np.mgrid[1 : rows + 1, 1 : cols + 1]
        return np.column_stack([i.ravel(), j.ravel(), np.zeros(i.size)]) * self.square

    def _pattern(self, width: int, height: int, px: float) -> np.ndarray:
        """The chessboard's `(height, width)` uint8 pattern at `px` pixels per metre, black top-left square:
        each pixel's covered fraction of white from the squares' true edges (grey where an edge cuts it)."""
        x = (np.arange(4 * width) + 0.5) / (4 * px * self.square)
        y = (np.arange(4 * height) + 0.5) / (4 * px * self.square)
        white = ((np.floor(x)[None, :] + np.floor(y)[:, None]) % 2).reshape(height, 4, width, 4).mean(axis=(1, 3))
        return np.round(255 * white).astype(np.uint8)

    def toml(self) -> str:
        cols, rows = _pair(self.inner)
        return (
            "# Plain chessboard; lengths in metres. inner: inner corners (OpenCV's pattern size).\n"
            "# World frame: board centre at the origin, printed side up (+y); see the docs' conventions.\n"
            "[board]\n"
            'kind = "chessboard"\n'
            f"inner = [{cols}, {rows}]  # columns, rows\n"
            f"square = {self.square!r}\n"
        )


BOARD_KINDS = (
    'a ChArUco board ([board] squares = [cols, rows], square, marker, dictionary; `hiddenjax board` writes one) or a '
    'plain chessboard ([board] kind = "chessboard", inner = [cols, rows] inner corners, square)'
)


def load_board(path) -> "Board | Chessboard":
    """Read a board file: a ChArUco `Board` or, with `kind = "chessboard"`, a `Chessboard`."""
    table = _board_table(path)
    kind = table.get("kind", "charuco")
    if kind == "charuco":
        return Board.load(path)
    if kind != "chessboard":
        raise ValueError(f"{path}: unknown board kind {kind!r}; a board file describes {BOARD_KINDS}")
    unknown = set(table) - {"kind", "inner", "square"}
    if unknown:
        raise ValueError(f"{path}: unknown key(s) {sorted(unknown)} in a chessboard's [board]; it takes inner and square")
    missing = {"inner", "square"} - set(table)
    if missing:
        raise ValueError(f"{path}: a chessboard's [board] needs {sorted(missing)} (inner: the inner-corner counts)")
    return Chessboard(inner=_pair(table["inner"]), square=float(table["square"]))


def _board_table(path) -> dict:
    table = read_toml(path).get("board")
    if not isinstance(table, dict):
        raise ValueError(f"{path}: no [board] table; a board file describes {BOARD_KINDS}")
    return table


def _pair(squares) -> tuple[int, int]:
    try:
        cols, rows = (int(v) for v in squares)
    except (TypeError, ValueError):
        raise ValueError(f"squares must be (columns, rows), two integers; got {squares!r}") from None
    return cols, rows


def write_board_pdf(path, image: np.ndarray, dpi: float) -> None:
    """Write a uint8 board image as a one-page PDF whose page prints it at its true size."""
    from PIL import Image

    with atomic_path(Path(path)) as tmp:
        Image.fromarray(image).save(tmp, format="PDF", resolution=float(dpi))
