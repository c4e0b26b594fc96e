import os
import shutil
from pathlib import Path

os.environ.setdefault("JAX_PLATFORMS", "cpu")
# One compilation cache for the whole run (JAX's persistent cache, keyed by the program, the compile
# options and the jax/jaxlib version): compiling is most of the suite's time on a CPU, and with it the
# xdist workers, the scripts, the CLI runs and the pages they start compile each program once. It
# lives in .pytest_cache, so a second run of the suite compiles almost nothing. Set by the environment
# before jax is imported, the scripts and commands the tests start inherit it.
OWN_CACHE = "JAX_COMPILATION_CACHE_DIR" not in os.environ  # a cache of the user's own is left as it is
COMPILATION_CACHE = Path(os.environ.setdefault(
    "JAX_COMPILATION_CACHE_DIR", str(Path(__file__).resolve().parents[1] / ".pytest_cache" / "jax")))
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0")
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES", "-1")
# No maximum size (JAX's default): with one, JAX lists every entry on each write, and the suite writes about 3000
# (2 cores: 9.5 minutes instead of 10.5). The workers and scripts fill the cache at once; an entry read while
# another process writes it is a warning and a compile (hiddenjax/_compilation_cache.py), and past 1 GiB the run
# that starts the workers clears it (`pytest_configure`).

import jax
import numpy as np
import pytest

import hiddenjax as hj
from hiddenjax.transport._embree import RayCaster

jax.config.update("jax_numpy_rank_promotion", "raise")

# hiddenjax's own programs compile with `hj.COMPILER_OPTIONS`: on jaxlib 0.10, the CPU's earlier fusion
# emitters. The tests' own programs and their array glue get them too (XLA reads XLA_FLAGS at its first
# compile, and the scripts and commands the tests start inherit it), and so do the sigmoid shadows' programs
# that run long (`runs_long`), which leave the emitters to XLA: briefly run here, they are faster compiled
# so. 2 cores, cold cache: the suite took 9.4 minutes and 955 CPU-seconds, against 11.0 and 1240 with
# XLA's default emitters and LLVM's optimizations off (10.0 and 1014 with the default emitters for the
# sigmoid shadows). Every program compiles optimized, as users' programs do: with LLVM's optimizations off,
# the earlier emitters computed one of the sunsky prior's programs wrongly.
_cpu_flags = [f"--{k}={str(v).lower()}" for k, v in hj.COMPILER_OPTIONS.items()
              if k.startswith("xla_cpu_") and k not in os.environ.get("XLA_FLAGS", "")]  # a caller's own choice stays
if _cpu_flags:
    os.environ["XLA_FLAGS"] = " ".join([os.environ.get("XLA_FLAGS", ""), *_cpu_flags]).strip()


def pytest_xdist_auto_num_workers(config):
    """`-n auto`: one worker per core, as memory allows (about 6 GiB a worker at its peak).

    A worker is busier than one core: XLA's runtime runs a program's operations on threads of its
    own. Once compiling is no longer half of a cold run, a worker beyond the cores does not pay for
    itself (2 cores, cold cache, XLA's default emitters unoptimized: 11.0 minutes and 1240
    CPU-seconds with 2 workers, 12.3 minutes and 1415 with 3). `PYTEST_XDIST_AUTO_NUM_WORKERS`
    still overrides it.
    """
    if os.environ.get("PYTEST_XDIST_AUTO_NUM_WORKERS"):
        return int(os.environ["PYTEST_XDIST_AUTO_NUM_WORKERS"])
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    try:
        memory = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**30
    except (ValueError, OSError, AttributeError):
        return cores
    return max(1, min(cores, int(memory // 6)))


def pytest_configure(config):
    """The cache only grows (each code change adds programs): the run that starts the workers clears it past 1 GiB."""
    if OWN_CACHE and not hasattr(config, "workerinput") and COMPILATION_CACHE.is_dir():
        size = sum(f.stat().st_size for f in COMPILATION_CACHE.iterdir() if f.is_file())
        if size > 1 << 30:
            shutil.rmtree(COMPILATION_CACHE, ignore_errors=True)


@pytest.fixture(autouse=True)
def _no_program_store():
    """Each test starts with hiddenjax's traced-program store off (`enable_compilation_cache`, which a command
    run in the process calls, turns it on): what a test traces, or counts, does not depend on the tests before
    it. The scripts and commands it starts keep theirs."""
    from hiddenjax import _program_store

    _program_store.enable(None)
    yield


@pytest.fixture
def getkey():
    keys = iter(jax.random.split(jax.random.key(0), 1000))
    return lambda: next(keys)


@pytest.fixture(scope="session")
def small_setup():
    """Teapot on a plane, 48x48 pixels: small enough for many builds per test run."""
    return hj.scenes.object_on_plane("teapot", width=48, height=48)


@pytest.fixture(scope="session")
def plane_only(small_setup):
    """The same camera over the plane alone: nothing can occlude."""
    return hj.Scene([small_setup.scene[0]]), small_setup.camera


def coarse_teapot():
    """The teapot's shape in 308 faces (the soft model's cost is per triangle), for fast soft-shadow tests."""
    return hj.scenes.teapot(12, rings=8, parts=6)


def relrmse(a, b):
    return float(np.linalg.norm(np.asarray(a) - np.asarray(b)) / np.linalg.norm(np.asarray(b)))


def hard_on_the_same_samples(scene, st):
    """The estimator of `SoftTransport.matrix` with Embree's hard visibility on the same directions."""
    x = np.asarray(st.points(), np.float64)
    W = np.asarray(st.directions, np.float64)
    (J, K, _), Q = W.shape, len(x)
    V = ~RayCaster(scene).occluded(np.repeat(x, J * K, axis=0), np.tile(W.reshape(-1, 3), (Q, 1))).reshape(Q, J, K)
    cos = np.einsum("qc,jkc->qjk", np.asarray(st.normals, np.float64), W)
    scale = np.asarray(st.omega)[None, :] / K
    E = np.where(st.above, np.asarray(st.closed) - scale * np.sum((1 - V) * cos, -1),
                 np.where(st.straddle, scale * np.sum(V * np.maximum(cos, 0), -1), 0.0))
    A = np.zeros((Q, st.grid.size))
    A[:, np.asarray(st.columns)] = np.asarray(st.albedo)[:, None] / np.pi * E
    return A
