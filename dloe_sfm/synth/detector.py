"""Detector error models for the simulator, fitted on real detections (docs/method.md,
"Development data: the detector model"; ``pipelines/detector_model``).

A model turns clean projections into detections as a 2D keypoint detector makes them, in units
of the person's height in the image (so it transfers to other image scales): a fixed bias per
(stream, joint), Student-t noise, missed joints, left/right swaps and a confidence per detection
drawn from the scores the real detector gave to errors of that size.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from importlib.resources import files

import numpy as np

from ..errors import InputError

DETECTORS = ("openpose",)
"""Bundled models (``detectors/<name>.json``)."""


@dataclass(frozen=True, kw_only=True)
class DetectorModel:
    """A fitted detector error model; lengths are relative to the person's height in pixels.

    ``dof`` / ``scale``: Student-t noise per image coordinate; the fixed per-(stream, joint)
    offset per coordinate has quantiles ``bias_quantiles`` at ``bias_values``; ``miss_rate``:
    fraction of joints not detected; ``swap_rate``: fraction of (image, left/right pair)
    exchanged; ``outlier_threshold``: noise beyond which a detection counts as an outlier;
    ``error_edges`` (B + 1,) bins of the error size with ``score_quantiles`` (B, Q) the scores'
    quantiles ``quantiles`` (Q,) in each;
    ``figures``: statistics of the real residuals the model was fitted on.
    """

    name: str
    dof: float
    scale: float
    bias_quantiles: np.ndarray
    bias_values: np.ndarray
    miss_rate: float
    swap_rate: float
    outlier_threshold: float
    error_edges: np.ndarray
    quantiles: np.ndarray
    score_quantiles: np.ndarray
    figures: dict

    @classmethod
    def load(cls, name: str) -> DetectorModel:
        """The bundled model ``name`` (one of ``DETECTORS``)."""
        if name not in DETECTORS:
            raise InputError(f"--detector must be one of {', '.join(DETECTORS)}, got {name!r}")
        data = json.loads((files(__package__) / "detectors" / f"{name}.json").read_text())
        conf = data["confidence"]
        return cls(
            name=data["name"], dof=data["residual"]["dof"], scale=data["residual"]["scale"],
            bias_quantiles=np.array(data["bias"]["quantiles"]),
            bias_values=np.array(data["bias"]["values"]),
            miss_rate=data["miss_rate"], swap_rate=data["swap_rate"],
            outlier_threshold=data["outlier_threshold"],
            error_edges=np.array(conf["error_edges"]), quantiles=np.array(conf["quantiles"]),
            score_quantiles=np.array(conf["score_quantiles"]), figures=data["figures"],
        )

    def confidence(self, error: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Scores in (0, 1] for relative errors ``error`` (any shape), drawn from the real
        scores of errors in the same bin."""
        which = np.clip(np.searchsorted(self.error_edges, error, side="right") - 1,
                        0, len(self.score_quantiles) - 1)
        u = rng.random(error.shape)
        score = np.empty(error.shape)
        for b, q in enumerate(self.score_quantiles):
            score[which == b] = np.interp(u[which == b], self.quantiles, q)
        return np.clip(score, 1e-3, 1.0)


def detect(
    model: DetectorModel,
    x_clean: np.ndarray,
    stream: np.ndarray,
    pairs: np.ndarray,
    rng: np.random.Generator,
    visible: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Detections of clean projections ``x_clean`` (N, ..., P, 2) pixels.

    Every image's person height in pixels is the y-extent of its clean points; ``stream`` (N,)
    picks the per-(stream, joint) bias, ``pairs`` (K, 2) the left/right joints that may swap;
    ``visible`` (N, ..., P) False where the observation was removed beforehand.
    Returns x (N, ..., P, 2) with NaN for misses, confidence (N, ..., P) in (0, 1] (0 where
    missing), and the ground truth: outliers (N, ..., P) and swaps (N, ..., K) bool.
    """
    n, p = x_clean.shape[0], x_clean.shape[-2]
    lead = (n,) + (1,) * (x_clean.ndim - 3)  # bias broadcast over the person slots
    height = np.nanmax(x_clean[..., 1], axis=-1) - np.nanmin(x_clean[..., 1], axis=-1)
    bias = np.interp(rng.random((int(stream.max()) + 1, p, 2)), model.bias_quantiles,
                     model.bias_values)
    noise = model.scale * rng.standard_t(model.dof, x_clean.shape)
    x = x_clean + (bias[stream].reshape(*lead, p, 2) + noise) * height[..., None, None]
    missed = rng.random(x.shape[:-1]) < model.miss_rate
    x[missed if visible is None else missed | ~visible] = np.nan
    seen = np.isfinite(x).all(axis=-1)
    both = seen[..., pairs[:, 0]] & seen[..., pairs[:, 1]]
    swap = both & (rng.random(both.shape) < model.swap_rate)
    idx = np.nonzero(swap)
    a, b = pairs[idx[-1], 0], pairs[idx[-1], 1]
    head = idx[:-1]
    x[(*head, a)], x[(*head, b)] = x[(*head, b)], x[(*head, a)]
    error = np.linalg.norm(x - x_clean, axis=-1) / height[..., None]
    confidence = np.where(seen, model.confidence(np.nan_to_num(error), rng), 0.0)
    outlier = seen & (np.linalg.norm(noise, axis=-1) > model.outlier_threshold)
    return x, confidence, outlier, swap
