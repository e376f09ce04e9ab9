"""Many captures and COLMAP workspaces in one run, as Dask tasks (``dloe-sfm batch``).

A job is a capture file solved like ``dloe-sfm solve`` or a COLMAP workspace reconstructed like
``dloe-sfm reconstruct``. :func:`read_jobs` takes them from capture files and TOML manifests
(docs/interfaces.md, "Batch manifest"); :func:`run_batch` runs them on a ``dask.distributed``
cluster (a local one by default, or an existing one by its scheduler's address) and writes every
job's output and ``batch.json`` into one folder. A job that fails is reported there, never fatal
to the others.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import os
import re
import threading
import time
import traceback
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from . import __version__, progress
from .cli import one_line
from .config import load_options, read_toml
from .core.assess import assess
from .core.capture import Capture
from .core.options import AUTO_WINDOW, Options, shown
from .core.parallel import THREAD_VARIABLES
from .core.result import Result
from .core.windows import solve_windowed
from .errors import InputError
from .io import atomic_path, check_output
from .keypoints import FORMATS
from .observations import PERSON_MODES

logger = logging.getLogger("dloe_sfm")

REPORT = "batch.json"
"""The batch's own file in its output folder (no job may be named so)."""
RESULT = "result.npz"
"""A solve job's result file inside its folder ``out/<name>/``."""
MAX_MANIFEST_BYTES = 1 << 24
"""A manifest lists jobs in a few hundred bytes each; a larger file is not one (and is not read)."""
SINGLE_THREADED = dict.fromkeys(THREAD_VARIABLES, "1")
"""Set in the local cluster's workers before they start: one BLAS / OpenMP thread each, so that
the workers (one per core) do not oversubscribe the cores."""


@dataclass(frozen=True)
class Job:
    """One capture (``kind`` ``"solve"``) or COLMAP workspace (``"reconstruct"``) of a batch,
    written to ``out/<name>/``.

    ``source``: the capture file or the workspace. ``arguments``: the keyword arguments of
    ``stages.reconstruct.main`` (``keypoints``, ``fmt``, ``stream_pattern``, ...; reconstruct
    jobs only). ``overrides``: the job's own ``--set`` pairs, applied after the batch's.
    """

    name: str
    kind: str
    source: Path
    arguments: dict = field(default_factory=dict)
    overrides: tuple[str, ...] = ()

    def inputs(self) -> dict[str, str | None]:
        """The job's input paths for ``batch.json``."""
        if self.kind == "solve":
            return {"capture": str(self.source)}
        keypoints = self.arguments.get("keypoints")
        return {"workspace": str(self.source),
                "keypoints": None if keypoints is None else str(keypoints),
                "format": self.arguments["fmt"]}

    def output(self) -> str:
        """Where the job writes, relative to the batch's folder."""
        return f"{self.name}/{RESULT}" if self.kind == "solve" else self.name


@dataclass(frozen=True)
class BatchReport:
    """What :func:`run_batch` wrote: ``out`` and the entries of ``out/batch.json``'s ``jobs``
    (in the jobs' order)."""

    out: Path
    jobs: list[dict]

    @property
    def failed(self) -> list[dict]:
        return [entry for entry in self.jobs if entry["status"] != "ok"]


# --- jobs from the command line and manifests ------------------------------------------------

def _check_name(name: object, where: str) -> str:
    """A job name: the name of its output folder."""
    if not isinstance(name, str):
        raise InputError(f"{where}: 'name' must be text, got {shown(name)}")
    if (not name or len(name) > 200 or not name.isprintable() or name.startswith(".")
            or "/" in name or "\\" in name or name == REPORT):
        raise InputError(f"{where}: 'name' {shown(name)} is not a folder name for its output "
                         f"(printable, no '/', not starting with '.', not {REPORT!r})")
    return name


