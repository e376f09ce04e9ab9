"""Check the detector-model and mixed-rate acceptance of issue 14 on the shared CMU mocap.

Every capture is simulated with the project's simulator and solved with the default options
(``Options()``; the capture knows its streams' frame rates, as ``simulate`` writes them), then
scored against the truth and the two yardsticks on the same capture: the oracle (the X-step on
the chain in true time order, points pinned to their rays) and pseudo-triangulation. Cases:

- detector: 4 streams at 24 / 25 / 29.97 / 30 Hz from random start times, 2.9 s, the OpenPose
  detector model (``--detector openpose``: heavy tails, per-camera joint bias, misses, swaps);
  walking_1, jumping_1, running_1 and soccer_1 at seeds 0-2, basketball_1 at seed 0. Target:
  at most 0.6 x the oracle, 0.5 x pseudo-triangulation, |tau| >= 0.98;
- new: the same settings on 13 other captures (seed 0 of soccer_2-5, directing_traffic_1 and 4,
  basketball_2, basketball_signal_2, walking_3, jumping_3, running_3; soccer_1 seeds 3 and 4),
  same target; kept out of the choices made on the first set, they showed where two rules of the
  clock check were wrong (docs/method.md, "Far fits and near-ties");
- mixed: 5 clean streams at 24 / 25 / 29.97 / 30 / 50 Hz from random start times, 2 s; walking_1,
  jumping_1, running_1, soccer_1 and basketball_signal_1 at seeds 0-1. Target: at most 1.3 x the
  oracle + 0.3 mm;
- six: 6 streams at 24 / 25 / 29.97 / 30 / 50 / 60 Hz (the issue's list of rates) from random
  start times, 2 s, the OpenPose detector model, on seed 0 of eight motions (walking_1, running_1,
  jumping_1, soccer_2, basketball_1, directing_traffic_1, walking_4, basketball_signal_3);
  six_missing: the same with a further 25 % of the joints missing at random. The detector
  target; both were made after every choice above, as a check (docs/method.md, "Six streams").
- lone, lone_noise, lone_detector: 300 lone photos over 3 s (``--lone-photos``: each its own
  handheld camera all around at a random distance and focal length, at a random instant; no
  sequencing information at all), clean, with 1 px noise and with the OpenPose detector model;
  walking_1, jumping_1, basketball_1, soccer_1, running_1 and directing_traffic_1 at seed 0.
  lone_new: seed 1 of soccer_2, basketball_2, walking_3, jumping_3 and running_3, clean and at
  1 px, kept out of every choice as a check. Target (issue 38): at most 1.5 x the oracle + 1 mm
  and 0.5 x pseudo-triangulation, |tau| >= 0.98. lone_new was looked at in the choices of the
  ray placement (docs/method.md, "Lone photos placed by their rays"), so lone_check was made
  after them and kept out of every later choice: seed 2 of six motions no other case uses
  (walking_5, jumping_5, running_5, basketball_4, soccer_4, directing_traffic_4), each clean,
  at 1 px and with the OpenPose detector model, 250 or 400 photos, same target. lone_check2:
  the same at seed 3 with the other photo count, made when lone_check had shown false events
  and kept out of their fix as a check.

    python pipelines/detector_captures/pipeline.py [--data ../shared/data/mocap]
        [--out outputs/detector_captures] [--cases detector new mixed six six_missing
        lone lone_noise lone_detector lone_new lone_check lone_check2] [--jobs 2]

Writes ``OUT/detector_captures.json`` (every run's figures and the machine) and prints a line
per run; about 25 minutes for all five cases with two jobs on 2 cores.
"""

from __future__ import annotations

import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

from dloe_sfm.core.options import Options
from dloe_sfm.core.parallel import map_in_processes
from dloe_sfm.core.solver import reconstruct
from dloe_sfm.evaluate import evaluate
from dloe_sfm.io import atomic_path
from dloe_sfm.synth import (
    SimulationSettings,
    load_mocap,
    pipeline_parser,
    resolve_motion,
    simulate,
)

