"""``dloe-sfm``: one subcommand per pipeline stage (also ``python -m <its module>``, ``STAGES``)."""

from __future__ import annotations

import argparse
import ctypes
import difflib
import importlib
import logging
import re
import signal
import sys
import threading

from tqdm import tqdm

from . import __version__, progress
from .errors import InputError

# subcommand -> (module with ``configure_parser(parser)`` and ``run(args) -> int``, summary)
STAGES = {
    "solve": ("dloe_sfm.stages.solve", "run DLOE on a capture file and write a result file"),
    "reconstruct": (
        "dloe_sfm.stages.reconstruct",
        "reconstruct moving points from keypoints on a COLMAP workspace",
    ),
    "simulate": (
        "dloe_sfm.stages.simulate", "simulate an unsynchronised capture of a mocap sequence"
    ),
    "evaluate": (
        "dloe_sfm.stages.evaluate", "score a result against ground truth (mm, Kendall tau)"
    ),
    "demo": ("dloe_sfm.stages.demo", "run the whole chain on the bundled demo workspace"),
    "benchmark": ("dloe_sfm.stages.benchmark", "the paper's experiments with every baseline"),
    "import-calibration": (
        "dloe_sfm.stages.import_calibration", "calibration file -> COLMAP model"
    ),
    "view": (
        "dloe_sfm.stages.view", "play a reconstruct output in open3d's window (or write a GIF)"
    ),
    "sync": ("dloe_sfm.stages.sync", "print each stream's time offset and rate of an output"),
    "batch": ("dloe_sfm.stages.batch", "run many captures / COLMAP workspaces as Dask tasks"),
}


class Parser(argparse.ArgumentParser):
    """An ``ArgumentParser`` that takes no abbreviated option (``--keypoint`` is not
    ``--keypoints``) and refuses an unknown one itself, naming the option it is close to."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, allow_abbrev=False, **kwargs)

    def parse_known_args(self, args=None, namespace=None):
        namespace, extras = super().parse_known_args(args, namespace)
        unknown = next((e for e in extras if e.startswith("-")), None)
        if unknown is not None:
            known = [s for a in self._actions for s in a.option_strings if s.startswith("--")]
            close = difflib.get_close_matches(unknown.split("=", 1)[0], known, n=1)
            hint = f"did you mean {close[0]}?" if close else f"see {self.prog} --help"
            self.error(f"unrecognized option {unknown}: {hint}")
        return namespace, extras


def _common_options(parser: argparse.ArgumentParser, *, top: bool) -> None:
    """``-v`` / ``-q`` on the main parser and on every subcommand (either place works); a
    subcommand's copy has no default, so it never resets what was given before it."""
    default = {} if top else {"default": argparse.SUPPRESS}
    group = parser.add_mutually_exclusive_group()
    group.add_argument("--verbose", "-v", action="store_true", help="debug logs (and COLMAP's)",
                       **default)
    group.add_argument("--quiet", "-q", action="store_true", help="warnings and errors only",
                       **default)


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The parser; only ``command``'s stage module is imported (the others load open3d etc.)."""
    parser = Parser(
        prog="dloe-sfm",
        description="Reconstruct moving points from asynchronous images on top of a COLMAP model.",
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    _common_options(parser, top=True)
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, (module_name, summary) in STAGES.items():
        p = sub.add_parser(name, help=summary, description=summary)
        _common_options(p, top=False)
        if name == command:
            module = importlib.import_module(module_name)
            module.configure_parser(p)
            p.set_defaults(_run=module.run)
    return parser


def run_stage(module_name: str, argv: list[str] | None = None) -> int:
    """Entry of ``python -m <stage module>``: the stage's own parser, same error handling."""
    module = importlib.import_module(module_name)
    name = module_name if module_name != "__main__" else module.__spec__.name
    parser = Parser(prog=f"python -m {name}", description=module.__doc__)
    _common_options(parser, top=True)
    module.configure_parser(parser)
    args = parser.parse_args(argv)
    return _execute(parser, module.run, args)


class _BarSafeHandler(logging.StreamHandler):
    """Writes each record through ``tqdm.write``, so a log line never lands on a progress bar."""

    def emit(self, record: logging.LogRecord) -> None:
        try:
            tqdm.write(self.format(record), file=self.stream)
        except Exception:  # logging's own contract: a failing handler never raises
            self.handleError(record)


def setup_logging(*, verbose: bool = False, quiet: bool = False) -> None:
    """The command line's logging: ``[time dloe_sfm LEVEL] message`` on stderr, INFO by
    default, DEBUG with ``verbose`` (COLMAP's logs too), WARNING with ``quiet``. The library
    itself only adds a ``NullHandler``; applications configure ``logging`` as they like."""
    logger = logging.getLogger("dloe_sfm")
    for handler in [h for h in logger.handlers if isinstance(h, _BarSafeHandler)]:
        logger.removeHandler(handler)
    handler = _BarSafeHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("[%(asctime)s %(name)s %(levelname)s] %(message)s",
                                           "%Y/%m/%d %H:%M:%S"))
    logger.addHandler(handler)
    logger.setLevel(logging.DEBUG if verbose else logging.WARNING if quiet else logging.INFO)
    logger.propagate = False


