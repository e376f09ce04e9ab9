"""Fuzz the ``dloe-sfm`` command line with hostile and odd inputs (issue 12).

Every case (``fuzz_cases.py``) builds its inputs in its own folder, from a pristine copy of
``assets/demo`` (the COLMAP workspace, binary model, ``keypoints.csv``) or from a small simulated
capture; this runs the real CLI on them in a subprocess (``python -m dloe_sfm.cli ...``, address
space capped at 6 GB, timeout) and checks what a user is promised:

- the exit code: 2 for a bad input (``error``), 0 for a valid one (``ok``), 143 after SIGTERM
  (``sigterm``); ``either`` when the issue leaves the outcome open (0 or 2, each checked);
- an error is ONE line ``dloe-sfm: error: ...`` and no traceback (the package's own log records
  ``[time dloe_sfm LEVEL] ...`` and progress-bar redraws may come before it);
- every input file is byte-identical afterwards (hashes of the case folder, and of
  ``assets/demo`` for ``dloe-sfm demo``);
- no partial output: ``--out`` is absent after an error, complete after a success
  (``report.json`` for a reconstruction, a loadable ``.npz`` for solve / simulate), and no temp
  file or folder (a name with ``tmp``, or a new sibling of ``--out``) is left behind;
- reruns of some valid cases into a fresh ``--out`` give bit-identical arrays.

    python pipelines/fuzz/pipeline.py [--out outputs/fuzz] [--jobs 2] [--only PATTERN] [--quick]
"""

from __future__ import annotations

import argparse
import concurrent.futures
import fnmatch
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
import zipfile
from collections.abc import Callable
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from fuzz_cases import (  # noqa: E402 - the sibling module, also when loaded by path
    REPO,
    Base,
    Case,
    Ctx,
    build_cases,
    child_env,
    tree_hash,
)

MEMORY_LIMIT = 6 * 2**30
MARKER = ".dloe-sfm-fuzz"  # marks a folder this harness owns (it may clear it)
ERROR_PREFIX = "dloe-sfm: error:"
# the package's log records (dloe_sfm/__init__.py) and tqdm redraws are not error messages
LOG_RECORD = re.compile(r"^\[\d{4}/\d\d/\d\d \d\d:\d\d:\d\d dloe_sfm [A-Z]+\] ")
# the child caps its own address space before importing the package (no preexec_fn: threads)
BOOT = ("import resource, sys; resource.setrlimit(resource.RLIMIT_AS, ({0}, {0})); "
        "from dloe_sfm.cli import main; sys.exit(main(sys.argv[1:]))")


# --------------------------------------------------------------------------------------------
# running and checking


def visible_lines(stderr: str) -> list[str]:
    """What a terminal shows of stderr, without the package's log records: the text after the
    last carriage return of each line (progress bars redraw with ``\\r``)."""
    lines = [line.rsplit("\r", 1)[-1] for line in stderr.split("\n")]
    return [line for line in lines if line.strip() and not LOG_RECORD.match(line)]


def is_temp(name: str) -> bool:
    """A temporary file or folder's name (``.out.x1y2.tmp``, ``.dloe_sfm-tmp-...``)."""
    return "tmp" in name.lower()


def listing(folder: Path) -> set[str]:
    return set(os.listdir(folder)) if folder.is_dir() else set()


def temp_names(root: Path) -> list[str]:
    found = []
    for folder, dirs, files in os.walk(root):
        found += [str(Path(folder, n).relative_to(root)) for n in dirs + files if is_temp(n)]
    return found


def complete(out: Path, kind: str | None) -> bool:
    """Whether ``out`` is a whole output of its kind."""
    try:
        if kind == "dir":
            if not (out / "report.json").is_file():
                return False
            json.loads((out / "report.json").read_text())
            with np.load(out / "trajectories.npz") as d:
                return "X" in d.files
        if kind == "npz":
            with np.load(out) as d:
                return bool(d.files) and all(d[k] is not None for k in d.files)
        if kind == "json":
            json.loads(out.read_text())
            return True
    except (OSError, ValueError, zipfile.BadZipFile):
        return False
    return kind is None


