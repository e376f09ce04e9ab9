"""Several people, events and detector errors from OpenPose files through the COLMAP stage.

Each case is simulated with ``dloe_sfm.synth.scenarios`` (CMU mocap, a ring of 4 unsynchronised
cameras), written as a COLMAP workspace (the ring cameras, one posed image per capture image,
``cam0/00012.jpg``, no image files) with one OpenPose JSON file per image (every person of the
image, in the simulator's shuffled order) and a layout file for the CMU skeleton, reconstructed
by the real stage (``dloe_sfm.stages.reconstruct.main``, like ``dloe-sfm reconstruct``), and
scored from the stage's outputs (trajectories.npz, sequence.csv, report.json) against the
simulator's truth:

1. people: two people 2 m apart; images whose detections all go to the right person (best
   global permutation of subject ids), every person's mean 3D error;
2. events: three clips filmed one after another by the same streams; event purity, per-clip
   error;
3. outliers: 5 % of one person's observations moved 20-100 px; error with the default robust
   loss and without it, down-weighted observations (report.json) against the true outliers;
4. swaps: 10 % of the left/right pairs swapped; true swaps listed in report.json's swaps_fixed;
5. crowd: three people 2 m apart under the detector model (``openpose``: noise, bias, outliers,
   missing points), the third seen only in the middle 40 % of the time (enters late, leaves
   early), and a false detection (another image's detection, moved 50-200 px) in 10 % of the
   images; per person the subject that took most of its detections, purity (the share of its
   detections that subject took), reconstructed (the share of its images where that subject has
   at least half its points) and the mean 3D error over its images, and the share of false
   detections left out;
6. crossing: two walkers 0.6 m apart, the second's walk turned back (``simulate_people``'s
   ``turns``), so they pass each other shoulder to shoulder mid-way, and a third person jumping
   0.6 m beside them, under the detector model; scored per person as the crowd case.

    python pipelines/multi_person/pipeline.py [--data assets/mocap] [--out outputs/multi_person]
"""

from __future__ import annotations

import argparse
import csv
import itertools
import json
import logging
import time
from collections import Counter
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np

from dloe_sfm.benchmark import machine_info
from dloe_sfm.colmap import CameraSpec, ImageSpec, write_model
from dloe_sfm.core.capture import Capture
from dloe_sfm.errors import InputError
from dloe_sfm.io import atomic_path, check_output
from dloe_sfm.keypoints import Layout
from dloe_sfm.stages.reconstruct import main as reconstruct_workspace
from dloe_sfm.synth import SimulationSettings, load_mocap, resolve_motion, simulate
from dloe_sfm.synth.mocap import symmetric_pairs
from dloe_sfm.synth.scenarios import (
    add_false_detections,
    add_outliers,
    limit_presence,
    simulate_events,
    simulate_people,
    swap_symmetric,
)
from dloe_sfm.truth import GroundTruth

logger = logging.getLogger("dloe_sfm")

REPO = Path(__file__).resolve().parents[2]
PEOPLE = ("walking_1", "jumping_1")
CROWD = ("walking_1", "jumping_1", "basketball_signal_1")
PRESENT = (0.3, 0.7)
"""The part of the duration the crowd case's third person is in view."""
FALSE_DETECTIONS = 0.1
CROSSING = ("walking_1", "walking_1", "jumping_1")
CROSSING_TURNS = (0.0, np.pi, 0.0)
CROSSING_NAMES = tuple(m + (" turned back" if a else "") for m, a in zip(CROSSING, CROSSING_TURNS,
                                                                          strict=True))
CROSSING_SPACING = 0.6
EVENTS = ("walking_1", "jumping_1", "basketball_signal_1")
SINGLE = "walking_1"
CASES = ("people", "events", "outliers", "swaps", "crowd", "crossing")


def cmu_layout(parents: np.ndarray) -> Layout:
    """The CMU skeleton of the mocap clips: points j0..j27, bones to the parents, left/right
    pairs of ``symmetric_pairs``."""
    return Layout(name="CMU_28", point_names=[f"j{j}" for j in range(len(parents))],
                  edges=[(j, int(p)) for j, p in enumerate(parents) if p >= 0],
                  symmetric_pairs=[tuple(map(int, pair)) for pair in symmetric_pairs(parents)])


def image_name(capture: Capture, n: int) -> str:
    return f"{capture.image_names[n]}.jpg"  # the simulator's names are cam<k>/<frame:05d>


