"""Progress bars (tqdm): off in the library, on from the command line with a terminal or
``--progress``, so a program that imports ``dloe_sfm`` never gets bars it did not ask for."""

from __future__ import annotations

from collections.abc import Iterable

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
