"""Output safety through the real CLI: inputs are never replaced, ``--overwrite`` only replaces
what dloe-sfm wrote, the output location is checked before any work, killed runs clean up."""

from __future__ import annotations

import errno
import hashlib
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest
from scenes import error_line, toy_capture
from scenes import run_cli as run

from dloe_sfm.io import MARKER, save_capture

FAST = ["--set", "max_iterations=2", "--set", "robust_iterations=0"]  # the solve is not tested


@pytest.fixture
def ws(tmp_path, assets_dir) -> Path:
    """A copy of the demo workspace (images/, sparse/0, keypoints.csv)."""
    return Path(shutil.copytree(assets_dir / "demo", tmp_path / "ws"))


@pytest.fixture
def capture(tmp_path) -> Path:
    return save_capture(tmp_path / "capture.npz", toy_capture()[0])


def snapshot(root: Path) -> dict[str, str | None]:
    """Every path below ``root`` with the SHA-256 of its bytes (None for folders)."""
    return {p.relative_to(root).as_posix():
            hashlib.sha256(p.read_bytes()).hexdigest() if p.is_file() else None
            for p in sorted(root.rglob("*"))}


def reconstruct(ws: Path, out: Path | str, *extra, plots: bool = False) -> list:
    return ["reconstruct", ws, "--keypoints", ws / "keypoints.csv", "--format", "csv",
            "--out", out, *FAST, *extra, *([] if plots else ["--no-plots"])]


def temps(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.glob(".dloe_sfm-tmp-*"))


@pytest.mark.parametrize(("out", "relation"), [
    ("ws", "contains"),
    ("ws/sparse/0", "is"),
    ("ws/sparse", "contains"),
    ("ws/images", "is"),
    ("ws/images/out", "lies inside"),
    ("ws/keypoints.csv", "is"),
    ("images_link", "is"),  # a symlink to ws/images
    ("config.toml", "is"),
])
def test_out_may_not_touch_an_input(ws, tmp_path, capsys, out, relation) -> None:
    (tmp_path / "images_link").symlink_to(ws / "images")
    (tmp_path / "config.toml").write_text("max_iterations = 2\n")
    before = snapshot(tmp_path)
    code, err = run(*reconstruct(ws, tmp_path / out, "--overwrite", "--config",
                                 tmp_path / "config.toml"), capsys=capsys)
    line = error_line(err)
    assert code == 2 and f"{tmp_path / out}: the output {relation} the input" in line, line
    assert snapshot(tmp_path) == before


def test_out_under_a_file(ws, tmp_path, capsys) -> None:
    before = snapshot(ws)
    code, err = run(*reconstruct(ws, ws / "README.md" / "out"), capsys=capsys)
    assert code == 2
    assert error_line(err).endswith(f"{ws / 'README.md' / 'out'}: cannot create it, "
                                    f"{ws / 'README.md'} is not a folder; choose another "
                                    "output path")
    assert snapshot(ws) == before


def unwritable_folder(tmp_path: Path) -> Path:
    if os.geteuid() != 0:
        locked = tmp_path / "locked"
        locked.mkdir(mode=0o555)
        return locked
    try:  # root ignores permissions; sysfs refuses new files even to root
        with tempfile.TemporaryFile(dir="/sys"):
            pass
    except OSError:
        return Path("/sys")
    pytest.skip("running as root, and no folder refuses root's writes (/sys accepts them)")


def test_unwritable_location(ws, tmp_path, capsys) -> None:
    locked = unwritable_folder(tmp_path)
    before = snapshot(ws)
    out = locked / "new" / "out"
    code, err = run(*reconstruct(ws, out), capsys=capsys)
    assert code == 2 and f"{out}: cannot write in {locked} (" in error_line(err)
    assert snapshot(ws) == before and not (locked / "new").exists()


def test_a_folder_of_the_users_own_is_refused_asking_for_another_out(ws, tmp_path, capsys
                                                                     ) -> None:
    out = tmp_path / "out"
    out.mkdir()
    (out / "thesis.tex").write_text("years of work")
    before = snapshot(tmp_path)
    for overwrite in ((), ("--overwrite",)):  # the first message already names the way out
        code, err = run(*reconstruct(ws, out, *overwrite), capsys=capsys)
        assert code == 2 and error_line(err).endswith(
            f"{out}: not written by dloe-sfm (no {MARKER} file in it), never replaced; "
            "choose another output path"), err
    assert snapshot(tmp_path) == before
    empty = tmp_path / "empty"
    empty.mkdir()
    code, err = run(*reconstruct(ws, empty), capsys=capsys)
    assert code == 2 and f"{empty}: output folder exists (use --overwrite" in error_line(err)


