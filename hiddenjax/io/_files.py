"""Atomic file writes: a reader never sees a half-written output, and the file gets the user's umask."""

import contextlib
import os
import tempfile
from pathlib import Path


def _umask() -> int:
    """The process's file-creation mask (read by setting it and setting it back)."""
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


@contextlib.contextmanager
def atomic_path(path):
    """Yield a temporary path beside `path` (same suffix); rename it onto `path` on success.

    On an exception the temporary file is removed and `path` is left untouched. The temporary
    file is created private (mode 0600) and given the mode an ordinary `open()` would give,
    `0666 & ~umask` (0644 under the usual umask 022), before it is renamed into place.
    """
    path = Path(path)
    if not path.parent.exists():
        raise ValueError(f"output folder does not exist: {path.parent}")
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=path.suffix, dir=path.parent)
    os.close(fd)
    try:
        yield Path(tmp)
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.remove(tmp)
        raise


def write_text(path, text: str) -> None:
    """Write a text file atomically (`atomic_path`)."""
    with atomic_path(path) as tmp:
        Path(tmp).write_text(text)


def read_toml(path) -> dict:
    """Read a TOML file; a missing, unreadable or malformed file is a `ValueError` naming it."""
    try:
        import tomllib
    except ModuleNotFoundError:  # Python 3.10
        import tomli as tomllib
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"file not found: {path}")
    try:
        return tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as e:
        raise ValueError(f"{path}: malformed TOML: {e}") from e
    except UnicodeDecodeError as e:
        raise ValueError(f"{path}: not a text (UTF-8) TOML file: {e}") from e
