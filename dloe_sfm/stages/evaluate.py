"""Score a result against ground truth: a result file against a simulated capture's truth, or a
``reconstruct`` output folder against a truth file."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from ..errors import InputError
from ..evaluate import evaluate, evaluate_output
from ..io import (
    atomic_path,
    check_not_input,
    load_capture,
    load_result,
    load_truth,
    without_empty_images,
)
from ..truth import FILE_KEYS, PER_IMAGE


def main(result: Path, capture: Path, *, references: bool = True, out: Path | None = None) -> dict:
    """Evaluate ``result`` (result.npz) against ``capture`` (capture.npz with ground truth), or
    a ``reconstruct`` output folder against a truth file (:func:`evaluate_output`). The
    capture's images that observe no point are left out, as ``solve`` does."""
    if out is not None:
        check_not_input(out, (result, capture))
    if Path(result).is_dir():
        scores = evaluate_output(result, capture)
    else:
        full = load_capture(capture, validate=False).validate(str(capture), empty_images=True)
        cap, kept = without_empty_images(full, capture)
        truth = load_truth(capture)
        if kept.size < full.num_images:
            for name, key in FILE_KEYS.items():
                value = getattr(truth, name)
                if name in PER_IMAGE and value is not None and len(value) != full.num_images:
                    raise InputError(f"{capture}: ground-truth key '{key}' has {len(value)} "
                                     f"rows for {full.num_images} images")
            truth = truth.subset(kept)
        scores = evaluate(cap, truth, load_result(result), references=references)
    if out is not None:
        with atomic_path(out) as tmp:
            tmp.write_text(json.dumps(scores, indent=2))
    return scores


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("result", type=Path,
                        help="result.npz, or a reconstruct output folder")
    parser.add_argument("capture", type=Path,
                        help="capture.npz with X_true and t_true; for a folder, a truth .npz "
                             "with image_names, X_true (metres) and optionally t_true (s)")
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

    from ..cli import run_stage

    sys.exit(run_stage(__name__))
