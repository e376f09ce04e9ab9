"""Solver options from a TOML file and ``--set key=value`` overrides.

A config file holds options at its top level or in a ``[solver]`` table (then nothing else).
Its values keep their TOML types: an integer for a number option is fine, a string is not, and
a float is not an integer (``Options`` says what each option takes). TOML has no null: the
string ``"none"`` sets an optional number (``lambda2``, ``robust_scale_px``) back to None.
``--set`` values are strings, parsed for the option's kind: numbers (``nan``, ``inf`` and
``none`` spelled so), ``true`` / ``false`` (also ``1 0 yes no on off``), enum names.
"""

from __future__ import annotations

import difflib
import sys
from pathlib import Path

from .core.options import RULES, Flag, Number, Options, check_option, shown
from .errors import InputError

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

MAX_CONFIG_BYTES = 1 << 20
"""A solver config is a few hundred bytes; a larger file is not one (and is not read)."""

_TRUE = ("true", "1", "yes", "on")
_FALSE = ("false", "0", "no", "off")


def _place(text: object, limit: int = 200) -> str:
    """A file name or ``--set`` argument for a message: escaped unless printable, cut to about
    ``limit`` characters."""
    text = str(text)
    text = text if text.isprintable() else repr(text)[1:-1]
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _checked(name: str, value: object, source: str) -> object:
    """``check_option`` with ``source`` (file or ``--set`` argument) leading its message; an
    unknown name close to an option's is answered with that option."""
    close = [] if name in RULES else difflib.get_close_matches(name, RULES, n=1)
    if close:
        raise InputError(f"{source}: unknown option {shown(name)}: did you mean '{close[0]}'?")
    try:
        return check_option(name, value)
    except InputError as e:
        raise InputError(f"{source}: {e}") from None


def _parsed(name: str, text: str) -> object:
    """A ``--set`` string as a value of option ``name`` (left a string when it is none)."""
    rule = RULES.get(name)
    word = text.lower()
    if isinstance(rule, Number):
        if rule.optional and word == "none":
            return None
        try:
            return int(text) if rule.integer else float(text)
        except ValueError:
            return text
    if isinstance(rule, Flag):
        return True if word in _TRUE else False if word in _FALSE else text
    return text


def read_toml(path: Path, *, what: str = "config file", kind: str = "a solver config",
              limit: int = MAX_CONFIG_BYTES) -> dict:
    """The TOML tables of ``path`` (a ``what``, e.g. a config file or a batch manifest);
    InputError for anything but a UTF-8 TOML file of at most ``limit`` bytes."""
    where = _place(path)
    try:
        if not path.exists():
            raise InputError(f"{where}: no such {what}")
        if path.is_dir():
            raise InputError(f"{where}: is a directory, not a {what}")
        if not path.is_file():
            raise InputError(f"{where}: not a regular file")
        with path.open("rb") as f:
            raw = f.read(limit + 1)
    except OSError as e:
        raise InputError(f"{where}: cannot read the {what} ({e.strerror or e})") from None
    if len(raw) > limit:
        raise InputError(f"{where}: larger than {limit} bytes, not {kind}")
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        raise InputError(f"{where}: not UTF-8 text (bad byte at offset {e.start})") from None
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise InputError(f"{where}: invalid TOML ({' '.join(str(e).split())})") from None
    except RecursionError:
        raise InputError(f"{where}: invalid TOML (nested too deeply)") from None


def _config_changes(path: Path) -> dict:
    """The options set by config file ``path``, checked."""
    where = _place(path)
    data = read_toml(path)
    if "solver" in data:
        table = data["solver"]
        if not isinstance(table, dict):
            raise InputError(f"{where}: 'solver' must be a table ([solver]), got {shown(table)}")
        others = [k for k in data if k != "solver"]
        if others:
            raise InputError(f"{where}: unknown key {shown(others[0])} beside the [solver] table")
        data, where = table, f"{where} [solver]"
    changes = {}
    for name, value in data.items():
        rule = RULES.get(name)
        if isinstance(rule, Number) and rule.optional and isinstance(value, str):
            value = None if value.lower() == "none" else value
        changes[name] = _checked(name, value, where)
    return changes


def load_options(
    config: Path | str | None = None,
    overrides: list[str] | None = None,
    base: Options | None = None,
) -> Options:
    """Options = ``base`` <- TOML file (top level or ``[solver]`` table) <- ``--set`` pairs.

    Every problem (a file that is not a small UTF-8 TOML file, an unknown key, a value of the
    wrong type or out of range) raises InputError naming the file or ``--set`` argument and the
    option.
    """
    changes: dict = {}
    if config is not None:
        changes.update(_config_changes(Path(config)))
    for item in overrides or []:
        if "=" not in item:
            raise InputError(f"--set {_place(item)}: expected key=value")
        key, text = (part.strip() for part in item.split("=", 1))
        changes[key] = _checked(key, _parsed(key, text), f"--set {_place(item)}")
    return (base or Options()).replace(**changes)
