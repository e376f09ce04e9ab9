"""Sub-frame synchronisation (docs/interfaces.md, "Synchronisation"): stream clocks with
uncertainty against simulated truth, ``--fps``, ``dloe-sfm sync``."""

from __future__ import annotations

import csv
import json
from dataclasses import replace

import numpy as np
import pytest

from dloe_sfm import reconstruct
from dloe_sfm.cli import main as cli_main
from dloe_sfm.core.clocked import Placement, on_clocks, outlier_arrays
from dloe_sfm.core.clocks import rank_times
from dloe_sfm.core.options import Options
from dloe_sfm.core.sync import capture_fps, check_fps, stream_clocks, with_fps
from dloe_sfm.errors import InputError
from dloe_sfm.export import export_outputs
from dloe_sfm.io import load_capture, load_result, save_capture, save_result
from dloe_sfm.stages.sync import parse_fps
from dloe_sfm.synth import SimulationSettings, load_mocap, simulate

RATES = (24.0, 25.0, 29.97, 30.0)
OFFSET_TOLERANCE = 0.1
"""Largest offset error on clean data, in reference frames."""


@pytest.fixture(scope="module")
def walking(assets_dir):
    """Walking at four rates from random start times (the capture knows its frame rates)."""
    seq = load_mocap(assets_dir / "mocap" / "walking_1.npz")
    return simulate(seq, SimulationSettings(rates=RATES, random_offsets=True, duration=1.5,
                                            seed=1))


@pytest.fixture(scope="module")
def solved(walking, tmp_path_factory):
    """The walk with its frame rates unknown, solved with default options and exported with
    the true frame rates (``--fps``)."""
    capture, truth = replace(walking.capture, fps=None), walking.truth
    result = reconstruct(capture, Options())
    out = tmp_path_factory.mktemp("sync") / "out"
    fps = {k: r for k, r in enumerate(RATES)}
    report = export_outputs(out, capture, result, plots=False, fps=fps)
    return capture, truth, out, report, result


def true_offsets(capture, truth, ref: int) -> dict[int, float]:
    """Every stream's frame 0 in the reference stream's frames (its frame 0 = 0)."""
    t0 = {int(s): truth.t[(capture.stream == s) & (capture.frame == 0)][0]
          for s in np.unique(capture.stream)}
    return {s: (t - t0[ref]) * RATES[ref] for s, t in t0.items()}


def test_offsets_match_the_truth_within_a_tenth_of_a_frame_and_three_sigma(solved):
    capture, truth, _, report, _ = solved
    assert report["time_unit"] == "s"
    event = report["sync"]["events"][0]
    ref = event["reference_stream"]
    truth_offsets = true_offsets(capture, truth, ref)
    assert set(event["streams"]) == {"0", "1", "2", "3"}
    for name, clock in event["streams"].items():
        error = clock["offset_frames"] - truth_offsets[int(name)]
        assert abs(error) < OFFSET_TOLERANCE, (name, error)
        if int(name) == ref:
            # the reference's own line through its times: 1 up to the least-squares rounding
            assert clock["offset_sd"] == 0.0 and clock["rate"] == pytest.approx(1.0, rel=1e-12)
            continue
        assert abs(error) < 3 * clock["offset_sd_frames"], (name, error, clock)
        assert clock["offset_ms"] == pytest.approx(1000 * clock["offset_frames"] / RATES[ref])
        assert abs(clock["implied_fps"] - RATES[int(name)]) < 3 * RATES[ref] * clock["rate_sd"]
        assert clock["fps_consistent"] and clock["fps_deviation_sd"] < 3, (name, clock)
    assert event["base"] in ("clock", "affine embedding")


def test_rank_times_give_bursts_an_honest_uncertainty(assets_dir):
    """Lone photos and bursts of 2-5 frames at random instants, in their true order: the rank
    base times them evenly between the reference burst's frames, and each other burst's
    offset comes with a standard uncertainty none of them lacks (a burst of two frames fits its
    line exactly) that covers the truth nearly as a normal one would (68 % within one, 95 %
    within two): over these 10 captures' 120 bursts 72 % and 91 % (bursts cluster images in
    time, more than the random instants the uncertainty assumes)."""
    motion, z = load_mocap(assets_dir / "mocap" / "walking_1.npz"), []
    for seed in range(10):
        sim = simulate(motion, SimulationSettings(
            duration=3.0, num_streams=0, lone_photos=40, bursts=13, seed=seed))
        capture, t_true = sim.capture, sim.truth.t
        order = np.argsort(t_true)
        ids, frames = capture.stream_ids, capture.frame
        counts = {int(s): int((ids == s).sum()) for s in np.unique(ids[capture.stream >= 0])}
        ref = max(counts, key=lambda s: (counts[s], -s))
        time = np.empty(t_true.size)
        time[order] = rank_times(ids[order], frames[order], ref)
        event = {"event": 0, "base": "rank", "clocks_dropped": False, "reference_stream": ref}
        clocks = stream_clocks(capture, np.zeros(t_true.size, dtype=np.int64), time, [event])
        true_line = {s: np.polyfit(frames[ids == s], t_true[ids == s], 1) for s in counts}
        period, start = true_line[ref]  # s per frame, s
        for s, clock in clocks[0]["streams"].items():
            if s != ref:
                assert clock["offset_sd"] > 0 and clock["rate_sd"] > 0, (seed, s, clock)
                z.append((clock["offset"] - (true_line[s][1] - start) / period)
                         / clock["offset_sd"])
    z = np.abs(np.array(z))
    assert z.size >= 100
    assert 0.6 <= np.mean(z <= 1) <= 0.85 and np.mean(z <= 2) >= 0.88, (np.mean(z <= 1),
                                                                         np.mean(z <= 2))


