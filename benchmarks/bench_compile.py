"""Compiling against running: the programs a first call compiles, cold and with the persistent cache.

    python benchmarks/bench_compile.py [--quick] [--out DIR] [--cases demo,solve,...] [--baseline CHECKOUT]

Every case runs in fresh processes (nothing compiled in memory) on one new, empty cache folder:
- **cold**: the first process, empty cache: every program is compiled (what a new user meets);
- **warm**: a second process on the cache the first one filled (every later call of the
  `hiddenjax` command, an example or a benchmark);
- **run**: the same call again inside the warm process (nothing left to compile or load).
For each: the programs compiled and those loaded from the cache (`jax.monitoring`'s backend-compile
and cache-hit events), the seconds spent getting them (compiling or loading), and the call's wall
seconds. The scene is built before the
counters start (Embree's transport is not a JAX program). Cases: `demo` (`hiddenjax demo`, its
stages' seconds from its results.json), `solve` (`hj.solve_illumination`, the default prior),
`solve_many` (`IlluminationOperator.solve_many` of 8 photos), `leverage` and `uncertainty`
(`hj.cues`), `fit_lights` (one point light from a 5 cm start), `operator` (`hj.transport_operator`
and its solve). Teapot fixture: 64x64 pixels and a 16x32 grid with `--quick`, else 128x128 and
32x64 (the full `hiddenjax demo`). `--baseline CHECKOUT` runs every case a second time on another
checkout of hiddenjax (e.g. `git worktree add /tmp/base <commit>`), in the same run, and prints
the ratios. Writes `compile.png` and `results.json`.
"""

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from _report import Table  # noqa: E402  (benchmarks/ is on sys.path when run as a script)

CASES = ("demo", "solve", "solve_many", "leverage", "uncertainty", "fit_lights", "operator")

# One case in this process: prints one JSON line (compilations, compile seconds, cache loads, wall seconds).
_CHILD = r"""
import json, os, sys, time
if os.environ.get("BENCH_COMPILE_CHECKOUT"):  # the baseline: its package ahead of an editable install's finder
    sys.path.insert(0, os.environ["BENCH_COMPILE_CHECKOUT"])
    sys.meta_path[:] = [f for f in sys.meta_path if not type(f).__module__.startswith("__editable__")]
from jax import monitoring
case, quick, out = sys.argv[1], sys.argv[2] == "1", sys.argv[3]
counts = dict(compiles=0, compile_seconds=0.0, cache_hits=0)
def on_duration(name, seconds, **_):
    if name == "/jax/core/compile/backend_compile_duration":
        counts["compiles"] += 1
        counts["compile_seconds"] += seconds
def on_event(name, **_):
    if name == "/jax/compilation_cache/cache_hits":
        counts["cache_hits"] += 1
monitoring.register_event_duration_secs_listener(on_duration)
monitoring.register_event_listener(on_event)
import numpy as np
from pathlib import Path
import hiddenjax as hj
hj.enable_compilation_cache() if hasattr(hj, "enable_compilation_cache") else None  # a baseline: JAX's variables
size, grid = (64, hj.EnvGrid(16, 32)) if quick else (128, hj.EnvGrid(32, 64))
samples, pixel_samples = (8, 1) if quick else (16, 4)
if case != "demo":
    setup = hj.scenes.object_on_plane("teapot", width=size, height=size)
    fixture = Path(out).parent / f"fixture_{size}"  # built by the first case that needs it, read by the others
    if (fixture / "photo.npy").exists():
        T, photo = hj.TransportMatrix.load(fixture / "A.npz"), np.load(fixture / "photo.npy")
    else:
        T = hj.transport_matrix(setup.scene, setup.camera, grid, samples=samples, pixel_samples=pixel_samples)
        sky = hj.scenes.procedural_sky(128, 256)
        photo = np.asarray(hj.reference_render(setup.scene, setup.camera, sky, samples=64, seed=1))
        fixture.mkdir(parents=True, exist_ok=True)
        T.save(fixture / "A.npz")
        np.save(fixture / "photo.npy", photo)
if case == "demo":
    from hiddenjax.cli import demo as run_demo
    import argparse
    call = lambda: run_demo(argparse.Namespace(out=out, quick=quick, mesh="teapot", quiet=True))["seconds"]
elif case == "solve":
    call = lambda: np.asarray(hj.solve_illumination(T, photo).env)
elif case == "solve_many":
    op = hj.solvers.IlluminationOperator.build(T, prior="l2")
    photos = np.stack([photo * (0.5 + 0.1 * k) for k in range(8)])
    call = lambda: np.asarray(op.solve_many(photos).env)
elif case == "leverage":
    call = lambda: np.asarray(hj.cues.leverage(T))
elif case == "uncertainty":
    call = lambda: np.asarray(hj.cues.uncertainty(T))
elif case == "fit_lights":
    light = np.array([[0.15, 0.45, 0.1]])
    image = np.asarray(hj.render_point_lights(setup.scene, setup.camera, light, [0.05]))
    call = lambda: np.asarray(hj.shadows.fit_lights(image, setup.scene, setup.camera, light + [[0.03, 0.0, 0.04]],
                                                     polish=False).positions)
elif case == "operator":
    def call():
        op = hj.transport_operator(setup.scene, setup.camera, grid, samples=samples, pixel_samples=pixel_samples)
        return np.asarray(hj.solve_illumination(op, photo).env)
rows = []
for _ in range(2):
    for k in counts:
        counts[k] = 0
    t0 = time.perf_counter()
    value = call()
    # JAX records a backend-compile event for a program loaded from the cache too: compiled = events - loaded
    rows.append(dict(counts, compiled=counts["compiles"] - counts["cache_hits"], seconds=time.perf_counter() - t0,
                     stages=value if isinstance(value, dict) else None))
print(json.dumps(dict(rows=rows, package=str(Path(hj.__file__).parent))))
"""


