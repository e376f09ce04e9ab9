"""Check the several-events / several-people / robust-observation targets on the shared mocap.

Four cases, each simulated with the project's own simulator (``dloe_sfm.synth.scenarios``) and
solved with the default options (the solver estimates the noise level; ``--told-noise``: told the
simulated one, as the figures before commit 05a07ab):

- events: three clips of different motions filmed one after another by the same 4 streams;
  event purity, and every clip's error against solving that clip alone (target <= 1.2 x);
- people: two people from two sequences in the same images, detections shuffled per image;
  images associated correctly (target >= 98 %), every person's error against solving that
  person alone from the same images (target <= 1.3 x);
- outliers: 5 % of the observations moved 20-100 px; error against the clean capture (target
  <= 1.25 x), also without the robust loss;
- swaps: 10 % of the left/right pairs swapped; swaps found (target >= 95 %).

    python pipelines/scenarios/pipeline.py [--data ../shared/data/mocap] [--out outputs/scenarios]
        [--told-noise]

Prints a table, writes ``scenarios.json`` (every run, settings, machine) and ``scenarios.png``.
"""

from __future__ import annotations

import json
import time
from collections import Counter
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from dloe_sfm.benchmark import machine_info
from dloe_sfm.core.capture import Capture
from dloe_sfm.core.options import Options
from dloe_sfm.core.solver import reconstruct
from dloe_sfm.evaluate import best_permutation, swaps_undone
from dloe_sfm.synth import (
    MocapSequence,
    SimulationSettings,
    load_mocap,
    pipeline_parser,
    resolve_motion,
)
from dloe_sfm.synth.mocap import symmetric_pairs
from dloe_sfm.synth.scenarios import (
    add_outliers,
    simulate_events,
    simulate_people,
    swap_symmetric,
)
from dloe_sfm.truth import GroundTruth, Simulated

EVENT_MIXES = [
    ("walking_1", "jumping_1", "basketball_signal_1"),
    ("running_1", "soccer_1", "directing_traffic_1"),
    ("basketball_1", "walking_2", "jumping_2"),
]
PEOPLE = [
    ("walking_1", "jumping_1"),
    ("running_1", "basketball_signal_1"),
    ("soccer_1", "directing_traffic_1"),
]
SINGLE = ["walking_1", "running_1", "jumping_1", "basketball_signal_1"]
NOISE = [0.0, 2.0]


def _error(X: np.ndarray, X_true: np.ndarray) -> float:
    return float(np.linalg.norm(X - X_true, axis=-1).mean() * 1000)


def _settings(noise: float, duration: float, seed: int) -> SimulationSettings:
    return SimulationSettings(duration=duration, noise=noise, seed=seed)


def _options(noise: float, told: bool) -> Options:
    """The default options; with ``told`` the simulated noise level as ``noise_px``."""
    return Options(noise_px=noise) if told else Options()


def _one_person(seq: MocapSequence, settings: SimulationSettings) -> Simulated:
    """One person at the ring's centre, as in the people case, as a one-subject capture."""
    cap, truth = simulate_people([seq], settings, shuffle=False)
    return Simulated(
        Capture(x=cap.x[:, 0], K=cap.K, R=cap.R, C=cap.C, stream=cap.stream, frame=cap.frame),
        GroundTruth(X=truth.X[:, 0], t=truth.t),
    )


def run_events(data: Path, mix: tuple, noise: float, duration: float, seed: int,
               told: bool) -> dict:
    seqs = [load_mocap(resolve_motion(data, m)) for m in mix]
    cap, sim = simulate_events(seqs, _settings(noise, duration, seed))
    opts = _options(noise, told)
    tic = time.perf_counter()
    r = reconstruct(cap, opts)
    sec = time.perf_counter() - tic
    truth, X_true = sim.events, sim.X
    majority = sum(Counter(truth[r.events == e]).most_common(1)[0][1] for e in np.unique(r.events))
    clips = []
    for k, m in enumerate(mix):
        idx = np.flatnonzero(truth == k)
        alone = reconstruct(cap.subset(idx), opts)
        mixed, solo = _error(r.X[idx], X_true[idx]), _error(alone.X, X_true[idx])
        clips.append({"motion": m, "mixed_mm": mixed, "alone_mm": solo, "ratio": mixed / solo})
    row = {"case": "events", "motions": list(mix), "noise_px": noise, "images": cap.num_images,
           "events_found": int(np.unique(r.events).size), "purity": majority / truth.size,
           "clips": clips, "seconds": sec}
    row["pass"] = row["purity"] >= 0.99 and all(c["ratio"] <= 1.2 for c in clips)
    return row