def test_the_captures_frame_rates_give_seconds_without_fps(walking, solved, tmp_path):
    """A capture that knows its frame rates (``fps``, as ``simulate`` writes) has its report
    count seconds without ``--fps``, with the offsets of the same capture solved without them
    and exported with ``--fps``: within a tenth of their standard uncertainty (0.009 ms at most
    against 0.35-0.62), the solve holding the known rates in its placement (docs/method.md,
    "Known rates in the placement"), the other's clocks starting from rates it fitted."""
    capture, _ = walking
    report = export_outputs(tmp_path / "out", capture, reconstruct(capture, Options()),
                            plots=False)
    assert report["time_unit"] == "s"
    told = solved[3]["sync"]["events"][0]["streams"]
    for name, clock in report["sync"]["events"][0]["streams"].items():
        assert clock["fps"] == RATES[int(name)]
        assert clock["offset_ms"] == pytest.approx(told[name]["offset_ms"],
                                                   abs=0.1 * told[name]["offset_sd_ms"])


def test_frame_rates_go_into_the_capture_and_round_trip(walking, tmp_path):
    """``--fps`` fills or replaces a capture's frame rates per stream (never a lone photo's),
    and the capture file keeps them."""
    capture = walking.capture
    unknown = replace(capture, fps=None)
    assert capture_fps(unknown) is None
    assert capture_fps(capture) == dict(enumerate(RATES))
    assert (with_fps(unknown, 25.0).fps == 25.0).all()
    changed = with_fps(capture, {1: 50.0})
    assert capture_fps(changed) == {0: 24.0, 1: 50.0, 2: 29.97, 3: 30.0}
    photos = with_fps(replace(unknown, stream=np.where(np.arange(capture.num_images) < 2, -1,
                                                          capture.stream)), 30.0)
    assert np.isnan(photos.fps[:2]).all() and (photos.fps[2:] == 30.0).all()
    loaded = load_capture(save_capture(tmp_path / "capture.npz", changed))
    np.testing.assert_array_equal(loaded.fps, changed.fps)


