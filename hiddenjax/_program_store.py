"""hiddenjax's traced programs kept on disk: a later process calls them without tracing or lowering them again.

JAX's persistent compilation cache (`enable_compilation_cache`) saves the compiling, but a new
process still traces each program and lowers it to StableHLO before it can look the executable
up, and for the exact solver that was most of a warm first call: on 2 cores, `_solve` (the
projected Newton solver, one `lax.switch` branch per free-block size) took 0.7 s to trace, 0.3 s
to lower and 0.3 s to load, then 0.2 s to run. This store keeps each program as JAX exports it
(`jax.export`: the lowered StableHLO module, serialized) under a key of everything its tracing
reads, so a later process deserializes it (a few ms), and JAX's cache serves the executable.

The key of a call of a `filter_jit` function is a hash of: the function's module and qualified
name; the source of every hiddenjax module; the versions of jax, jaxlib, numpy, equinox and Python;
JAX's settings that change a trace (those `jax.jit` keys its programs on: x64, promotion rules, ...)
and default backend; the pytree of the arguments, arrays as
their shape, dtype and weak type (the dynamic arguments) and everything else as pickled (the
static ones, as `eqx.filter_jit` treats them). A call that cannot be keyed so (an argument that
does not pickle, an array on another backend or sharded over devices, a function defined inside
another) or exported (a program with host callbacks) runs as before, traced: the store never
changes what a call computes, only whether it is traced again.

On by `enable_compilation_cache()`, in the folder `hiddenjax-programs` of JAX's cache (JAX's
eviction ignores it); the same trust as that cache (its owner's alone). Entries are written to a
temporary file and renamed, so processes filling it at once do not read half-written ones; past
`MAX_BYTES` the least recently written entries go.
"""

import functools
import hashlib
import os
import pickle
import sys
import tempfile
import warnings
from pathlib import Path

import equinox as eqx
import jax
import numpy as np

try:  # the only way to a weakly typed array (JAX's own casts); private, so a JAX without it keeps the store off
    from jax._src.lax.lax import _convert_element_type
except ImportError:
    _convert_element_type = None

MAX_BYTES = 256 << 20
_folder: Path | None = None
_loaded: list[dict] = []  # each stored function's programs in this process (`stored_call`)


class _Clear:
    """`jax.clear_caches()` also forgets the stored programs, and turns the store off in this process: a
    later call traces again, as after the clear (a caller who changed the code it traces expects that)."""

    @staticmethod
    def cache_clear():
        global _folder
        _folder = None
        for programs in _loaded:
            programs.clear()


try:  # JAX's registry of the caches that jax.clear_caches() clears
    from jax._src.util import register_cache

    register_cache(_Clear, "hiddenjax's stored programs")
except ImportError:
    pass


def enable(folder) -> None:
    """Keep programs in `folder` (created private to its owner; None turns the store off). A folder that
    cannot be created is a warning, and the store stays off."""
    global _folder
    _folder = None
    if folder is None or _convert_element_type is None:
        return
    try:
        Path(folder).mkdir(mode=0o700, parents=True, exist_ok=True)
    except OSError as e:
        warnings.warn(f"traced programs will not be kept: cannot create {folder} ({e.strerror or e})", RuntimeWarning,
                      stacklevel=3)
        return
    _folder = Path(folder)


def folder() -> Path | None:
    """The store's folder in this process, or None when it is off."""
    return _folder


class _Array:
    """Where an output of a stored program goes in its output skeleton."""


class _Input(eqx.Module):
    """Where an argument returned as it is goes in an output skeleton (the array itself, not a copy of it)."""

    index: int


@functools.cache
def _source_digest() -> str:
    """A hash of every hiddenjax module's source and of the versions of the libraries that trace with it."""
    digest = hashlib.sha256()
    package = Path(__file__).resolve().parent
    for path in sorted(package.rglob("*.py")):
        digest.update(str(path.relative_to(package)).encode() + b"\0" + path.read_bytes())
    import jaxlib

    for module in (jax, jaxlib, np, eqx, sys):
        digest.update(str(getattr(module, "__version__", getattr(module, "version", ""))).encode())
    return digest.hexdigest()