def write_inputs(folder: Path, capture: Capture, layout: Layout, image_size: int) -> None:
    """``folder/workspace`` (COLMAP model: one PINHOLE camera per stream, one image per capture
    image), ``folder/openpose`` (one ``<image>_keypoints.json`` per image) and
    ``folder/layout.json``.

    Capture pixels are COLMAP's (x ~ K R (X - C), the top-left pixel's centre at (0.5, 0.5));
    OpenPose's top-left pixel centre is (0, 0), so its values are the capture's minus 0.5.
    """
    streams = np.unique(capture.stream)
    first = [int(np.flatnonzero(capture.stream == s)[0]) for s in streams]
    cameras = [CameraSpec(model="PINHOLE", width=image_size, height=image_size,
                          params=capture.K[n][[0, 1, 0, 1], [0, 1, 2, 2]]) for n in first]
    camera_of = {int(s): k for k, s in enumerate(streams)}
    images = [ImageSpec(name=image_name(capture, n), camera=camera_of[int(capture.stream[n])],
                        R=capture.R[n], C=capture.C[n]) for n in range(capture.num_images)]
    write_model(folder / "workspace" / "sparse" / "0", cameras, images)

    people = capture.x.reshape(capture.num_images, -1, capture.num_points, 2)
    for n in range(capture.num_images):
        found = np.isfinite(people[n]).all(axis=-1, keepdims=True)
        values = np.where(found, np.concatenate([people[n] - 0.5, np.ones_like(found)], axis=-1),
                          0.0)
        file = folder / "openpose" / f"{capture.image_names[n]}_keypoints.json"
        file.parent.mkdir(parents=True, exist_ok=True)
        file.write_text(json.dumps({"people": [{"pose_keypoints_2d": v.ravel().tolist()}
                                               for v in values]}))
    (folder / "layout.json").write_text(json.dumps(asdict(layout)))


def run_stage(folder: Path, capture: Capture, *, name: str = "reconstruction",
              overrides: list[str] | None = None, plots: bool = False) -> dict:
    """The reconstruct stage on ``folder``'s inputs into ``folder/<name>``; its outputs read back
    in the capture's image order: X (N, P', 3), events (N,), report, detection_subject (N, M')
    when several subjects, subject_id / point_id (P'), seconds (the stage's wall time)."""
    tic = time.perf_counter()
    out = reconstruct_workspace(folder / "workspace", folder / "openpose", "openpose",
                                folder / name, layout=folder / "layout.json",
                                overrides=overrides, plots=plots)
    seconds = time.perf_counter() - tic
    wanted = [image_name(capture, n) for n in range(capture.num_images)]
    with np.load(out / "trajectories.npz") as npz:
        traj = {k: npz[k] for k in npz.files}
    row = {str(image): i for i, image in enumerate(traj["image_names"])}
    if set(row) != set(wanted):
        raise InputError(f"{out}: trajectories.npz does not hold the {len(wanted)} images")
    back = np.array([row[image] for image in wanted])
    with open(out / "sequence.csv", newline="") as f:
        event_of = {r["image"]: int(r["event"]) for r in csv.DictReader(f)}
    p = traj["X"].shape[1]
    return {
        "X": traj["X"][back],
        "events": np.array([event_of[image] for image in wanted]),
        "subject_id": traj.get("subject_id", np.zeros(p, dtype=np.int64)),
        "point_id": traj.get("point_id", np.arange(p)),
        "detection_subject": traj["detection_subject"][back] if "detection_subject" in traj
        else None,
        "report": json.loads((out / "report.json").read_text()),
        "seconds": seconds,
    }


def mean_error_mm(X: np.ndarray, X_true: np.ndarray) -> float:
    """Mean 3D error over the exported points (those the data do not support are NaN there and
    left out: report.json ``image_status`` counts them)."""
    return float(np.nanmean(np.linalg.norm(X - X_true, axis=-1)) * 1000)


def found_subjects(out: dict, truth: np.ndarray) -> np.ndarray:
    """(N, M) the stage's subject of every detection slot of ``truth`` (N, M) (-1: none; the
    files hold at most M)."""
    found = out["detection_subject"][:, :truth.shape[1]]
    return np.pad(found, ((0, 0), (0, truth.shape[1] - found.shape[1])), constant_values=-1)


