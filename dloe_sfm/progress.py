"""Progress bars (tqdm): off in the library, on from the command line with a terminal or
``--progress``, so a program that imports ``dloe_sfm`` never gets bars it did not ask for."""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager

from tqdm.auto import tqdm

_enabled = False


def enable(on: bool = True) -> None:
    """Show (or hide) the bars of file reading, observation building, export and the solve."""
    global _enabled
    _enabled = on


def enabled() -> bool:
    return _enabled


def bar(iterable: Iterable | None = None, **kwargs) -> tqdm:
    """``tqdm(iterable, **kwargs)``, hidden unless :func:`enable` was called."""
    kwargs["disable"] = kwargs.get("disable", False) or not _enabled
    return tqdm(iterable, **kwargs)


@contextmanager
def solver_bar() -> Iterator[Callable[[int, int, dict], None] | None]:
    """A bar over the solver's sweeps: yields the ``progress`` callback for
    :func:`dloe_sfm.core.solver.reconstruct` (``cb(done, total, info)``), or None (no bar)
    unless :func:`enable` was called. Every solve (an event, a robust re-solve) starts it
    again; it shows the sweep's cost and change."""
    if not _enabled:
        yield None
        return
    with tqdm(total=0, desc="DLOE", unit="it", leave=False) as sweeps:

        def update(done: int, total: int, info: dict) -> None:
            if done <= sweeps.n:  # the next solve
                sweeps.reset(total=total)
            sweeps.total = total
            sweeps.update(done - sweeps.n)
            sweeps.set_postfix(cost=f"{info['cost']:.3e}", change=f"{info['change']:.1e}")

        yield update