class _Fields:
    """The fields of one ``[[job]]`` table, checked as they are taken."""

    def __init__(self, table: dict, manifest: Path, where: str):
        self.table, self.folder, self.where = table, manifest.parent, where

    def fail(self, key: str, problem: str) -> InputError:
        return InputError(f"{self.where}: '{key}' {problem}")

    def text(self, key: str) -> str | None:
        value = self.table.get(key)
        if value is not None and not isinstance(value, str):
            raise self.fail(key, f"must be text, got {shown(value)}")
        return value

    def path(self, key: str, what: str) -> Path | None:
        """A path (relative to the manifest's folder) to an existing ``what`` (file, folder,
        file or folder)."""
        text = self.text(key)
        if text is None:
            return None
        path = (self.folder / text).resolve()
        found = {"file": path.is_file(), "folder": path.is_dir(),
                 "file or folder": path.exists()}[what]
        if not found:
            raise self.fail(key, f"{shown(text)}: no such {what} ({path})")
        return path

    def number(self, key: str, *, positive: bool = False) -> float | None:
        value = self.table.get(key)
        if value is None:
            return None
        if (isinstance(value, bool) or not isinstance(value, (int, float))
                or not math.isfinite(value) or (positive and value <= 0)):
            kind = "a positive number" if positive else "a finite number"
            raise self.fail(key, f"must be {kind}, got {shown(value)}")
        return value

    def person(self) -> str | int | None:
        value = self.table.get("person")
        if value is None or value in PERSON_MODES:
            return value
        if isinstance(value, bool) or not isinstance(value, int) or value < 0:
            raise self.fail("person", f"must be {', '.join(PERSON_MODES)} or an index >= 0, "
                                      f"got {shown(value)}")
        return value

    def fps(self) -> float | dict[int, float] | None:
        value = self.table.get("fps")
        if not isinstance(value, dict):
            return self.number("fps", positive=True)
        rates = {}
        for stream, rate in value.items():
            try:
                key = int(stream)
            except ValueError:
                raise self.fail("fps", f"has stream {shown(stream)}; streams are numbered as "
                                       "in report.json's sync") from None
            if key in rates:
                raise self.fail("fps", f"gives stream {key} twice")
            if (isinstance(rate, bool) or not isinstance(rate, (int, float))
                    or not (math.isfinite(rate) and rate > 0)):
                raise self.fail("fps", f"must give positive numbers, got {shown(rate)} for "
                                       f"stream {key}")
            rates[key] = float(rate)
        return rates

    def overrides(self) -> tuple[str, ...]:
        value = self.table.get("set", [])
        if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
            raise self.fail("set", f"must be a list of \"key=value\" texts, got {shown(value)}")
        try:
            load_options(None, value)
        except InputError as e:
            raise InputError(f"{self.where}: {e}") from None
        return tuple(value)


_COMMON = ("name", "set")
_SOLVE_KEYS = ("capture",)
_RECONSTRUCT_KEYS = ("workspace", "format", "keypoints", "stream_pattern", "min_score", "person",
                     "layout", "aruco_dict", "plots", "export_rate", "fps")


def _manifest_job(table: object, manifest: Path, index: int) -> Job:
    """``[[job]]`` table number ``index`` (from 1) of ``manifest`` as a Job."""
    where = f"{manifest}: [[job]] {index}"
    if not isinstance(table, dict):
        raise InputError(f"{where}: not a table")
    if "name" in table:
        where = f"{where} ({_check_name(table['name'], where)})"
    if ("capture" in table) == ("workspace" in table):
        raise InputError(f"{where}: give either 'capture' (a solve job) or 'workspace' "
                         "(a reconstruct job)")
    kind = "solve" if "capture" in table else "reconstruct"
    allowed = _COMMON + (_SOLVE_KEYS if kind == "solve" else _RECONSTRUCT_KEYS)
    unknown = [k for k in table if k not in allowed]
    if unknown:
        raise InputError(f"{where}: unknown field {shown(unknown[0])} for a {kind} job "
                         f"(fields: {', '.join(allowed)})")
    f = _Fields(table, manifest, where)
    overrides = f.overrides()
    if kind == "solve":
        source = f.path("capture", "file")
        return Job(name=table.get("name", source.stem), kind=kind, source=source,
                   overrides=overrides)
    source = f.path("workspace", "folder")
    fmt = f.text("format")
    if fmt is None or fmt.lower() not in FORMATS:
        raise f.fail("format", f"must be one of {', '.join(FORMATS)}, got {shown(fmt)}")
    aruco = fmt.lower() == "aruco"
    keypoints = f.path("keypoints", "file or folder")
    if keypoints is None and not aruco:
        raise f.fail("keypoints", f"is missing (required for format {fmt!r})")
    if "aruco_dict" in table and not aruco:
        raise f.fail("aruco_dict", f"is only for format 'aruco', not {fmt!r}")
    pattern = f.text("stream_pattern")
    if pattern is not None:
        try:
            re.compile(pattern)
        except re.error as e:
            raise f.fail("stream_pattern", f"is not a regular expression ({e})") from None
    layout = f.text("layout")
    if layout is not None and Path(layout).suffix.lower() == ".json":
        layout = f.path("layout", "file")
    plots = table.get("plots", True)
    if not isinstance(plots, bool):
        raise f.fail("plots", f"must be true or false, got {shown(plots)}")
    arguments = {"keypoints": keypoints, "fmt": fmt, "stream_pattern": pattern,
                 "min_score": f.number("min_score"), "person": f.person(), "layout": layout,
                 "aruco_dict": f.text("aruco_dict"), "plots": plots,
                 "export_rate": f.number("export_rate", positive=True), "fps": f.fps()}
    arguments = {k: v for k, v in arguments.items() if v is not None}
    return Job(name=table.get("name", source.name), kind=kind, source=source,
               arguments=arguments, overrides=overrides)


