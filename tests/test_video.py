"""Video: frames minus a background as signed maps, one factorization; reading clips; `hiddenjax video`."""

import json

import cv2
import numpy as np
import pytest

import hiddenjax as hj
from hiddenjax import photo
from hiddenjax.cli import main

GRID = hj.EnvGrid(8, 16)


@pytest.fixture(scope="module")
def walk(small_setup):
    """A teapot's matrix, and frames of a sky plus a patch walking around the horizon, rendered
    through a matrix with 4x the directions and another seed (not the solve's own A)."""
    T = hj.transport_matrix(small_setup.scene, small_setup.camera, GRID, samples=8, pixel_samples=2, progress=False)
    T_photo = hj.transport_matrix(small_setup.scene, small_setup.camera, GRID, samples=32, pixel_samples=2, seed=5,
                                  progress=False)
    sky = GRID.downsample(hj.scenes.procedural_sky(32, 64)).mean(axis=-1)
    cols = np.arange(0, 16, 2)
    envs = np.repeat(sky[None], len(cols), axis=0)
    envs[np.arange(len(cols)), 2, cols] += 20 * sky.mean()
    frames = np.stack([np.asarray(hj.render(T_photo, e)) for e in envs]).astype(np.float32)
    return T, frames, cols, sky


def test_maps_are_the_signed_solves_of_the_differences_and_follow_the_patch(walk):
    T, frames, cols, _ = walk
    maps = photo.differential_maps(T, frames, "median", batch=3)  # batches of 3: a padded last batch
    background = np.median(frames, axis=0)
    for k in (0, 5):
        one = hj.solve_illumination(T, frames[k] - background, prior="l2", nonneg=False).env
        np.testing.assert_allclose(maps[k], np.asarray(one), atol=2e-4 * np.abs(maps).max())
    found = np.array([np.unravel_index(np.argmax(m), GRID.shape) for m in maps])
    assert np.all(found[:, 0] == 2)
    assert np.all(np.minimum(np.abs(found[:, 1] - cols), 16 - np.abs(found[:, 1] - cols)) <= 1)
    first = photo.differential_maps(T, frames, "first")
    assert np.abs(first[0]).max() == 0.0
    with pytest.raises(ValueError, match="background must be one of"):
        photo.differential_maps(T, frames, "mean")
    with pytest.raises(ValueError, match="on the matrix's camera"):
        photo.differential_maps(T, frames[:, :10], "median")


def write_clip(path, frames_u8, fps=10.0):
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, frames_u8.shape[2:0:-1])
    for f in frames_u8:
        writer.write(np.ascontiguousarray(f[..., ::-1]))
    writer.release()


def test_read_video_resizes_linearizes_and_subsamples(tmp_path):
    levels = np.linspace(40, 220, 12).astype(np.uint8)
    clip = np.repeat(levels[:, None, None, None], 3, -1) * np.ones((1, 96, 128, 3), np.uint8)
    write_clip(tmp_path / "clip.avi", clip)
    video = photo.read_video(tmp_path / "clip.avi", 32, 24, every=2, max_frames=5)
    assert video.frames.shape == (5, 24, 32, 3) and list(video.indices) == [0, 2, 4, 6, 8]
    assert video.fps == pytest.approx(10.0)
    code = lambda v: hj.io.srgb_to_linear(np.asarray(v, dtype=np.float64) / 255.0)
    kept = levels[[0, 2, 4, 6, 8]].astype(float)
    mean = video.frames.mean(axis=(1, 2, 3))  # within 3 code values of the written level (MJPG is lossy)
    assert np.all((mean > code(kept - 3)) & (mean < code(kept + 3))), (mean, code(kept))
    with pytest.raises(ValueError, match="cannot open the video"):
        photo.read_video(tmp_path / "missing.mp4", 32, 24)


def test_video_command_writes_maps_and_refuses_bad_clips(walk, tmp_path, capsys):
    T, frames, _, _ = walk
    T.save(tmp_path / "A.npz")
    display = np.round(np.clip(hj.io.tonemap(frames, white=float(frames.max())), 0, 255)).astype(np.uint8)
    write_clip(tmp_path / "clip.avi", np.repeat(display[..., None], 3, -1))
    out = tmp_path / "maps"
    assert main(["video", str(tmp_path / "A.npz"), str(tmp_path / "clip.avi"), "-o", str(out),
                 "--video", str(tmp_path / "maps.mp4")]) == 0
    results = json.loads((out / "results.json").read_text())
    assert results["frames"] == len(frames) and results["frames_per_second"] > 0
    assert np.load(out / "maps.npz")["maps"].shape == (len(frames), 8, 16, 3)
    assert len(list(out.glob("map_*.png"))) == len(frames) and (tmp_path / "maps.mp4").stat().st_size > 0
    capsys.readouterr()
    for clip, words in ((tmp_path / "nope.mp4", "cannot open the video"), (tmp_path / "A.npz", "cannot open the video")):
        assert main(["video", str(tmp_path / "A.npz"), str(clip), "-o", str(tmp_path / "bad")]) == 1
        err = capsys.readouterr().err.strip()
        assert "\n" not in err and words in err, err
        assert not (tmp_path / "bad").exists()
