"""The `hiddenjax` command fed generated bad input (hypothesis): it answers, in one or two lines, and leaves nothing.

Every command gets broken files of each kind it reads (random bytes; valid files cut short or with
bytes flipped; images with NaN, inf, negative, huge, wrong-shaped or integer values; scene files with
bad numbers, missing sections and broken meshes) and option values at and past their limits. For
each example: the exit status is 0, 1 (bad input) or 2 (usage), nothing escapes as an exception,
a failure prints at most two lines on stderr and no traceback, leaves no output or temporary file,
a success writes finite values, and the inputs are untouched. The default run draws a few hundred
examples; the `slow` profile (`-m slow`) more than 2000.
"""

import contextlib
import hashlib
import io
import shutil
import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import hiddenjax as hj
from hiddenjax.cli import main
from test_cli import SCENE as PLANE_SCENE

SCENE = PLANE_SCENE + """[[surface]]
mesh = "box.ply"
albedo = 0.7
[surface.transform]
scale = [0.2, 0.2, 0.2]
translation = [0.0, 0.1, 0.0]
"""

EXAMPLES = {"default": 40, "slow": 320}  # per command: 8 commands, 320 examples by default, 2560 in `slow`

CORNER = """[corner]
class = "L"
setting = "fixed-lamp"
mirror = false
[corner.camera]
origin = [-0.1, 0.12, -0.5]
target = [-0.05, 0.0, 0.05]
fov = 60.0
"""


@pytest.fixture(scope="module")
def base(tmp_path_factory):
    """Valid inputs of every kind, from which the broken ones are made."""
    import trimesh

    d = tmp_path_factory.mktemp("fuzz")
    trimesh.creation.box().export(d / "box.ply")
    (d / "scene.toml").write_text(SCENE)
    quiet = contextlib.redirect_stderr(io.StringIO())
    with quiet, contextlib.redirect_stdout(io.StringIO()):
        assert main(["transport", str(d / "scene.toml"), "-o", str(d / "A.npz"), "--quiet"]) == 0
        assert main(["board", "-o", str(d / "board.png"), "--dpi", "50"]) == 0
    T = hj.TransportMatrix.load(d / "A.npz")
    photo = np.asarray(hj.render(T, np.ones((4, 8, 3), np.float32)))
    hj.io.write_exr(d / "photo.exr", photo)
    hj.io.write_image(d / "photo.hdr", photo)
    hj.io.write_image(d / "photo.png", np.clip(photo / photo.max(), 0, 1))
    hj.io.write_exr(d / "env.exr", np.ones((4, 8, 3), np.float32))
    np.save(d / "array.npy", photo)
    (d / "corner.toml").write_text(CORNER)
    rng = np.random.default_rng(0)
    empty = rng.random((24, 32, 3)).astype(np.float32)
    hj.io.write_exr(d / "f0.exr", empty)
    lit = empty.copy()
    lit[12:, :16] *= 1.1  # light from the hidden side, on the floor at the lower left
    hj.io.write_exr(d / "f1.exr", lit)
    return d


def _valid(base: Path, kind: str) -> bytes:
    return (base / {"exr": "photo.exr", "hdr": "photo.hdr", "png": "photo.png", "npz": "A.npz", "toml": "scene.toml",
                    "ply": "box.ply", "board": "board.toml", "corner": "corner.toml"}[kind]).read_bytes()


@st.composite
def broken_bytes(draw, base, kind):
    """A file of `kind` that is wrong: random bytes, a valid one cut short, or one with bytes flipped."""
    valid = _valid(base, kind)
    how = draw(st.sampled_from(["random", "cut", "flip", "empty"]))
    if how == "random":
        return draw(st.binary(min_size=1, max_size=4096))
    if how == "empty":
        return b""
    if how == "cut":
        return valid[: draw(st.integers(0, len(valid) - 1))]
    data = bytearray(valid)
    for position in draw(st.lists(st.integers(0, len(data) - 1), min_size=1, max_size=16)):
        data[position] = draw(st.integers(0, 255))
    return bytes(data)


