"""The benchmark suites: motions, methods, the varied factors and their grids, DLOE variants."""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path

from ..core.options import Options
from ..synth import SimulationSettings

# ten CMU motions covering the paper's categories (running clips are only ~1.4 s long)
MOTIONS = ["walking_1", "walking_2", "running_1", "jumping_1", "soccer_1", "soccer_2",
           "basketball_1", "basketball_2", "basketball_signal_1", "directing_traffic_1"]
QUICK_MOTIONS = ["walking_1", "jumping_1"]
CATEGORIES = {"walking": "linear", "running": "linear", "jumping": "non-linear",
              "soccer": "non-linear", "basketball": "non-linear",
              "basketball_signal": "repeating", "directing_traffic": "repeating"}
KENDALL_MOTIONS = ["walking_1", "walking_2", "basketball_1", "soccer_1", "jumping_1",
                   "basketball_signal_1", "directing_traffic_1"]

METHODS = ["pseudo-triangulation", "TB", "HPF", "SEDL", "DLOE oracle", "DLOE no sequencing",
           "DLOE graph only", "DLOE"]


@dataclass(frozen=True)
class Sweep:
    """One factor of the simulation varied over ``values`` (``quick`` in ``--quick`` mode)."""

    field: str
    values: tuple[float, ...]
    quick: tuple[float, ...]
    label: str


SWEEPS = {
    "noise": Sweep("noise", (0.0, 1.0, 2.0, 3.0, 4.0, 5.0), (0.0, 3.0), "2D noise sigma (px)"),
    "rate": Sweep("rate", (30.0, 15.0, 7.5), (30.0, 7.5), "frame rate per stream (Hz)"),
    "missing": Sweep("missing", (0.1, 0.2, 0.3, 0.4, 0.5), (0.1, 0.5), "missing points (fraction)"),
    "density": Sweep("drop", (0.1, 0.2, 0.3, 0.4, 0.5), (0.1, 0.5), "dropped frames (fraction)"),
}
ABLATION_NOISE = ((2.0, 4.0), (3.0,))
RUNTIME_SIZES = ((100, 250, 500, 1000, 2000), (60, 120, 240))
RUNTIME_MOTION = "basketball_signal_1"
STAGES = ("init", "events", "alternation", "robust rounds", "clocks", "sequencing", "assess",
          "export")
"""Stages of a solve the runtime suite times (``jobs.StageMeter``), then writing its outputs."""
RUNTIME_STREAMS = 8
"""Streams (at 30 Hz) of the runtime suite's captures unless ``--streams`` says otherwise."""
STREAMS_SIZES = (((11_000, 16, 30.0), (10_000, 64, 6.5)), ((1_100, 16, 30.0), (1_000, 64, 6.5)))
"""(images, streams, Hz) of the ``streams`` suite's captures (issue 38: 11 000 images from 16
cameras and 10^4 from 64, each within a minute), and of its ``--quick`` grid."""
LONE_SIZES = (((300, None), (300, "openpose"), (1_000, None), (4_000, None)),
              ((60, None), (60, "openpose")))
"""(lone photos, detector model) of the ``lone`` suite's captures, every photo its own camera
at a random instant (issue 38: 300 under the detector model within 15 s, 4 000 clean within a
minute, growing at most as N^1.2), and of its ``--quick`` grid."""
SUITES = [*SWEEPS, "kendall", "ablation", "runtime", "streams", "lone"]


def ablation_variants(base: Options) -> dict[str, dict]:
    """Option overrides of the DLOE variants: all terms, and S, T or R dropped (O always on).

    Options have no switch for S; dropping it is emulated by multiplying the weights of the other
    terms (lambda1, lambda3 and the W ridge) by 1e6, which leaves S with a relative weight of 1e-6
    (the minimiser of a cost is unchanged by scaling the whole cost).
    """
    big = 1e6
    return {"DLOE (S+T+O+R)": {},
            "no S": {"lambda1": base.lambda1 * big, "lambda3": base.lambda3 * big,
                     "ridge": base.ridge * big},
            "no T": {"lambda1": 0.0},
            "no R": {"lambda3": 0.0}}


def category(motion: str) -> str:
    """The paper's category of a motion (``walking_1`` or a path to ``li2018_train_...npz``)."""
    stem = Path(motion).stem.removeprefix("li2018_train_").rstrip("_0123456789")
    return CATEGORIES.get(stem, stem)


def simulation_settings(seed: int, duration: float, **changes) -> dict:
    """The :class:`SimulationSettings` of one run as a dict (picklable, saved with the runs)."""
    return asdict(SimulationSettings(duration=duration, seed=seed, **changes))