DETECTOR = [(m, s) for m in ("walking_1", "jumping_1", "running_1", "soccer_1")
            for s in (0, 1, 2)] + [("basketball_1", 0)]
NEW = [(m, 0) for m in ("soccer_2", "soccer_3", "soccer_4", "soccer_5", "directing_traffic_1",
                        "directing_traffic_4", "basketball_2", "basketball_signal_2", "walking_3",
                        "jumping_3", "running_3")] + [("soccer_1", 3), ("soccer_1", 4)]
MIXED = [(m, s) for m in ("walking_1", "jumping_1", "running_1", "soccer_1",
                          "basketball_signal_1") for s in (0, 1)]
SIX = [(m, 0) for m in ("walking_1", "running_1", "jumping_1", "soccer_2", "basketball_1",
                        "directing_traffic_1", "walking_4", "basketball_signal_3")]
LONE = [(m, 0) for m in ("walking_1", "jumping_1", "basketball_1", "soccer_1", "running_1",
                         "directing_traffic_1")]
LONE_NEW = [(m, 1) for m in ("soccer_2", "basketball_2", "walking_3", "jumping_3", "running_3")]
LONE_NEW = [(f"{m}@{noise}", s) for m, s in LONE_NEW for noise in (0, 1)]
LONE_CHECK = [(f"{m}@{noise}:{photos}", 2) for k, m in enumerate(
    ("walking_5", "jumping_5", "running_5", "basketball_4", "soccer_4", "directing_traffic_4"))
    for j, noise in enumerate(("0", "1", "openpose")) for photos in [(250, 400)[(k + j) % 2]]]
LONE_CHECK2 = [(f"{m.partition(':')[0]}:{650 - int(m.partition(':')[2])}", 3)
               for m, _ in LONE_CHECK]
CASES = {"detector": DETECTOR, "new": NEW, "mixed": MIXED, "six": SIX, "six_missing": SIX,
         "lone": LONE, "lone_noise": LONE, "lone_detector": LONE, "lone_new": LONE_NEW,
         "lone_check": LONE_CHECK, "lone_check2": LONE_CHECK2}


def settings(case: str, seed: int, variant: str = "") -> SimulationSettings:
    """The simulation of ``case`` (module docstring) at ``seed``; lone_new and lone_check name
    their noise in ``variant`` (px, or a detector model), then lone_check its photos after a
    colon."""
    if case.startswith("lone"):
        noise, _, photos = variant.partition(":")
        detector = "openpose" if case == "lone_detector" or noise == "openpose" else None
        noise = 1.0 if case == "lone_noise" else float(noise) if noise and not detector else 0.0
        return SimulationSettings(duration=3.0, num_streams=0, lone_photos=int(photos or 300),
                                  seed=seed, noise=noise, detector=detector)
    if case == "mixed":
        return SimulationSettings(duration=2.0, num_streams=5, rates=(24, 25, 29.97, 30, 50),
                                  random_offsets=True, seed=seed)
    if case.startswith("six"):
        return SimulationSettings(duration=2.0, num_streams=6, rates=(24, 25, 29.97, 30, 50, 60),
                                  random_offsets=True, detector="openpose",
                                  missing=0.25 if case == "six_missing" else 0.0, seed=seed)
    return SimulationSettings(duration=2.9, num_streams=4, rates=(24, 25, 29.97, 30),
                              random_offsets=True, detector="openpose", seed=seed)