def bad_values():
    return st.sampled_from([np.nan, np.inf, -np.inf, -1.0, 0.0, 1e38, -1e38, 1e-45, 3e38])


@st.composite
def bad_image(draw, shape=(10, 12, 3)):
    """An image file (EXR, HDR, PNG, NPY) holding values or a shape that make no photo of this scene."""
    how = draw(st.sampled_from(["values", "shape", "dtype", "bytes"]))
    rng = np.random.default_rng(draw(st.integers(0, 2**16)))
    image = rng.random(shape).astype(np.float32)
    suffix = draw(st.sampled_from([".exr", ".hdr", ".png", ".npy"]))
    if how == "values":
        mask = rng.random(shape[:2]) < draw(st.floats(0.0, 1.0))
        image[mask] = draw(bad_values())
    elif how == "shape":
        image = rng.random(draw(st.sampled_from([(0, 0), (1, 1), (10, 12, 2), (10, 12, 5), (12, 10, 3), (10, 12, 3, 1),
                                                 (2, 3), (1000, 1, 3)]))).astype(np.float32)
    elif how == "dtype":
        with np.errstate(invalid="ignore", over="ignore"):  # values beyond the dtype's range are the point
            image = (rng.random(shape) * draw(st.sampled_from([1, 255, 65535, 1e10]))).astype(
                draw(st.sampled_from([np.uint8, np.int32, np.float16, np.float64, np.bool_, np.complex64])))
    else:
        return suffix, draw(st.binary(max_size=2048))
    return suffix, image


def _write_image(path: Path, image) -> None:
    """Write `image` as its suffix says, however wrong it is (bytes when no writer takes it)."""
    if isinstance(image, bytes):
        path.write_bytes(image)
        return
    if path.suffix == ".npy":
        np.save(path, image)
        path.with_suffix(".npy").rename(path)
        return
    try:
        writer = hj.io.write_exr if path.suffix == ".exr" else hj.io.write_image
        writer(path, image)
    except Exception:  # no writer takes it: random bytes instead, still a broken file of that name
        path.write_bytes(np.asarray(image).tobytes()[:2048])


def _digest(folder: Path) -> dict:
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in folder.iterdir() if p.is_file()}


def run_command(folder: Path, argv: list[str], outputs: list[str]):
    """Run `hiddenjax ARGV` in this process and check the contract; returns the exit status."""
    inputs = _digest(folder)
    before = set(folder.iterdir())
    err, out = io.StringIO(), io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(out):
        try:
            status = main(argv)
        except SystemExit as stop:  # argparse: usage errors
            status = stop.code
    stderr = err.getvalue()
    assert status in (0, 1, 2), (argv, status, stderr)
    assert "Traceback" not in stderr, (argv, stderr)
    after = _digest(folder)
    assert {name: after.get(name) for name in inputs} == inputs, f"{argv} changed its inputs"
    if status:
        lines = stderr.strip().splitlines()
        assert 1 <= len(lines) <= 2, (argv, stderr)
        left = set(folder.iterdir()) - before
        assert not left, (argv, sorted(p.name for p in left), stderr)
    else:
        for name in outputs:
            path = folder / name
            if path.suffix == ".exr" and path.exists():
                assert np.all(np.isfinite(hj.io.read_image(path))), (argv, "wrote non-finite values")
        for name in outputs:  # the next example starts clean
            path = folder / name
            shutil.rmtree(path) if path.is_dir() else path.unlink(missing_ok=True)
    return status


def fuzz(profile):
    return settings(max_examples=EXAMPLES[profile], deadline=None, derandomize=True, database=None,
                    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow,
                                           HealthCheck.data_too_large])


@contextlib.contextmanager
def workspace(base: Path, *names):
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        for name in names:
            shutil.copy(base / name, folder / name)
        yield folder


def _solve_options():
    floats = st.one_of(bad_values(), st.floats(allow_nan=True, allow_infinity=True))
    return st.fixed_dictionaries({}, optional={
        "--prior": st.sampled_from(["hdr", "l2", "tv", "sunsky", "bogus"]),
        "--smooth": floats.map(str), "--ridge": floats.map(str),
        "--grid": st.tuples(st.integers(-2, 9), st.integers(-2, 9)).map(lambda g: f"{g[0]} {g[1]}"),
        "--signed": st.just(None), "--absolute": st.just(None)})


