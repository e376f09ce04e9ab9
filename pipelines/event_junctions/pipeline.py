"""Junctions between events of lone photos: the factor each needs to be joined, against
``events.RUN_ON_FACTOR``.

Lone photos are cut into events before the solve and solved apart; where two events that follow
one another run on across their junction (``events.runs_on``) they are reported as one. For
every capture this solves it with the default options (``plain_solve`` then ``finish_single``,
as ``reconstruct``) and measures, at every junction of its final order between two events it
was solved apart in, the least factor that would join them (``events.junction_factor``). A
junction is a true gap where the images on either side come from different clips or from
either side of a stretch left without photos; else it is a cut through one motion, which the
factor should join.

Cases (each 300 lone photos over 3 s unless its settings say otherwise):
- the lone-photo cases of ``pipelines/detector_captures`` (``lone``, ``lone_noise``,
  ``lone_detector``, ``lone_new``, ``lone_check``, ``lone_check2``): one motion each;
- ``clips``: two clips 2 s apart (``simulate_events``), jumping_1 then running_1 and running_1
  then basketball_1 (seed 0), walking_1 then jumping_1 (seed 0), walking_2 then walking_3
  (seed 1);
- ``holes``: walking_1, jumping_1, basketball_1, soccer_1, directing_traffic_1 and walking_3
  (seed 5) with the photos of a second (1.0-2.0 s) or of half a second (1.0-1.5 s) left out;
- ``seed4``: walking_2, walking_4, jumping_2, jumping_4, running_2, running_4, basketball_3,
  basketball_5, soccer_3 and soccer_5 at seed 4, clean and at 1 px: one motion each.

    python pipelines/event_junctions/pipeline.py [--data ../shared/data/mocap]
        [--out outputs/event_junctions] [--cases lone_check clips holes ...] [--jobs 2]

Writes ``OUT/event_junctions.json`` (every junction and the machine) and prints a line per
junction, then the largest factor a cut through one motion needed and the least a gap did.
"""

from __future__ import annotations

import json
import os
import platform
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

from dloe_sfm.core.events import RUN_ON_FACTOR, junction_factor
from dloe_sfm.core.options import Options
from dloe_sfm.core.parallel import map_in_processes
from dloe_sfm.core.pipeline import finish_single, plain_solve
from dloe_sfm.io import atomic_path
from dloe_sfm.synth import (
    SimulationSettings,
    load_mocap,
    pipeline_parser,
    resolve_motion,
    sibling_pipeline,
    simulate,
)
from dloe_sfm.synth.scenarios import simulate_events

CLIPS = [(("jumping_1", "running_1"), 0), (("running_1", "basketball_1"), 0),
         (("walking_1", "jumping_1"), 0), (("walking_2", "walking_3"), 1)]
HOLES = [(m, hole) for m in ("walking_1", "jumping_1", "basketball_1", "soccer_1",
                             "directing_traffic_1", "walking_3") for hole in (1.0, 0.5)]
SEED4 = [(m, noise) for m in ("walking_2", "walking_4", "jumping_2", "jumping_4", "running_2",
                              "running_4", "basketball_3", "basketball_5", "soccer_3",
                              "soccer_5") for noise in (0.0, 1.0)]
HOLE_START = 1.0
"""Seconds into the clip where the ``holes`` cases' stretch without photos starts."""


detector_captures = sibling_pipeline(__file__, "detector_captures")
"""``pipelines/detector_captures``: its lone-photo cases."""


def jobs_of(case: str) -> list[tuple]:
    """(case, name, seed, what) of every capture of ``case``."""
    if case == "clips":
        return [(case, "+".join(m), seed, m) for m, seed in CLIPS]
    if case == "holes":
        return [(case, f"{m} without {hole:g} s", 5, (m, hole)) for m, hole in HOLES]
    if case == "seed4":
        return [(case, f"{m}@{noise:g}", 4, (m, noise)) for m, noise in SEED4]
    return [(case, m, seed, m) for m, seed in detector_captures.CASES[case]]