def _read_manifest(path: Path) -> list[Job]:
    """The jobs of manifest ``path`` (a TOML file of ``[[job]]`` tables)."""
    data = read_toml(path, what="manifest", kind="a batch manifest", limit=MAX_MANIFEST_BYTES)
    unknown = [k for k in data if k != "job"]
    if unknown:
        raise InputError(f"{path}: unknown key {shown(unknown[0])} (a manifest holds [[job]] "
                         "tables only)")
    tables = data.get("job")
    if not isinstance(tables, list) or not tables:
        raise InputError(f"{path}: no [[job]] tables")
    return [_manifest_job(table, path, i) for i, table in enumerate(tables, 1)]


def read_jobs(items: Iterable[Path | str]) -> list[Job]:
    """The jobs of ``items``: capture files (a solve job each, named by the file's stem) and
    TOML manifests (``*.toml``). Every problem (a missing file, a bad field, two jobs of the
    same name) is a one-line InputError naming the file and the job / field."""
    jobs, origins = [], {}
    for item in map(Path, items):
        if item.suffix.lower() == ".toml":
            if not item.is_file():
                raise InputError(f"{item}: no such manifest file")
            found = _read_manifest(item)
        elif item.is_file():
            found = [Job(name=_check_name(item.stem, str(item)), kind="solve",
                         source=item.resolve())]
        elif item.is_dir():
            raise InputError(f"{item}: is a folder; give capture files or TOML manifests (a "
                             "workspace is a manifest's job)")
        else:
            raise InputError(f"{item}: no such capture file")
        for job in found:
            if job.name in origins:
                raise InputError(f"{item}: a second job named {job.name!r} (the first from "
                                 f"{origins[job.name]}); give each job its own name")
            origins[job.name] = item
        jobs.extend(found)
    return jobs


# --- one job, in a worker ---------------------------------------------------------------------

class _JobLog(logging.Handler):
    """Keeps the ``dloe_sfm`` log records of the jobs running in this process, by thread."""

    def __init__(self):
        super().__init__(logging.INFO)
        self.jobs: dict[int, list[logging.LogRecord]] = {}
        self.level_before = logging.NOTSET
        self.lock = threading.Lock()

    def emit(self, record: logging.LogRecord) -> None:
        records = self.jobs.get(record.thread)
        if records is not None:
            records.append(record)

    @contextlib.contextmanager
    def collect(self) -> Iterator[list[logging.LogRecord]]:
        """The records the calling thread logs meanwhile (INFO and above)."""
        package = logging.getLogger("dloe_sfm")
        records: list[logging.LogRecord] = []
        with self.lock:
            if not self.jobs:
                package.addHandler(self)
                self.level_before = package.level
                if not package.isEnabledFor(logging.INFO):
                    package.setLevel(logging.INFO)
            self.jobs[threading.get_ident()] = records
        try:
            yield records
        finally:
            with self.lock:
                del self.jobs[threading.get_ident()]
                if not self.jobs:
                    package.removeHandler(self)
                    package.setLevel(self.level_before)


_job_log = _JobLog()


def _solve(job: Job, folder: Path, config: Path | None, overrides: list[str]) -> dict:
    from .stages import solve

    result = solve.main(job.source, folder / RESULT, config=config, overrides=overrides)
    return {"images": int(result.X.shape[0]), "iterations": int(result.nit),
            "events": int(result.events.max()) + 1, "message": str(result.message)}


