"""The CLI fuzz harness (pipelines/fuzz): its cases, and three fast ones end to end."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from types import ModuleType

import pytest

from dloe_sfm.synth import load_pipeline

PIPELINES = Path(__file__).resolve().parents[1] / "pipelines"


@pytest.fixture(scope="module")
def fuzz() -> ModuleType:
    return load_pipeline(PIPELINES, "fuzz")


def test_cases_are_many_unique_and_declared(fuzz) -> None:
    cases = fuzz.build_cases()
    names = [c.name for c in cases]
    assert len(cases) >= 150
    assert len(set(names)) == len(names)
    assert {c.expect for c in cases} <= {"error", "ok", "either", "sigterm"}
    assert sum(c.expect == "ok" for c in cases) >= 10
    assert {"output", "cameras", "corrupt", "hostile", "keypoints", "options"} <= {
        c.group for c in cases}
    assert 20 <= len(fuzz.select(cases, None, quick=True)) <= 60


def test_visible_lines_drop_log_records_and_progress_redraws(fuzz) -> None:
    stderr = ("[2026/01/02 03:04:05 dloe_sfm INFO] loaded\n"
              "observations:  10%|#  | 1/10\r                \r"
              "[2026/01/02 03:04:05 dloe_sfm WARNING] odd\n"
              "dloe-sfm: error: bad\n")
    assert fuzz.visible_lines(stderr) == ["dloe-sfm: error: bad"]


def test_fast_error_cases_end_to_end(fuzz, tmp_path) -> None:
    """Three bad inputs give one-line errors with nothing changed; the same 0-byte capture
    declared valid is reported as a wrong exit code (the harness can fail)."""
    cases = {c.name: c for c in fuzz.build_cases()}
    picked = [cases[n] for n in ("npz_zero_bytes", "out_is_workspace",
                                 "reconstruct_toml_invalid")]
    wrong = dataclasses.replace(cases["npz_zero_bytes"], name="zero_bytes_declared_ok",
                                expect="ok")
    doc = fuzz.run_cases([*picked, wrong], tmp_path / "fuzz", jobs=2, timeout=60,
                         log=lambda s: None)
    rows = {r["case"]: r for r in doc["cases"]}
    for case in picked:
        row = rows[case.name]
        assert row["failures"] == [], row
        assert row["exit"] == "2" and row["stderr"].startswith("dloe-sfm: error:")
    assert rows["zero_bytes_declared_ok"]["failures"] == ["exit"]
    assert doc["summary"]["cases"] == 4 and doc["summary"]["passed"] == 3
    assert (tmp_path / "fuzz" / "summary.json").is_file()
    assert doc["line"].startswith("4 cases: 0 tracebacks, 1 wrong exit codes, 0 partial")