def subject_columns(out: dict, subject: int) -> np.ndarray:
    """The exported columns of ``subject``, in point order."""
    columns = np.flatnonzero(out["subject_id"] == subject)
    return columns[np.argsort(out["point_id"][columns])]


def score_people(capture: Capture, gt: GroundTruth, out: dict, motions: tuple[str, ...]) -> dict:
    """Association (best global permutation of subject ids) and every person's error."""
    truth, X_true = gt.subjects, gt.X
    found = found_subjects(out, truth)
    m = truth.shape[1]
    num = max(m, int(found.max()) + 1)

    def associated(perm: tuple[int, ...]) -> np.ndarray:
        mapped = np.where(found >= 0, np.array(perm)[np.maximum(found, 0)], -1)
        return (mapped == truth).all(axis=1)

    perm = max(itertools.permutations(range(num)), key=lambda q: associated(q).sum())
    people = []
    for k, motion in enumerate(motions):
        subject = perm.index(k)
        columns = subject_columns(out, subject)
        error = mean_error_mm(out["X"][:, columns], X_true[:, k]) if columns.size else None
        people.append({"motion": motion, "subject_id": subject, "error_mm": error})
    return {"images": capture.num_images, "subjects_found": int(out["report"]["subjects"]),
            "associated": float(associated(perm).mean()), "people": people}


def score_crowd(capture: Capture, gt: GroundTruth, out: dict, motions: tuple[str, ...]) -> dict:
    """Per person: its subject (the one that took most of its detections), purity,
    reconstructed share of its images and mean 3D error over them; false detections (truth -1)
    left out."""
    truth = gt.subjects
    found = found_subjects(out, truth)
    people = []
    for k, motion in enumerate(motions):
        mine = truth == k
        taken = found[mine]
        subject = int(np.bincount(taken[taken >= 0]).argmax()) if (taken >= 0).any() else -1
        images = np.flatnonzero(mine.any(axis=1))
        columns = subject_columns(out, subject)
        X = out["X"][images][:, columns]
        people.append({
            "motion": motion, "subject_id": subject, "images": int(images.size),
            "purity": float((taken == subject).mean()),
            "reconstructed": float((np.isfinite(X).all(axis=-1).mean(axis=-1) >= 0.5).mean())
            if columns.size else 0.0,
            "error_mm": mean_error_mm(X, gt.X[images, k]) if columns.size else None,
        })
    false = (truth == -1) & capture.visible.any(axis=2)
    return {"images": capture.num_images, "subjects_found": int(out["report"]["subjects"]),
            "people": people, "false_detections": int(false.sum()),
            "false_left_out": float((found[false] < 0).mean()) if false.any() else 1.0}


def score_events(capture: Capture, gt: GroundTruth, out: dict, motions: tuple[str, ...]) -> dict:
    """Event purity (images of an estimated event in its majority clip / all) and per-clip error."""
    truth, events = gt.events, out["events"]
    majority = sum(Counter(truth[events == e].tolist()).most_common(1)[0][1]
                   for e in np.unique(events))
    clips = [{"motion": motion, "images": int((truth == k).sum()),
              "error_mm": mean_error_mm(out["X"][truth == k], gt.X[truth == k])}
             for k, motion in enumerate(motions)]
    return {"images": capture.num_images, "events_found": int(np.unique(events).size),
            "purity": majority / truth.size, "clips": clips}


def _rows_of(capture: Capture, layout: Layout) -> tuple[dict[str, int], dict[str, int]]:
    """Image name -> capture row, point name -> point index."""
    return ({image_name(capture, n): n for n in range(capture.num_images)},
            {name: j for j, name in enumerate(layout.point_names)})


def score_outliers(capture: Capture, gt: GroundTruth, out: dict, plain: dict,
                   layout: Layout) -> dict:
    """Error with and without the robust loss; down-weighted observations vs the true outliers."""
    truth = gt.outliers
    image, point = _rows_of(capture, layout)
    flagged = np.zeros_like(truth)
    for obs in out["report"]["downweighted"]["observations"]:
        flagged[image[obs["image"]], point[obs["point"]]] = True
    hits = int((flagged & truth).sum())
    return {"images": capture.num_images, "outliers": int(truth.sum()),
            "downweighted": int(flagged.sum()),
            "recall": hits / max(int(truth.sum()), 1), "precision": hits / max(flagged.sum(), 1),
            "error_mm": mean_error_mm(out["X"], gt.X),
            "error_no_robust_mm": mean_error_mm(plain["X"], gt.X)}