def _options(options: dict) -> list[str]:
    argv = []
    for flag, value in options.items():
        argv += [flag] if value is None else [flag, *value.split(" ")]
    return argv


def _commands(profile):
    @fuzz(profile)
    @given(data=st.data())
    def solve(base, data):
        image = data.draw(st.one_of(bad_image(), st.tuples(st.sampled_from([".exr", ".hdr", ".png"]),
                                                          st.just("valid"))))
        suffix, content = image
        with workspace(base, "A.npz", "photo.exr", "photo.hdr", "photo.png") as folder:
            name = "photo" + suffix
            if not isinstance(content, str):
                name = "bad" + suffix
                _write_image(folder / name, content)
            matrix = "A.npz"
            if data.draw(st.booleans()):
                (folder / "B.npz").write_bytes(data.draw(broken_bytes(base, "npz")))
                matrix = "B.npz"
            options = _options(data.draw(_solve_options()))
            run_command(folder, ["solve", str(folder / matrix), str(folder / name), "-o", str(folder / "env.exr"),
                                 *options], ["env.exr"])

    @fuzz(profile)
    @given(data=st.data())
    def render(base, data):
        suffix, content = data.draw(bad_image(shape=(4, 8, 3)))
        with workspace(base, "A.npz") as folder:
            _write_image(folder / ("env" + suffix), content)
            out = data.draw(st.sampled_from(["image.exr", "image.hdr", "image.png", "image.jpg"]))
            run_command(folder, ["render", str(folder / "A.npz"), str(folder / ("env" + suffix)), "-o",
                                 str(folder / out)], [out])

    @fuzz(profile)
    @given(data=st.data())
    def cues(base, data):
        suffix, content = data.draw(bad_image())
        with workspace(base, "A.npz") as folder:
            _write_image(folder / ("photo" + suffix), content)
            ridge = data.draw(st.one_of(bad_values(), st.floats(1e-6, 1.0)))
            run_command(folder, ["cues", str(folder / "A.npz"), "--image", str(folder / ("photo" + suffix)), "-o",
                                 str(folder / "cues"), "--ridge", str(ridge)], ["cues"])

    @fuzz(profile)
    @given(data=st.data())
    def transport(base, data):
        with workspace(base, "scene.toml", "box.ply") as folder:
            part = data.draw(st.sampled_from(["toml", "ply", "numbers", "options"]))
            options = []
            if part == "toml":
                (folder / "scene.toml").write_bytes(data.draw(broken_bytes(base, "toml")))
            elif part == "ply":
                (folder / "box.ply").write_bytes(data.draw(broken_bytes(base, "ply")))
            elif part == "numbers":
                text = SCENE
                for key in data.draw(st.lists(st.sampled_from(["height = 4", "width = 8", "samples = 4",
                                                               "width = 12", "height = 10", "fov = 40.0",
                                                               "albedo = 0.5", "pixel_samples = 1"]),
                                              min_size=1, max_size=3)):
                    value = data.draw(st.sampled_from(["nan", "inf", "-1", "0", "1e12", "\"x\"", "[]", "-0.0"]))
                    text = text.replace(key, f"{key.split(' = ')[0]} = {value}", 1)
                (folder / "scene.toml").write_text(text)
            else:
                for flag in data.draw(st.lists(st.sampled_from(["--samples", "--pixel-samples", "--seed"]),
                                               min_size=1, max_size=3, unique=True)):
                    options += [flag, str(data.draw(st.sampled_from([-1, 0, 2**31, 10**12, 3])))]
            out = data.draw(st.sampled_from(["A.npz", "A.txt"]))
            run_command(folder, ["transport", str(folder / "scene.toml"), "-o", str(folder / out), "--quiet",
                                 *options], [out])

    @fuzz(profile)
    @given(data=st.data())
    def video(base, data):
        with workspace(base, "A.npz") as folder:
            suffix = data.draw(st.sampled_from([".mp4", ".avi", ".npy"]))
            (folder / ("clip" + suffix)).write_bytes(data.draw(st.binary(max_size=4096)))
            run_command(folder, ["video", str(folder / "A.npz"), str(folder / ("clip" + suffix)), "-o",
                                 str(folder / "maps")], ["maps"])

    @fuzz(profile)
    @given(data=st.data())
    def calibrate(base, data):
        with workspace(base, "board.toml", "board.png") as folder:
            if data.draw(st.booleans()):
                (folder / "board.toml").write_bytes(data.draw(broken_bytes(base, "board")))
            photos = []
            for k in range(data.draw(st.integers(1, 3))):
                suffix, content = data.draw(bad_image(shape=(60, 80, 3)))
                _write_image(folder / f"p{k}{suffix}", content)
                photos.append(str(folder / f"p{k}{suffix}"))
            run_command(folder, ["calibrate", str(folder / "board.toml"), *photos, "-o", str(folder / "camera.toml")],
                        ["camera.toml"])

    @fuzz(profile)
    @given(squares=st.tuples(st.integers(-1, 40), st.integers(-1, 40)), square=bad_values(), marker=bad_values(),
           dpi=st.sampled_from([-1.0, 0.0, 1.0, 1e9, float("nan"), 300.0]))
    def board(base, squares, square, marker, dpi):
        with workspace(base) as folder:
            run_command(folder, ["board", "-o", str(folder / "b.png"), "--squares", str(squares[0]), str(squares[1]),
                                 "--square", str(square), "--marker", str(marker), "--dpi", str(dpi)],
                        ["b.png", "b.toml"])

    @fuzz(profile)
    @given(data=st.data())
    def corner(base, data):
        with workspace(base, "corner.toml", "f0.exr", "f1.exr") as folder:
            frames = [str(folder / "f0.exr"), str(folder / "f1.exr")]
            part = data.draw(st.sampled_from(["frame", "file", "options", "video"]))
            options = ["--corner", str(folder / "corner.toml")]
            if part == "frame":
                suffix, content = data.draw(bad_image(shape=(24, 32, 3)))
                _write_image(folder / ("bad" + suffix), content)
                frames[data.draw(st.integers(0, 1))] = str(folder / ("bad" + suffix))
            elif part == "file":
                (folder / "corner.toml").write_bytes(data.draw(broken_bytes(base, "corner")))
            elif part == "options":
                numbers = st.sampled_from(["-1", "0", "1", "2", "3", "100000", "nan", "x"])
                for flag in data.draw(st.lists(st.sampled_from(["--window", "--every", "--max-frames", "--crop",
                                                                "--class", "--setting", "--background",
                                                                "--refine"]), min_size=1, max_size=3, unique=True)):
                    if flag == "--crop":
                        options += [flag, *(data.draw(numbers) for _ in range(3))]
                    elif flag in ("--class", "--setting"):
                        options += [flag, data.draw(st.sampled_from(["L", "T", "table", "random-lamp", "Z"]))]
                    elif flag == "--background":
                        options += [flag, data.draw(st.sampled_from(["median", "first", "none.exr",
                                                                     str(folder / "f0.exr")]))]
                    elif flag == "--refine":
                        options += [flag]
                    else:
                        options += [flag, data.draw(numbers)]
            else:
                (folder / "clip.mp4").write_bytes(data.draw(st.binary(max_size=4096)))
                frames = [str(folder / "clip.mp4")]
            run_command(folder, ["corner", *frames, "-o", str(folder / "out"), "--quiet", *options], ["out"])

    return dict(solve=solve, render=render, cues=cues, transport=transport, video=video, calibrate=calibrate,
                board=board, corner=corner)


COMMANDS = _commands("default")
SLOW = _commands("slow")


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_fuzzed_command_answers_in_one_line(base, command):
    COMMANDS[command](base)


@pytest.mark.slow
@pytest.mark.parametrize("command", sorted(SLOW))
def test_fuzzed_command_answers_in_one_line_long(base, command):
    SLOW[command](base)
