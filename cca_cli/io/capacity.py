"""What this machine can hold: the memory a run may plan on, and sizes in bytes as people read them."""

from __future__ import annotations

import math
import os

from cca_cli.errors import ConfigError

__all__ = ["memory_available", "size_text"]


def size_text(n: float) -> str:
    """Bytes as ``10.7 GB`` (decimal units)."""
    if not math.isfinite(n):
        return "more than any machine has"
    for unit in ("B", "kB", "MB", "GB", "TB", "PB"):
        if abs(n) < 1000 or unit == "PB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.3g} {unit}"
        n /= 1000
    return f"{n:.3g} PB"


def memory_available() -> float:
    """Bytes of memory a stage may plan to use: ``CCA_MEMORY_LIMIT`` or the free memory now."""
    limit = os.environ.get("CCA_MEMORY_LIMIT", "").strip()
    if limit:
        scale = {"K": 1e3, "M": 1e6, "G": 1e9, "T": 1e12}.get(limit[-1].upper(), 1.0)
        try:
            value = float(limit[:-1] if scale != 1.0 else limit) * scale
        except ValueError:
            value = math.nan
        if not (math.isfinite(value) and value > 0):
            raise ConfigError(f"CCA_MEMORY_LIMIT={limit!r}: give a positive number of bytes, e.g. 8G or 512M")
        return value
    try:
        import psutil

        return float(psutil.virtual_memory().available)
    except ImportError:  # pragma: no cover - psutil comes with dask.distributed
        pages = os.sysconf("SC_AVPHYS_PAGES") if hasattr(os, "sysconf") else 0
        return float(pages * os.sysconf("SC_PAGE_SIZE")) if pages else math.inf