def passes(case: str, row: dict) -> bool:
    """Issue 14's acceptance rule for one run of ``case``."""
    if case == "mixed":
        return row["error_mm"] <= 1.3 * row["oracle_mm"] + 0.3
    if case.startswith("lone"):
        # issue 38: images flagged order_ambiguous (at most 5 %) are left out of the order's check
        tau = (row["kendall_tau_unambiguous"] if row["order_ambiguous"] <= 0.05 * row["images"]
               else row["kendall_tau"])
        return (row["error_mm"] <= 1.5 * row["oracle_mm"] + 1.0
                and row["error_mm"] <= 0.5 * row["pseudo_triangulation_mm"]
                and tau >= 0.98)
    return (row["error_mm"] <= 0.6 * row["oracle_mm"]
            and row["error_mm"] <= 0.5 * row["pseudo_triangulation_mm"]
            and row["kendall_tau"] >= 0.98)


def run_one(job: tuple[Path, str, str, int]) -> dict:
    """Simulate, solve with the default options and score one capture."""
    data, case, motion, seed = job
    motion, _, variant = motion.partition("@")
    sim = simulate(load_mocap(resolve_motion(data, motion)), settings(case, seed, variant))
    tic = time.perf_counter()
    result = reconstruct(sim.capture, Options())
    seconds = time.perf_counter() - tic
    scores = evaluate(sim.capture, sim.truth, result)
    clocked = result.clock is not None and bool(np.isfinite(result.clock).any())
    row = {"case": case, "motion": job[2], "seed": seed, "images": sim.capture.num_images,
           "error_mm": scores["error_mm"], "oracle_mm": scores["oracle_mm"],
           "pseudo_triangulation_mm": scores["pseudo_triangulation_mm"],
           "kendall_tau": abs(scores["kendall_tau"]),
           "kendall_tau_unambiguous": abs(scores.get("kendall_tau_unambiguous",
                                                     scores["kendall_tau"])),
           "order_ambiguous": scores["order_ambiguous"], "clocks": clocked,
           "noise_px": result.noise_px, "seconds": seconds,
           "events": int(result.events.max()) + 1,
           "flagged": int((result.image_status != "ok").sum())}
    row["pass"] = passes(case, row)
    return row


def run(data: Path, out: Path, cases: list[str], jobs: int) -> list[dict]:
    """Every capture of ``cases``, ``jobs`` at a time; the rows, also in ``out``."""
    todo = [(data, case, m, s) for case in cases for m, s in CASES[case]]
    rows = []
    for row in map_in_processes(run_one, todo, jobs):
        rows.append(row)
        print(f"{row['case']:8s} {row['motion']:20s} seed {row['seed']}  N={row['images']:4d}  "
              f"{row['error_mm']:6.2f} mm: {row['error_mm'] / row['oracle_mm']:.3f} x oracle, "
              f"{row['error_mm'] / row['pseudo_triangulation_mm']:.3f} x pseudo-tri  "
              f"|tau| {row['kendall_tau']:.4f} ({row['kendall_tau_unambiguous']:.4f} without "
              f"{row['order_ambiguous']} ambiguous)  {'clocks' if row['clocks'] else 'graph '}  "
              f"{row['events']} event(s), {row['flagged']} flagged  "
              f"{row['seconds']:5.1f} s  {'PASS' if row['pass'] else 'FAIL'}", flush=True)
    meta = {"machine": platform.platform(), "cpus": os.cpu_count(),
            "python": sys.version.split()[0], "numpy": np.__version__, "jobs": jobs}
    out.mkdir(parents=True, exist_ok=True)
    with atomic_path(out / "detector_captures.json") as tmp:
        tmp.write_text(json.dumps({"meta": meta, "runs": rows}, indent=2))
    return rows


def main() -> None:
    p = pipeline_parser(__file__, __doc__, "detector_captures")
    p.add_argument("--cases", nargs="+", default=list(CASES), choices=list(CASES))
    p.add_argument("--jobs", type=int, default=2, help="worker processes, one thread each")
    a = p.parse_args()
    rows = run(a.data, a.out, a.cases, a.jobs)
    for case in a.cases:
        mine = [r for r in rows if r["case"] == case]
        print(f"{case}: {sum(r['pass'] for r in mine)} of {len(mine)} pass")


if __name__ == "__main__":
    main()
