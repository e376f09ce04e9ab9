"""The benchmark's runs: one job per simulated capture, run in spawned single-threaded workers.

A job takes a spec (a picklable dict: motion file, simulation settings, suite-specific fields)
and returns its records (one dict per method, order or solve); jobs are top-level functions so a
spawned worker can import them.
"""

from __future__ import annotations

import logging
import multiprocessing as mp
import resource
import tempfile
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
from tqdm.auto import tqdm

from ..baselines import high_pass_filter, pseudo_triangulation, sedl, trajectory_basis
from ..core import alternation, heldout, pipeline, solver
from ..core.capture import Capture
from ..core.embedding import line_embedding
from ..core.options import Distance, Embedding, Options
from ..core.parallel import single_threaded_children
from ..core.problem import initialise
from ..core.sequencing import (
    affine_time,
    distance_matrix,
    kendall_tau,
    order_from_embedding,
)
from ..core.solver import reconstruct
from ..errors import InputError
from ..evaluate import oracle_reconstruct, point_errors
from ..synth import SimulationSettings, load_mocap, simulate
from .suites import STAGES, category

logger = logging.getLogger("dloe_sfm")


def run_method(
    name: str, capture: Capture, t_true: np.ndarray, options: Options
) -> tuple[np.ndarray, dict]:
    """Reconstruct ``capture`` with one of :data:`~.suites.METHODS` (``t_true`` (N,) the true
    times, for the methods given them and the scores); returns (X (N, P, 3), extra facts)."""
    if name == "pseudo-triangulation":
        return pseudo_triangulation(capture, options), {}
    if name == "TB":
        return trajectory_basis(capture, t_true), {}
    if name == "HPF":
        return high_pass_filter(capture, t_true), {}
    if name == "SEDL":
        return sedl(capture, options=options), {}
    if name == "DLOE oracle":
        return oracle_reconstruct(capture, t_true), {}
    if name == "DLOE no sequencing":
        options = options.replace(prior_weight=0.0, spectral_prior=False, stream_clocks="off")
    elif name == "DLOE graph only":  # the paper's method: no stream clocks
        options = options.replace(stream_clocks="off")
    elif name != "DLOE":
        raise InputError(f"unknown method '{name}'")
    result = reconstruct(capture, options)
    return result.X, {"nit": result.nit, "kendall_tau": kendall_tau(result.order, t_true),
                      "events": int(result.events.max()) + 1}


def sweep_job(spec: dict) -> list[dict]:
    """Simulate one capture and reconstruct it with every method (or DLOE variant) of ``spec``."""
    capture, truth = simulate(load_mocap(spec["motion"]), SimulationSettings(**spec["settings"]))
    # DLOE is told the detector noise, as the paper set lambda2 for its noise experiments
    base = Options(noise_px=spec["settings"].get("noise", 0.0))
    records = []
    for method, overrides in spec["methods"].items():
        record = {"method": method, "motion": Path(spec["motion"]).stem, "seed":
                  spec["settings"]["seed"], "setting": spec["setting"],
                  "num_images": capture.num_images}
        t0 = time.perf_counter()
        try:
            name = "DLOE" if spec["suite"] == "ablation" else method
            X, extra = run_method(name, capture, truth.t, base.replace(**overrides))
        except Exception as e:  # one failing method must not sink a long sweep
            logger.warning("%s on %s failed: %s", method, record["motion"], e)
            record["failed"] = f"{type(e).__name__}: {e}"
            records.append(record)
            continue
        record["seconds"] = time.perf_counter() - t0
        record.update(point_errors(X, truth.X, capture.visible))
        record.update(extra)
        records.append(record)
    return records


def kendall_job(spec: dict) -> list[dict]:
    """|tau| of every (embedding, distance) order on the initial and the DLOE shapes."""
    capture, truth = simulate(load_mocap(spec["motion"]), SimulationSettings(**spec["settings"]))
    t_true = truth.t
    options = Options()
    shapes = {"initial": initialise(capture, options), "optimised": reconstruct(capture, options).X}
    records = []
    for stage, X in shapes.items():
        row = {"motion": Path(spec["motion"]).stem, "category": category(spec["motion"]),
               "seed": spec["settings"]["seed"], "stage": stage,
               "num_images": capture.num_images}
        for distance in Distance:
            Z = distance_matrix(X, capture.stream_ids, capture.frame, distance)
            for embedding in (Embedding.SPECTRAL, Embedding.MDS, Embedding.SHP):
                order = order_from_embedding(line_embedding(Z, embedding))
                records.append({**row, "distance": distance.value, "embedding": embedding.value,
                                "kendall_tau": kendall_tau(order, t_true)})
        clock = affine_time(X, capture.stream_ids, capture.frame)
        records.append({**row, "distance": "arc", "embedding": Embedding.AFFINE.value,
                        "kendall_tau": kendall_tau(order_from_embedding(clock), t_true)})
    return records