def simulated(data: Path, case: str, seed: int, what) -> tuple:
    """(capture, every image's clip or side of the hole, or None) of one job."""
    base = SimulationSettings(duration=3.0, num_streams=0, lone_photos=300, seed=seed)
    if case == "clips":
        sim = simulate_events([load_mocap(resolve_motion(data, m)) for m in what], base)
        return sim.capture, sim.truth.events
    if case == "holes":
        motion, hole = what
        sim = simulate(load_mocap(resolve_motion(data, motion)), base)
        t = sim.truth.t
        keep = np.flatnonzero((t < HOLE_START) | (t > HOLE_START + hole))
        return sim.capture.subset(keep), (t[keep] > HOLE_START).astype(np.int64)
    if case == "seed4":
        motion, noise = what
        sim = simulate(load_mocap(resolve_motion(data, motion)), replace(base, noise=noise))
        return sim.capture, None
    motion, _, variant = what.partition("@")
    sim = simulate(load_mocap(resolve_motion(data, motion)),
                   detector_captures.settings(case, seed, variant))
    return sim.capture, None


def run_one(job: tuple) -> list[dict]:
    """Solve one capture with the default options; every junction of its final order."""
    data, (case, name, seed, what) = job
    capture, sides = simulated(data, case, seed, what)
    options = Options()
    result, labels = plain_solve(capture, options)
    result = finish_single(capture, options, result, labels)
    along = labels[result.order]
    starts = np.flatnonzero(np.diff(along)) + 1
    stretches = np.split(result.order, starts)
    rows = []
    for before, after in zip(stretches[:-1], stretches[1:], strict=True):
        gap = sides is not None and (np.bincount(sides[before]).argmax()
                                     != np.bincount(sides[after]).argmax())
        rows.append({"case": case, "capture": name, "seed": seed, "images": capture.num_images,
                     "factor": junction_factor(result.X, before, after, capture.num_images),
                     "gap": bool(gap), "events": int(result.events.max()) + 1})
    return rows


def run(data: Path, out: Path, cases: list[str], jobs: int) -> list[dict]:
    """Every junction of every capture of ``cases``, ``jobs`` captures at a time; also in
    ``out``."""
    todo = [(data, job) for case in cases for job in jobs_of(case)]
    rows = []
    for found in map_in_processes(run_one, todo, jobs):
        rows += found
        for r in found:
            print(f"{r['case']:11s} {r['capture']:30s} seed {r['seed']}  N={r['images']:4d}  "
                  f"factor {r['factor']:6.2f}  {'gap' if r['gap'] else 'one motion'}  "
                  f"{r['events']} event(s) reported", flush=True)
    meta = {"machine": platform.platform(), "cpus": os.cpu_count(),
            "python": sys.version.split()[0], "numpy": np.__version__, "jobs": jobs,
            "run_on_factor": RUN_ON_FACTOR}
    out.mkdir(parents=True, exist_ok=True)
    with atomic_path(out / "event_junctions.json") as tmp:
        tmp.write_text(json.dumps({"meta": meta, "junctions": rows}, indent=2))
    return rows


def main() -> None:
    cases = ["lone", "lone_noise", "lone_detector", "lone_new", "lone_check", "lone_check2",
             "clips", "holes", "seed4"]
    p = pipeline_parser(__file__, __doc__, "event_junctions")
    p.add_argument("--cases", nargs="+", default=cases, choices=cases)
    p.add_argument("--jobs", type=int, default=2, help="worker processes, one thread each")
    a = p.parse_args()
    rows = run(a.data, a.out, a.cases, a.jobs)
    one = [r["factor"] for r in rows if not r["gap"]]
    gaps = [r["factor"] for r in rows if r["gap"]]
    print(f"RUN_ON_FACTOR {RUN_ON_FACTOR:g}: cuts through one motion needed at most "
          f"{max(one, default=float('nan')):.2f} ({len(one)} junctions), gaps at least "
          f"{min(gaps, default=float('nan')):.2f} ({len(gaps)})")


if __name__ == "__main__":
    main()