def run_people(data: Path, pair: tuple, noise: float, duration: float, seed: int,
               told: bool) -> dict:
    seqs = [load_mocap(resolve_motion(data, m)) for m in pair]
    cap, sim = simulate_people(seqs, _settings(noise, duration, seed))
    opts = _options(noise, told)
    tic = time.perf_counter()
    r = reconstruct(cap, opts)
    sec = time.perf_counter() - tic
    truth, X_true = sim.subjects, sim.X
    s = len(pair)
    perm = best_permutation(r.assignment, truth)  # subject k is person perm[k]
    associated = float((np.array(perm)[r.assignment] == truth).all(axis=1).mean())
    slot_of = np.argsort(truth, axis=1)
    people = []
    for k in range(s):
        person = perm[k]
        alone = Capture(x=cap.x[np.arange(cap.num_images), slot_of[:, person]], K=cap.K, R=cap.R,
                        C=cap.C, stream=cap.stream, frame=cap.frame)
        solo = _error(reconstruct(alone, opts).X, X_true[:, person])
        joint = _error(r.X[:, r.subject_id == k], X_true[:, person])
        people.append({"motion": pair[person], "together_mm": joint, "alone_mm": solo,
                       "ratio": joint / solo})
    row = {"case": "people", "motions": list(pair), "noise_px": noise, "images": cap.num_images,
           "subjects_found": int(r.assignment.max() + 1), "associated": associated,
           "people": people, "seconds": sec}
    row["pass"] = associated >= 0.98 and all(p["ratio"] <= 1.3 for p in people)
    return row


def run_outliers(data: Path, motion: str, noise: float, duration: float, seed: int,
                 told: bool) -> dict:
    seq = load_mocap(resolve_motion(data, motion))
    cap, sim = _one_person(seq, _settings(noise, duration, seed))
    X_true = sim.X
    bad, sim = add_outliers(cap, sim, 0.05, seed=seed + 1)
    truth = sim.outliers
    opts = _options(noise, told)
    clean = _error(reconstruct(cap, opts).X, X_true)
    tic = time.perf_counter()
    r = reconstruct(bad, opts)
    sec = time.perf_counter() - tic
    plain = _error(reconstruct(bad, opts.replace(robust_loss="none")).X, X_true)
    found = np.zeros_like(truth)
    found[tuple(r.outliers.T)] = True
    robust = _error(r.X, X_true)
    row = {"case": "outliers", "motions": [motion], "noise_px": noise, "images": cap.num_images,
           "clean_mm": clean, "robust_mm": robust, "no_robust_mm": plain,
           "ratio": robust / clean, "ratio_no_robust": plain / clean,
           "outliers": int(truth.sum()), "rejected": int(found.sum()),
           "recall": float((found & truth).sum() / truth.sum()),
           "precision": float((found & truth).sum() / max(found.sum(), 1)), "seconds": sec}
    row["pass"] = row["ratio"] <= 1.25
    return row


def run_swaps(data: Path, motion: str, noise: float, duration: float, seed: int,
              told: bool) -> dict:
    seq = load_mocap(resolve_motion(data, motion))
    cap, sim = _one_person(seq, _settings(noise, duration, seed))
    pairs = symmetric_pairs(seq.parents)
    bad, sim = swap_symmetric(cap, sim, pairs, 0.1, seed=seed + 2)
    truth = sim.swaps
    opts = _options(noise, told)
    clean = _error(reconstruct(cap, opts).X, sim.X)
    tic = time.perf_counter()
    r = reconstruct(bad, opts)
    sec = time.perf_counter() - tic
    fixed = swaps_undone(r.swaps, pairs, truth.shape)
    row = {"case": "swaps", "motions": [motion], "noise_px": noise, "images": cap.num_images,
           "swapped": int(truth.sum()), "found": float((fixed & truth).sum() / truth.sum()),
           "false_swaps": int((fixed & ~truth).sum()), "clean_mm": clean,
           "error_mm": _error(r.X, sim.X), "seconds": sec}
    row["pass"] = row["found"] >= 0.95
    return row


CASES = {"events": (run_events, EVENT_MIXES), "people": (run_people, PEOPLE),
         "outliers": (run_outliers, SINGLE), "swaps": (run_swaps, SINGLE)}