def test_overwrite_replaces_our_own_output_and_removes_stale_temps(ws, tmp_path, capsys) -> None:
    out = tmp_path / "out"
    assert run(*reconstruct(ws, out), capsys=capsys)[0] == 0
    assert (out / MARKER).read_text().startswith("dloe-sfm ")
    first = snapshot(out)
    first.pop("report.json")  # holds timings
    (out / "edited.txt").write_text("replaced with the rest")
    dead = subprocess.Popen([sys.executable, "-c", ""])
    dead.wait()  # its pid no longer runs: its temporaries are stale
    stale = tmp_path / f".dloe_sfm-tmp-{dead.pid}-abcd1234-out"
    live = tmp_path / f".dloe_sfm-tmp-{os.getpid()}-abcd1234-out"  # a run still writing
    other = tmp_path / f".dloe_sfm-tmp-{dead.pid}-abcd1234-other"  # another output's
    for folder in (stale, live, other):
        folder.mkdir()
        (folder / "report.json").write_text("{}")
    before = snapshot(ws)

    code, err = run(*reconstruct(ws, out, "--overwrite"), capsys=capsys)
    assert code == 0, err
    second = snapshot(out)
    assert second.pop("report.json") and second == first  # identical results, extra file gone
    assert temps(tmp_path) == sorted([live.name, other.name])
    assert snapshot(ws) == before


def test_write_failure_is_one_line_and_leaves_nothing(ws, tmp_path, capsys, monkeypatch) -> None:
    def disk_full(*args, **kwargs):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(np, "savez_compressed", disk_full)
    before = snapshot(tmp_path)
    out = tmp_path / "new" / "out"
    code, err = run(*reconstruct(ws, out), capsys=capsys)
    assert code == 2
    assert error_line(err).endswith(f"{out}: cannot write it ({os.strerror(errno.ENOSPC)})")
    assert snapshot(tmp_path) == before


def test_demo_refuses_a_foreign_folder(ws, tmp_path, capsys) -> None:
    out = tmp_path / "photos"
    out.mkdir()
    (out / "holiday.jpg").write_bytes(b"\xff\xd8")
    before = snapshot(tmp_path)
    code, err = run("demo", "--out", out, "--workspace", ws, "--no-plots", capsys=capsys)
    assert code == 2 and f"{out}: not written by dloe-sfm" in error_line(err)
    assert snapshot(tmp_path) == before


def test_solve_never_replaces_its_capture(capture, tmp_path, capsys) -> None:
    (tmp_path / "link.npz").symlink_to(capture)
    before = snapshot(tmp_path)
    for out in (capture, tmp_path / "link.npz"):
        code, err = run("solve", capture, "--out", out, "--overwrite", capsys=capsys)
        assert code == 2 and f"{out}: the output is the input file" in error_line(err)
    assert snapshot(tmp_path) == before


def test_solve_replaces_only_a_result_and_only_with_overwrite(capture, tmp_path, capsys) -> None:
    notes, result = tmp_path / "notes.npz", tmp_path / "result.npz"
    shutil.copy(capture, notes)  # an npz, but not a result
    before = snapshot(tmp_path)
    for overwrite in ((), ("--overwrite",)):
        code, err = run("solve", capture, "--out", notes, *overwrite, capsys=capsys)
        assert code == 2 and error_line(err).endswith(
            f"{notes}: exists and is not a dloe-sfm result file, never replaced; choose "
            "another output path"), err
    assert snapshot(tmp_path) == before

    assert run("solve", capture, "--out", result, *FAST, capsys=capsys)[0] == 0
    code, err = run("solve", capture, "--out", result, *FAST, capsys=capsys)
    assert code == 2 and "use --overwrite" in error_line(err)
    with np.load(result) as r:
        first = r["X"]
    assert run("solve", capture, "--out", result, "--overwrite", *FAST, capsys=capsys)[0] == 0
    with np.load(result) as r:
        np.testing.assert_array_equal(r["X"], first)
    assert temps(tmp_path) == []


def test_error_messages_are_escaped_to_one_line(tmp_path, capsys) -> None:
    bad = tmp_path / "evil\nname\x1b[31m\r.npz"
    code, err = run("solve", bad, "--out", tmp_path / "r.npz", capsys=capsys)
    line = error_line(err)
    assert code == 2 and "evil\\nname\\x1b[31m\\r.npz" in line and "\x1b" not in line


def test_sigterm_cleans_up_and_exits_143(ws, tmp_path) -> None:
    out = tmp_path / "out"
    before = snapshot(ws)
    # with plots, the export (into a temporary folder) lasts seconds: terminate it there
    proc = subprocess.Popen([sys.executable, "-m", "dloe_sfm",
                             *map(str, reconstruct(ws, out, plots=True))],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 120
        while not temps(tmp_path) and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.01)
        assert temps(tmp_path), "the run ended before its export started"
        proc.send_signal(signal.SIGTERM)
        _, stderr = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 143, stderr
    lines = [line for line in re.split(r"[\r\n]", stderr) if line.strip()]
    assert lines[-1] == "terminated", stderr
    assert not any(re.search(r"Traceback|SIGTERM|stack trace|Aborted", line) for line in lines)
    assert not out.exists() and temps(tmp_path) == []
    assert snapshot(ws) == before
