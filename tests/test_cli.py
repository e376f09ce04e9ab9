"""``dloe-sfm solve / simulate / evaluate`` end to end, and bad input: one line, exit code 2."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from dloe_sfm.config import load_options
from dloe_sfm.core.options import Embedding
from dloe_sfm.errors import InputError
from dloe_sfm.io import load_capture, load_result, load_truth, save_npz


def dloe(*args, cwd=None):
    return subprocess.run(
        [sys.executable, "-m", "dloe_sfm", *map(str, args)],
        capture_output=True,
        text=True,
        cwd=cwd,
        timeout=300,
    )


@pytest.fixture(scope="module")
def capture_file(tmp_path_factory, assets_dir):
    out = tmp_path_factory.mktemp("cli") / "capture.npz"
    r = dloe(
        "simulate",
        assets_dir / "mocap" / "jumping_1.npz",
        "--out",
        out,
        "--duration",
        "1.0",
        "--seed",
        "3",
    )
    assert r.returncode == 0, r.stderr
    return out


def test_simulate_writes_the_protocol(capture_file):
    cap = load_capture(capture_file)
    assert cap.num_points == 28 and np.unique(cap.stream).tolist() == [0, 1, 2, 3]
    t = load_truth(capture_file).t
    assert np.unique(t).size == t.size  # no two images share an instant
    for s in range(4):  # 30 Hz per stream, offsets of a quarter period
        ts = np.sort(t[cap.stream == s])
        assert np.allclose(np.diff(ts), 1 / 30) and np.isclose(ts[0] * 120, s)


def test_simulate_takes_lone_photos_and_bursts_as_counts(assets_dir, tmp_path):
    """``--lone-photos`` and ``--bursts`` are counts on the command line, as in the settings."""
    out = tmp_path / "crowd.npz"
    r = dloe("simulate", assets_dir / "mocap" / "jumping_1.npz", "--out", out, "--duration",
             "1.0", "--num-streams", "1", "--lone-photos", "12", "--bursts", "2")
    assert r.returncode == 0, r.stderr
    cap = load_capture(out)
    assert (cap.stream == -1).sum() == 12 and np.unique(cap.stream[cap.stream >= 0]).size == 3


def test_solve_then_evaluate(capture_file, tmp_path):
    out = tmp_path / "result.npz"
    r = dloe("solve", capture_file, "--out", out, "--set", "embedding=shp")
    assert r.returncode == 0, r.stderr
    res = load_result(out)
    n = load_capture(capture_file).num_images
    assert res.X.shape == (n, 28, 3) and sorted(res.order.tolist()) == list(range(n))
    assert res.A.shape == (n, n) and res.A.nnz < 12 * n
    assert res.events.shape == (n,) and res.cost_history.ndim == 1 and res.seconds > 0
    r = dloe("evaluate", out, capture_file, "--json", tmp_path / "scores.json")
    assert r.returncode == 0, r.stderr
    scores = dict(line.split() for line in r.stdout.strip().splitlines())
    assert float(scores["kendall_tau"]) > 0.99
    assert float(scores["error_mm"]) < 1.5 * float(scores["oracle_mm"]) + 0.5
    assert float(scores["error_mm"]) < 0.5 * float(scores["pseudo_triangulation_mm"])


@pytest.mark.slow
def test_two_people_through_the_command_line(assets_dir, tmp_path):
    """simulate --mix people -> solve (a capture with x (N, 2, P, 2)) -> evaluate."""
    cap, res = tmp_path / "people.npz", tmp_path / "result.npz"
    mocap = assets_dir / "mocap"
    r = dloe("simulate", mocap / "walking_1.npz", mocap / "basketball_signal_1.npz", "--mix",
             "people", "--duration", "1.0", "--rate", "15", "--out", cap)
    assert r.returncode == 0, r.stderr
    assert load_capture(cap).x.shape[1:] == (2, 28, 2)
    r = dloe("solve", cap, "--out", res)
    assert r.returncode == 0, r.stderr
    result = load_result(res)
    assert result.X.shape[1:] == (56, 3) and result.assignment.shape[1] == 2
    assert np.array_equal(result.subject_id, np.repeat([0, 1], 28))
    r = dloe("evaluate", res, cap)
    assert r.returncode == 0, r.stderr
    scores = dict(line.split() for line in r.stdout.strip().splitlines())
    assert float(scores["associated"]) >= 0.98
    assert float(scores["subject_0_error_mm"]) < 10 and float(scores["subject_1_error_mm"]) < 10


def corrupt(src, dst, **changes):
    with np.load(src) as d:
        arrays = {k: d[k] for k in d.files}
    for k, v in changes.items():
        if v is None:
            arrays.pop(k)
        else:
            arrays[k] = v(arrays[k].copy()) if callable(v) else v
    save_npz(dst, **arrays)
    return dst


def nan_camera(C):
    C[3] = np.nan
    return C


def blind_images(*images):
    def blind(x):
        x[list(images)] = np.nan
        return x
    return blind


def test_solve_skips_images_that_observe_no_point(capture_file, tmp_path):
    """An image where the detector found nobody is real input: solve leaves it out with one
    warning naming it, the result file lists it, evaluate pairs the same images."""
    blind = corrupt(capture_file, tmp_path / "blind.npz", x=blind_images(5, 9))
    out = tmp_path / "result.npz"
    r = dloe("solve", blind, "--out", out, "--set", "embedding=shp")
    assert r.returncode == 0, r.stderr
    warnings = [line for line in r.stderr.splitlines() if "WARNING" in line]
    assert len(warnings) == 1, warnings
    assert "2 image(s) observe no point" in warnings[0]
    assert "'cam0/00005', 'cam0/00009'" in warnings[0] and str(blind) in warnings[0]
    n = load_capture(capture_file).num_images
    assert load_result(out).X.shape[0] == n - 2
    with np.load(out) as result:
        assert result["skipped_images"].tolist() == ["cam0/00005", "cam0/00009"]
    r = dloe("evaluate", out, blind, "--no-references")
    assert r.returncode == 0, r.stderr
    scores = dict(line.split() for line in r.stdout.strip().splitlines())
    assert float(scores["kendall_tau"]) > 0.99


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"K": None}, "missing key(s) 'K'"),
        ({"x": lambda x: x[:, :, :1]}, "field 'x' must have shape (N, P, 2)"),
        ({"R": lambda R: R[:-1]}, "field 'R' must have shape"),
        ({"C": nan_camera}, "field 'C' is not finite for image 3"),
        ({"stream": lambda s: np.zeros_like(s)}, "one stream"),
        ({"x": lambda x: np.where(np.arange(len(x))[:, None, None] < 2, x, np.nan)},
         "images observe a point, at least 3 needed"),
        ({"x": lambda x: np.where(np.isnan(x), x, np.inf)}, "infinite"),
        ({"fps": lambda f: f[:-1]}, "field 'fps' must have shape"),
        ({"fps": lambda f: np.where(np.arange(f.size) == 4, -1.0, f)},
         "field 'fps' must be a positive frame rate or NaN (unknown), got -1 for image 4 "
         "('cam0/00004')"),
        ({"fps": lambda f: np.where(np.arange(f.size) == 2, 31.0, f)},
         "field 'fps' holds several rates for stream 0 (30, 31)"),
    ],
)
def test_bad_captures_exit_2_and_write_nothing(capture_file, tmp_path, changes, message):
    bad = corrupt(capture_file, tmp_path / "bad.npz", **changes)
    out = tmp_path / "result.npz"
    r = dloe("solve", bad, "--out", out)
    assert r.returncode == 2
    err = r.stderr.strip().splitlines()
    assert len(err) == 1 and message in err[0] and str(bad) in err[0], err
    assert not out.exists() and list(tmp_path.glob(".dloe_sfm-tmp-*")) == []


def test_not_an_npz(tmp_path):
    bad = tmp_path / "capture.npz"
    bad.write_text("hello")
    r = dloe("solve", bad, "--out", tmp_path / "r.npz")
    assert r.returncode == 2 and "not a readable .npz" in r.stderr


def test_config_file_and_overrides(tmp_path):
    cfg = tmp_path / "solver.toml"
    cfg.write_text("[solver]\nnum_candidates = 6\nembedding = 'mds'\nlambda2 = 0.01\n")
    opts = load_options(cfg, ["num_candidates=5", "spectral_prior=true"])
    assert opts.num_candidates == 5 and opts.embedding is Embedding.MDS
    assert opts.lambda2 == 0.01 and opts.spectral_prior is True
    with pytest.raises(InputError, match="unknown option 'lamda1'"):
        load_options(None, ["lamda1=3"])
    with pytest.raises(InputError, match="'num_candidates' must be an integer in"):
        load_options(None, ["num_candidates=many"])
    cfg.write_text("num_candidates = [")
    with pytest.raises(InputError, match="invalid TOML"):
        load_options(cfg)


def test_every_stage_has_help(capsys):
    from dloe_sfm.cli import STAGES, main

    for stage in STAGES:  # in this process: argparse's help and exit, as on the command line
        with pytest.raises(SystemExit) as exit_info:
            main([stage, "--help"])
        out = capsys.readouterr().out
        assert exit_info.value.code == 0 and out.startswith(f"usage: dloe-sfm {stage}"), stage
    r = dloe("reconstruct", "--help")
    assert r.returncode == 0 and r.stdout.startswith("usage: dloe-sfm reconstruct"), r.stderr
    r = subprocess.run(
        [sys.executable, "-m", "dloe_sfm.stages.solve", "--help"], capture_output=True, text=True
    )
    assert r.returncode == 0 and "python -m dloe_sfm.stages.solve" in r.stdout


def test_version_logging_and_progress_follow_the_flags(capture_file, tmp_path):
    from dloe_sfm import __version__

    r = dloe("--version")
    assert r.returncode == 0 and r.stdout.strip() == f"dloe-sfm {__version__}"
    fast = ["--set", "max_iterations=5", "--set", "robust_iterations=0"]
    # stderr is a pipe, not a terminal: logs (INFO by default), no progress bar
    r = dloe("solve", capture_file, "--out", tmp_path / "a.npz", *fast)
    assert r.returncode == 0 and "dloe_sfm INFO] solving" in r.stderr and "it/s" not in r.stderr
    # -q after the subcommand: nothing below a warning
    r = dloe("solve", capture_file, "--out", tmp_path / "b.npz", *fast, "-q")
    assert r.returncode == 0 and "INFO" not in r.stderr, r.stderr
    # --progress forces the bar, and it ends at 100 % although the solve stops early
    r = dloe("solve", capture_file, "--out", tmp_path / "c.npz", *fast, "--progress", "-v")
    assert r.returncode == 0 and "DEBUG" in r.stderr
    bars = [part for part in r.stderr.replace("\r", "\n").splitlines() if part.startswith("DLOE")]
    assert bars and "100%" in bars[-1], bars[-3:]
    # the library itself only adds a NullHandler
    code = ("import logging, dloe_sfm; h = logging.getLogger('dloe_sfm').handlers; "
            "print([type(x).__name__ for x in h])")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert r.stdout.strip() == "['NullHandler']", r.stdout + r.stderr


@pytest.mark.parametrize(("args", "message"), [
    (["solve", "CAPTURE", "--out", "OUT", "--overwrit"],  # an abbreviation is not taken
     "dloe-sfm solve: error: unrecognized option --overwrit: did you mean --overwrite?"),
    (["--verbos", "solve", "CAPTURE", "--out", "OUT"],
     "dloe-sfm: error: unrecognized option --verbos: did you mean --verbose?"),
    (["solve", "CAPTURE", "--out", "OUT", "--zzz"],
     "dloe-sfm solve: error: unrecognized option --zzz: see dloe-sfm solve --help"),
])
def test_an_abbreviated_or_unknown_option_is_refused_naming_the_one_meant(
        capture_file, tmp_path, args, message):
    named = {"CAPTURE": capture_file, "OUT": tmp_path / "r.npz"}
    r = dloe(*(named.get(a, a) for a in args))
    assert r.returncode == 2 and r.stderr.splitlines()[-1] == message, r.stderr
    assert not (tmp_path / "r.npz").exists()


def test_no_parser_takes_abbreviations():
    from dloe_sfm.synth.mocap import pipeline_parser

    assert pipeline_parser(__file__, None, "x").allow_abbrev is False
    repo = Path(__file__).resolve().parents[1]
    for script in sorted(repo.glob("pipelines/*/pipeline.py")):
        text = script.read_text()
        made = text.count("argparse.ArgumentParser(")
        assert made == text.count("argparse.ArgumentParser(allow_abbrev=False"), script
