"""`jit` and `filter_jit` for hiddenjax's own programs: `jax.jit` and `eqx.filter_jit` with its compiler options.

On a GPU, XLA by default writes each matrix product as a Triton kernel and tunes it by compiling
and timing dozens of tile configurations against cuBLAS. hiddenjax's programs hold many products
of a few fixed shapes (row blocks of `A`, Gram matrices, triangular solves), and that tuning was
nearly all of their compile time: on one H100, with `xla_gpu_enable_triton_gemm` off, the cue
maps' first call fell from 32.4 s to 2.2 s (leverage) and 20.8 s to 2.2 s (uncertainty), and the
default solve's from 13.9 s to 4.3 s, while the compiled calls ran as fast as before (0.03,
0.02 and 0.10 s: cuBLAS serves these products as well). The option is a per-program compile
option, so it touches only hiddenjax's programs, never JAX's configuration or a user's own
`jax.jit`; the CPU backend ignores it. Called inside a user's `jax.jit`, hiddenjax's functions
are traced into that program and compiled with the user's options
(`jax.jit(f, compiler_options=hj.COMPILER_OPTIONS)` gives them the same).

On a CPU, jaxlib 0.10's XLA writes each fusion through its MLIR fusion emitters; its earlier
emitters (`xla_cpu_use_fusion_emitters` off) compile hiddenjax's programs in 0.6-0.8 of the time
and run the solvers and cue maps as fast, with the same maps (2 cores, cold cache: the default
solve's first call 3.8 -> 2.4 s, the demo's 5.4 -> 4.4 s; `benchmarks/bench_compile.py`). The
sigmoid shadows' programs run long, over many triangles, and the newer emitters' code runs them
about 10% faster (a light fit's compiled call 13.7 s against 15.1 s): `jit(..., runs_long=True)`
leaves the emitters to XLA for them (its default, or what `XLA_FLAGS` chooses). The option is set
only on the jaxlib line where it was measured: a name a jaxlib does not know is an error, not a
warning.
"""

import functools

import equinox as eqx
import jax
import jaxlib
import numpy as np

from . import _program_store


def _jaxlib_line() -> tuple[int, int]:
    major, minor = (jaxlib.__version__.split(".") + ["0"])[:2]
    return int(major), int(minor)


_CPU_EMITTERS = {"xla_cpu_use_fusion_emitters": False} if _jaxlib_line() == (0, 10) else {}
COMPILER_OPTIONS = {"xla_gpu_enable_triton_gemm": False} | _CPU_EMITTERS
"""The compile options of hiddenjax's own programs: XLA's Triton GEMM tuning off on GPUs (ignored on CPUs),
and on jaxlib 0.10 the CPU's earlier fusion emitters (ignored on GPUs)."""
_RUNS_LONG_OPTIONS = {k: v for k, v in COMPILER_OPTIONS.items() if k not in _CPU_EMITTERS}


def jit(fun=None, *, runs_long: bool = False, **kwargs):
    """`jax.jit(fun, **kwargs)` with `COMPILER_OPTIONS`; also a decorator factory (`jit(static_argnums=0)`).

    `runs_long`: a program whose running, not its compiling, is its cost (the sigmoid shadows):
    the CPU's fusion emitters are left to XLA, its default or `XLA_FLAGS` (module doc).
    """
    if fun is None:
        return lambda f: jit(f, runs_long=runs_long, **kwargs)
    return _top_level_options(jax.jit, fun, kwargs, runs_long)


def filter_jit(fun=None, *, runs_long: bool = False, **kwargs):
    """`eqx.filter_jit(fun, **kwargs)` with `COMPILER_OPTIONS`; also a decorator factory; `runs_long` as `jit`'s."""
    if fun is None:
        return lambda f: filter_jit(f, runs_long=runs_long, **kwargs)
    return _top_level_options(eqx.filter_jit, fun, kwargs, runs_long)


def _top_level_options(make, fun, kwargs, runs_long):
    """`make(fun, **kwargs)` with the compiler options where it is a program of its own.

    JAX takes compile options only for a top-level program: called while another program is
    traced (a user's `jax.jit`, a `lax.scan` body, one hiddenjax function inside another), the
    same function is staged into that program without them.
    """
    options = _RUNS_LONG_OPTIONS if runs_long else COMPILER_OPTIONS
    own, nested = make(fun, compiler_options=options, **kwargs), make(fun, **kwargs)
    if make is eqx.filter_jit and not kwargs:  # kept on disk once enable_compilation_cache() is called
        own = _program_store.stored_call(fun, options, own)

    @functools.wraps(fun)
    def call(*args, **kw):
        if _staged(args, kw):
            return nested(*args, **kw)
        try:
            return own(*args, **kw)
        except ValueError as error:  # staged all the same (a traced value that is not an argument)
            if "compiler_options" not in str(error):
                raise
            return nested(*args, **kw)

    return call


def _staged(args, kwargs) -> bool:
    """Whether an argument is a tracer of a program being staged (a caller's `jax.jit`, a `lax.scan` body, ...).

    JAX refuses compile options there only once it has traced `fun` (when it binds the program into
    the caller's), and `eqx.filter_jit`'s retry without them would trace `fun` again, each level of
    nesting doubling the tracing (the exact solver's program: 0.38 s a trace); such a call goes
    straight to the form without options. Told by the tracer's class name, which JAX does not export:
    should it change, calls try the options first and retry without them, slower but the same.
    """
    return any(type(leaf).__name__ == "DynamicJaxprTracer" for leaf in jax.tree_util.tree_leaves((args, kwargs)))


def host_array(x, dtype=None) -> jax.Array:
    """A host array as a JAX array, cast on the host and transferred: no JAX program.

    `jnp.asarray(x, dtype)` of a numpy array whose dtype differs compiles a conversion program per
    shape and dtype when called eagerly; `np.asarray` then `jax.device_put` compiles nothing.
    """
    return jax.device_put(np.asarray(x, dtype))


def traced_number(v):
    """A Python number (`int`, `float`; not a bool) as a weakly typed JAX scalar, anything else as it is.

    `eqx.filter_jit` keys its cache on non-array leaves: as a number, every new value would compile
    the program again; as an array it is an argument of one program. `jax.device_put` keeps the
    number weakly typed, as `jnp.asarray` does, without compiling a program (`stage`) to do it.
    """
    return jax.device_put(v) if type(v) in (int, float) else v
