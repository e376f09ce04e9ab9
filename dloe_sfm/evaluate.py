"""Score a result against a capture's ground truth: 3D error (mm) and |Kendall tau|."""

from __future__ import annotations

import csv
import itertools
import json
import logging
from pathlib import Path

import numpy as np

from .core.capture import Capture
from .core.clocks import time_chain
from .core.options import Options
from .core.problem import initialise, normalise
from .core.result import Result
from .core.sequencing import kendall_tau
from .core.xstep import x_step
from .errors import InputError
from .io import NpzReader
from .truth import GroundTruth

logger = logging.getLogger("dloe_sfm")


def point_errors(
    X: np.ndarray, X_true: np.ndarray, visible: np.ndarray, *, unit: float = 1000.0
) -> dict[str, float]:
    """Mean Euclidean error over all (n, p), and over observed / missing ones, in mm (metres in)."""
    e = np.linalg.norm(X - X_true, axis=2) * unit
    out = {"error_mm": float(e.mean()), "error_observed_mm": float(e[visible].mean())}
    out["error_missing_mm"] = float(e[~visible].mean()) if (~visible).any() else float("nan")
    out["error_median_mm"] = float(np.median(e))
    return out


def best_permutation(assignment: np.ndarray, truth: np.ndarray) -> tuple[int, ...]:
    """Subject ids are arbitrary: the permutation (subject k = person perm[k]) under which the
    most images have every detection of ``assignment`` (N, M) on its ``truth`` (N, M) person."""
    s = int(max(assignment.max(), truth.max())) + 1
    return max(itertools.permutations(range(s)),
               key=lambda q: (np.array(q)[assignment] == truth).all(axis=1).mean())


