"""Sigmoid shadow volumes: value and gradient w.r.t. the light position, time and peak memory.

    python benchmarks/bench_shadows.py [--quick] [--out DIR]

Problem (issue 4): a ~5k-triangle teapot (0.3 m) on a plane, 128x128 pixels, one point light;
`value_and_grad` of the summed shaded image with culled sigmoid shadow volumes, jitted, at several
temperatures (1/m). Baselines in the same run: the dense (unculled, chunked) evaluation, and raw
Embree hard-shadow rendering of the same image. Scaling in triangles and lights at T = 1000.
The differentiable transport matrix `A(theta)` (`SoftTransport`, 32x32 pixels, 8x16 grid, 4
directions per env pixel) and its forward derivative in the object's position, against
Embree's `transport_matrix` with the same sample counts.
Peak memory: growth of the process's peak resident set (VmHWM, reset before each timed run).
"""

import argparse
import json
import re
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import matplotlib
import numpy as np

import hiddenjax as hj
from _report import Table, finish_plot  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

LIGHT = np.array([0.3, 0.6, 0.2])


def _peak_mb():
    Path("/proc/self/clear_refs").write_text("5")
    return lambda: int(re.search(r"VmHWM:\s+(\d+)", Path("/proc/self/status").read_text()).group(1)) / 1024


def _rss_mb():
    return int(re.search(r"VmRSS:\s+(\d+)", Path("/proc/self/status").read_text()).group(1)) / 1024


def timed(fn, *args, repeat=3):
    jax.block_until_ready(fn(*args))  # compile
    base = _rss_mb()
    peak = _peak_mb()
    t = time.perf_counter()
    for _ in range(repeat):
        out = jax.block_until_ready(fn(*args))
    return (time.perf_counter() - t) / repeat, max(0.0, peak() - base), out


def setup(sections, size):
    scene, cam = hj.scenes.object_on_plane(hj.scenes.teapot(sections), size=0.3, width=size, height=size)
    return scene, cam, hj.shadows.ShadowScene.from_scene(scene, cam)


