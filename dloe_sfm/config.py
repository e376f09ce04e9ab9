"""Solver options from a TOML file and ``--set key=value`` overrides."""

from __future__ import annotations

import sys
from dataclasses import fields
from enum import Enum
from pathlib import Path

from .core.options import Options
from .errors import InputError

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib


def _coerce(name: str, value, source: str):
    field = {f.name: f for f in fields(Options)}.get(name)
    if field is None:
        known = ", ".join(f.name for f in fields(Options))
        raise InputError(f"{source}: unknown option '{name}' (known: {known})")
    default = getattr(Options(), name)
    try:
        if isinstance(default, Enum):
            return type(default)(str(value).lower())
        if isinstance(default, bool):
            if isinstance(value, str):
                if value.lower() not in ("true", "false", "1", "0", "yes", "no", "on", "off"):
                    raise ValueError(value)
                return value.lower() in ("true", "1", "yes", "on")
            return bool(value)
        if isinstance(default, int):
            return int(value)
        if isinstance(default, float) or default is None:  # None: an optional number (lambda2)
            return float(value)
    except ValueError:
        raise InputError(f"{source}: option '{name}' cannot take the value {value!r}") from None
    return value


def load_options(
    config: Path | str | None = None,
    overrides: list[str] | None = None,
    base: Options | None = None,
) -> Options:
    """Options = ``base`` <- TOML file (top level or ``[solver]`` table) <- ``--set`` pairs."""
    changes: dict = {}
    if config is not None:
        config = Path(config)
        if not config.exists():
            raise InputError(f"{config}: no such config file")
        try:
            data = tomllib.loads(config.read_text())
        except tomllib.TOMLDecodeError as e:
            raise InputError(f"{config}: invalid TOML ({e})") from None
        data = data.get("solver", data)
        for k, v in data.items():
            changes[k] = _coerce(k, v, str(config))
    for item in overrides or []:
        if "=" not in item:
            raise InputError(f"--set {item!r}: expected key=value")
        k, v = item.split("=", 1)
        changes[k.strip()] = _coerce(k.strip(), v.strip(), f"--set {item}")
    return (base or Options()).replace(**changes)