# C0 / C1 controls (newlines, ESC of ANSI sequences) and Unicode line separators
_CONTROL = re.compile("[\x00-\x1f\x7f-\x9f\u2028\u2029]")


def one_line(message: str) -> str:
    """``message`` with control characters escaped (``\\n``, ``\\x1b``): always one line."""
    return _CONTROL.sub(lambda m: m[0].encode("unicode_escape").decode("ascii"), message)


class _Terminated(KeyboardInterrupt):
    """SIGTERM, raised in the main thread like SIGINT's KeyboardInterrupt, so every ``finally``
    (temporary outputs) runs; otherwise pycolmap's (glog's) handler prints a C++ stack trace."""


def _terminate(signum, frame) -> None:
    signal.signal(signal.SIGTERM, signal.SIG_IGN)  # a second SIGTERM must not cut the cleanup
    raise _Terminated


def _execute(parser: argparse.ArgumentParser, run, args: argparse.Namespace) -> int:
    setup_logging(verbose=args.verbose, quiet=args.quiet)
    bars = progress.enabled()
    progress.enable(bars or getattr(args, "progress", False) or sys.stderr.isatty())
    in_main_thread = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGTERM, _terminate) if in_main_thread else None
    try:
        return int(run(args) or 0)
    except InputError as e:
        parser.exit(2, f"{parser.prog}: error: {one_line(str(e))}\n")
    except _Terminated:
        parser.exit(143, "terminated\n")
    except KeyboardInterrupt:
        parser.exit(130, "interrupted\n")
    finally:
        progress.enable(bars)  # a program that called the CLI in-process keeps its own setting
        if in_main_thread:
            signal.signal(signal.SIGTERM, signal.SIG_DFL if previous is None else previous)


def keep_freed_memory() -> None:
    """With glibc, serve allocations up to 32 MB from the heap and keep freed memory there.
    By default glibc maps the solver's numpy temporaries of a few MB afresh each time and hands
    them back on free, a page fault per 4 kB each time: 2-3 s of system time in a 15 s solve of
    310 images (docs/method.md, "Speed"). Elsewhere nothing is changed."""
    try:
        libc = ctypes.CDLL("libc.so.6")
        libc.mallopt(-3, 32 << 20)  # M_MMAP_THRESHOLD
        libc.mallopt(-1, 256 << 20)  # M_TRIM_THRESHOLD
    except (OSError, AttributeError):
        pass


def main(argv: list[str] | None = None) -> int:
    keep_freed_memory()
    argv = sys.argv[1:] if argv is None else list(argv)
    command = next((a for a in argv if a in STAGES), None)
    parser = build_parser(command)
    args = parser.parse_args(argv)
    return _execute(parser, args._run, args)


if __name__ == "__main__":
    sys.exit(main())
