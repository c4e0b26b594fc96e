"""Atomic file writes: a reader never sees a half-written output."""

import contextlib
import os
import tempfile
from pathlib import Path


@contextlib.contextmanager
def atomic_path(path):
    """Yield a temporary path beside `path` (same suffix); rename it onto `path` on success.

    On an exception the temporary file is removed and `path` is left untouched.
    """
    path = Path(path)
    if not path.parent.exists():
        raise ValueError(f"output folder does not exist: {path.parent}")
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=path.suffix, dir=path.parent)
    os.close(fd)
    try:
        yield Path(tmp)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.remove(tmp)
        raise


def write_text(path, text: str) -> None:
    """Write a text file atomically (`atomic_path`)."""
    with atomic_path(path) as tmp:
        Path(tmp).write_text(text)