def output_arrays(out: Path, kind: str) -> dict[str, np.ndarray]:
    """The arrays a rerun must reproduce (a result's wall time excepted)."""
    path = out / "trajectories.npz" if kind == "dir" else out
    with np.load(path) as d:
        return {k: d[k] for k in d.files if k != "seconds"}


def same_arrays(a: dict[str, np.ndarray], b: dict[str, np.ndarray]) -> bool:
    return a.keys() == b.keys() and all(
        a[k].dtype == b[k].dtype and a[k].shape == b[k].shape and a[k].tobytes() == b[k].tobytes()
        for k in a)


def run_cli(argv: list[str], cwd: Path, timeout: float, *, interrupt: int | None = None,
            out: Path | None = None) -> tuple[int | str, str, float]:
    """(exit code, or 'timeout'; stderr; seconds) of ``dloe-sfm argv`` under the memory cap.

    With ``interrupt``, that signal is sent as soon as a new entry other than ``out`` appears
    beside ``out`` (the temporary output); exit code 'not interrupted' when none did."""
    tic = time.perf_counter()
    watch = None if out is None else out.parent
    seen = listing(watch) if watch is not None else set()
    with tempfile.TemporaryFile() as err:
        proc = subprocess.Popen([sys.executable, "-c", BOOT.format(MEMORY_LIMIT), *argv],
                                cwd=cwd, stdout=subprocess.DEVNULL, stderr=err, env=child_env())
        sent = interrupt is None
        try:
            while not sent and proc.poll() is None and time.perf_counter() - tic < timeout:
                if watch is not None and listing(watch) - seen - {out.name}:
                    proc.send_signal(interrupt)
                    sent = True
                time.sleep(0.005)
            code: int | str = proc.wait(timeout=max(0.1, timeout - (time.perf_counter() - tic)))
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
            code = "timeout"
        err.seek(0)
        stderr = err.read().decode("utf-8", "replace")
    return code if sent else "not interrupted", stderr, time.perf_counter() - tic


def exit_label(code: int | str) -> str:
    if isinstance(code, int) and code < 0:
        return f"killed by {signal.Signals(-code).name}"
    return str(code)