def sequence_times(out) -> tuple[np.ndarray, list[str]]:
    """``sequence.csv``'s times and image names, in its rows' order."""
    with open(out / "sequence.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    return np.array([float(r["time"]) for r in rows]), [r["image"] for r in rows]


def test_sequence_times_are_seconds_with_fps(solved):
    capture, truth, out, _, _ = solved
    t, images = sequence_times(out)
    index = {str(n): i for i, n in enumerate(capture.image_names)}
    t_true = truth.t[[index[name] for name in images]]
    error = t - t_true
    period = 1 / max(RATES)
    assert np.sqrt(np.mean((error - error.mean()) ** 2)) < 0.1 * period


@pytest.mark.parametrize(("values", "expected"), [
    (None, None), (["30"], 30.0), (["0=30", "1=29.97"], {0: 30.0, 1: 29.97}),
])
def test_parse_fps(values, expected):
    assert parse_fps(values) == expected


@pytest.mark.parametrize(("values", "message"), [
    (["0"], "positive"), (["nan"], "positive"), (["0=30", "1=-1"], "positive"),
    (["cam=30"], "unknown stream 'cam'"), (["0=30", "0=25"], "twice"), (["30", "1=25"], "pairs"),
])
def test_parse_fps_errors_are_one_line(values, message):
    with pytest.raises(InputError, match=message) as e:
        parse_fps(values)
    assert "\n" not in str(e.value)


def test_unknown_stream_is_named():
    with pytest.raises(InputError, match="unknown stream 7"):
        check_fps({0: 30.0, 7: 25.0}, np.array([0, 0, 1, 1]))
    check_fps({0: 30.0, 1: 25.0}, np.array([0, 0, 1, 1]))


def test_sync_command_prints_and_round_trips_json(solved, tmp_path, capsys):
    _, _, out, report, _ = solved
    target = tmp_path / "sync.json"
    assert cli_main(["sync", str(out), "--json", str(target)]) == 0
    printed = capsys.readouterr().out
    event = report["sync"]["events"][0]
    assert f"reference stream {event['reference_stream']}" in printed and "±" in printed
    table = json.loads(target.read_text())
    assert table["reference_stream"] == event["reference_stream"]
    for name, clock in event["streams"].items():
        entry = table["streams"][name]
        assert entry["offset_frames"] == clock["offset_frames"]
        assert entry["offset_s"] == pytest.approx(clock["offset_ms"] / 1000)
        assert entry["rate"] == clock["rate"]
    # an existing file: refused without --overwrite, replaced with it; --fps overrides
    with pytest.raises(SystemExit) as e:
        cli_main(["sync", str(out), "--json", str(target)])
    assert e.value.code == 2
    assert cli_main(["sync", str(out), "--json", str(target), "--overwrite", "--fps", "60"]) == 0
    assert json.loads(target.read_text())["reference_fps"] == 60.0
    other = tmp_path / "other.json"
    other.write_text("{}")
    capsys.readouterr()
    for path in (other, out / "report.json"):
        for overwrite in ([], ["--overwrite"]):  # never replaced: another file is asked for
            with pytest.raises(SystemExit) as e:
                cli_main(["sync", str(out), "--json", str(path), *overwrite])
            assert e.value.code == 2
            assert "; choose another" in capsys.readouterr().err
    assert other.read_text() == "{}"


def test_clocks_that_miss_the_known_frame_rates_are_flagged(solved, tmp_path, log_lines, capsys):
    """Told the 24 and 25 Hz streams run at 30 (as a wrong ``--fps`` would), the report and
    the sync command flag their clocks, and the export says so; the other streams' clocks
    match their rates."""
    capture, _, _, _, result = solved
    told = dict(enumerate((30.0, 30.0, 29.97, 30.0)))
    report = export_outputs(tmp_path / "out", capture, result, plots=False, fps=told)
    event = report["sync"]["events"][0]
    ref = event["reference_stream"]
    for name, clock in event["streams"].items():
        s = int(name)
        if s == ref:
            assert "fps_consistent" not in clock
            continue
        wrong = RATES[s] != told[s]
        assert clock["fps_consistent"] is not wrong, (name, clock)
        if wrong:
            assert clock["fps_deviation"] == pytest.approx(RATES[s] / told[s] - 1, abs=0.01)
            span = np.ptp(capture.frame[capture.stream == s])
            drift = (told[ref] / RATES[s] - told[ref] / told[s]) * span
            assert clock["fps_drift_frames"] == pytest.approx(drift, rel=0.02)
            assert any(f"stream {name}: its clock runs at" in line for line in log_lines)
    assert cli_main(["sync", str(tmp_path / "out")]) == 0
    printed = capsys.readouterr().out
    assert printed.count("  !") == 2 and "not to be trusted" in printed
    # the sync command's --fps replaces the rates the check is made against
    assert cli_main(["sync", str(tmp_path / "out"), "--fps", *[f"{k}={r}" for k, r in
                                                                enumerate(RATES)]]) == 0
    assert "!" not in capsys.readouterr().out


def test_a_rate_a_whole_factor_off_is_named_with_the_fps_to_give(solved, tmp_path, log_lines,
                                                                 capsys):
    """Told a stream runs at a quarter of its rate (its images' rate, where its frame numbers
    count every 4th frame), the warning and ``dloe-sfm sync`` name the factor and the --fps the
    clock implies."""
    capture, _, _, report, result = solved
    ref = report["sync"]["events"][0]["reference_stream"]
    s = next(k for k in range(len(RATES)) if k != ref)
    told = {k: r / 4 if k == s else r for k, r in enumerate(RATES)}
    export_outputs(tmp_path / "out", capture, result, plots=False, fps=told)
    hint = "(about 4), as when its frame numbers count frames at another rate than the images'"
    fix = f"--fps {s}={RATES[s]:g} if they count frames at that rate"
    assert [line for line in log_lines if f"stream {s}: its clock runs at" in line
            and hint in line and line.endswith(fix)], log_lines
    assert cli_main(["sync", str(tmp_path / "out")]) == 0
    assert f"! stream {s}: its clock runs" in capsys.readouterr().out


def test_dropped_clocks_time_the_event_and_widen_its_offsets(solved, tmp_path, log_lines,
                                                             capsys):
    """An event whose fitted clocks the held-out check dropped for its points (DLOE's graph
    gives them) is still timed by those clocks: its times and offsets are theirs, and their
    uncertainty takes in how far DLOE's own time line puts each stream (in the reference's
    frames, whatever the clocks' own origin and unit), which the report, the export's log and
    the sync command say."""
    capture, _, _, _, result = solved
    assert result.clock is not None  # in the reference's frames: stream 1 a frame later
    shifted = result.clock + np.where(capture.stream == 1, 1.0, 0.0)
    order = np.argsort(shifted, kind="stable")
    fps = dict(enumerate(RATES))
    alone = export_outputs(tmp_path / "alone", capture, replace(result, clock=shifted,
                                                                order=order),
                           plots=False, fps=fps)
    # DLOE's own time line (the embedding) is the unshifted clocks
    dropped = replace(result, clock=None, clock_dropped=5.0 + 2.0 * shifted, order=order)
    report = export_outputs(tmp_path / "out", capture, dropped, plots=False, fps=fps)
    event, before = report["sync"]["events"][0], alone["sync"]["events"][0]
    assert event["base"] == before["base"] == "clock" and event["clocks_dropped"]
    assert not before["clocks_dropped"]
    ref = event["reference_stream"]
    for name, clock in event["streams"].items():
        old = before["streams"][name]
        assert clock["offset_frames"] == pytest.approx(old["offset_frames"], abs=1e-9)
        if int(name) == ref:
            assert clock["clock_disagreement_frames"] == 0.0 and clock["offset_sd"] == 0.0
            continue
        apart = clock["clock_disagreement_frames"]
        assert apart == pytest.approx(-1.0 if name == "1" else 0.0, abs=1e-6), (name, apart)
        assert clock["clock_disagreement_ms"] == pytest.approx(1000 * apart / RATES[ref])
        assert clock["offset_sd_frames"] == pytest.approx(np.hypot(old["offset_sd_frames"],
                                                                   apart))
    (t, images), (t_alone, images_alone) = (sequence_times(tmp_path / name)
                                            for name in ("out", "alone"))
    assert images == images_alone
    np.testing.assert_allclose(t, t_alone, atol=1e-9)
    # a result file keeps both time lines: an export from it reports the same
    loaded = load_result(save_result(tmp_path / "result.npz", dropped))
    again = export_outputs(tmp_path / "again", capture, loaded, plots=False, fps=fps)
    assert again["sync"] == report["sync"]
    assert any("predicted held-out detections worse" in line for line in log_lines)
    target = tmp_path / "sync.json"
    assert cli_main(["sync", str(tmp_path / "out"), "--json", str(target)]) == 0
    assert "up to 1.00 frames" in capsys.readouterr().out
    table = json.loads(target.read_text())
    assert table["events"][0]["clocks_dropped"]
    assert table["streams"]["1"]["clock_disagreement_s"] == pytest.approx(-1.0 / RATES[ref])


def test_dropped_clocks_order_their_event_and_leave_its_points(solved):
    """The events whose clocks the held-out check dropped keep DLOE's points, graph and time
    line (the embedding, which the sync report's disagreement measures against), and take
    their order from the clocks (``clocked.on_clocks``)."""
    capture, _, _, _, result = solved
    graph = replace(result, clock=None)
    shifted = result.clock + np.where(capture.stream == 1, 1.0, 0.0)
    rejected, residual = outlier_arrays(result)
    placed = Placement(np.arange(capture.num_images), shifted, result.W, result.D, result.X,
                       rejected, residual, result.noise_px, capture, None, 0.0)
    out = on_clocks(graph, [], checked=False, dropped=[placed])
    np.testing.assert_array_equal(out.order, np.argsort(shifted, kind="stable"))
    assert not np.array_equal(out.order, graph.order)
    np.testing.assert_array_equal(out.clock_dropped, shifted)
    assert out.clock is None and out.X is graph.X and out.W is graph.W
    np.testing.assert_array_equal(out.embedding, graph.embedding)


def test_sync_command_errors_are_one_line(tmp_path, capsys):
    for folder, message in ((tmp_path / "missing", "no report.json"),
                            (tmp_path, "cannot read it")):
        if folder == tmp_path:
            (tmp_path / "report.json").write_text("{not json")
        with pytest.raises(SystemExit) as e:
            cli_main(["sync", str(folder)])
        assert e.value.code == 2
        err = capsys.readouterr().err
        assert message in err and err.count("\n") == 1
    clock = {"offset_frames": 1.0, "offset_sd_frames": 0.1, "rate": 1.0, "rate_sd": 0.01}
    for report in ({"images": 3}, {"sync": {"events": [{"streams": {"1": {**clock, "fps": 0}}}]}},
                   {"sync": {"events": [{"streams": {"1": {**clock, "frame_span": "9"}}}]}}):
        (tmp_path / "report.json").write_text(json.dumps(report))
        with pytest.raises(SystemExit):
            cli_main(["sync", str(tmp_path)])
        assert "no valid 'sync' entry" in capsys.readouterr().err
