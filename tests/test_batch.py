"""``dloe-sfm batch``: captures and workspaces as Dask tasks, results identical to the serial runs;
a failing job reported, never fatal; bad manifests and outputs refused before anything runs."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scenes import error_line, run_cli

from dloe_sfm import batch
from dloe_sfm.io import MARKER, save_capture
from dloe_sfm.synth import SimulationSettings, load_mocap, simulate

SETTINGS = ["max_iterations=10"]  # every solve of this file: the batch's --set and the serial one


SERIAL = """
import json, sys
from dloe_sfm.stages import solve
for capture, out, overrides in json.loads(sys.argv[1]):
    solve.main(capture, out, overrides=overrides)
"""


@pytest.fixture(scope="module")
def captures(tmp_path_factory, assets_dir) -> tuple[list[Path], list[Path]]:
    """Four small simulated captures (24 images each) and their serial solves
    (``stages.solve.main`` one after another, with one BLAS / OpenMP thread like the workers);
    the last serial result: the first capture with ``robust_loss=none`` too."""
    root = tmp_path_factory.mktemp("captures")
    seq = load_mocap(assets_dir / "mocap" / "jumping_1.npz")
    files = []
    for seed in range(4):
        cap, truth = simulate(seq, SimulationSettings(duration=0.8, rate=10, num_streams=3,
                                                      noise=1.0, seed=seed))
        files.append(save_capture(root / f"take{seed}.npz", cap, truth))
    runs = [(f, root / f"serial{i}.npz", SETTINGS) for i, f in enumerate(files)]
    runs.append((files[0], root / "serial0-robust-off.npz", [*SETTINGS, "robust_loss=none"]))
    r = subprocess.run([sys.executable, "-c", SERIAL,
                        json.dumps([[str(c), str(o), s] for c, o, s in runs])],
                       env={**os.environ, **batch.SINGLE_THREADED}, capture_output=True,
                       text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    return files, [out for _, out, _ in runs]


def assert_same_result(got: Path, expected: Path) -> None:
    """Every array of two result files equal, exactly; ``seconds`` (the solve's wall time)
    aside."""
    with np.load(got) as a, np.load(expected) as b:
        assert sorted(a.files) == sorted(b.files)
        for key in a.files:
            if key != "seconds":
                np.testing.assert_array_equal(a[key], b[key], err_msg=key, strict=True)


def test_jobs_match_the_serial_solves_and_a_bad_one_is_reported(captures, tmp_path,
                                                                 capsys) -> None:
    files, serial = captures
    bad = tmp_path / "broken.npz"
    bad.write_bytes(b"not a zip file")
    out = tmp_path / "season"
    environ = dict(os.environ)
    code, err = run_cli("batch", *files[:2], bad, *files[2:], "--out", out, "--workers", "2",
                        *(a for s in SETTINGS for a in ("--set", s)), capsys=capsys)
    assert code == 1
    assert f"1 of 5 jobs failed: see {out / 'batch.json'}" in err.splitlines()
    assert dict(os.environ) == environ  # the local cluster's thread settings undone
    for file, expected in zip(files, serial[:4], strict=True):
        assert_same_result(out / file.stem / "result.npz", expected)
    report = json.loads((out / "batch.json").read_text())
    assert (report["ok"], report["failed"]) == (4, 1)
    entries = {e["name"]: e for e in report["jobs"]}
    assert [e["name"] for e in report["jobs"]] == ["take0", "take1", "broken", "take2", "take3"]
    failed = entries.pop("broken")
    assert failed["status"] == "failed" and failed["output"] is None
    assert failed["error"] == f"{bad}: not a readable .npz file (File is not a zip file)"
    assert not (out / "broken").exists()
    for name, entry in entries.items():
        assert entry["status"] == "ok" and entry["error"] is None
        assert entry["kind"] == "solve" and entry["output"] == f"{name}/result.npz"
        assert entry["inputs"] == {"capture": str(files[int(name[-1])])}
        summary = entry["summary"]
        assert summary["images"] == 24 and summary["events"] == 1
        assert summary["iterations"] >= 1 and summary["message"]
        assert entry["seconds"] > 0
    assert (out / MARKER).is_file()
    assert sorted(p.name for p in out.iterdir()) == sorted([MARKER, "batch.json", *entries])


def test_manifest_with_a_workspace_on_an_existing_cluster(captures, tmp_path, assets_dir) -> None:
    """A manifest (paths relative to it) of a workspace and a capture with its own options, run
    on a running cluster (its workers single-threaded) into a previous batch's folder."""
    files, serial = captures
    folder = tmp_path / "manifests"
    folder.mkdir()
    field = os.path.relpath(assets_dir / "field", folder)
    (folder / "jobs.toml").write_text(f"""
[[job]]
name = "field"
workspace = "{field}"
format = "csv"
keypoints = "{field}/keypoints.csv"
plots = false
fps = {{ 0 = 10, 1 = 10, 2 = 10, 3 = 10 }}

[[job]]
name = "robust-off"
capture = "{os.path.relpath(files[0], folder)}"
set = ["robust_loss=none"]
""")
    out = tmp_path / "batch"
    out.mkdir()  # an earlier batch's output: replaced
    (out / MARKER).write_text("dloe-sfm\n")
    (out / "batch.json").write_text("{}")
    (out / "old").mkdir()
    jobs = batch.read_jobs([folder / "jobs.toml"])
    assert [(j.name, j.kind) for j in jobs] == [("field", "reconstruct"), ("robust-off", "solve")]
    environ = dict(os.environ)
    with batch._client(None, 1) as client:
        threads = client.run(lambda: {k: os.environ.get(k) for k in batch.SINGLE_THREADED})
        assert list(threads.values()) == [batch.SINGLE_THREADED]
        address = client.scheduler.address
        report = batch.run_batch(jobs, out, scheduler=address,
                                 overrides=SETTINGS, overwrite=True)
    assert dict(os.environ) == environ
    assert not report.failed
    assert not (out / "old").exists()
    assert_same_result(out / "robust-off" / "result.npz", serial[4])
    written = json.loads((out / "batch.json").read_text())
    assert written["scheduler"] == address
    entry = written["jobs"][0]
    assert entry["inputs"] == {"workspace": str((assets_dir / "field").resolve()),
                               "keypoints": str((assets_dir / "field" / "keypoints.csv").resolve()),
                               "format": "csv"}
    assert entry["output"] == "field" and entry["summary"]["images"] == 26
    recon = json.loads((out / "field" / "report.json").read_text())
    assert recon["images"] == 26 and recon["time_unit"] == "s"
    assert not (out / "field" / "plots").exists()
    assert written["jobs"][1]["overrides"] == ["robust_loss=none"]


@pytest.mark.parametrize("table, field", [
    ('capture = "take0.npz"\nkeypoint = "x.json"', "'keypoint'"),
    ('capture = "missing.npz"', "'capture'"),
    ('capture = "take0.npz"\nset = ["lambda1=-1"]', "lambda1"),
    ('capture = "take0.npz"\nset = "lambda1=1"', "'set'"),
    ('capture = "take0.npz"\nname = "a/b"', "'name'"),
    ('workspace = "."\nformat = "csv"\nkeypoints = "take0.npz"\nmin_score = "high"',
     "'min_score'"),
    ('workspace = "."\nformat = "csv"\nkeypoints = "take0.npz"\nperson = -1', "'person'"),
    ('workspace = "."\nformat = "csv"\nkeypoints = "take0.npz"\nfps = { a = 30 }', "'fps'"),
    ('workspace = "."\nformat = "csv"', "'keypoints'"),
    ('workspace = "."\nformat = "yolo"\nkeypoints = "take0.npz"', "'format'"),
    ('workspace = "."\ncapture = "take0.npz"', "'capture'"),
    ('capture = "take0.npz" oops', "invalid TOML"),
])
def test_a_bad_manifest_is_one_line_and_nothing_runs(captures, tmp_path, capsys, table,
                                                     field) -> None:
    files, _ = captures
    (tmp_path / "take0.npz").write_bytes(files[0].read_bytes())
    manifest = tmp_path / "jobs.toml"
    manifest.write_text(f'[[job]]\ncapture = "take0.npz"\n\n[[job]]\n{table}\n')
    out = tmp_path / "out"
    code, err = run_cli("batch", manifest, "--out", out, capsys=capsys)
    line = error_line(err)
    assert code == 2 and line.startswith("dloe-sfm: error: ")
    assert str(manifest) in line and field in line
    if "TOML" not in field:
        assert "[[job]] 2" in line
    assert not out.exists()


def test_outputs_and_names_are_checked_first(captures, tmp_path, capsys) -> None:
    files, _ = captures
    manifest = tmp_path / "jobs.toml"
    manifest.write_text(f'[[job]]\ncapture = "{files[1]}"\nname = "{files[0].stem}"\n')
    code, err = run_cli("batch", files[0], manifest, "--out", tmp_path / "o", capsys=capsys)
    assert code == 2 and f"a second job named '{files[0].stem}'" in error_line(err)
    occupied = tmp_path / "occupied"
    occupied.mkdir()
    (occupied / "notes.txt").write_text("mine")
    for mark in ("", MARKER):  # a folder of the user's, a reconstruct output: not a batch's
        if mark:
            (occupied / mark).write_text("dloe-sfm\n")
        for overwrite in ((), ("--overwrite",)):  # the first message says what to do
            code, err = run_cli("batch", files[0], "--out", occupied, *overwrite, capsys=capsys)
            assert code == 2 and error_line(err).endswith(
                f"{occupied}: not written by dloe-sfm (no batch.json file in it), never "
                "replaced; choose another output path"), err
    assert (occupied / "notes.txt").read_text() == "mine"
    code, err = run_cli("batch", files[0], "--out", files[0].parent / "x", "--set", "bad",
                        capsys=capsys)
    assert code == 2 and "--set bad" in error_line(err)
    code, err = run_cli("batch", files[0], "--out", tmp_path / "x", "--workers", "2",
                        "--scheduler", "tcp://127.0.0.1:1", capsys=capsys)
    assert code == 2 and "--workers" in error_line(err)
    code, err = run_cli("batch", files[0].parent, "--out", tmp_path / "x", capsys=capsys)
    assert code == 2 and "is a folder" in error_line(err)
    code, err = run_cli("batch", files[0], "--out", files[0].parent, capsys=capsys)
    assert code == 2 and "the output contains the input file" in error_line(err)
    assert not (tmp_path / "x").exists() and not (files[0].parent / "x").exists()


@pytest.mark.slow
def test_windows_of_one_capture_on_a_local_cluster(assets_dir) -> None:
    """A capture's overlapping time windows as Dask tasks: the numbers of the windows solved
    in this process (one BLAS thread each way)."""
    from dloe_sfm.core.options import Options
    from dloe_sfm.core.solver import reconstruct
    from dloe_sfm.synth import SimulationSettings as Settings

    cap, truth = simulate(load_mocap(assets_dir / "mocap" / "basketball_signal_1.npz"),
                          Settings(duration=1.5, num_streams=4, rate=30.0))
    options = Options(window_images=80, workers=1, max_iterations=30)
    on_dask = batch.solve_in_windows(cap, options, workers=2)
    here = reconstruct(cap, options)
    np.testing.assert_array_equal(on_dask.X, here.X)
    np.testing.assert_array_equal(on_dask.order, here.order)
    assert (on_dask.W != here.W).nnz == 0
    assert np.array_equal(on_dask.image_status, here.image_status)
    assert 1000 * np.linalg.norm(on_dask.X - truth.X, axis=2).mean() < 1.0