def check_case(case: Case, root: Path, base: Base, timeout: float) -> dict:
    """Build, run and check one case in ``root/<name>``; a dict row of the table."""
    folder = root / case.name
    if folder.exists():
        shutil.rmtree(folder)
    folder.mkdir(parents=True)
    row = {"case": case.name, "group": case.group, "expect": case.expect, "exit": None,
           "seconds": 0.0, "failures": [], "stderr": ""}
    try:
        run = case.setup(Ctx(folder, base))
        for argv in run.pre:
            code, stderr, _ = run_cli(argv, run.cwd or folder, timeout)
            if code != 0:
                raise RuntimeError(f"preparing run exited {exit_label(code)}: "
                                   f"{(visible_lines(stderr) or [''])[-1]}")
        out = run.out
        if out is not None and not out.is_absolute():
            out = (run.cwd or folder) / out
        beside = listing(out.parent) if out is not None else set()
        if run.pre_kill is not None:
            code, _, _ = run_cli(run.pre_kill, run.cwd or folder, timeout,
                                 interrupt=signal.SIGKILL, out=out)
            if code != -signal.SIGKILL:
                raise RuntimeError(f"the run to kill during its export ended {exit_label(code)}")
    except Exception as e:  # noqa: BLE001 - a broken setup is reported as the case's failure
        row["failures"].append("setup")
        row["stderr"] = f"setup failed: {type(e).__name__}: {e}"[:300]
        return row

    existed = out is not None and (out.exists() or out.is_symlink())
    out_is_input = existed and not run.replaced
    was_complete = existed and complete(out, run.kind)

    def exclude(path: Path) -> bool:
        return is_temp(path.name) or (out is not None and not out_is_input and path == out)

    inputs = [folder, *run.extra_inputs]
    before = [tree_hash(p, exclude) for p in inputs]
    code, stderr, seconds = run_cli(run.argv, run.cwd or folder, timeout,
                                    interrupt=run.interrupt, out=out)
    after = [tree_hash(p, exclude) for p in inputs]
    lines = visible_lines(stderr)
    row.update(exit=exit_label(code), seconds=round(seconds, 2),
               stderr=(lines or [""])[-1 if "Traceback" in stderr else 0][:300])

    failures = row["failures"]
    if "Traceback" in stderr:
        failures.append("traceback")
    wanted = {"error": (2,), "ok": (0,), "either": (0, 2), "sigterm": (143,)}[case.expect]
    if code not in wanted:
        failures.append("exit")
    if code == 2 and (len(lines) != 1 or not lines[0].startswith(ERROR_PREFIX)):
        failures.append("message")
    if code == 143 and len(lines) != 1:
        failures.append("message")
    # new folders above the output are made for it, not inputs changed
    made = {str(p.relative_to(folder)) for p in (out.parents if out is not None else [])
            if p.is_relative_to(folder) and p != folder}
    changed = [sorted(set(b) ^ set(a) - (made - set(b))
                      | {k for k in b.keys() & a.keys() if b[k] != a[k]})
               for b, a in zip(before, after, strict=True)]
    if any(changed):
        failures.append("changed")
        row["changed"] = [c[:5] for c in changed if c]
    temps = temp_names(folder)
    if out is not None and out.parent.is_relative_to(folder):  # the output's temp siblings
        temps += sorted(listing(out.parent) - beside - {out.name})
    if temps:
        failures.append("partial")
        row["temps"] = temps[:5]
    elif out is not None and not out_is_input:
        if code == 0:
            broken = run.kind is not None and not complete(out, run.kind)
        elif existed:  # our previous output, damaged by a failed run?
            broken = was_complete and not complete(out, run.kind)
        else:  # nothing may be written by a failed run
            broken = out.exists() or out.is_symlink()
        if broken:
            failures.append("partial")

    if case.rerun and code == 0 and not failures and out is not None and run.kind:
        fresh = folder / ("rerun" + out.suffix)
        argv = [str(fresh) if a == str(run.out) else a for a in run.argv]
        argv = [a for a in argv if a != "--overwrite"]
        code2, stderr2, _ = run_cli(argv, run.cwd or folder, timeout)
        try:
            same = code2 == 0 and same_arrays(output_arrays(out, run.kind),
                                              output_arrays(fresh, run.kind))
        except (OSError, ValueError, zipfile.BadZipFile):
            same = False
        if not same:
            failures.append("rerun")
        row["rerun"] = "identical" if same else f"differs (exit {exit_label(code2)})"
    return row


def select(cases: list[Case], only: str | None, quick: bool) -> list[Case]:
    if quick:
        cases = [c for c in cases if c.quick]
    if only:
        pattern = only if any(ch in only for ch in "*?[") else f"*{only}*"
        cases = [c for c in cases if fnmatch.fnmatch(c.name, pattern)]
    return cases


def prepare_out(out: Path) -> None:
    """Own ``out``: create it, or clear it when this harness made it; refuse anything else."""
    if out.exists():
        if not out.is_dir() or (any(out.iterdir()) and not (out / MARKER).exists()):
            raise SystemExit(f"{out}: exists and is not a fuzz output folder; choose another "
                             "--out")
        shutil.rmtree(out)
    out.mkdir(parents=True)
    (out / MARKER).write_text("made by pipelines/fuzz/pipeline.py; cleared on every run\n")


