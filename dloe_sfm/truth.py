"""Ground truth of a simulated capture: what the simulators return beside the capture."""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import NamedTuple

import numpy as np

from .core.capture import Capture

FILE_KEYS = {"X": "X_true", "t": "t_true", "x_clean": "x_clean", "events": "event_true",
             "subjects": "subject_true", "outliers": "outlier_true", "swaps": "swap_true",
             "parents": "parents", "settings": "settings"}
"""Field -> key of a ``capture.npz`` (docs/interfaces.md, capture file)."""
PER_IMAGE = ("X", "t", "x_clean", "events", "subjects", "outliers", "swaps")
"""Fields with one entry per image (first axis N), restricted by :meth:`GroundTruth.subset`."""


@dataclass(kw_only=True)
class GroundTruth:
    """The true scene of a capture of N images (P points, S people, K symmetric pairs).

    Attributes
    ----------
    X : (N, P, 3) or (N, S, P, 3) float
        True points of every image in metres (by person with several people).
    t : (N,) float
        True time of every image in seconds.
    x_clean : (N, P, 2) or (N, S, P, 2) float or None
        Projections before noise and removal (detection slots as in the capture's x).
    events : (N,) int or None
        The clip (event) of every image.
    subjects : (N, S) int or None
        The person of every detection slot.
    outliers : (N, P) or (N, S, P) bool or None
        Observations that are wrong detections.
    swaps : (N, K) or (N, S, K) bool or None
        (image, symmetric pair) entries whose two points are exchanged.
    parents : (P,) int or None
        Skeleton parent of every point (-1 = root).
    settings : 0-d str array or None
        The simulation settings (``str(asdict(SimulationSettings))``).
    """

    X: np.ndarray
    t: np.ndarray
    x_clean: np.ndarray | None = None
    events: np.ndarray | None = None
    subjects: np.ndarray | None = None
    outliers: np.ndarray | None = None
    swaps: np.ndarray | None = None
    parents: np.ndarray | None = None
    settings: np.ndarray | None = None

    def subset(self, idx: np.ndarray) -> GroundTruth:
        """The truth of images ``idx`` (as :meth:`Capture.subset`)."""
        idx = np.asarray(idx)
        values = {f.name: getattr(self, f.name) for f in fields(self)}
        return GroundTruth(**{
            name: v[idx] if name in PER_IMAGE and v is not None else v
            for name, v in values.items()
        })

    def arrays(self) -> dict[str, np.ndarray]:
        """The file keys (``X_true``, ``t_true``, ...) of the fields that are set."""
        return {key: np.asarray(getattr(self, name)) for name, key in FILE_KEYS.items()
                if getattr(self, name) is not None}

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray]) -> GroundTruth:
        """The truth from file keys (``X_true`` and ``t_true`` required; others optional)."""
        return cls(**{name: arrays[key] for name, key in FILE_KEYS.items() if key in arrays})


class Simulated(NamedTuple):
    """A simulated capture and its ground truth: ``capture, truth = simulate(...)``."""

    capture: Capture
    truth: GroundTruth
