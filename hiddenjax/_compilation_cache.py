"""JAX's persistent compilation cache in the user's cache folder: compile a program once per machine.

Compiling, not running, is most of a fresh call's time on a CPU (a first `hiddenjax demo --quick`
spends most of its seconds in XLA). JAX can keep every compiled program on disk, keyed by the
program, its compile options, the device and the jax/jaxlib versions, and load it in a later
process instead of compiling again. Importing hiddenjax never turns this on (it is JAX's global
configuration, the user's to choose); the `hiddenjax` command, the examples and the benchmarks call
`enable_compilation_cache()` first, and a library user can do the same in one line.

The cache holds executables that JAX runs without checking them, so it must be a folder only its
owner can write: the default is private (mode 0700) under the platform's cache folder, one per jax
version; a folder that others can write, or that cannot be written, is a warning and a run without
the cache. Processes may fill one cache at once (test workers, a benchmark's children): JAX writes
an entry in place, and one read half-written by another process fails to decompress (the
compressed stream carries its end), which JAX reports as a warning and compiles the program
instead; it never loads a truncated program. No maximum size is given to JAX, whose eviction
lists every entry on each write (3000 programs written into one cache took 79 s so, against 0.1 s
without); instead `trim` removes the least recently used programs beyond `MAX_BYTES`, at most once
a day, when a process turns the cache on. On GPUs XLA's per-fusion autotuning results are kept
beside it (JAX's `jax_persistent_cache_enable_xla_caches` default).

`HIDDENJAX_CACHE` moves the cache (a folder) or turns it off (`off`, `0`, `false`, `no`); a cache
chosen through JAX itself (`JAX_COMPILATION_CACHE_DIR` or `jax.config`) is left as it is. Beside the
compiled programs, in its folder `hiddenjax-programs`, hiddenjax keeps its own programs as traced
(`_program_store`), so that a later process neither traces nor lowers them to find them.
"""

import os
import stat
import sys
import tempfile
import time
import warnings
from pathlib import Path

import jax

from . import _program_store

ENVIRONMENT = "HIDDENJAX_CACHE"
OFF = ("off", "0", "false", "no", "none")
PROGRAMS = "hiddenjax-programs"  # the traced programs' folder inside the cache (`_program_store`)
MAX_BYTES = 4 << 30  # `trim` removes the least recently used programs past this
TRIM_EVERY_S = 24 * 3600  # `trim` lists the folder at most this often (a marker file holds the time)
TRIM_MARKER = ".trimmed"


def default_cache_dir() -> Path:
    """The platform's per-user cache folder for hiddenjax's compiled programs, one per jax version.

    Linux and other Unix: `$XDG_CACHE_HOME/hiddenjax/jax-VERSION` (default `~/.cache`); macOS:
    `~/Library/Caches/hiddenjax/jax-VERSION`; Windows: `%LOCALAPPDATA%\\hiddenjax\\jax-VERSION`.
    """
    if sys.platform == "darwin":
        base = Path.home() / "Library" / "Caches"
    elif os.name == "nt":
        base = Path(os.environ.get("LOCALAPPDATA") or Path.home() / "AppData" / "Local")
    else:
        base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return base / "hiddenjax" / f"jax-{jax.__version__}"


def compilation_cache_dir() -> Path | None:
    """The folder of JAX's persistent compilation cache in this process, or None when it is off."""
    path = jax.config.jax_compilation_cache_dir
    return Path(path) if path and jax.config.jax_enable_compilation_cache else None


def enable_compilation_cache(path=None) -> Path | None:
    """Keep compiled programs on disk, so a later process loads them instead of compiling (JAX's persistent cache).

    **Arguments:**
    - `path`: the cache folder; default `HIDDENJAX_CACHE` if set (a folder, or `off`), else
      `default_cache_dir()`. It is created private to its owner (mode 0700).

    hiddenjax's own traced programs are kept in its folder `hiddenjax-programs` (module doc).

    **Returns:** the folder in use, or None when the cache stays off (turned off, or the folder is
    not usable: then a warning says why and the run goes on compiling as usual). A cache already
    set through JAX (`JAX_COMPILATION_CACHE_DIR`, `jax.config`) is kept and returned. Every
    program is cached however briefly it compiled (most of a first call's programs take well under
    JAX's default threshold of a second each). Call it before the first computation: JAX reads the
    setting when it first compiles.
    """
    if path is None and compilation_cache_dir() is not None:
        _program_store.enable(compilation_cache_dir() / PROGRAMS)
        return compilation_cache_dir()
    if path is None:
        chosen = os.environ.get(ENVIRONMENT, "").strip()
        if chosen.lower() in OFF:
            return None
        path = chosen or default_cache_dir()
    folder = Path(path).expanduser()
    problem = _unusable(folder)
    if problem:
        warnings.warn(f"compiled programs will not be cached: {problem} (set {ENVIRONMENT} to another folder, "
                      f"or to 'off')", RuntimeWarning, stacklevel=2)
        return None
    jax.config.update("jax_compilation_cache_dir", str(folder))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", -1)
    trim(folder)
    _program_store.enable(folder / PROGRAMS)
    return folder


def _unusable(folder: Path) -> str | None:
    """Why `folder` cannot hold a trusted cache (created if missing), or None."""
    try:
        folder.mkdir(mode=0o700, parents=True, exist_ok=True)
    except OSError as e:
        return f"cannot create {folder} ({e.strerror or e})"
    if not folder.is_dir():
        return f"{folder} is not a folder"
    info = folder.stat()
    if hasattr(os, "getuid") and info.st_uid != os.getuid():
        return f"{folder} belongs to another user (a shared cache would run programs they wrote)"
    if info.st_mode & (stat.S_IWGRP | stat.S_IWOTH):
        return f"{folder} can be written by other users (a shared cache would run programs they wrote)"
    try:
        with tempfile.NamedTemporaryFile(dir=folder, prefix=".write-test-"):
            pass
    except OSError as e:
        return f"cannot write to {folder} ({e.strerror or e})"
    return None


def trim(folder: Path, max_bytes: int = MAX_BYTES, every_s: float = TRIM_EVERY_S) -> int:
    """Remove JAX's least recently used programs from `folder` until they hold at most `max_bytes`; the bytes removed.

    An entry is JAX's `KEY-cache` file (with its `KEY-atime`, which JAX writes only under its own
    eviction); its last use is the later of the file's access and modification times. The folder is
    listed at most once per `every_s` seconds (the time of the last listing is the marker file's), so
    a process that turns the cache on pays one `stat` rather than a listing of thousands of entries.
    """
    marker = folder / TRIM_MARKER
    try:
        if time.time() - marker.stat().st_mtime < every_s:
            return 0
    except OSError:
        pass
    try:
        marker.touch()
        entries = []
        with os.scandir(folder) as listing:
            for entry in listing:
                if entry.name.endswith("-cache") and entry.is_file(follow_symlinks=False):
                    info, key = entry.stat(follow_symlinks=False), entry.name[:-len("-cache")]
                    files = [folder / f"{key}-cache", folder / f"{key}-atime"]
                    entries.append((max(info.st_atime, info.st_mtime), info.st_size, files))
    except OSError:
        return 0
    return _program_store.remove_oldest(entries, max_bytes)