def _reconstruct(job: Job, folder: Path, config: Path | None, overrides: list[str]) -> dict:
    from .stages import reconstruct

    out = reconstruct.main(job.source, out=folder, config=config, overrides=overrides,
                           **job.arguments)
    report = json.loads((out / "report.json").read_text(encoding="utf-8"))
    return {"images": report["images"], "iterations": report["solver"]["iterations"],
            "events": report["events"], "message": report["solver"]["message"]}


def _run_job(job: Job, folder: Path, config: Path | None, overrides: list[str]) -> dict:
    """Run ``job`` into ``folder`` (a Dask task): its outcome, never an exception. ``log``
    holds the job's log lines and ``traceback`` that of an unexpected error, for the client's
    log."""
    run = _solve if job.kind == "solve" else _reconstruct
    tic = time.perf_counter()
    summary = error = trace = None
    with _job_log.collect() as records:
        try:
            summary = run(job, folder, config, [*overrides, *job.overrides])
        except InputError as e:
            error = str(e)
        except Exception as e:
            error, trace = f"{type(e).__name__}: {e}", traceback.format_exc()
    return {"summary": summary, "error": error, "seconds": time.perf_counter() - tic,
            "log": [(r.levelno, r.getMessage()) for r in records], "traceback": trace}


# --- the batch ---------------------------------------------------------------------------------

@contextlib.contextmanager
def _client(scheduler: str | None, workers: int) -> Iterator:
    """A ``distributed.Client`` of the cluster at ``scheduler``, or of a new local cluster of
    ``workers`` single-threaded worker processes (closed on exit). The local workers have no
    Dask memory limit: the stages check the memory a solve needs themselves, and a limit of RAM
    / workers would pause or restart a worker running one large job that fits in RAM."""
    import dask
    from distributed import Client, LocalCluster

    if scheduler is not None:
        try:
            client = Client(scheduler)
        except (OSError, ValueError, TypeError) as e:
            raise InputError(f"--scheduler {shown(scheduler)}: cannot connect "
                             f"({' '.join(str(e).split()) or type(e).__name__})") from None
        with client:
            yield client
        return
    # the nanny sets these in its own process before it spawns a worker: put ours back after
    environ = dict(os.environ)
    spawn_env = {**dask.config.get("distributed.nanny.pre-spawn-environ"), **SINGLE_THREADED}
    try:
        with dask.config.set({"distributed.nanny.pre-spawn-environ": spawn_env}), \
                LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                             memory_limit=0, dashboard_address=None) as cluster, \
                Client(cluster) as client:
            yield client
    finally:
        for key in set(os.environ) - set(environ):
            del os.environ[key]
        os.environ.update(environ)