def _rss_mb() -> float:
    """Peak resident set size of this process so far, MB (Linux reports kB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


# (module, function, stage) wrapped by StageMeter; a solve_events inside robust_rounds is a
# robust round, not the first alternation
_METERED = (
    (pipeline, "initialise", "init"),
    (pipeline, "initial_events", "events"),
    (pipeline, "segment_events", "events"),
    (pipeline, "solve_events", "alternation"),
    (pipeline, "robust_rounds", "robust rounds"),
    (pipeline, "clocks_and_offsets", "clocks"),
    (pipeline, "sequence", "sequencing"),
    (alternation, "sequence", "sequencing"),
    (heldout, "sequence", "sequencing"),
    (solver, "assess", "assess"),
)


class StageMeter:
    """Wall seconds and peak-memory rise of every stage of the solves run inside it.

    Wraps the pipeline's stage functions (:data:`_METERED`) while active. Time is exclusive: a
    stage called inside another (sequencing inside the alternation, the alternation inside a
    robust round) is charged to itself only, so the stages never overlap. ``rise_mb``:
    how far each stage raised the process's peak resident set (its high-water mark), MB.
    """

    def __init__(self) -> None:
        self.seconds = dict.fromkeys(STAGES, 0.0)
        self.rise_mb = dict.fromkeys(STAGES, 0.0)
        self._open: list[str] = []  # stages of the calls under way
        self._stack: list[list[float]] = []  # per open call: [time, rise] of nested calls
        self._saved: list[tuple] = []

    def _wrap(self, fn: Callable, stage: str) -> Callable:
        def metered(*args, **kwargs):
            inside_robust = "robust rounds" in self._open
            name = "robust rounds" if stage == "alternation" and inside_robust else stage
            self._open.append(name)
            self._stack.append([0.0, 0.0])
            rss, t0 = _rss_mb(), time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                seconds, rise = time.perf_counter() - t0, _rss_mb() - rss
                nested = self._stack.pop()
                self._open.pop()
                self.seconds[name] += seconds - nested[0]
                self.rise_mb[name] += rise - nested[1]
                if self._stack:
                    self._stack[-1][0] += seconds
                    self._stack[-1][1] += rise

        return metered

    def __enter__(self) -> StageMeter:
        for module, attr, stage in _METERED:
            fn = getattr(module, attr)
            self._saved.append((module, attr, fn))
            setattr(module, attr, self._wrap(fn, stage))
        return self

    def __exit__(self, *exc) -> None:
        for module, attr, fn in reversed(self._saved):
            setattr(module, attr, fn)
        self._saved.clear()


def runtime_job(spec: dict) -> list[dict]:
    """Time one DLOE solve in a fresh process: its steps, its stages (:class:`StageMeter`) and
    the peak memory before and after the solve."""
    capture, truth = simulate(load_mocap(spec["motion"]), SimulationSettings(**spec["settings"]))
    before = _rss_mb()
    with StageMeter() as meter:
        result = reconstruct(capture, Options())
    from ..export import export_outputs  # open3d is slow to import: only here

    # the outputs of a solve (trajectories, point clouds, report; no plots) into a scratch folder
    rss, t0 = _rss_mb(), time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        export_outputs(Path(tmp) / "out", capture, result, plots=False)
    meter.seconds["export"] = time.perf_counter() - t0
    meter.rise_mb["export"] = _rss_mb() - rss
    t = result.timings
    steps = t["w_step"] + t["d_step"] + t["x_step"]
    return [{"target": spec["setting"], "detector": spec["settings"]["detector"],
             "num_images": capture.num_images,
             "num_streams": int(np.unique(capture.stream_ids).size),
             "num_points": capture.num_points, "nit": result.nit, "seconds": result.seconds,
             "per_iteration": steps / max(result.nit, 1),
             **{f"{k}_per_iteration": t[k] / max(result.nit, 1)
                for k in ("w_step", "d_step", "x_step")},
             "timings": t, "stage_seconds": meter.seconds, "stage_rise_mb": meter.rise_mb,
             "rss_before_mb": before, "peak_rss_mb": _rss_mb(),
             "error_mm": point_errors(result.X, truth.X, capture.visible)["error_mm"]}]


def run_jobs(job: Callable[[dict], list[dict]], specs: list[dict], jobs: int, desc: str, *,
             fresh: bool = False) -> list[dict]:
    """Run ``job`` on every spec in ``jobs`` spawned single-threaded worker processes.

    With ``fresh`` every spec gets a new process of its own, one at a time, so its peak memory is
    its own; that process is not a pool's daemon, so a solve in it may start worker processes
    of its own (``core.parallel``: events from ``MIN_PARALLEL_SLOTS`` (image, point) slots).
    """
    records: list[dict] = []
    spawn = mp.get_context("spawn")
    with single_threaded_children():
        if fresh:
            for spec in tqdm(specs, desc=desc, unit="run"):
                with ProcessPoolExecutor(1, mp_context=spawn) as pool:
                    records += pool.submit(job, spec).result()
            return records
        with spawn.Pool(max(1, jobs)) as pool:
            for out in tqdm(pool.imap(job, specs), total=len(specs), desc=desc, unit="run"):
                records += out
    return records