def run_case(case: str, quick: bool, cache: Path, out: Path, checkout: Path | None = None) -> list[dict]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("JAX_COMPILATION_CACHE")}
    # JAX's own variables, which any version of hiddenjax honours (enable_compilation_cache keeps them)
    env.update(JAX_COMPILATION_CACHE_DIR=str(cache), JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0",
               JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES="-1")
    if checkout is not None:
        env["BENCH_COMPILE_CHECKOUT"] = str(checkout.resolve())
    done = subprocess.run([sys.executable, "-c", _CHILD, case, "1" if quick else "0", str(out)], env=env,
                          capture_output=True, text=True)
    if done.returncode:
        raise RuntimeError(f"case {case} failed:\n{done.stderr[-3000:]}")
    out = json.loads(done.stdout.strip().splitlines()[-1])
    print(f"  {case}: hiddenjax from {out['package']}", flush=True)
    return out["rows"]


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path("out/bench_compile"))
    parser.add_argument("--quick", action="store_true", help="64x64 pixels, 16x32 grid")
    parser.add_argument("--cases", default=",".join(CASES), help=f"comma-separated, of {', '.join(CASES)}")
    parser.add_argument("--baseline", type=Path, help="another checkout of hiddenjax, measured in the same run")
    args = parser.parse_args(argv)
    cases = [c for c in args.cases.split(",") if c]
    unknown = sorted(set(cases) - set(CASES))
    if unknown:
        parser.error(f"unknown cases {unknown}: choose from {', '.join(CASES)}")
    args.out.mkdir(parents=True, exist_ok=True)

    import jax

    results = dict(config=dict(quick=args.quick, cases=cases, jax=jax.__version__,
                               baseline=None if args.baseline is None else str(args.baseline),
                               platform=os.environ.get("JAX_PLATFORMS") or jax.default_backend(),
                               cores=len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()),
                   cases={})
    table = Table()
    table.append(("case", "cold: compiled / compile s / call s", "warm: loaded / compiled / call s", "run s"))
    def measure(case, checkout=None):
        with tempfile.TemporaryDirectory(prefix="hiddenjax-cache-") as cache:
            t0 = time.perf_counter()
            cold, run = run_case(case, args.quick, Path(cache), args.out / case, checkout)
            warm, _ = run_case(case, args.quick, Path(cache), args.out / case, checkout)
        return dict(cold=cold, warm=warm, run=run, bench_seconds=time.perf_counter() - t0)

    def row(name, entry):
        cold, warm, run = entry["cold"], entry["warm"], entry["run"]
        table.append((name, f"{cold['compiled']:4d} / {cold['compile_seconds']:5.2f} / {cold['seconds']:6.2f}",
                      f"{warm['cache_hits']:4d} / {warm['compiled']:3d} / {warm['seconds']:6.2f}",
                      f"{run['seconds']:6.2f}"))
        if cold["stages"]:
            stages = ", ".join(f"{k} {cold['stages'][k]:.2f} / {warm['stages'][k]:.2f} s" for k in cold["stages"])
            print(f"  {name} stages, cold / warm: {stages}", flush=True)

    for case in cases:
        results["cases"][case] = entry = measure(case)
        row(case, entry)
        if args.baseline:
            entry["baseline"] = base = measure(case, args.baseline)
            row(f"{case} (baseline)", base)
            entry["speedup"] = {k: base[k]["seconds"] / entry[k]["seconds"] for k in ("cold", "warm", "run")}
            print(f"  {case}: {', '.join(f'{k} {v:.2f}x' for k, v in entry['speedup'].items())} faster than the "
                  f"baseline", flush=True)
    table.print_all()

    fig, ax = plt.subplots(figsize=(7, 3.6))
    names = list(results["cases"])
    x = range(len(names))
    for offset, (label, key) in enumerate((("cold (empty cache)", "cold"), ("warm (persistent cache)", "warm"),
                                           ("run (compiled)", "run"))):
        ax.bar([i + (offset - 1) * 0.27 for i in x], [results["cases"][n][key]["seconds"] for n in names], 0.27,
               label=label)
    ax.set_xticks(list(x), names, rotation=20)
    ax.set_ylabel("seconds of the call")
    ax.set_title(f"first call, cached call, compiled call ({'quick' if args.quick else 'full'} fixture)")
    ax.legend()
    fig.tight_layout()
    fig.savefig(args.out / "compile.png", dpi=120)
    (args.out / "results.json").write_text(json.dumps(results, indent=2))
    print(f"wrote {args.out}/results.json and compile.png")


if __name__ == "__main__":
    main()
