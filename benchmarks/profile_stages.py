"""Where the demo's solve and cue stages spend their time on this platform: compile, run, and the kernels.

    python benchmarks/profile_stages.py [--quick] [--out DIR]

The demo's fixture (the teapot, 128x128 pixels, 32x64 grid, `samples=16, pixel_samples=4`;
`--quick`: 64x64, 16x32, 8 and 1) and a photo from the independent renderer. For each stage
(`IlluminationOperator.build(T).solve(photo)`, then the cue maps `LinearCues.build(T)` with
`leverage`, `uncertainty`, `cooks_distance`): the first call (tracing, compiling or loading from
the cache, running), then the best of three further calls, then one more call under
`jax.profiler.trace`, whose device events are summed by name: the kernels that take the time,
how many were launched, and the host-device copies. Run it with `JAX_PLATFORMS=cuda,cpu` for the
GPU and `JAX_PLATFORMS=cpu` for the CPU (`benchmarks/run_gpu.sh` runs both). Writes
`results.json` and `profile.png` and prints the tables.
"""

import argparse
import json
import os
import tempfile
import time
from collections import defaultdict
from pathlib import Path

os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")

import jax
import numpy as np

import hiddenjax as hj
from hiddenjax import cues
from hiddenjax.solvers import IlluminationOperator


def stages(T, photo):
    grey = photo.mean(axis=-1)

    def solve():
        return np.asarray(IlluminationOperator.build(T).solve(photo).env)

    def cue_maps():
        linear = cues.LinearCues.build(T)
        return [np.asarray(m) for m in (linear.leverage(), linear.uncertainty(), linear.cooks_distance(grey))]

    return dict(solve=solve, cues=cue_maps)


def device_events(folder: Path, top: int = 12) -> dict:
    """Sum the profiler's events by name, per device (or the CPU client's threads on the CPU platform).

    `{plane: {part: {busy_ms, events, copies, top: [(name, ms, count)]}}}` with the parts `kernels`
    (a GPU's stream lines, or the CPU client's operations) and `modules` (the programs that ran).
    """
    from jax.profiler import ProfileData

    def summary(totals, counts):
        ranked = sorted(totals, key=totals.get, reverse=True)
        copies = sum(c for n, c in counts.items() if "memcpy" in n.lower())
        return dict(busy_ms=round(sum(totals.values()), 2), events=sum(counts.values()), copies=copies,
                    top=[(n[:100], round(totals[n], 3), counts[n]) for n in ranked[:top]])

    out = {}
    for path in folder.rglob("*.xplane.pb"):
        for plane in ProfileData.from_file(str(path)).planes:
            gpu = plane.name.startswith("/device:")
            if not gpu and plane.name != "/host:CPU":
                continue
            parts = {"kernels": (defaultdict(float), defaultdict(int)), "modules": (defaultdict(float), defaultdict(int))}
            for line in plane.lines:
                name = line.name
                part = ("kernels" if name.startswith("Stream") else "modules" if name == "XLA Modules" else None) \
                    if gpu else ("kernels" if "PjRtCpuClient" in name else None)
                if part is None:
                    continue
                totals, counts = parts[part]
                for event in line.events:
                    if event.name.startswith(("ThreadpoolListener", "SlinkyThreadPool", "end: ", "ThunkExecutor")):  # containers
                        continue
                    totals[event.name] += event.duration_ns / 1e6
                    counts[event.name] += 1
            out[plane.name] = {part: summary(*tc) for part, tc in parts.items() if tc[0]}
    return out


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path("out/profile_stages"))
    parser.add_argument("--quick", action="store_true", help="64x64 pixels, 16x32 grid")
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    hj.enable_compilation_cache()

    size, grid = (64, hj.EnvGrid(16, 32)) if args.quick else (128, hj.EnvGrid(32, 64))
    samples, pixel_samples = (8, 1) if args.quick else (16, 4)
    setup = hj.scenes.object_on_plane("teapot", width=size, height=size)
    T = hj.transport_matrix(setup.scene, setup.camera, grid, samples=samples, pixel_samples=pixel_samples)
    sky = hj.scenes.procedural_sky(128, 256)
    photo = np.asarray(hj.reference_render(setup.scene, setup.camera, sky, samples=64, seed=1))
    results = dict(platform=jax.default_backend(), devices=[str(d) for d in jax.devices()], quick=args.quick,
                   jax=jax.__version__, stages={})
    print(f"platform {results['platform']}: {results['devices']}", flush=True)
    for name, call in stages(T, photo).items():
        t0 = time.perf_counter()
        call()
        first = time.perf_counter() - t0
        runs = []
        for _ in range(3):
            t0 = time.perf_counter()
            call()
            runs.append(time.perf_counter() - t0)
        with tempfile.TemporaryDirectory() as folder:
            with jax.profiler.trace(folder):
                call()
            events = device_events(Path(folder))
        results["stages"][name] = dict(first_seconds=round(first, 3), run_seconds=round(min(runs), 4), devices=events)
        print(f"{name}: first call {first:.2f} s, then {min(runs):.3f} s", flush=True)
        for plane, parts in events.items():
            for part, summary in parts.items():
                print(f"  {plane} {part}: {summary['busy_ms']:.1f} ms busy in {summary['events']} events "
                      f"({summary['copies']} copies)", flush=True)
                for kernel, ms, count in summary["top"]:
                    print(f"    {ms:9.3f} ms  x{count:<6d} {kernel}", flush=True)
    (args.out / "results.json").write_text(json.dumps(results, indent=1))
    _picture(args.out, results)


def _picture(out: Path, results: dict) -> None:
    """`profile.png`: per stage, the kernels (or CPU operations) that take the time, in milliseconds."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    stages = results["stages"]
    fig, axes = plt.subplots(1, len(stages), figsize=(6.5 * len(stages), 3.6))
    for ax, (name, stage) in zip(np.atleast_1d(axes), stages.items()):
        parts = next(iter(stage["devices"].values()), {})
        top = parts.get("kernels", {}).get("top", [])[:8][::-1]
        ax.barh([k[:40] for k, _, _ in top], [ms for _, ms, _ in top], color="tab:blue")
        ax.set_xlabel("milliseconds in one compiled call")
        ax.set_title(f"{name} on {results['platform']}: first call {stage['first_seconds']:.2f} s, "
                     f"then {stage['run_seconds']:.3f} s", fontsize=9)
        ax.tick_params(axis="y", labelsize=7)
    fig.tight_layout()
    fig.savefig(out / "profile.png", dpi=110)


if __name__ == "__main__":
    main()
