"""Memory budgets: `"4GiB"`-style sizes as bytes."""

import re

_UNITS = {"": 1, "b": 1, "k": 1e3, "kb": 1e3, "m": 1e6, "mb": 1e6, "g": 1e9, "gb": 1e9, "t": 1e12, "tb": 1e12,
          "kib": 2**10, "mib": 2**20, "gib": 2**30, "tib": 2**40}


def parse_memory(value, name: str = "memory") -> int:
    """Bytes from an integer or a string such as `"4GiB"`, `"512 MiB"`, `"2e9"` or `"8GB"`; clear error otherwise."""
    if isinstance(value, bool):
        raise ValueError(f"{name} must be a number of bytes or a size such as '4GiB', got {value!r}")
    if isinstance(value, (int, float)):
        number, unit = float(value), ""
    elif isinstance(value, str) and (m := re.fullmatch(r"\s*([0-9.]+(?:[eE][0-9]+)?)\s*([A-Za-z]*)\s*", value)):
        number, unit = float(m.group(1)), m.group(2).lower()
    else:
        number, unit = float("nan"), ""
    if unit not in _UNITS or not number > 0 or number == float("inf"):
        raise ValueError(f"{name} must be a positive number of bytes or a size such as '4GiB' or '512MiB', "
                         f"got {value!r}")
    return int(number * _UNITS[unit])


def format_bytes(n: float) -> str:
    """`n` bytes as `"1.50 GiB"`, `"12.0 MiB"` or `"512 B"`."""
    for unit, size in (("TiB", 2**40), ("GiB", 2**30), ("MiB", 2**20), ("KiB", 2**10)):
        if n >= size:
            return f"{n / size:.{2 if unit in ('TiB', 'GiB') else 1}f} {unit}"
    return f"{int(n)} B"
