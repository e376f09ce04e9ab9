"""Run many captures and COLMAP workspaces as Dask tasks, each like ``solve`` / ``reconstruct``."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ..batch import REPORT, BatchReport, read_jobs, run_batch


def main(items: list[Path | str], out: Path | str, *, scheduler: str | None = None,
         workers: int | None = None, config: Path | str | None = None,
         overrides: list[str] | None = None, overwrite: bool = False) -> BatchReport:
    """The jobs of ``items`` (capture files and TOML manifests: ``batch.read_jobs``) run into
    ``out`` (``batch.run_batch``); every input is checked before any job runs."""
    return run_batch(read_jobs(items), out, scheduler=scheduler, workers=workers, config=config,
                     overrides=overrides, overwrite=overwrite, protected=items)


def _workers(value: str) -> int:
    """``--workers``: a positive integer."""
    try:
        count = int(value)
    except ValueError:
        count = 0
    if count < 1:
        raise argparse.ArgumentTypeError(f"must be a positive integer, got {value!r}")
    return count


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("items", nargs="+", type=Path, metavar="ITEM",
                        help="capture.npz files (a solve job each, named by the file's stem) "
                             "and TOML manifests of [[job]] tables (docs/interfaces.md)")
    parser.add_argument("--out", type=Path, required=True,
                        help="output folder: OUT/<job>/ per job and OUT/batch.json (must not "
                             "exist, see --overwrite)")
    parser.add_argument("--scheduler", metavar="ADDRESS",
                        help="run on the existing Dask cluster of this scheduler "
                             "(tcp://host:port; its workers must see the same files); default: "
                             "a local cluster")
    parser.add_argument("--workers", type=_workers, metavar="N",
                        help="worker processes of the local cluster (default: one per core)")
    parser.add_argument("--config", type=Path, help="TOML file of solver options, for every job")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                        help="override one solver option for every job (repeatable; a "
                             "manifest job's own 'set' comes after)")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace an existing output folder written by dloe-sfm batch")
    parser.add_argument("--progress", action="store_true",
                        help="show the progress bar (default: only on a terminal)")


def run(args: argparse.Namespace) -> int:
    report = main(args.items, args.out, scheduler=args.scheduler, workers=args.workers,
                  config=args.config, overrides=args.overrides, overwrite=args.overwrite)
    if report.failed:
        print(f"{len(report.failed)} of {len(report.jobs)} jobs failed: see "
              f"{args.out / REPORT}", file=sys.stderr)
        return 1
    print(f"{len(report.jobs)} jobs written to {args.out}")
    return 0


if __name__ == "__main__":
    from ..cli import run_stage

    sys.exit(run_stage(__name__))
