"""``dloe-sfm``: one subcommand per pipeline stage (also ``python -m dloe_sfm.<stage>``)."""

from __future__ import annotations

import argparse
import importlib
import logging
import sys

from .errors import InputError

# subcommand -> (module with ``configure_parser(parser)`` and ``run(args) -> int``, summary)
STAGES = {
    "solve": ("dloe_sfm.solve", "run DLOE on a capture file and write a result file"),
    "reconstruct": (
        "dloe_sfm.reconstruct",
        "reconstruct moving points from keypoints on a COLMAP workspace",
    ),
    "simulate": ("dloe_sfm.simulate", "simulate an unsynchronised capture of a mocap sequence"),
    "evaluate": ("dloe_sfm.evaluate", "score a result against ground truth (mm, Kendall tau)"),
    "demo": ("dloe_sfm.demo", "run the whole chain on the bundled demo workspace"),
    "benchmark": ("dloe_sfm.benchmark", "the paper's experiments with every baseline"),
}


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The parser; only ``command``'s stage module is imported (the others load open3d etc.)."""
    parser = argparse.ArgumentParser(
        prog="dloe-sfm",
        description="Reconstruct moving points from asynchronous images on top of a COLMAP model.",
    )
    parser.add_argument("--verbose", "-v", action="store_true", help="debug logs (and COLMAP's)")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, (module_name, summary) in STAGES.items():
        p = sub.add_parser(name, help=summary, description=summary)
        if name == command:
            module = importlib.import_module(module_name)
            module.configure_parser(p)
            p.set_defaults(_run=module.run)
    return parser


def run_stage(module_name: str, argv: list[str] | None = None) -> int:
    """Entry of ``python -m dloe_sfm.<stage>``: the stage's own parser, same error handling."""
    module = importlib.import_module(module_name)
    name = module_name if module_name != "__main__" else module.__spec__.name
    parser = argparse.ArgumentParser(prog=f"python -m {name}", description=module.__doc__)
    parser.add_argument("--verbose", "-v", action="store_true")
    module.configure_parser(parser)
    args = parser.parse_args(argv)
    return _execute(parser, module.run, args)


def _execute(parser: argparse.ArgumentParser, run, args: argparse.Namespace) -> int:
    if args.verbose:
        logging.getLogger("dloe_sfm").setLevel(logging.DEBUG)
    try:
        return int(run(args) or 0)
    except InputError as e:
        parser.exit(2, f"{parser.prog}: error: {e}\n")
    except KeyboardInterrupt:
        parser.exit(130, "interrupted\n")


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    command = next((a for a in argv if a in STAGES), None)
    parser = build_parser(command)
    args = parser.parse_args(argv)
    return _execute(parser, args._run, args)


if __name__ == "__main__":
    sys.exit(main())