def solve_in_windows(capture: Capture, options: Options | None = None, *,
                     scheduler: str | None = None, workers: int | None = None) -> Result:
    """One capture too large for one solve: its overlapping time windows (``core.windows``,
    ``options.window_images`` images each, at least 2: default 10 000) solved as Dask tasks on
    the cluster at ``scheduler`` or a local one of ``workers`` processes (default: one per
    core), stitched here and assessed as :func:`dloe_sfm.core.solver.reconstruct` does. The same
    numbers as the windows solved in this process."""
    options = options or Options()
    size = options.window_size(capture.num_images) or min(AUTO_WINDOW, capture.num_images // 2)
    with _client(scheduler, workers or os.cpu_count() or 1) as client:
        def mapper(fn, items):
            return client.gather(client.map(fn, list(items), pure=False))

        result = solve_windowed(capture, options, size, size // 10, mapper)
    return assess(capture, result, lambda1=options.lambda1)


def _check_jobs(jobs: Sequence[Job]) -> None:
    if not jobs:
        raise InputError("no jobs to run")
    names = set()
    for job in jobs:
        _check_name(job.name, f"job {job.name!r}")
        if job.kind not in ("solve", "reconstruct"):
            raise InputError(f"job {job.name!r}: kind must be 'solve' or 'reconstruct', "
                             f"got {shown(job.kind)}")
        if job.name in names:
            raise InputError(f"two jobs named {job.name!r}; give each job its own name")
        names.add(job.name)


def _protected(job: Job) -> list[Path | str | None]:
    """The inputs of ``job`` the batch's output may not be, contain or lie inside."""
    if job.kind == "solve":
        return [job.source]
    layout = job.arguments.get("layout")
    return [job.source / "images", job.source / "sparse", job.arguments.get("keypoints"),
            layout if isinstance(layout, Path) else None]


def run_batch(jobs: Sequence[Job], out: Path | str, *, scheduler: str | None = None,
              workers: int | None = None, config: Path | str | None = None,
              overrides: Sequence[str] | None = None, overwrite: bool = False,
              protected: Sequence[Path | str] = ()) -> BatchReport:
    """Run ``jobs`` as Dask tasks; every job writes ``out/<name>/`` (a solve job its
    ``result.npz``, a reconstruct job the stage's folder), ``out/batch.json`` says how each
    went (docs/interfaces.md, "Batch outputs").

    ``scheduler``: the address of a running cluster's scheduler (``tcp://host:port``), whose
    workers see the same files; default a local cluster of ``workers`` (default one per core)
    processes of one thread and one BLAS thread each. ``config`` and ``overrides`` (solver
    options, ``--config`` / ``--set``) apply to every job, before its own ``overrides``.
    ``protected``: further inputs (the manifests) ``out`` may not be, contain or lie inside.

    ``out`` is checked first: never an input, an existing folder only replaced with
    ``overwrite`` and when ``dloe-sfm batch`` wrote it; it is written atomically once every job
    is done (on an interrupt nothing is left). A job that fails is reported in ``batch.json``,
    the others go on.
    """
    jobs = list(jobs)
    _check_jobs(jobs)
    overrides = list(overrides or [])
    load_options(config, overrides)
    if scheduler is not None and workers is not None:
        raise InputError("--workers is for the local cluster, not with --scheduler")
    if workers is not None and workers < 1:
        raise InputError(f"--workers must be at least 1, got {workers}")
    out = Path(out)
    config = None if config is None else Path(config).resolve()
    target = check_output(out, overwrite=overwrite, marker=REPORT, protected=[
        config, *protected, *(p for job in jobs for p in _protected(job))])
    with atomic_path(target, mark=True) as tmp:
        tmp.mkdir()
        with _client(scheduler, min(workers or os.cpu_count() or 1, len(jobs))) as client:
            entries = _run_all(client, jobs, tmp, out, config, overrides)
        report = {
            "dloe_sfm_version": __version__,
            "scheduler": scheduler or "local",
            "config": None if config is None else str(config),
            "overrides": overrides,
            "ok": sum(e["status"] == "ok" for e in entries.values()),
            "failed": sum(e["status"] != "ok" for e in entries.values()),
            "jobs": [entries[job.name] for job in jobs],
        }
        (tmp / REPORT).write_text(json.dumps(report, indent=2) + "\n", encoding="utf-8")
    return BatchReport(out=out, jobs=report["jobs"])


def _run_all(client, jobs: list[Job], tmp: Path, out: Path, config: Path | None,
             overrides: list[str]) -> dict[str, dict]:
    """Submit every job, collect their ``batch.json`` entries as they finish (by name)."""
    from distributed import as_completed

    futures = {client.submit(_run_job, job, tmp / job.name, config, overrides, pure=False): job
               for job in jobs}
    entries = {}
    with progress.bar(total=len(jobs), desc="batch", unit="job") as bar:
        for future in as_completed(futures):
            job = futures[future]
            try:
                outcome = future.result()
            except Exception as e:  # the task itself failed (a worker died, a lost cluster)
                outcome = {"summary": None, "error": f"{type(e).__name__}: {e}",
                           "seconds": None, "log": [], "traceback": None}
            for level, line in outcome["log"]:
                logger.log(level if level >= logging.WARNING else logging.DEBUG, "%s: %s",
                           job.name, line.replace(str(tmp), str(out)))
            entry = {"name": job.name, "kind": job.kind, "inputs": job.inputs(),
                     "overrides": list(job.overrides), "output": None, "status": "failed",
                     "error": None, "seconds": outcome["seconds"]}
            if outcome["error"] is None:
                entry.update(output=job.output(), status="ok", summary=outcome["summary"])
                s = outcome["summary"]
                logger.info("%s: ok in %.1f s (%d images, %d iterations, %d event(s)): %s",
                            job.name, outcome["seconds"], s["images"], s["iterations"],
                            s["events"], out / job.output())
            else:
                entry["error"] = one_line(outcome["error"].replace(str(tmp), str(out)))
                if outcome["traceback"]:
                    logger.debug("%s: %s", job.name, outcome["traceback"])
                logger.warning("%s: failed: %s", job.name, entry["error"])
            entries[job.name] = entry
            bar.update()
    return entries
