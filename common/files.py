"""File writing shared by the parts: whole files or nothing."""

from __future__ import annotations

import math
import os
from pathlib import Path


def atomic_write_text(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` through a temporary file beside it and ``os.replace``.

    A reader, or a crash mid-write, sees the old file or the new one, never part of one.
    """
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


def finite_json(obj):
    """``obj`` (nested dicts, lists, tuples) with every non-finite float (NaN, inf) replaced by
    None, so that ``json.dumps`` writes strict JSON (``null``), which every parser reads."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: finite_json(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [finite_json(v) for v in obj]
    return obj
