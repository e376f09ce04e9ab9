"""Score a result against a capture's ground truth: 3D error (mm) and |Kendall tau|."""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

import numpy as np

from .core.capture import Capture
from .core.options import Options
from .core.sequencing import kendall_tau
from .core.solver import initialise, oracle_reconstruct
from .errors import InputError
from .io import load_capture, load_result

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


def evaluate(
    capture: Capture, X: np.ndarray, order: np.ndarray, *, references: bool = True
) -> dict[str, float]:
    """Errors of X and |tau| of order against ``capture.extras`` X_true / t_true.

    With ``references`` also the two yardsticks on the same capture: the oracle (X-step with the
    true temporal chain, points pinned to their rays) and pseudo-triangulation.
    """
    for key in ("X_true", "t_true"):
        if key not in capture.extras:
            raise InputError(f"capture has no ground truth '{key}' to evaluate against")
    X_true, t_true = capture.extras["X_true"], capture.extras["t_true"]
    if X.shape != X_true.shape:
        raise InputError(f"result X has shape {X.shape}, the capture's X_true {X_true.shape}")
    vis = capture.visible
    out = point_errors(X, X_true, vis)
    out["kendall_tau"] = kendall_tau(order, t_true)
    if references:
        out["oracle_mm"] = point_errors(oracle_reconstruct(capture, t_true), X_true, vis)[
            "error_mm"
        ]
        out["pseudo_triangulation_mm"] = point_errors(initialise(capture, Options()), X_true, vis)[
            "error_mm"
        ]
    return out


def main(result: Path, capture: Path, *, references: bool = True, out: Path | None = None) -> dict:
    """Evaluate ``result`` (result.npz) against ``capture`` (capture.npz with ground truth)."""
    cap = load_capture(capture)
    res = load_result(result)
    scores = evaluate(cap, res["X"], res["order"], references=references)
    if out is not None:
        Path(out).write_text(json.dumps(scores, indent=2))
    return scores


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("result", type=Path, help="result.npz")
    parser.add_argument("capture", type=Path, help="capture.npz with X_true and t_true")
    parser.add_argument(
        "--no-references",
        dest="references",
        action="store_false",
        help="skip the oracle and pseudo-triangulation yardsticks",
    )
    parser.add_argument("--json", dest="out", type=Path, help="also write the scores as JSON")


def run(args: argparse.Namespace) -> int:
    scores = main(args.result, args.capture, references=args.references, out=args.out)
    width = max(len(k) for k in scores)
    for k, v in scores.items():
        print(f"{k:<{width}}  {v:.4f}")
    return 0


if __name__ == "__main__":
    import sys

    from .cli import run_stage

    sys.exit(run_stage(__name__))
