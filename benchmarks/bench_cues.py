"""Cue maps: leverage for every pixel and the full uncertainty map, time and peak memory.

    python benchmarks/bench_cues.py [--quick] [--out DIR]

Problem: the teapot fixture's transport matrix (all 128x128 = 16384 pixels x 2048 directions,
float32). Baseline, in the same run: the textbook dense numpy computation
(`inv(B)`, then `rowsum((A inv(B)) * A)`), in float64, which also gives the reference values for
the float32 error. Peak memory is the growth of a fresh process's peak resident set (VmHWM) while
the computation runs a second time (after compiling), compared with the size of `A`; "eager" calls
the public functions as the guides do, "jit" compiles the whole computation as one program.
"""

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

# Child processes compute too: on a GPU the parent must not take JAX's default 75% of its memory first.
os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")

import jax
import numpy as np

import hiddenjax as hj
from _report import Table  # noqa: E402  (benchmarks/ is on sys.path when run as a script)

RIDGE = hj.solvers.DEFAULT_RIDGE


def cue_maps(T, method="cholesky"):
    """Leverage `(P,)` and uncertainty `(h, w)` from one factorization (the benchmarked computation)."""
    cues = hj.cues.LinearCues.build(T, ridge=RIDGE, method=method)
    return cues.leverage(), cues.uncertainty()


# The probe runs the computation once (compiling it), resets the peak resident set (VmHWM, via
# /proc/self/clear_refs) and runs it again: the growth is the computation's, not the compiler's.
_MEMORY_PROBE = """
import json, re, sys
import jax
sys.path.insert(0, sys.argv[2])
from bench_cues import cue_maps
import hiddenjax as hj
hwm = lambda: int(re.search(r"VmHWM:\\s+(\\d+) kB", open("/proc/self/status").read()).group(1)) * 1024
T = hj.TransportMatrix.load(sys.argv[1])
method, how = sys.argv[3], sys.argv[4]
run = (lambda T: cue_maps(T, method)) if how == "eager" else jax.jit(lambda T: cue_maps(T, method))
jax.block_until_ready(run(T))
open("/proc/self/clear_refs", "w").write("5")
base = hwm()
jax.block_until_ready(run(T))
print(json.dumps(dict(increase=hwm() - base, A=T.A.nbytes)))
"""


def peak_memory(path, method, how):
    """Growth of the peak resident set while the cue maps run (`how`: 'jit' or 'eager')."""
    out = subprocess.run([sys.executable, "-c", _MEMORY_PROBE, str(path), str(Path(__file__).parent), method, how],
                         capture_output=True, text=True, check=True)
    r = json.loads(out.stdout.strip().splitlines()[-1])
    return r["increase"], r["A"]


def dense_numpy(A, ridge):
    """The textbook computation in float64: `inv(B)`, the hat diagonal and `sqrt(diag(inv(B)))`."""
    A = A.astype(np.float64)
    B = A.T @ A
    B += ridge * np.mean(np.diag(B)) * np.eye(B.shape[0])
    Binv = np.linalg.inv(B)
    return np.einsum("ij,ij->i", A @ Binv, A), np.sqrt(np.diag(Binv))


def best_of(fn, repeats):
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = jax.block_until_ready(fn())
        times.append(time.perf_counter() - t0)
    return out, min(times)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path("out/bench_cues"))
    parser.add_argument("--quick", action="store_true")
    args = parser.parse_args(argv)
    hj.enable_compilation_cache()  # programs compiled once per machine (docs: compilation cache)
    args.out.mkdir(parents=True, exist_ok=True)
    q = args.quick
    size, grid = (48, hj.EnvGrid(8, 16)) if q else (128, hj.EnvGrid(32, 64))
    setup = hj.scenes.object_on_plane("teapot", width=size, height=size)
    # keep_occluder: the teapot's own pixels too, so all 128x128 = 16384 pixels are rows
    T = hj.transport_matrix(setup.scene, setup.camera, grid, samples=16, pixel_samples=1, keep_occluder=True,
                            progress=not q)
    P, N = T.A.shape
    rows = Table()
    results = dict(config=dict(pixels=P, directions=N, dtype="float32", ridge=RIDGE, quick=q,
                               A_MiB=T.A.nbytes / 2**20))

    (h64, u64), t_numpy = best_of(lambda: dense_numpy(np.asarray(T.A), RIDGE), 1 if not q else 2)
    maps = {}
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "A.npz"
        T.save(path)
        for method, how in (("cholesky", "eager"), ("cholesky", "jit"), ("qr", "jit")):
            run = (lambda T: cue_maps(T, method)) if how == "eager" else jax.jit(lambda T: cue_maps(T, method))
            jax.block_until_ready(run(T))  # compile
            (h, u), t_ours = best_of(lambda: run(T), 3)
            maps[method] = (np.asarray(h), np.asarray(u))
            err_h = float(np.max(np.abs(np.asarray(h) - h64)))
            err_u = float(np.max(np.abs(np.asarray(u).ravel() - u64) / u64))
            increase, a_bytes = peak_memory(path, method, how)
            results[f"{method}_{how}"] = dict(seconds=t_ours, speedup_vs_numpy=t_numpy / t_ours,
                                              max_abs_error_leverage=err_h, max_rel_error_uncertainty=err_u,
                                              peak_increase_bytes=increase, peak_increase_over_A=increase / a_bytes)
            rows.append((f"leverage + uncertainty, {method}, {how}", f"{t_ours:.2f} s",
                         f"{t_numpy / t_ours:.1f}x numpy; target < 5 s",
                         f"|dh| {err_h:.1e}, rel du {err_u:.1e}; memory +{increase / a_bytes:.2f}x A (target < 2x)"))
    results["numpy_float64_seconds"] = t_numpy
    results["A_bytes"] = a_bytes
    rows.append(("dense numpy float64 (inv, A inv(B))", f"{t_numpy:.2f} s", "reference values", ""))

    photo = hj.render(T, grid.downsample(hj.scenes.procedural_sky(64, 128)).mean(-1))
    cooks = jax.jit(lambda T, y: hj.cues.LinearCues.build(T, ridge=RIDGE).cooks_distance(y))
    jax.block_until_ready(cooks(T, photo))
    _, t_cooks = best_of(lambda: cooks(T, photo), 3)
    results["cooks_distance_seconds"] = t_cooks
    rows.append(("Cook's distance, one photo (incl. the factorization)", f"{t_cooks:.2f} s", "", ""))
    rows.print_all()
    image = lambda rows: np.asarray(T.rows_to_image(rows))
    white = max(results[f"{m}_jit"]["max_abs_error_leverage"] for m in ("cholesky", "qr"))  # one scale for both
    hj.io.contact_sheet(args.out / "bench_cues.png", [
        ("leverage", image(maps["cholesky"][0]), "map"),
        ("log10 uncertainty / min", np.log10(maps["cholesky"][1] / maps["cholesky"][1].min()), "map"),
        ("|h - h64|, refined Cholesky", image(np.abs(maps["cholesky"][0] - h64)), "map", white),
        ("|h - h64|, QR", image(np.abs(maps["qr"][0] - h64)), "map", white),
    ])
    (args.out / "results.json").write_text(json.dumps(results, indent=2))


if __name__ == "__main__":
    main()
