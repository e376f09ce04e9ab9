"""The machine's memory, checked before large allocations (a solve, the arrays of a file)."""

from __future__ import annotations

import os
import resource

from .core.capture import Capture
from .core.options import Options
from .errors import InputError


def available_memory() -> int | None:
    """Bytes a new allocation can get: ``MemAvailable`` (/proc/meminfo), else the physical
    memory, capped by the process's address-space limit (``ulimit -v``); None when unknown."""
    avail = None
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    avail = int(line.split()[1]) * 1024
                    break
    except (OSError, ValueError, IndexError):
        pass
    if avail is None:
        try:
            avail = os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
        except (ValueError, OSError, AttributeError):
            return None
    limit = resource.getrlimit(resource.RLIMIT_AS)[0]
    if limit != resource.RLIM_INFINITY:
        try:
            with open("/proc/self/statm") as f:
                used = int(f.read().split()[0]) * os.sysconf("SC_PAGE_SIZE")
        except (OSError, ValueError, IndexError):
            used = 0
        avail = min(avail, max(limit - used, 0))
    return avail


def format_bytes(n: float) -> str:
    """``n`` bytes in the largest binary unit that keeps it >= 1 (e.g. ``'3.2 GiB'``)."""
    for unit in ("B", "KiB", "MiB", "GiB", "TiB"):
        if abs(n) < 1024 or unit == "TiB":
            return f"{n:.1f} {unit}" if unit != "B" else f"{int(n)} B"
        n /= 1024
    raise AssertionError("unreachable")


def check_memory(needed: int, what: str) -> None:
    """Raise a one-line InputError when ``needed`` bytes exceed the memory available."""
    avail = available_memory()
    if avail is not None and needed > avail:
        raise InputError(
            f"{what} needs about {format_bytes(needed)} of memory, "
            f"{format_bytes(avail)} available"
        )


def check_solve_memory(capture: Capture, options: Options, source: object) -> None:
    """Check :meth:`Capture.memory_estimate` of a solve against the machine before it starts."""
    check_memory(
        capture.memory_estimate(options),
        f"{source}: solving {capture.num_images} images x {capture.num_points} points",
    )
