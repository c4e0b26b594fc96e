"""One solve on several devices or processes: the transport's pixel rows sharded with JAX.

The teapot on a white plane, photographed by the independent reference renderer under the
procedural sky; `hj.transport.transport_matrix_sharded` builds `A` with its rows split over every
device of every process (each process casts only its own rows with Embree), and
`hj.solve_illumination` reduces `A^T A` and `A^T y` over them with `psum`. The same command runs
on one CPU, on several CPU devices, on a GPU, and across processes or hosts:

    python examples/distributed_solve.py [--quick] [--out DIR]          # one process, its devices
    python examples/distributed_solve.py --devices 4                    # four CPU devices
    # two processes on this machine (a loopback coordinator); on a cluster, one per host:
    python examples/distributed_solve.py --processes 2 --process-id 0 --coordinator 127.0.0.1:23456 &
    python examples/distributed_solve.py --processes 2 --process-id 1 --coordinator 127.0.0.1:23456

Process 0 writes `env.exr`, `env.npy`, `env.png` and `results.json` (devices, processes, times,
errors against the sky on the grid).
"""

import argparse
import json
import os
import time
from pathlib import Path


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path("out/distributed_solve"))
    parser.add_argument("--quick", action="store_true", help="small configuration (seconds)")
    parser.add_argument("--devices", type=int, default=None,
                        help="CPU devices in this process (XLA's --xla_force_host_platform_device_count)")
    parser.add_argument("--processes", type=int, default=1, help="processes in the run (jax.distributed)")
    parser.add_argument("--process-id", type=int, default=0, help="this process's index, 0 .. processes - 1")
    parser.add_argument("--coordinator", default="127.0.0.1:23456", help="host:port of process 0")
    parser.add_argument("--x64", action="store_true", help="solve in float64 (results equal across layouts to 1e-10)")
    parser.add_argument("--prior", default=None, help="the prior (default: solve_illumination's)")
    args = parser.parse_args(argv)
    if args.devices is not None:  # before JAX starts
        if args.devices < 1:
            parser.error(f"--devices must be >= 1, got {args.devices}")
        os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") +
                                   f" --xla_force_host_platform_device_count={args.devices}")
    if not 0 <= args.process_id < args.processes:
        parser.error(f"--process-id must be in 0 .. {args.processes - 1}, got {args.process_id}")

    import jax

    if args.processes > 1:
        jax.config.update("jax_cpu_collectives_implementation", "gloo")  # CPU collectives across processes
        jax.distributed.initialize(args.coordinator, num_processes=args.processes, process_id=args.process_id)
    if args.x64:
        jax.config.update("jax_enable_x64", True)
    import equinox as eqx
    import jax.numpy as jnp
    import numpy as np

    import hiddenjax as hj

    hj.enable_compilation_cache()  # programs compiled once per machine (docs: compilation cache)

    size, grid = (48, hj.EnvGrid(16, 32)) if args.quick else (128, hj.EnvGrid(32, 64))
    setup = hj.scenes.object_on_plane("teapot", width=size, height=size)
    sky = hj.scenes.procedural_sky(64 if args.quick else 256, 128 if args.quick else 512)
    photo = hj.reference_render(setup.scene, setup.camera, sky, samples=32 if args.quick else 256, pixel_samples=1,
                                seed=1)

    t0 = time.perf_counter()
    T = hj.transport.transport_matrix_sharded(setup.scene, setup.camera, grid, samples=8 if args.quick else 16,
                                              progress=False)
    t_build = time.perf_counter() - t0
    if args.x64:
        T = eqx.tree_at(lambda t: t.A, T, T.A.astype(jnp.float64))
    t0 = time.perf_counter()
    solution = hj.solve_illumination(T, photo, prior=args.prior)
    env = np.asarray(solution.env)
    t_solve = time.perf_counter() - t0

    if jax.process_index() == 0:
        args.out.mkdir(parents=True, exist_ok=True)
        np.save(args.out / "env.npy", env)
        hj.io.write_exr(args.out / "env.exr", env.astype(np.float32))
        hj.io.write_png(args.out / "env.png", env.astype(np.float32))
        errors = hj.metrics.env_errors(env, grid.downsample(sky))
        results = dict(
            devices=len(jax.devices()), processes=jax.process_count(), rows=int(T.A.shape[0]),
            rows_per_device=int(T.A.shape[0]) // len(jax.devices()), grid=list(grid.shape), x64=args.x64,
            build_seconds=t_build, solve_seconds=t_solve, kkt_residual=float(np.max(solution.kkt_residual)),
            errors={k: float(v) for k, v in errors.items()},
        )
        (args.out / "results.json").write_text(json.dumps(results, indent=2))
        print(json.dumps(results, indent=2))
    if args.processes > 1:
        jax.distributed.shutdown()


if __name__ == "__main__":
    main()