def run_cases(cases: list[Case], out: Path, *, jobs: int = 2, timeout: float = 120.0,
              keep: bool = False, log: Callable[[str], None] = print) -> dict:
    """Run ``cases`` (``jobs`` at a time) into ``out`` (cleared first); returns the summary,
    also written to ``out/summary.json``."""
    prepare_out(out)
    base = Base(out / "base")
    base.root.mkdir()
    rows: dict[str, dict] = {}
    tic = time.perf_counter()

    def one(case: Case) -> dict:
        row = check_case(case, out / "cases", base, timeout)
        if not row["failures"] and not keep:
            shutil.rmtree(out / "cases" / case.name, ignore_errors=True)
        return row

    with concurrent.futures.ThreadPoolExecutor(max_workers=max(1, jobs)) as pool:
        futures = {pool.submit(one, case): case for case in cases}
        for k, future in enumerate(concurrent.futures.as_completed(futures), 1):
            row = future.result()
            rows[row["case"]] = row
            verdict = "pass" if not row["failures"] else "FAIL " + ",".join(row["failures"])
            log(f"[{k}/{len(cases)}] {row['case']}: {verdict}")

    ordered = [rows[c.name] for c in cases]
    summary = summarise(ordered)
    summary["seconds"] = round(time.perf_counter() - tic, 1)
    doc = {"summary": summary, "line": summary_line(summary),
           "failed": [{"case": r["case"], "failures": r["failures"], "exit": r["exit"],
                       "stderr": r["stderr"]} for r in ordered if r["failures"]],
           "cases": ordered, "settings": {"jobs": jobs, "timeout_s": timeout,
                                          "memory_limit_bytes": MEMORY_LIMIT,
                                          "python": sys.version.split()[0],
                                          "commit": git_commit()}}
    (out / "summary.json").write_text(json.dumps(doc, indent=1, default=str))
    return doc


def summarise(rows: list[dict]) -> dict:
    def count(flag: str) -> int:
        return sum(flag in r["failures"] for r in rows)
    return {"cases": len(rows), "tracebacks": count("traceback"), "wrong_exit": count("exit"),
            "partial": count("partial"), "changed": count("changed"), "rerun": count("rerun"),
            "bad_messages": count("message"), "setup_failures": count("setup"),
            "passed": sum(not r["failures"] for r in rows)}


def summary_line(s: dict) -> str:
    line = (f"{s['cases']} cases: {s['tracebacks']} tracebacks, {s['wrong_exit']} wrong exit "
            f"codes, {s['partial']} partial outputs, {s['changed']} changed inputs, "
            f"{s['rerun']} rerun mismatches")
    extra = f"; {s['bad_messages']} error messages not one line"
    if s["setup_failures"]:
        extra += f", {s['setup_failures']} cases failed to build"
    return line + extra


def git_commit() -> str | None:
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO, text=True,
                              capture_output=True).stdout.strip() or None
    except OSError:
        return None


def print_table(rows: list[dict]) -> None:
    width = max(len(r["case"]) for r in rows)
    print(f"{'case':<{width}}  {'expect':<6}  {'exit':>6}  {'s':>6}  {'verdict':<16}  stderr")
    for r in rows:
        verdict = "pass" if not r["failures"] else ",".join(r["failures"])
        first = r["stderr"].encode("unicode_escape").decode("ascii")[:110]
        print(f"{r['case']:<{width}}  {r['expect']:<6}  {r['exit'] or '-':>6}  "
              f"{r['seconds']:>6.1f}  {verdict:<16}  {first}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(allow_abbrev=False, description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=REPO / "outputs" / "fuzz",
                        help="work folder (cleared; default outputs/fuzz)")
    parser.add_argument("--jobs", type=int, default=2, help="cases run in parallel")
    parser.add_argument("--only", metavar="PATTERN",
                        help="cases whose name matches (glob, or a substring)")
    parser.add_argument("--quick", action="store_true",
                        help="a representative subset (~35 cases)")
    parser.add_argument("--timeout", type=float, default=120.0, help="seconds per CLI run")
    parser.add_argument("--keep", action="store_true",
                        help="keep the folders of passing cases (failing ones are always kept)")
    parser.add_argument("--list", action="store_true", help="list the cases and exit")
    args = parser.parse_args(argv)

    cases = select(build_cases(), args.only, args.quick)
    if args.list:
        for c in cases:
            print(f"{c.name}  {c.expect}  {c.group}{'  quick' if c.quick else ''}")
        return 0
    if not cases:
        parser.error("no case matches")
    doc = run_cases(cases, args.out, jobs=args.jobs, timeout=args.timeout, keep=args.keep,
                    log=lambda s: print(s, file=sys.stderr, flush=True))
    print_table(doc["cases"])
    print(doc["line"])
    print(f"details: {args.out / 'summary.json'}; failing cases' inputs in {args.out / 'cases'}")
    return 0 if not doc["failed"] else 1


if __name__ == "__main__":
    sys.exit(main())