def score_swaps(capture: Capture, gt: GroundTruth, out: dict, layout: Layout) -> dict:
    """True swaps listed in swaps_fixed (an (image, pair) exchanged an odd number of times)."""
    truth = gt.swaps
    image, point = _rows_of(capture, layout)
    pair_of = {frozenset(pair): k for k, pair in enumerate(layout.symmetric_pairs)}
    exchanged = np.zeros(truth.shape, dtype=np.int64)
    for swap in out["report"]["swaps_fixed"]["swaps"]:
        exchanged[image[swap["image"]], pair_of[frozenset(point[p] for p in swap["points"])]] += 1
    fixed = exchanged % 2 == 1
    return {"images": capture.num_images, "swapped": int(truth.sum()),
            "listed": int(out["report"]["swaps_fixed"]["count"]),
            "found": float((fixed & truth).sum() / max(truth.sum(), 1)),
            "false_swaps": int((fixed & ~truth).sum()),
            "error_mm": mean_error_mm(out["X"], gt.X)}


def run_case(case: str, folder: Path, data: Path, settings: SimulationSettings,
             overrides: list[str], plots: bool) -> dict:
    """Simulate, write, reconstruct and score one case in ``folder``."""
    if case == "people":
        seqs = [load_mocap(resolve_motion(data, m)) for m in PEOPLE]
        capture, gt = simulate_people(seqs, settings, spacing=2.0)
    elif case == "events":
        seqs = [load_mocap(resolve_motion(data, m)) for m in EVENTS]
        capture, gt = simulate_events(seqs, settings, gap=2.0)
    elif case == "crowd":
        seqs = [load_mocap(resolve_motion(data, m)) for m in CROWD]
        capture, gt = simulate_people(seqs, replace(settings, detector="openpose"), spacing=2.0)
        capture, gt = limit_presence(capture, gt, 2, *(f * gt.t.max() for f in PRESENT))
        capture, gt = add_false_detections(capture, gt, FALSE_DETECTIONS, seed=settings.seed + 3)
    elif case == "crossing":
        seqs = [load_mocap(resolve_motion(data, m)) for m in CROSSING]
        capture, gt = simulate_people(seqs, replace(settings, detector="openpose"),
                                      spacing=CROSSING_SPACING, turns=CROSSING_TURNS)
    else:
        capture, gt = simulate(load_mocap(resolve_motion(data, SINGLE)), settings)
    layout = cmu_layout(gt.parents)
    if case == "outliers":
        capture, gt = add_outliers(capture, gt, 0.05, seed=settings.seed + 1)
    elif case == "swaps":
        capture, gt = swap_symmetric(capture, gt, np.array(layout.symmetric_pairs), 0.1,
                                     seed=settings.seed + 2)
    write_inputs(folder, capture, layout, settings.image_size)
    out = run_stage(folder, capture, overrides=overrides, plots=plots)
    if case == "people":
        row = score_people(capture, gt, out, PEOPLE)
    elif case == "events":
        row = score_events(capture, gt, out, EVENTS)
    elif case == "crowd":
        row = score_crowd(capture, gt, out, CROWD)
    elif case == "crossing":
        row = score_crowd(capture, gt, out, CROSSING_NAMES)
    elif case == "outliers":
        plain = run_stage(folder, capture, name="reconstruction_no_robust",
                          overrides=[*overrides, "robust_loss=none"])
        row = score_outliers(capture, gt, out, plain, layout)
    else:
        row = score_swaps(capture, gt, out, layout)
    return {"case": case, **row, "seconds_stage": out["seconds"],
            "seconds_solve": out["report"]["timings"]["solve"]}