TRACE_CONTEXT: list = []
"""Context variables that change what hiddenjax's functions trace (`_qp.checks_on_host`'s): part of the key."""


def _trace_context() -> tuple:
    """JAX's settings that change a trace (what `jax.jit` keys its programs on: x64, promotion rules, ...)
    and `TRACE_CONTEXT`'s values."""
    try:
        from jax._src.config import trace_context

        values = tuple(trace_context())
    except ImportError:  # a jax without it: every setting
        values = tuple(sorted((k, repr(v)) for k, v in jax.config.values.items()))
    return values + tuple(var.get() for var in TRACE_CONTEXT)


def _described(leaves) -> tuple | None:
    """A call's leaves for its key: arrays as `("array", shape, dtype, weak type)`, the rest `(type, leaf)`;
    None where it cannot be stored (a traced, sharded or other-backend array)."""
    backend = jax.default_backend()
    described = []
    for leaf in leaves:
        if isinstance(leaf, jax.Array):
            if isinstance(leaf, jax.core.Tracer) or len(leaf.devices()) != 1:
                return None
            if next(iter(leaf.devices())).platform != backend:
                return None
            described.append(("array", leaf.shape, str(leaf.dtype), leaf.weak_type))
        elif eqx.is_array(leaf):  # numpy: an argument, as eqx.filter_jit takes it
            described.append(("array", np.shape(leaf), str(np.result_type(leaf)), False))
        else:
            described.append((type(leaf), leaf))
    return tuple(described)


def _disk_key(fun, signature) -> str | None:
    """The file name of a call's program: a hash of what its tracing reads (module doc); None if it does not pickle."""
    if "<" in fun.__qualname__:  # a lambda or a function inside another: its closure is not in the key
        return None
    treedef, described, context = signature
    skeleton = jax.tree_util.tree_unflatten(treedef, [d if d[0] == "array" else d[1] for d in described])
    try:
        context = [type(v).__name__ if " at 0x" in repr(v) else repr(v) for v in context]  # lasting text
        blob = pickle.dumps((fun.__module__, fun.__qualname__, skeleton, context, jax.default_backend()), protocol=4)
    except Exception:  # noqa: BLE001  (a static argument that does not pickle: not stored)
        return None
    return hashlib.sha256(_source_digest().encode() + blob).hexdigest()


def stored_call(fun, options: dict, fallback):
    """`fallback` (`eqx.filter_jit(fun)` with `options`) with its programs kept in the store when it is on."""
    programs = {}  # signature -> the deserialized program's caller, or None (not stored: the fallback)
    _loaded.append(programs)

    @functools.wraps(fun)
    def call(*args, **kwargs):
        if _folder is None:
            return fallback(*args, **kwargs)
        leaves, treedef = jax.tree_util.tree_flatten((args, kwargs))
        described = _described(leaves)
        if described is None:
            return fallback(*args, **kwargs)
        signature = (treedef, described, _trace_context())
        try:
            known = signature in programs
        except TypeError:  # an unhashable static leaf: traced, as eqx.filter_jit takes it
            return fallback(*args, **kwargs)
        if not known:
            programs[signature] = _load_or_export(fun, options, signature, leaves)
        program = programs[signature]
        if program is None:
            return fallback(*args, **kwargs)
        return program([leaf for leaf in leaves if eqx.is_array(leaf)])

    return call