def objective(shadows, T, dense=False):
    tri = jnp.asarray(np.asarray(shadows.occluder.triangles).reshape(-1, 3, 3))

    def f(light):
        if dense:
            v = hj.shadows.soft_visibility(shadows.points, tri, light, T)
            return jnp.sum(hj.shadows.shading(shadows.points, shadows.normals, shadows.albedo, light) * v)
        return jnp.sum(hj.shadows.light_images(shadows, light[None], T))

    return jax.jit(jax.value_and_grad(f))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=Path("out/bench_shadows"))
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args(argv)
    hj.enable_compilation_cache()  # programs compiled once per machine (docs: compilation cache)
    args.out.mkdir(parents=True, exist_ok=True)
    size, sections = (48, 32) if args.quick else (128, 80)
    scene, cam, shadows = setup(sections, size)
    F = sum(len(s.triangles) for s in scene[1:])
    light = jnp.asarray(LIGHT, jnp.float32)
    table = Table()
    table.append(("case", "time (s)", "peak growth (MB)", "vs Embree hard render"))
    t = time.perf_counter()
    hard = hj.render_point_lights(scene, cam, LIGHT[None], pixel_samples=1)
    t_embree = time.perf_counter() - t
    table.append((f"Embree hard render, {size}x{size}, {F} tris", f"{t_embree:.3f}", "-", "1.0x"))
    results = dict(pixels=int(shadows.points.shape[0]), triangles=F, embree_s=t_embree, culled={}, scaling={})
    for T in (100.0, 300.0, 1000.0, 3000.0):
        s, mb, _ = timed(objective(shadows, T), light)
        results["culled"][T] = dict(seconds=s, peak_mb=mb)
        table.append((f"culled value+grad, T={T:g}", f"{s:.3f}", f"{mb:.0f}", f"{s / t_embree:.1f}x"))
    s, mb, _ = timed(objective(shadows, 1000.0, dense=True), light, repeat=1)
    results["dense_T1000"] = dict(seconds=s, peak_mb=mb)
    table.append(("dense value+grad, T=1000", f"{s:.3f}", f"{mb:.0f}", f"{s / t_embree:.1f}x"))
    for sec in ((16, 32) if args.quick else (32, 64, 80, 128)):
        _, _, sh_k = setup(sec, size)
        Fk = int(np.sum(np.any(np.asarray(sh_k.occluder.triangles) != 0, axis=(2, 3)))) - 2
        s, mb, _ = timed(objective(sh_k, 1000.0), light)
        results["scaling"][f"triangles={Fk}"] = dict(seconds=s, peak_mb=mb)
        table.append((f"culled, T=1000, {Fk} tris", f"{s:.3f}", f"{mb:.0f}", "-"))
    lights = jnp.asarray(LIGHT + np.random.default_rng(0).normal(0, 0.1, (4, 3)), jnp.float32)
    multi = jax.jit(jax.value_and_grad(lambda l: jnp.sum(hj.shadows.light_images(shadows, l, 1000.0))))
    s, mb, _ = timed(multi, lights)
    results["scaling"]["lights=4"] = dict(seconds=s, peak_mb=mb)
    table.append(("culled, T=1000, 4 lights", f"{s:.3f}", f"{mb:.0f}", "-"))

    px, grid = (16, hj.EnvGrid(4, 8)) if args.quick else (32, hj.EnvGrid(8, 16))
    scene_a, cam_a = hj.scenes.object_on_plane(hj.scenes.teapot(sections), size=0.3, width=px, height=px)
    t = time.perf_counter()
    hj.transport_matrix(scene_a, cam_a, grid, samples=4, pixel_samples=1, progress=False)
    t_a = time.perf_counter() - t
    table.append((f"Embree transport_matrix, {px}x{px}, {grid.height}x{grid.width} grid, 4 dirs", f"{t_a:.3f}", "-",
                  "baseline for A"))
    st = hj.shadows.SoftTransport.from_scene(scene_a, cam_a, grid, samples=4)
    soft_a = jax.jit(lambda t: st.matrix(st.occluder.map_vertices(lambda v: v + t, surface=1), 1000.0))
    zero, step = jnp.zeros(3), jnp.array([1.0, 0.0, 0.0])
    s, mb, _ = timed(soft_a, zero, repeat=1)
    results["soft_transport"] = dict(pixels=px, grid=list(grid.shape), embree_s=t_a, matrix_s=s, matrix_peak_mb=mb)
    table.append(("SoftTransport.matrix, T=1000", f"{s:.3f}", f"{mb:.0f}", f"{s / t_a:.0f}x Embree A"))
    s, mb, _ = timed(jax.jit(lambda t, d: jax.jvp(soft_a, (t,), (d,))), zero, step, repeat=1)
    results["soft_transport"].update(jvp_s=s, jvp_peak_mb=mb)
    table.append(("SoftTransport.matrix + jvp (pose), T=1000", f"{s:.3f}", f"{mb:.0f}", f"{s / t_a:.0f}x Embree A"))
    table.print_all()

    images = [hard] + [np.asarray(hj.shadows.render_lights(shadows, LIGHT[None], temperature=T)) for T in (100.0, 1000.0)]
    titles = ["Embree hard", "sigmoid T=100", "sigmoid T=1000"]
    hj.io.contact_sheet(args.out / "shadows.png", [(t, i / hard.max()) for t, i in zip(titles, images)])
    fig, ax = plt.subplots(figsize=(5, 3.5))
    Ts = sorted(results["culled"])
    ax.loglog(Ts, [results["culled"][T]["seconds"] for T in Ts], "o-", label="culled value+grad")
    ax.axhline(t_embree, color="k", ls="--", label="Embree hard render")
    finish_plot(fig, ax, args.out / "temperature.png", "temperature T (1/m)", "seconds", f"{size}x{size}, {F} triangles")
    (args.out / "results.json").write_text(json.dumps(results, indent=2, default=str))


if __name__ == "__main__":
    main()
