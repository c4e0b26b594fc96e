"""Past one dense matrix: finer maps from one photo, matrix-free, and the solve sharded over devices and processes.

    python benchmarks/bench_scale.py [--quick] [--out DIR] [--memory 8GiB] [--grids 32x64,64x128,128x256,256x512]

Scene: the teapot fixture on its plane, a 256x256 photo (`--quick`: 64x64) from the independent
reference renderer (never `A x`) under the real panorama immenstadter_horn (a clear sky whose
small sun holds 17% of the light), at 512x256 (`data_fixtures/hdri/immenstadter_horn_512.hdr`).
For each grid, in a process of its own (so its peak memory is its own): the matrix-free
`hj.transport_operator` (one footprint sample per pixel; directions per env pixel so that the
density of directions is 16 per 32x64 cell down to one per cell), then `hj.solve_illumination`
with the default prior (the exact solve when `16 N^2` bytes fit `--memory`, else the matrix-free
projected Newton-CG from the 32x64 solution). Quality against the truth on the finest grid
(each map spread over its cells): `env_errors` over the upper hemisphere, the sun's direction
(the brightest cell's centre against the panorama's sun) and the power within 3 degrees of it.
Each grid also times one `A^T (A x)` of an RGB map where the operator's products run, and on an
accelerator with scipy's CPU products as well.
Beside them, in the same run: the dense `transport_matrix` and its solve where it fits, and the
sharded solve (`examples/distributed_solve.py`, 128x128, 32x64) on 1 and 4 CPU devices and in 2
processes. Writes `scale.png` (the maps) and `results.json`.
"""

import argparse
import json
import os
import resource
import socket
import subprocess
import sys
import time
from pathlib import Path

# Child processes compute too: on a GPU the parent must not take JAX's default 75% of its memory first.
os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")

import numpy as np

HERE = Path(__file__).resolve().parent
PANORAMA = HERE.parent / "data_fixtures" / "hdri" / "immenstadter_horn_512.hdr"
FINEST = (256, 512)


def parse_grid(text):
    h, w = (int(v) for v in text.lower().split("x"))
    return h, w


def peak_gib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20  # kilobytes on Linux