def swaps_undone(swaps: np.ndarray, pairs: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """(N, K) bool: the (image, pair) entries that the result's ``swaps`` (image, a, b)
    exchanged an odd number of times, ``pairs`` (K, 2) the capture's symmetric pairs."""
    count = np.zeros(shape, dtype=np.int64)
    for n, a, _ in swaps:
        count[n, np.flatnonzero(pairs[:, 0] == a)] += 1
    return count % 2 == 1


def oracle_reconstruct(
    capture: Capture, times: np.ndarray, *, lambda1: float = 0.0, lambda2: float = np.inf
) -> np.ndarray:
    """DLOE's X-step with the true temporal chain as W: the accuracy reference.

    Every image is linked to its temporal predecessor and successor among all images, with
    barycentric weights from the true times (so constant-velocity motion is reproduced exactly).
    The first and last images have no neighbour on one side: their rows get D = 0, and they are
    placed by their neighbours' rows. Returns (N, P, 3) in world units.
    """
    W, D = time_chain(times)
    options = Options()
    X0 = initialise(capture, options)
    norm = normalise(capture, options, X0)
    X = x_step(W, D, norm.problem, lambda1=lambda1, lambda2=lambda2, X_prev=norm.to_normal(X0))
    return norm.to_world(X)


def evaluate(
    capture: Capture, truth: GroundTruth, result: Result, *, references: bool = True
) -> dict[str, float]:
    """Errors of ``result.X`` and |tau| of ``result.order`` against the truth's X and t.

    With ``references`` also the two yardsticks on the same capture: the oracle (X-step with the
    true temporal chain, points pinned to their rays) and pseudo-triangulation (one subject).
    What else the truth knows adds: images associated correctly (``subjects``: subjects matched
    by the best permutation, errors then per subject), event purity (``events``, when the result
    has events), and the rejected outliers and fixed swaps against ``outliers`` / ``swaps``.
    """
    _check_truth(capture, truth, result)
    X, X_true, t_true = result.X, truth.X, truth.t
    out: dict[str, float] = {}
    vis = capture.visible
    if X_true.ndim == 4:  # several subjects: X_true (N, S, P, 3) by person
        out.update(_subjects(truth, result))
        s, p = X_true.shape[1:3]
        perm = [int(out[f"subject_{k}_person"]) for k in range(s)]
        X_true = X_true[:, perm].reshape(X_true.shape[0], s * p, 3)
        vis = np.ones(X_true.shape[:2], dtype=bool)
        references = False
    if X.shape != X_true.shape:
        raise InputError(f"result X has shape {X.shape}, the capture's X_true {X_true.shape}")
    out.update(point_errors(X, X_true, vis))
    out["kendall_tau"] = kendall_tau(result.order, t_true)
    ambiguous = result.order_ambiguous
    if ambiguous is not None and ambiguous.any() and (~ambiguous).sum() >= 2:
        # issue 38: the order of the images whose place the solve could pin down
        rest = result.rank[~ambiguous]
        out["kendall_tau_unambiguous"] = kendall_tau(np.argsort(rest), t_true[~ambiguous])
    out["order_ambiguous"] = 0 if ambiguous is None else int(ambiguous.sum())
    if truth.events is not None and result.events.size:
        true_events, found = truth.events, result.events
        majority = sum(np.bincount(true_events[found == e]).max() for e in np.unique(found))
        out["events_found"] = float(np.unique(found).size)
        out["event_purity"] = majority / true_events.size
    if truth.outliers is not None:
        outliers = truth.outliers
        hit = np.zeros(outliers.shape, dtype=bool)
        if result.outliers.size:
            hit[tuple(result.outliers.T)] = True
        out["outliers_rejected"] = float(hit.sum())
        out["outlier_recall"] = float((hit & outliers).sum() / max(outliers.sum(), 1))
        out["outlier_precision"] = float((hit & outliers).sum() / max(hit.sum(), 1))
    if truth.swaps is not None and capture.symmetric_pairs is not None:
        swaps, pairs = truth.swaps, capture.symmetric_pairs
        fixed = swaps_undone(result.swaps, pairs, swaps.shape)
        out["swaps_found"] = float((fixed & swaps).sum() / max(swaps.sum(), 1))
        out["swaps_false"] = float((fixed & ~swaps).sum())
    if references:
        out["oracle_mm"] = point_errors(oracle_reconstruct(capture, t_true), X_true, vis)[
            "error_mm"
        ]
        out["pseudo_triangulation_mm"] = point_errors(initialise(capture, Options()), X_true, vis)[
            "error_mm"
        ]
    return out


def _check_truth(capture: Capture, truth: GroundTruth, result: Result) -> None:
    """Shapes and values of the ground truth and of the result's extra arrays, so that a bad
    file is a one-line InputError naming the key (the file's: ``X_true``, ``outliers``, ...)."""
    n = capture.num_images
    observations = capture.visible.shape

    def need(ok: bool, key: str, what: str) -> None:
        if not ok:
            raise InputError(f"ground truth / result key '{key}' must be {what}")

    X_true = truth.X
    need(X_true.ndim in (3, 4) and X_true.shape[0] == n and X_true.shape[-1] == 3
         and np.isfinite(X_true).all(), "X_true", f"finite, (N, P, 3) or (N, S, P, 3), N = {n}")
    need(truth.t.shape == (n,) and np.isfinite(truth.t).all(), "t_true",
         f"finite, shape ({n},)")
    integer = np.issubdtype
    if truth.events is not None:
        e = truth.events
        need(e.shape == (n,) and integer(e.dtype, np.integer) and (e >= 0).all(), "event_true",
             f"non-negative integers, shape ({n},)")
    if truth.outliers is not None:
        need(truth.outliers.shape == observations, "outlier_true", f"of shape {observations}")
    if truth.swaps is not None and capture.symmetric_pairs is not None:
        need(truth.swaps.shape == (n, len(capture.symmetric_pairs)), "swap_true",
             f"of shape ({n}, {len(capture.symmetric_pairs)})")
    if truth.subjects is not None:
        st = truth.subjects
        need(st.shape == observations[:2] and integer(st.dtype, np.integer) and (st >= -1).all()
             and (X_true.ndim != 4 or (st < X_true.shape[1]).all()), "subject_true",
             f"integers in -1..S-1, shape {observations[:2]}")
    if result.outliers.size:
        o = result.outliers
        need(o.ndim == 2 and o.shape[1] == len(observations) and (o >= 0).all()
             and (o < np.array(observations)).all(), "outliers",
             f"(K, {len(observations)}) indices into {observations}")
    if result.swaps.size:
        w = result.swaps
        need(w.ndim == 2 and w.shape[1] == 3 and ((w[:, 0] >= 0) & (w[:, 0] < n)).all(),
             "swaps", f"(K, 3) with images in 0..{n - 1}")
    if result.assignment is not None:
        a = result.assignment
        need(a.shape == observations[:2] and (a >= -1).all(), "assignment",
             f"integers >= -1, shape {observations[:2]}")


def _subjects(truth: GroundTruth, result: Result) -> dict[str, float]:
    """Association of a several-subject result against the truth's ``subjects`` and
    per-person errors."""
    if result.assignment is None or truth.subjects is None:
        raise InputError("a several-subject capture needs the result's 'assignment' and the "
                         "capture's 'subject_true' to be evaluated")
    X, X_true, assignment = result.X, truth.X, result.assignment
    s, p = X_true.shape[1:3]
    if assignment.max() + 1 != s:
        raise InputError(f"result has {assignment.max() + 1} subjects, the capture {s} people")
    perm = best_permutation(assignment, truth.subjects)
    out = {"associated": float((np.array(perm)[assignment] == truth.subjects).all(axis=1).mean())}
    for k, person in enumerate(perm):
        out[f"subject_{k}_person"] = float(person)
        out[f"subject_{k}_error_mm"] = float(
            np.linalg.norm(X[:, k * p:(k + 1) * p] - X_true[:, person], axis=2).mean() * 1000
        )
    return out


def similarity(X: np.ndarray, Y: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Scale s, rotation R (3, 3) and translation t (3,) with ``Y ~ s R X + t`` in least squares
    (Umeyama 1991), X and Y (M, 3) corresponding points, M >= 3 not all on a line."""
    mx, my = X.mean(axis=0), Y.mean(axis=0)
    U, S, Vt = np.linalg.svd((Y - my).T @ (X - mx) / len(X))
    d = np.ones(3)
    d[2] = np.sign(np.linalg.det(U @ Vt)) or 1.0
    R = U @ np.diag(d) @ Vt
    var = ((X - mx) ** 2).sum() / len(X)
    s = float((S * d).sum() / var) if var > 0 else 1.0
    return s, R, my - s * R @ mx


def _sequence_times(path: Path) -> dict[str, float]:
    """Image -> estimated time from a ``sequence.csv`` with a ``time`` column ({} without)."""
    if not path.is_file():
        return {}
    try:
        with open(path, newline="", encoding="utf-8") as f:
            rows = list(csv.DictReader(f))
        return {row["image"]: float(row["time"]) for row in rows
                if row.get("time") not in (None, "")}
    except (OSError, UnicodeDecodeError, KeyError, ValueError, csv.Error) as e:
        raise InputError(f"{path}: cannot read the image times ({e})") from None


def _sync_rms(t_est: np.ndarray, t_true: np.ndarray, events: np.ndarray) -> float:
    """RMS, in the truth's unit, of the true times left after an affine map from the estimated
    ones (their unit and origin are the reference stream's) fitted per event."""
    residuals = []
    for e in np.unique(events):
        sel = (events == e) & np.isfinite(t_est) & np.isfinite(t_true)
        if sel.sum() < 3:
            continue
        A = np.stack([t_est[sel], np.ones(sel.sum())], axis=1)
        coef = np.linalg.lstsq(A, t_true[sel], rcond=None)[0]
        residuals.append(t_true[sel] - A @ coef)
    return float(np.sqrt(np.mean(np.concatenate(residuals) ** 2))) if residuals else float("nan")


def evaluate_output(folder: Path | str, truth: Path | str) -> dict[str, float]:
    """Score a ``reconstruct`` output folder against a truth file (``image_names`` (N,), ``X_true``
    (N, P, 3) in metres, optionally ``t_true`` (N,) seconds; the demo's ``ground_truth.npz``).

    Mean / median 3D error in mm as written and after the similarity that best aligns the result
    to the truth (for a model in another frame or scale), |Kendall tau| of the order and the RMS
    sync error (ms, after an affine map per event of ``sequence.csv``'s times) when the truth has
    times; and, where ``report.json`` flags images whose place in the order the data could not
    pin down (``image_status.order_ambiguous``), their count and the order and sync without
    them (``kendall_tau_unambiguous``, ``sync_rms_unambiguous_ms``), as :func:`evaluate` does.
    """
    folder, truth = Path(folder), Path(truth)
    if not (folder / "trajectories.npz").is_file():
        raise InputError(f"{folder}: not a reconstruct output folder (no trajectories.npz)")
    with NpzReader(folder / "trajectories.npz") as f:
        for key in ("X", "order", "image_names", "events"):
            if key not in f.files:
                raise InputError(f"{f.path}: missing key '{key}'")
        X, order = f.read("X"), f.read("order", "iu")
        names, events = [str(n) for n in f.read("image_names", "U")], f.read("events", "iu")
    with NpzReader(truth) as g:
        for key in ("image_names", "X_true"):
            if key not in g.files:
                raise InputError(f"{truth}: missing key '{key}'")
        truth_names = g.read("image_names", "U")
        X_true = g.read("X_true")
        t_true = g.read("t_true") if "t_true" in g.files else None
    n = len(names)
    if X.ndim != 3 or X.shape[::2] != (n, 3) or order.shape != (n,) or events.shape != (n,):
        raise InputError(f"{folder / 'trajectories.npz'}: keys 'X' (N, P, 3), 'order' and "
                         f"'events' (N,) do not match its {n} image names")
    m = len(truth_names)
    if X_true.ndim != 3 or X_true.shape[::2] != (m, 3) or (
            t_true is not None and t_true.shape != (m,)):
        raise InputError(f"{truth}: keys 'X_true' (N, P, 3) and 't_true' (N,) do not match its "
                         f"{m} image names")
    row = {str(name): i for i, name in enumerate(truth_names)}
    missing = [name for name in names if name not in row]
    if missing:
        raise InputError(f"{truth}: no ground truth for image(s) {missing[:5]}")
    idx = np.array([row[name] for name in names], dtype=np.int64)
    X_true = X_true[idx]
    if X_true.shape != X.shape:
        raise InputError(f"{truth}: 'X_true' has {X_true.shape[1:]} points per image, "
                         f"the result {X.shape[1:]}")
    ok = np.isfinite(X).all(axis=2) & np.isfinite(X_true).all(axis=2)
    if ok.sum() < 3:
        raise InputError(f"{folder}: fewer than 3 points with both a result and a truth")
    e = 1000 * np.linalg.norm(X - X_true, axis=2)[ok]
    s, R, t = similarity(X[ok], X_true[ok])
    e_aligned = 1000 * np.linalg.norm(s * X[ok] @ R.T + t - X_true[ok], axis=1)
    scores = {"images": len(names), "error_mm": float(e.mean()),
              "error_median_mm": float(np.median(e)), "error_aligned_mm": float(e_aligned.mean()),
              "alignment_scale": s}
    if t_true is not None:
        t_true = t_true[idx].astype(np.float64)
        scores["kendall_tau"] = kendall_tau(order, t_true)
        times = _sequence_times(folder / "sequence.csv")
        t_est = np.array([times.get(name, np.nan) for name in names])
        if times:
            scores["sync_rms_ms"] = 1000 * _sync_rms(t_est, t_true, events)
        flagged = _order_ambiguous(folder / "report.json")
        ambiguous = np.array([name in flagged for name in names], dtype=bool)
        scores["order_ambiguous"] = int(ambiguous.sum())
        if ambiguous.any() and (~ambiguous).sum() >= 2:
            rank = np.empty(n, dtype=np.int64)
            rank[order] = np.arange(n)
            kept = ~ambiguous
            scores["kendall_tau_unambiguous"] = kendall_tau(np.argsort(rank[kept]), t_true[kept])
            if times:
                scores["sync_rms_unambiguous_ms"] = 1000 * _sync_rms(t_est[kept], t_true[kept],
                                                                     events[kept])
    return scores


def _order_ambiguous(path: Path) -> set[str]:
    """Names of the images ``report.json`` flags as placed where the data could not pin them
    down (``image_status.order_ambiguous``; none without the file or the key)."""
    if not path.is_file():
        return set()
    try:
        report = json.loads(path.read_text(encoding="utf-8"))
        names = report.get("image_status", {}).get("order_ambiguous", [])
        return {str(name) for name in names}
    except (OSError, UnicodeDecodeError, ValueError, AttributeError, TypeError) as e:
        raise InputError(f"{path}: cannot read the flagged images ({e})") from None
