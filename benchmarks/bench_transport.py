"""Transport-matrix build: throughput vs raw Embree, memory, scaling, accuracy vs time (and vs Mitsuba).

    python benchmarks/bench_transport.py [--quick] [--out DIR]

Every baseline is measured in the same run. Accuracy is the median relative column error of a
matrix against a high-sample reference of the same model: hiddenjax against `samples=32,
pixel_samples=16` with another seed on a random eighth of the pixels (footprint noise counts, as
it does in Mitsuba's spp),
Mitsuba's path tracer (max depth 4, one launch per column) against 1024 spp on a random subset of
upper-hemisphere columns, its time extrapolated to all columns. The defaults' rendered-image
error (64x64, the procedural sky with its sun, three seeds) is taken against `samples=128,
pixel_samples=4` (another seed) and against `samples=32, pixel_samples=16`, whose footprint noise
is smaller.
"""

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

# Child processes compute too: on a GPU the parent must not take JAX's default 75% of its memory first.
os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

import hiddenjax as hj  # noqa: E402
from _report import Table, finish_plot  # noqa: E402  (benchmarks/ is on sys.path when run as a script)
from hiddenjax.transport._embree import RayCaster, primary_hits  # noqa: E402


def build(setup, grid, **kw):
    t0 = time.perf_counter()
    T = hj.transport_matrix(setup.scene, setup.camera, grid, progress=False, **kw)
    return T, time.perf_counter() - t0


def common_rows(T, ref):
    """Rows of two transport matrices restricted to the pixels both observe."""
    shared, ia, ib = np.intersect1d(np.asarray(T.pixels), np.asarray(ref.pixels), return_indices=True)
    return np.asarray(T.A)[ia], np.asarray(ref.A)[ib]


def column_errors(A, ref):
    """Relative error of each nonzero column of `A (P, N)` against `ref (P, N)`."""
    A, ref = np.asarray(A, dtype=np.float64), np.asarray(ref, dtype=np.float64)
    norms = np.linalg.norm(ref, axis=0)
    keep = norms > 0
    return np.linalg.norm(A - ref, axis=0)[keep] / norms[keep]


def build_name(adaptive: bool, sub_points: bool) -> str:
    """The row label of a build: fixed sampling, adaptive (the default: with sub-points) or adaptive without them."""
    return "fixed" if not adaptive else "adaptive (default)" if sub_points else "adaptive, no sub-points"


def fixed_seconds(accuracy, error: float, pixel_samples: int) -> float | None:
    """Seconds fixed sampling with `pixel_samples` needs for median column error `error`: its curve
    interpolated log-log between its points (None outside it: no time without extrapolating)."""
    fixed = sorted((f for f in accuracy if not f["adaptive"] and f["pixel_samples"] == pixel_samples),
                   key=lambda f: -f["median_column_error"])
    errs = np.log([f["median_column_error"] for f in fixed])
    err = np.log(error)
    if len(fixed) < 2 or not errs[-1] <= err <= errs[0]:
        return None
    return float(np.exp(np.interp(-err, -errs, np.log([f["seconds"] for f in fixed]))))


def equal_error(accuracy):
    """Each adaptive build against fixed sampling at the same median column error: the fixed curve
    with the adaptive build's pixel samples (`fixed_seconds`), and the fastest fixed curve of any
    pixel samples that reaches that error (`frontier_seconds`: what a user choosing the fixed
    build's settings for that accuracy would wait)."""
    out = []
    pxs = sorted({f["pixel_samples"] for f in accuracy if not f["adaptive"]})
    for r in (r for r in accuracy if r["adaptive"]):
        err = r["median_column_error"]
        same = fixed_seconds(accuracy, err, r["pixel_samples"])
        times = [t for t in (fixed_seconds(accuracy, err, px) for px in pxs) if t is not None]
        if same is None and not times:
            continue  # outside every fixed curve
        best = min(times)
        out.append(dict(samples=r["samples"], pixel_samples=r["pixel_samples"], sub_points=r["sub_points"],
                        seconds=r["seconds"],
                        median_column_error=err, fixed_seconds=same,
                        speedup=None if same is None else same / r["seconds"],
                        frontier_seconds=best, frontier_speedup=best / r["seconds"]))
    return out