def describe(row: dict) -> str:
    """One table line of a case."""
    if row["case"] == "people":
        errors = ", ".join(f"{p['motion']} {p['error_mm']:.2f} mm" for p in row["people"])
        body = (f"{row['subjects_found']} subjects, associated {100 * row['associated']:.1f} % "
                f"of images; {errors}")
    elif row["case"] == "events":
        errors = ", ".join(f"{c['motion']} {c['error_mm']:.2f} mm" for c in row["clips"])
        body = f"{row['events_found']} events, purity {row['purity']:.3f}; {errors}"
    elif row["case"] == "outliers":
        body = (f"{row['error_mm']:.2f} mm (no robust loss {row['error_no_robust_mm']:.2f}); "
                f"down-weighted {row['downweighted']} of {row['outliers']} outliers: recall "
                f"{row['recall']:.3f}, precision {row['precision']:.3f}")
    elif row["case"] in ("crowd", "crossing"):
        people = ", ".join(
            f"{p['motion']} {p['error_mm']:.2f} mm, purity {p['purity']:.3f}, "
            f"{100 * p['reconstructed']:.1f} % of {p['images']}" for p in row["people"])
        body = f"{row['subjects_found']} subjects; {people}"
        if row["false_detections"]:
            body += (f"; {100 * row['false_left_out']:.1f} % of {row['false_detections']} false "
                     "detections left out")
    else:
        body = (f"{100 * row['found']:.1f} % of {row['swapped']} swaps fixed, "
                f"{row['false_swaps']} false; {row['error_mm']:.2f} mm")
    return (f"{row['case']:8s} {row['images']:4d} images  {body}  "
            f"({row['seconds_stage']:.1f} s stage, {row['seconds_solve']:.1f} s solve)")


def main(out_dir: Path, *, data: Path | None = None, cases: tuple[str, ...] = CASES,
         duration: float = 3.0, rate: float = 30.0, noise: float = 0.0, seed: int = 0,
         plots: bool = False, overwrite: bool = False) -> dict:
    """Run ``cases`` into ``out_dir/<case>/`` (workspace/, openpose/, layout.json,
    reconstruction/); returns the document also saved as ``out_dir/results.json``."""
    out_dir = Path(out_dir)
    data = Path(data) if data is not None else REPO / "assets" / "mocap"
    unknown = sorted(set(cases) - set(CASES))
    if unknown:
        raise InputError(f"unknown case(s) {', '.join(unknown)} (known: {', '.join(CASES)})")
    out_dir = check_output(out_dir, protected=[data], overwrite=overwrite)
    settings = SimulationSettings(duration=duration, rate=rate, noise=noise, seed=seed)
    overrides = [f"noise_px={noise}"] if noise > 0 else []
    rows = []
    with atomic_path(out_dir, mark=True) as tmp:
        tmp.mkdir()
        for case in cases:
            rows.append(run_case(case, tmp / case, data, settings, overrides, plots))
            print(describe(rows[-1]), flush=True)
        document = {"machine": machine_info(), "data": str(data.resolve()),
                    "settings": {**asdict(settings), "people": PEOPLE, "spacing_m": 2.0,
                                 "events": EVENTS, "gap_s": 2.0, "single": SINGLE,
                                 "outlier_fraction": 0.05, "outlier_px": [20.0, 100.0],
                                 "swap_fraction": 0.1, "crowd": CROWD, "crowd_present": PRESENT,
                    "false_detections": FALSE_DETECTIONS, "crowd_detector": "openpose",
                    "crossing": CROSSING_NAMES, "crossing_spacing_m": CROSSING_SPACING,
                    "solver_overrides": overrides},
                    "cases": rows}
        (tmp / "results.json").write_text(json.dumps(document, indent=2))
    return document


if __name__ == "__main__":
    from dloe_sfm.cli import setup_logging

    parser = argparse.ArgumentParser(allow_abbrev=False, description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, default=REPO / "assets" / "mocap",
                        help="mocap clips (assets/mocap or ../shared/data/mocap)")
    parser.add_argument("--out", type=Path, default=REPO / "outputs" / "multi_person")
    parser.add_argument("--cases", nargs="+", default=list(CASES), choices=CASES)
    parser.add_argument("--duration", type=float, default=3.0, help="seconds of each clip")
    parser.add_argument("--rate", type=float, default=30.0, help="frames/s of every stream")
    parser.add_argument("--noise", type=float, default=0.0,
                        help="2D noise (px), also passed to the solver as noise_px")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--plots", action="store_true", help="the stage's plots/ too")
    parser.add_argument("--overwrite", action="store_true")
    parser.add_argument("--verbose", "-v", action="store_true", help="the stage's logs")
    args = parser.parse_args()
    setup_logging(quiet=not args.verbose)
    try:
        main(args.out, data=args.data, cases=tuple(args.cases), duration=args.duration,
             rate=args.rate, noise=args.noise, seed=args.seed, plots=args.plots,
             overwrite=args.overwrite)
    except InputError as e:
        parser.exit(2, f"{parser.prog}: error: {e}\n")