def _load_or_export(fun, options, signature, leaves):
    """The caller of a call's stored program (exported and stored first if it is not yet), or None."""
    key = _disk_key(fun, signature)
    if key is None:
        return None
    path = _folder / f"{fun.__name__}-{key}"
    unexportable = path.with_name(path.name + ".none")  # marks a program that is traced in every process
    if unexportable.exists():
        return None
    try:
        serialized, skeleton, weak = pickle.loads(path.read_bytes())
        exported = jax.export.deserialize(serialized)
    except Exception:  # noqa: BLE001  (missing, unreadable, from another version: export it again)
        try:
            made = _export(fun, leaves, signature[0])
        except ImportError:  # no `flatbuffers` to serialize with: traced as before
            return None
        if made is None:  # not exported (its tracing then runs twice, this once): no later process tries again
            _write(unexportable, b"")
            return None
        serialized, skeleton, weak = made
        _write(path, pickle.dumps(made, protocol=4))
        exported = jax.export.deserialize(serialized)  # as a later process reads it

    def outputs(*dynamic):  # a serialized program's outputs lose their weak types: given back, as traced
        computed = exported.call(*dynamic)
        return [_convert_element_type(x, x.dtype, weak_type=w) if w else x for x, w in zip(computed, weak)]

    outputs.__name__ = outputs.__qualname__ = fun.__name__  # the program's name in JAX's logs and cache
    run = jax.jit(outputs, compiler_options=options)

    slots, out_treedef = jax.tree_util.tree_flatten(skeleton, is_leaf=lambda x: isinstance(x, _Input))

    def program(dynamic):
        computed = iter(run(*dynamic))
        return jax.tree_util.tree_unflatten(out_treedef, [
            next(computed) if isinstance(x, _Array) else _as_jax(dynamic[x.index]) if isinstance(x, _Input) else x
            for x in slots])

    return program


def _as_jax(x):
    """An argument returned as it is, as a jitted function returns it: a JAX array (numpy transferred, no program)."""
    return x if isinstance(x, jax.Array) else jax.device_put(x)


def _export(fun, leaves, treedef):
    """`(serialized jax.export.Exported of fun on the call's arrays, output skeleton, the outputs' weak types)`
    for the call whose `(args, kwargs)` flatten to `leaves, treedef`, or None where it cannot be exported."""
    is_dynamic = [eqx.is_array(leaf) for leaf in leaves]
    traced = []

    def flat(*dynamic):
        fed = iter(dynamic)
        a, kw = jax.tree_util.tree_unflatten(treedef, [next(fed) if d else x for d, x in zip(is_dynamic, leaves)])
        out_leaves, out_treedef = jax.tree_util.tree_flatten(fun(*a, **kw))
        given = {id(x): k for k, x in enumerate(dynamic)}  # arguments returned as they are (an operator's A)
        slots = [_Input(given[id(x)]) if id(x) in given else _Array() if eqx.is_array(x) else x for x in out_leaves]
        arrays = [x for x, slot in zip(out_leaves, slots) if isinstance(slot, _Array)]
        traced.append(jax.tree_util.tree_unflatten(out_treedef, slots))
        traced.append([jax.typeof(x).weak_type for x in arrays])
        return arrays

    flat.__name__ = flat.__qualname__ = fun.__name__
    try:
        exported = jax.export.export(jax.jit(flat))(*[x for d, x in zip(is_dynamic, leaves) if d])
        made = (exported.serialize(), *traced)
        pickle.dumps(made, protocol=4)
    except ImportError:  # jax.export's serialization needs `flatbuffers`
        raise
    except Exception:  # noqa: BLE001  (host callbacks, effects, unpicklable outputs: traced each process instead)
        return None
    return made


def remove_oldest(entries, max_bytes: int) -> int:
    """Remove the oldest of `entries`, each `(last use, bytes, its files)`, until the rest hold at most `max_bytes`.

    Returns the bytes removed. A file that cannot be removed (another process removed it first) is left.
    """
    total, removed = sum(size for _, size, _ in entries), 0
    for _, size, files in sorted(entries, key=lambda e: e[0]):
        if total <= max_bytes:
            break
        for file in files:
            try:
                file.unlink()
            except OSError:
                continue
        total, removed = total - size, removed + size
    return removed


def _write(path: Path, data: bytes) -> None:
    """Write an entry whole (a temporary file renamed), then trim the store to `MAX_BYTES`; a failure is a warning."""
    try:
        with tempfile.NamedTemporaryFile(dir=path.parent, prefix=".tmp-", delete=False) as f:
            f.write(data)
        os.replace(f.name, path)
        remove_oldest([(info.st_mtime, info.st_size, [p]) for p in path.parent.iterdir()
                       if p.is_file() and (info := p.stat())], MAX_BYTES)
    except OSError as e:
        warnings.warn(f"a traced program was not stored in {path.parent}: {e}", RuntimeWarning, stacklevel=3)