def raw_embree_rate(setup, rays: int, seed=0):
    """Occlusion queries per second of embreex on `rays` rays from the observed surface points."""
    caster = RayCaster(setup.scene)
    hits, _ = primary_hits(caster, setup.camera, 1, seed)
    on_plane = hits.surface == 0
    rng = np.random.default_rng(seed)
    batch = min(rays, 1 << 22)
    idx = rng.integers(0, on_plane.sum(), batch)
    origins = hits.position[on_plane][idx] + caster.offset * hits.normal[on_plane][idx]
    d = rng.normal(size=(batch, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)  # uniform over the sphere, as the N columns are
    origins, d = origins.astype(np.float32), d.astype(np.float32)
    done, elapsed = 0, 0.0
    while done < rays:
        n = min(batch, rays - done)
        t0 = time.perf_counter()
        caster.occluded(origins[:n], d[:n])
        elapsed += time.perf_counter() - t0
        done += n
    return rays / elapsed


# VmHWM (the peak resident set of this address space) rather than ru_maxrss, which Linux carries
# over from the parent at fork and would hide the build's growth.
_MEMORY_PROBE = """
import json, re, sys
import hiddenjax as hj
hwm = lambda: int(re.search(r"VmHWM:\\s+(\\d+) kB", open("/proc/self/status").read()).group(1)) * 1024
size, H, W, S, px = map(int, sys.argv[1:6])
setup = hj.scenes.object_on_plane("teapot", width=size, height=size)
hj.transport_matrix(setup.scene, setup.camera, hj.EnvGrid(4, 8), samples=1, pixel_samples=1, progress=False)
base = hwm()
T = hj.transport_matrix(setup.scene, setup.camera, hj.EnvGrid(H, W), samples=S, pixel_samples=px, progress=False)
peak = hwm()
print(json.dumps(dict(increase=peak - base, A=T.A.nbytes)))
"""


def peak_memory(size, grid, samples, pixel_samples):
    """Growth of the peak resident set of a fresh process during one build (Embree and XLA included)."""
    args = [str(v) for v in (size, grid.height, grid.width, samples, pixel_samples)]
    out = subprocess.run([sys.executable, "-c", _MEMORY_PROBE, *args], capture_output=True, text=True, check=True)
    r = json.loads(out.stdout.strip().splitlines()[-1])
    return r["increase"], r["A"]


def mitsuba_columns(setup, grid, T_mask, spps, ref_spp, n_columns, seed=0):
    """Mitsuba path tracer, one launch per column: time per column and column errors per spp."""
    try:
        from hiddenjax.transport._mitsuba import MitsubaRenderer
    except ImportError:
        return None
    try:
        renderer = MitsubaRenderer(setup.scene, setup.camera, grid, integrator="path", max_depth=4)
    except ImportError as e:
        return {"skipped": str(e)}
    rng = np.random.default_rng(seed)
    columns = rng.choice(grid.size // 2, size=n_columns, replace=False)  # upper hemisphere
    out = {"variant": renderer.variant, "columns": columns.tolist(), "per_spp": {}}

    def render_columns(spp, s):
        cols, t = [], 0.0
        for j in columns:
            env = np.zeros(grid.size)
            env[j] = 1.0
            t0 = time.perf_counter()
            img = renderer.render(env.reshape(grid.shape), spp=spp, seed=s)
            t += time.perf_counter() - t0
            cols.append(img.mean(axis=2)[T_mask])
        return np.stack(cols, 1), t

    renderer.render(np.ones(grid.shape), spp=1)  # JIT warm-up, not timed
    ref, _ = render_columns(ref_spp, 12345)
    for spp in spps:
        cols, t = render_columns(spp, 1)
        out["per_spp"][spp] = dict(
            seconds_all_columns=t / n_columns * grid.size,
            median_column_error=float(np.median(column_errors(cols, ref))),
        )
    return out


def plot_accuracy(results, path):
    """Median column error against build time: fixed (solid) and adaptive (dashed) per footprint
    samples, one colour each, and Mitsuba's path tracer."""
    fig, ax = plt.subplots(figsize=(9, 4.5))
    for px, colour, marker in ((1, "C0", "o"), (4, "C1", "^"), (9, "C2", "v"), (16, "C3", "D")):
        for adaptive, sub, style in ((False, False, "-"), (True, False, "--"), (True, True, ":")):
            acc = [r for r in results["accuracy"]
                   if r["pixel_samples"] == px and r["adaptive"] == adaptive and r.get("sub_points", False) == sub]
            if not acc:
                continue
            ax.loglog([r["seconds"] for r in acc], [100 * r["median_column_error"] for r in acc],
                      marker + style, color=colour, label=f"{build_name(adaptive, sub)}, pixel_samples={px}")
            for r in acc:
                ax.annotate(f"S={r['samples']}", (r["seconds"], 100 * r["median_column_error"]), fontsize=7)
    mit = results.get("mitsuba")
    if isinstance(mit, dict) and "per_spp" in mit:
        ms = mit["per_spp"]
        ax.loglog([m["seconds_all_columns"] for m in ms.values()], [100 * m["median_column_error"] for m in ms.values()],
                  "s-", color="C4", label=f"Mitsuba 3 path ({mit['variant']})")
    c = results["config"]
    finish_plot(fig, ax, path, "seconds for all columns", "median column error (%)",
                f"{c['image']}x{c['image']} px, {c['grid'][0]}x{c['grid'][1]} grid, {c['occluder_faces']}-face teapot",
                legend=dict(loc="upper left", bbox_to_anchor=(1.01, 1), fontsize=8))


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path("out/bench_transport"))
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--no-mitsuba", action="store_true")
    args = parser.parse_args(argv)
    hj.enable_compilation_cache()  # programs compiled once per machine (docs: compilation cache)
    args.out.mkdir(parents=True, exist_ok=True)
    q = args.quick
    size, grid = (48, hj.EnvGrid(8, 16)) if q else (128, hj.EnvGrid(32, 64))
    setup = hj.scenes.object_on_plane("teapot", width=size, height=size)
    faces = len(setup.scene[1].triangles)
    results = dict(config=dict(image=size, grid=list(grid.shape), occluder_faces=faces, quick=q))
    rows = Table()

    build(setup, hj.EnvGrid(4, 8), samples=1, pixel_samples=1)  # warm-up (JAX, Embree), not timed
    # 1. throughput against raw Embree, same number of (pixel, direction-sample) pairs (fixed sampling)
    T, t = build(setup, grid, samples=16, pixel_samples=1, adaptive=False)
    pairs = T.A.shape[0] * grid.size * 16
    raw = raw_embree_rate(setup, pairs)
    results["throughput"] = dict(pairs=pairs, build_seconds=t, pairs_per_second=pairs / t,
                                 raw_embree_rays_per_second=raw, ratio_to_raw=pairs / t / raw)
    rows.append(("build (S=16, 1 px sample)", f"{t:.2f} s", f"{pairs / t / 1e6:.1f} M pairs/s",
                 f"raw embreex {raw / 1e6:.1f} M rays/s -> {pairs / t / raw:.2f}x"))

    # 2. memory: peak resident-set growth in a fresh process
    results["memory"] = []
    for px in (1, 4):
        peak, a_bytes = peak_memory(size, grid, 16, px)
        results["memory"].append(dict(pixel_samples=px, peak_increase_bytes=peak, A_bytes=a_bytes, ratio=peak / a_bytes))
        rows.append((f"peak RSS growth (S=16, px={px})", f"{peak / 2**20:.0f} MiB", f"A = {a_bytes / 2**20:.0f} MiB",
                     f"{peak / a_bytes:.2f}x A"))

    # 3. accuracy vs time, against a reference converged in directions and footprint
    subset = np.random.default_rng(3).random((size, size)) < 0.125
    ref, t_ref = build(setup, grid, samples=16 if q else 32, pixel_samples=16, seed=1, mask=subset, adaptive=False)
    results["reference"] = dict(samples=16 if q else 32, pixel_samples=16, pixels=int(ref.A.shape[0]), seconds=t_ref)
    results["scaling"], results["accuracy"] = [], []
    curves = [(False, False, 1, (2, 4, 8, 16, 32)), (False, False, 4, (2, 4, 8, 16, 32)), (False, False, 9, (2, 4, 8, 16)),
              (False, False, 16, (2, 4, 8)), (True, False, 1, (4, 8, 16, 32)), (True, False, 4, (4, 8, 16, 32)),
              (True, False, 9, (4, 8, 16)), (True, False, 16, (4,)), (True, True, 4, (4, 8, 16, 32)), (True, True, 9, (4, 8))]
    for adaptive, sub, px, sample_counts in curves:
        for S in sample_counts:
            T_s, t_s = build(setup, grid, samples=S, pixel_samples=px, seed=0, adaptive=adaptive, sub_points=sub)
            err = float(np.median(column_errors(*common_rows(T_s, ref))))
            results["accuracy"].append(dict(samples=S, pixel_samples=px, adaptive=adaptive, sub_points=sub, seconds=t_s,
                                            median_column_error=err))
            rows.append((f"{build_name(adaptive, sub)} samples={S}, pixel_samples={px}", f"{t_s:.2f} s",
                         f"median column err {100 * err:.2f}%", ""))
    results["equal_error"] = equal_error(results["accuracy"])
    for r in results["equal_error"]:
        same = "outside its px curve" if r["speedup"] is None else \
            f"{r['speedup']:.1f}x (same px, {r['fixed_seconds']:.1f} s)"
        rows.append((f"{build_name(True, r['sub_points'])} S={r['samples']}, px={r['pixel_samples']} vs fixed",
                     f"{r['seconds']:.2f} s",
                     f"at {100 * r['median_column_error']:.2f}%: {same}",
                     f"{r['frontier_speedup']:.1f}x the fastest fixed ({r['frontier_seconds']:.1f} s)"))
    small = hj.scenes.object_on_plane("teapot", width=size // 2, height=size // 2)
    coarse = hj.EnvGrid(grid.height // 2, grid.width // 2)
    for label, s, g in (("pixels / 4", small, grid), ("grid / 4", setup, coarse)):
        _, t_x = build(s, g, samples=16, pixel_samples=1, adaptive=False)
        results["scaling"].append(dict(change=label, seconds=t_x, ratio_to_full=t_x / t))
        rows.append((f"{label} (S=16)", f"{t_x:.2f} s", f"{t_x / t:.2f}x the full build", ""))

    # 4. defaults: Monte Carlo error of a rendered image under the procedural sky (with a sun)
    img_size = 32 if q else 64
    dsetup = hj.scenes.object_on_plane("teapot", width=img_size, height=img_size)
    env = grid.downsample(hj.scenes.procedural_sky(128, 256))
    Tr, _ = build(dsetup, grid, samples=32 if q else 128, pixel_samples=hj.transport.DEFAULT_PIXEL_SAMPLES, seed=7,
                  adaptive=False)
    # against Tr the error holds two footprints' noise, the build's and the reference's (about 0.44%
    # together at 64x64); against 16 footprint samples the reference's part is 4x smaller in
    # variance, and the build's direction noise and bias show (docs: transport build)
    Tf, _ = build(dsetup, grid, samples=16 if q else 32, pixel_samples=16, seed=9, adaptive=False)
    results["defaults"] = {}

    def relative_error(Td, Tref, mask):
        a, b = np.asarray(hj.render(Td, env))[mask], np.asarray(hj.render(Tref, env))[mask]
        return float(np.linalg.norm(a - b) / np.linalg.norm(b))

    for adaptive, sub in ((True, False), (False, False), (True, True)):
        errors, errors_fine = [], []
        for seed in range(3):  # the error of one build is itself noisy: three seeds
            Td, _ = build(dsetup, grid, seed=seed, adaptive=adaptive, sub_points=sub)
            errors.append(relative_error(Td, Tr, Td.mask & Tr.mask))
            errors_fine.append(relative_error(Td, Tf, Td.mask & Tr.mask & Tf.mask))
        _, t_default = build(setup, grid, adaptive=adaptive, sub_points=sub)
        name = build_name(adaptive, sub)
        results["defaults"][name] = dict(
            samples=hj.transport.DEFAULT_SAMPLES, pixel_samples=hj.transport.DEFAULT_PIXEL_SAMPLES, image=img_size,
            render_relrmse_vs_high_sample=float(np.mean(errors)), seeds=errors, seconds_full_size=t_default,
            render_relrmse_vs_16_footprint_samples=float(np.mean(errors_fine)), seeds_16_footprint_samples=errors_fine)
        rows.append((f"defaults S={hj.transport.DEFAULT_SAMPLES}, px={hj.transport.DEFAULT_PIXEL_SAMPLES}, {name}",
                     f"{t_default:.2f} s", f"render MC error {100 * np.mean(errors):.2f}% (3 seeds)",
                     f"{100 * np.mean(errors_fine):.3f}% against 16 footprint samples"))

    # an observed closed convex object (its own shading as the camera): nothing can shadow it, so no rays
    ball = SimpleNamespace(scene=hj.Scene([hj.Surface(hj.scenes.sphere(4), 0.8, smooth=True)]),
                           camera=hj.Camera.look_at((0, 0.5, 1.55), (0, 0.5, 0), (0, 1, 0), 40.0, size, size))
    T_ball, t_ball = build(ball, grid)
    teapot = results["defaults"][build_name(True, True)]["seconds_full_size"]
    results["convex"] = dict(pixels=int(T_ball.A.shape[0]), seconds=t_ball, teapot_seconds=teapot)
    rows.append((f"observed sphere alone, defaults ({T_ball.A.shape[0]} px)", f"{t_ball:.2f} s",
                 f"the teapot on its table: {teapot:.2f} s", f"{t_ball / teapot:.2f}x"))

    # 5. Mitsuba 3, the user's alternative, on the same scene
    mit = None if args.no_mitsuba else mitsuba_columns(
        setup, grid, T.mask, spps=(16, 64), ref_spp=256 if q else 1024, n_columns=4 if q else 24)
    results["mitsuba"] = mit if mit is not None else "not installed (pip install mitsuba): skipped"
    if mit and "per_spp" in mit:
        for spp, m in mit["per_spp"].items():
            rows.append((f"Mitsuba path, {spp} spp", f"{m['seconds_all_columns']:.1f} s",
                         f"median column err {100 * m['median_column_error']:.2f}%", "(extrapolated to all columns)"))
        target = mit["per_spp"][64]["median_column_error"]
        ok = [r for r in results["accuracy"] if r["median_column_error"] <= target]
        if ok:
            best = min(ok, key=lambda r: r["seconds"])
            speedup = mit["per_spp"][64]["seconds_all_columns"] / best["seconds"]
            results["equal_accuracy"] = dict(mitsuba_64spp_error=target, hiddenjax_samples=best["samples"],
                                             hiddenjax_pixel_samples=best["pixel_samples"],
                                             hiddenjax_seconds=best["seconds"], speedup=speedup)
            rows.append(("equal accuracy vs Mitsuba 64 spp", f"{best['seconds']:.2f} s",
                         f"S={best['samples']}, px={best['pixel_samples']}",
                         f"{speedup:.1f}x faster"))

    rows.print_all()
    (args.out / "results.json").write_text(json.dumps(results, indent=2, default=float))

    plot_accuracy(results, args.out / "accuracy_vs_time.png")
    return results


if __name__ == "__main__":
    main()