def _describe(row: dict) -> str:
    head = f"{row['case']:8s} {'+'.join(row['motions']):48s} {row['noise_px']:3.0f} px"
    if row["case"] == "events":
        ratios = " ".join(f"{c['ratio']:.2f}" for c in row["clips"])
        body = (f"{row['events_found']} events, purity {row['purity']:.3f}, "
                f"mixed/alone {ratios}")
    elif row["case"] == "people":
        ratios = " ".join(f"{p['ratio']:.2f}" for p in row["people"])
        body = (f"{row['subjects_found']} subjects, associated {row['associated']:.3f}, "
                f"together/alone {ratios}")
    elif row["case"] == "outliers":
        body = (f"clean {row['clean_mm']:.2f}, robust {row['robust_mm']:.2f} "
                f"({row['ratio']:.2f}x), no robust {row['no_robust_mm']:.2f} mm "
                f"({row['ratio_no_robust']:.1f}x); rejected {row['rejected']}/"
                f"{row['outliers']}, recall {row['recall']:.3f}, prec. {row['precision']:.3f}")
    else:
        body = (f"found {row['found']:.3f} of {row['swapped']}, {row['false_swaps']} false; "
                f"{row['error_mm']:.2f} mm (clean {row['clean_mm']:.2f})")
    return f"{head}  {body}  {row['seconds']:5.1f} s  {'PASS' if row['pass'] else 'FAIL'}"


def plot(rows: list[dict], path: Path) -> Path:
    """One panel per case: each run's measure against its target line."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = [
        ("events", "mixed / alone error", lambda r: [c["ratio"] for c in r["clips"]], 1.2),
        ("people", "together / alone error", lambda r: [p["ratio"] for p in r["people"]], 1.3),
        ("outliers", "error / clean error", lambda r: [r["ratio"], r["ratio_no_robust"]], 1.25),
        ("swaps", "swaps found", lambda r: [r["found"]], 0.95),
    ]
    fig, axes = plt.subplots(1, 4, figsize=(16, 3.8))
    for ax, (case, label, values, limit) in zip(axes, panels, strict=True):
        runs = [r for r in rows if r["case"] == case]
        for i, r in enumerate(runs):
            v = values(r)
            if case == "outliers":
                ax.scatter([i], [v[1]], marker="x", color="tab:red",
                           label="no robust loss" if i == 0 else None)
                v = v[:1]
            ax.scatter([i] * len(v), v, color="tab:blue", label="DLOE" if i == 0 else None)
        ax.axhline(limit, color="k", ls="--", lw=1, label="target")
        ax.set_xticks(range(len(runs)))
        ax.set_xticklabels([f"{'+'.join(m[:4] for m in r['motions'])}\n{r['noise_px']:.0f}px"
                            for r in runs], fontsize=6, rotation=45)
        if case == "outliers":
            ax.set_yscale("log")
        ax.set_title(f"{case}: {label}", fontsize=9)
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def main(data: Path, out: Path, cases: list[str], duration: float, seed: int,
         jobs: int, told: bool = False) -> list[dict]:
    tasks = [(CASES[c][0], data, item, noise, duration, seed, told)
             for c in cases for item in CASES[c][1] for noise in NOISE]
    rows = []
    with ProcessPoolExecutor(max_workers=jobs) as pool:
        futures = [pool.submit(*t) for t in tasks]
        for f in futures:
            rows.append(f.result())
            print(_describe(rows[-1]), flush=True)
    out.mkdir(parents=True, exist_ok=True)
    meta = {"machine": machine_info(), "duration_s": duration, "seed": seed, "told_noise": told,
            "streams": "4 x 30 Hz", "options": Options().to_dict()}
    (out / "scenarios.json").write_text(json.dumps({"meta": meta, "runs": rows}, indent=2))
    plot(rows, out / "scenarios.png")
    return rows


if __name__ == "__main__":
    from dloe_sfm.cli import setup_logging

    setup_logging()
    p = pipeline_parser(__file__, __doc__, "scenarios")
    p.add_argument("--cases", nargs="+", default=list(CASES), choices=list(CASES))
    p.add_argument("--duration", type=float, default=3.0, help="seconds of each clip")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--jobs", type=int, default=2)
    p.add_argument("--told-noise", action="store_true",
                   help="tell the solver the simulated noise (noise_px) instead of estimating it")
    a = p.parse_args()
    result = main(a.data, a.out, a.cases, a.duration, a.seed, a.jobs, a.told_noise)
    print(f"{sum(r['pass'] for r in result)} passed, {sum(not r['pass'] for r in result)} failed")
