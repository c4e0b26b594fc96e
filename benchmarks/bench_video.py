"""Video throughput: signed differential maps of many frames, one factorization for all.

    python benchmarks/bench_video.py [--quick] [--out DIR]

Scene: the teapot fixture on its plane, 64x64 pixels, a 16x32 grid (the issue's size). Frames:
a procedural sky plus a small bright patch walking around the horizon (a person passing), each
frame rendered through a transport matrix built with 4x the directions and another seed (never
the solve's own `A`), 0.5% noise. Timed (best of 3, after a first call): the read-to-map path of
`hj.photo.differential_maps` (the median background, then `solve_many` on batches of 256 frames),
against the same-run baselines of one signed solve per frame (`IlluminationOperator.solve`,
`nonneg=False`, compiled once) and of `solve_many` on the stack; every method's time includes
forming and factorizing the normal matrix once (the clip's whole solve). Also checks that the maps agree
and that each map's brightest cell follows the walking patch. Writes `video.png` (frames, maps)
and `results.json`.
"""

import argparse
import json
import time
from pathlib import Path

import jax
import numpy as np

import hiddenjax as hj
from _report import Table  # noqa: E402  (benchmarks/ is on sys.path when run as a script)


def frames_of_a_walk(grid, count, seed=0):
    """Env maps `(F, h, w)`: a procedural sky plus a 1-cell patch at the horizon, moving in azimuth."""
    sky = grid.downsample(hj.scenes.procedural_sky(64, 128)).mean(axis=-1)
    row = grid.height // 2 - 2
    maps = np.repeat(sky[None], count, axis=0)
    cols = np.round(np.linspace(0, grid.width - 1, count)).astype(int)
    maps[np.arange(count), row, cols] += 20 * float(sky.mean())
    return maps, row, cols


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path("out/bench_video"))
    parser.add_argument("--quick", action="store_true", help="fewer frames")
    args = parser.parse_args(argv)
    hj.enable_compilation_cache()  # programs compiled once per machine (docs: compilation cache)
    args.out.mkdir(parents=True, exist_ok=True)
    count = 200 if args.quick else 1000
    grid = hj.EnvGrid(16, 32)
    setup = hj.scenes.object_on_plane("teapot", width=64, height=64)
    T = hj.transport_matrix(setup.scene, setup.camera, grid, samples=16, pixel_samples=4, progress=False)
    T_photo = hj.transport_matrix(setup.scene, setup.camera, grid, samples=64, pixel_samples=4, seed=7, progress=False)
    envs, row, cols = frames_of_a_walk(grid, count)
    rng = np.random.default_rng(0)
    frames = np.stack([np.asarray(hj.render(T_photo, e)) for e in envs])
    frames = (frames * (1 + rng.normal(0, 0.005, frames.shape))).astype(np.float32)

    def ours():
        return hj.photo.differential_maps(T, frames, "median")

    background = hj.photo.background_frame(frames, "median")
    diffs = frames - background[None]
    build = lambda: hj.solvers.IlluminationOperator.build(T, prior="l2")
    solve = jax.jit(lambda op, d: op.solve(d, nonneg=False).env)

    def per_frame():  # every method forms and factorizes the normal matrix once per clip
        op = build()
        return np.stack([np.asarray(solve(op, d)) for d in diffs])

    def many():
        return np.asarray(build().solve_many(diffs, nonneg=False).env)

    table = Table()
    table.append(("method", "seconds", "frames/s", "vs one solve per frame"))
    results = dict(frames=count, pixels=int(np.asarray(T.mask).sum()), grid=[grid.height, grid.width])
    timings = {}
    for name, fn in (("one solve per frame (baseline)", per_frame), ("solve_many", many),
                     ("differential_maps", ours)):
        out = fn()  # compile, and the maps to compare
        best = min(_time(fn) for _ in range(3))
        timings[name] = (best, out)
    base = timings["one solve per frame (baseline)"][0]
    for name, (seconds, _) in timings.items():
        table.append((name, f"{seconds:.3f}", f"{count / seconds:.0f}", f"{base / seconds:.1f}x"))
        results[name] = dict(seconds=seconds, frames_per_second=count / seconds)
    table.print_all()
    maps = timings["differential_maps"][1]
    reference = timings["one solve per frame (baseline)"][1]
    results["max_relative_difference_to_baseline"] = float(np.abs(maps - reference).max() / np.abs(reference).max())
    found = np.array([np.unravel_index(np.argmax(m), grid.shape) for m in maps])
    wrap = np.minimum(np.abs(found[:, 1] - cols), grid.width - np.abs(found[:, 1] - cols))
    results["patch_found_within_one_cell"] = float(np.mean((np.abs(found[:, 0] - row) <= 1) & (wrap <= 1)))
    print(f"maps agree with the per-frame solves to {results['max_relative_difference_to_baseline']:.1e}; "
          f"the walking patch is the brightest cell (within one) in {results['patch_found_within_one_cell']:.0%} "
          f"of the frames")
    pick = np.linspace(0, count - 1, 4).astype(int)
    limit = float(np.percentile(np.abs(maps), 99.9))
    panels = [(f"frame {k}", frames[k]) for k in pick] + [(f"map {k}", maps[k], "signed", limit) for k in pick]
    hj.io.contact_sheet(args.out / "video.png", panels, height=128, columns=4)
    (args.out / "results.json").write_text(json.dumps(results, indent=2))
    return results


def _time(fn):
    t0 = time.perf_counter()
    fn()
    return time.perf_counter() - t0


if __name__ == "__main__":
    main()