def one(args):
    """One grid in this process: build, solve, score; prints a JSON line."""
    import jax

    import hiddenjax as hj

    hj.enable_compilation_cache()

    h, w = parse_grid(args.one)
    grid = hj.EnvGrid(h, w)
    photo = np.load(args.out / "photo.npy")
    size = photo.shape[0]
    setup = hj.scenes.object_on_plane("teapot", width=size, height=size)
    samples = max(1, 16 * 2048 // grid.size)
    t0 = time.perf_counter()
    if args.dense:
        T = hj.transport_matrix(setup.scene, setup.camera, grid, samples=samples, pixel_samples=1, progress=False,
                                max_bytes=args.memory)
        held = T.A.nbytes
    else:
        T = hj.transport_operator(setup.scene, setup.camera, grid, samples=samples, pixel_samples=1, progress=False,
                                  memory=args.memory, products=args.products)
        held = T.nbytes
    build = time.perf_counter() - t0
    build_peak = peak_gib()
    products = {} if args.dense else product_seconds(T)
    t0 = time.perf_counter()
    sol = hj.solve_illumination(T, photo, throw=False)
    env = np.asarray(sol.env)
    solve = time.perf_counter() - t0
    np.save(args.out / f"env_{h}x{w}{'_dense' if args.dense else ''}.npy", env)
    exact = args.dense or hj.solvers._solve.fits_normal_matrix((T,))
    print(json.dumps(dict(grid=[h, w], dense=args.dense, exact_solve=bool(exact), pixels=int(T.shape[0]),
                          samples=samples, build_seconds=build, solve_seconds=solve, held_gib=held / 2**30,
                          build_peak_gib=build_peak, peak_gib=peak_gib(), kkt_residual=float(np.max(sol.kkt_residual)),
                          products=getattr(T, "products", "dense"), product_seconds=products,
                          platform=jax.default_backend(),
                          steps=int(np.max(sol.steps)))))


def product_seconds(T, repeats: int = 3) -> dict:
    """Seconds of one `A^T (A x)` with an RGB `x` (a matrix-free solve's step is one per CG
    iteration), best of `repeats`, where the operator's sparse products run (`T.products`) and, on an
    accelerator, also with scipy's on the CPU: the same operator, its `products` switched for the timing."""
    import jax

    x = np.random.default_rng(0).random((T.grid.size, 3))
    chosen, seconds = T.products, {}
    for where in dict.fromkeys([chosen] + (["cpu"] if jax.default_backend() != "cpu" else [])):
        T.products = where
        np.asarray(T.rmatvec(np.asarray(T.matvec(x))))  # the device rows made and the program compiled
        times = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            np.asarray(T.rmatvec(np.asarray(T.matvec(x))))
            times.append(time.perf_counter() - t0)
        seconds[where] = min(times)
    T.products = chosen
    return seconds


def score(env, truth_fine, sun):
    """Metrics of a map spread over the finest grid against the truth there."""
    import hiddenjax as hj

    fh, fw = truth_fine.shape[0] // env.shape[0], truth_fine.shape[1] // env.shape[1]
    fine = np.repeat(np.repeat(env, fh, axis=0), fw, axis=1)
    errors = {k: float(v) for k, v in hj.metrics.env_errors(fine, truth_fine).items()}
    grid = hj.EnvGrid(*env.shape[:2])
    lum = env.mean(axis=-1)
    top = np.unravel_index(np.argmax(lum[: grid.height // 2]), lum.shape)
    found = grid.directions()[top]
    finest = hj.EnvGrid(*truth_fine.shape[:2])
    near = np.degrees(np.arccos(np.clip(finest.directions() @ sun, -1, 1))) <= 3.0
    omega = finest.solid_angles()
    power = lambda m: float(np.sum(m.mean(axis=-1)[near] * omega[near]))
    s = errors["scale"]  # the least-squares scale of env_errors: the estimate's power in the truth's units
    return errors | dict(sun_error_deg=float(np.degrees(np.arccos(np.clip(found @ sun, -1, 1)))),
                         sun_power_ratio=s * power(fine) / power(truth_fine))


def distributed(out: Path, extra, processes=1) -> dict:
    script = HERE.parent / "examples" / "distributed_solve.py"
    command = [sys.executable, str(script), "--out", str(out), *extra]
    t0 = time.perf_counter()
    if processes > 1:
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            port = s.getsockname()[1]
        command += ["--processes", str(processes), "--coordinator", f"127.0.0.1:{port}"]
        runs = [subprocess.Popen(command + ["--process-id", str(k)], stdout=subprocess.DEVNULL,
                                 stderr=subprocess.DEVNULL) for k in range(processes)]
        if any(r.wait() for r in runs):
            raise RuntimeError(f"{command} failed")
    else:
        subprocess.run(command, check=True, capture_output=True)
    return json.loads((out / "results.json").read_text()) | dict(wall_seconds=time.perf_counter() - t0)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path("out/bench_scale"))
    parser.add_argument("--quick", action="store_true", help="a 64x64 photo, 8x16 and 16x32 grids")
    parser.add_argument("--memory", default="8GiB", help="the memory budget of every build and solve")
    parser.add_argument("--grids", default=None, help="comma-separated HxW grids (default 32x64 .. 256x512)")
    parser.add_argument("--skip", default="", help="comma-separated parts to leave out: layouts, dense")
    parser.add_argument("--products", default="auto", choices=("auto", "cpu", "device"),
                        help="where the operator's sparse products run (transport_operator's products=)")
    parser.add_argument("--one", help=argparse.SUPPRESS)
    parser.add_argument("--dense", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    if args.one:
        return one(args)

    import hiddenjax as hj

    hj.enable_compilation_cache()  # programs compiled once per machine (docs: compilation cache)

    grids = [parse_grid(g) for g in (args.grids or ("8x16,16x32" if args.quick else
                                                     "32x64,64x128,128x256,256x512")).split(",")]
    size = 64 if args.quick else 256
    panorama = hj.io.read_image(PANORAMA)
    setup = hj.scenes.object_on_plane("teapot", width=size, height=size)
    t0 = time.perf_counter()
    photo = np.asarray(hj.reference_render(setup.scene, setup.camera, panorama, samples=64 if args.quick else 256,
                                           pixel_samples=1 if args.quick else 2, seed=1))
    print(f"photo {size}x{size} from the reference renderer: {time.perf_counter() - t0:.0f} s", flush=True)
    np.save(args.out / "photo.npy", photo)
    finest = hj.EnvGrid(*(grids[-1] if args.quick else FINEST))
    truth_fine = finest.downsample(panorama)
    lum = truth_fine.mean(axis=-1) * finest.solid_angles()
    sun = finest.directions()[np.unravel_index(np.argmax(lum), lum.shape)]

    results = dict(photo=[size, size], memory=args.memory)

    def save(**parts):  # after every run, so a long study keeps what it measured
        results.update(parts)
        (args.out / "results.json").write_text(json.dumps(results, indent=2))

    layouts = []
    extra = ["--quick"] if args.quick else []
    skip = set(filter(None, args.skip.split(",")))
    for name, options, processes in () if "layouts" in skip else (
            ("1 device", [], 1), ("4 CPU devices", ["--devices", "4"], 1), ("2 processes", [], 2)):
        result = distributed(args.out / name.replace(" ", "_"), extra + options, processes)
        layouts.append(dict(layout=name) | result)
    for layout in layouts:
        base = np.load(args.out / "1_device" / "env.npy")
        env = np.load(args.out / layout["layout"].replace(" ", "_") / "env.npy")
        layout["relative_difference"] = float(np.linalg.norm(env - base) / np.linalg.norm(base))
        layout["seconds_vs_1_device"] = (layout["build_seconds"] + layout["solve_seconds"]) / (
            layouts[0]["build_seconds"] + layouts[0]["solve_seconds"])
        print(f"{layout['layout']:14s} build {layout['build_seconds']:6.1f} s  solve {layout['solve_seconds']:6.1f} s"
              f"  x{layout['seconds_vs_1_device']:.2f} of 1 device  map vs 1 device {layout['relative_difference']:.1e}",
              flush=True)
    save(layouts=layouts)

    runs = []
    plan = [(g, dense) for k, g in enumerate(grids)
            for dense in ((False, True) if k < 2 and "dense" not in skip else (False,))]
    for (h, w), dense in plan:
        command = [sys.executable, __file__, "--out", str(args.out), "--one", f"{h}x{w}", "--memory", args.memory,
                   "--products", args.products]
        done = subprocess.run(command + (["--dense"] if dense else []), capture_output=True, text=True)
        if done.returncode:
            print(f"{h}x{w}{' dense' if dense else ''} failed:\n{done.stderr[-2000:]}", flush=True)
            runs.append(dict(grid=[h, w], dense=dense, failed=done.stderr.strip().splitlines()[-1]))
            continue
        run = json.loads(done.stdout.strip().splitlines()[-1])
        env = np.load(args.out / f"env_{h}x{w}{'_dense' if dense else ''}.npy")
        run |= score(env, truth_fine, sun)
        runs.append(run)
        print(f"{h}x{w} {'dense' if dense else 'operator':8s} build {run['build_seconds']:7.1f} s  solve "
              f"{run['solve_seconds']:7.1f} s ({'exact' if run['exact_solve'] else 'matrix-free'}, KKT "
              f"{run['kkt_residual']:.1e}, {run['steps']} steps)  A^T A x "
              + ", ".join(f"{v:.3f} s ({k})" for k, v in run.get("product_seconds", {}).items())
              + f"  held {run['held_gib']:.2f} GiB  peak {run['peak_gib']:.2f} GiB "
              f"(build {run['build_peak_gib']:.2f})  "
              f"tone-mapped SSIM {run['ssim_tm']:.3f}  SSIM {run['ssim']:.3f}  relRMSE {run['relrmse']:.3f}  "
              f"sun {run['sun_error_deg']:.2f} deg, power x{run['sun_power_ratio']:.2f}", flush=True)
        save(runs=runs)
        _picture(args.out, runs, truth_fine)


def _picture(out, runs, truth_fine):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    shown = [r for r in runs if not r.get("failed") and not r["dense"]]
    fig, axes = plt.subplots(1, len(shown) + 1, figsize=(3.2 * (len(shown) + 1), 2.2))
    scale = float(truth_fine[: truth_fine.shape[0] // 2].mean())
    tone = lambda m: np.clip((m / scale) / (1 + m / scale), 0, 1)
    for ax, r in zip(axes, shown):
        env = np.load(out / f"env_{r['grid'][0]}x{r['grid'][1]}.npy") * r["scale"]
        ax.imshow(tone(env[: env.shape[0] // 2]), interpolation="nearest")
        ax.set_title(f"{r['grid'][0]}x{r['grid'][1]}: SSIM-tm {r['ssim_tm']:.2f}", fontsize=8)
    axes[-1].imshow(tone(truth_fine[: truth_fine.shape[0] // 2]), interpolation="nearest")
    axes[-1].set_title("truth (upper hemisphere)", fontsize=8)
    for ax in axes:
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(out / "scale.png", dpi=120)


if __name__ == "__main__":
    main()
