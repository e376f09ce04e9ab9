"""Benchmark DLOE against the paper's baselines on simulated mocap captures (the paper's protocol).

Suites (``dloe-sfm benchmark SUITE``, :func:`main`):

- ``noise``, ``rate``, ``missing``, ``density``: mean 3D error (mm) of every method while one
  factor of the capture varies (2D noise, frame rate per stream, missing points, dropped frames).
- ``kendall``: |Kendall tau| of the spectral / MDS / SHP orders from Euclidean and arc distances,
  on the pseudo-triangulated and on the DLOE shapes (the paper's Table 1).
- ``ablation``: DLOE without the S, T or R term at moderate and high noise.
- ``runtime``: time per iteration and per step, and peak memory, against the number of images.
- ``streams``: the same for many cameras (:data:`.suites.STREAMS_SIZES`: 11 000 images from 16
  streams, 10 000 from 64).
- ``lone``: the same for lone photos, every one its own camera (:data:`.suites.LONE_SIZES`: 300
  under the detector model, 300 to 4 000 clean; growth fitted on the clean ones).

Every suite writes ``results.json`` (every run, settings, seeds, machine, git commit),
``table.md`` and ``<suite>.png`` to ``outputs/benchmark/<suite>/``.

Modules: :mod:`.suites` (what each suite runs), :mod:`.jobs` (the runs, in worker processes),
:mod:`.report` (summaries, tables, plots, machine facts).
"""

from __future__ import annotations

import importlib.resources
import logging
import math
import sys
import time
from pathlib import Path

from ..core.options import Options
from ..errors import InputError
from ..synth import load_mocap, resolve_motion
from .jobs import kendall_job, run_jobs, runtime_job, sweep_job
from .report import (
    fit_exponent,
    kendall_table,
    machine_info,
    plot_bars,
    plot_kendall,
    plot_runtime,
    plot_sweep,
    runtime_table,
    summarise_kendall,
    summarise_runtime,
    summarise_sweep,
    sweep_table,
    write_results,
)
from .suites import (
    ABLATION_NOISE,
    KENDALL_MOTIONS,
    LONE_SIZES,
    METHODS,
    MOTIONS,
    QUICK_MOTIONS,
    RUNTIME_MOTION,
    RUNTIME_SIZES,
    RUNTIME_STREAMS,
    STREAMS_SIZES,
    SUITES,
    SWEEPS,
    ablation_variants,
    simulation_settings,
)

__all__ = ["DEFAULT_DATA", "DEFAULT_OUT", "LONE_SIZES", "METHODS", "STREAMS_SIZES", "SUITES",
           "InputError", "fit_exponent", "machine_info", "main"]

logger = logging.getLogger("dloe_sfm")

# the bundled clips (walking_1, jumping_1, basketball_signal_1, package data) run the --quick
# grids and any suite restricted to them with --motions; the full suites take --data (the CMU set)
DEFAULT_DATA = Path(str(importlib.resources.files("dloe_sfm") / "assets" / "mocap"))
DEFAULT_OUT = Path("outputs") / "benchmark"


def main(suite: str, *, out: Path | None = None, data: Path | None = None, quick: bool = False,
         seeds: int | None = None, motions: list[str] | None = None, jobs: int = 1,
         duration: float | None = None, sizes: list[int] | None = None,
         streams: int | None = None, rate: float | None = None) -> dict:
    """Run one benchmark suite; returns the document written to ``<out>/results.json``.

    Parameters
    ----------
    suite : one of :data:`SUITES`.
    out : output directory (default ``outputs/benchmark/<suite>``).
    data : folder of mocap ``.npz`` files (default: the bundled clips, ``assets/mocap``).
    quick : reduced grid (2 motions, 1 seed, 2 settings, 1 s clips) for smoke tests.
    seeds : number of random seeds per (motion, setting) (default 3, quick 1).
    motions : motion names (``walking_1`` or file stems / paths) instead of the suite's default.
    jobs : worker processes (each single-threaded); the runtime suite always runs one at a time.
    duration : clip length in seconds (default 2.5 s ~ the paper's 300 frames, quick 1 s).
    sizes : runtime suite: target numbers of images (the streams and lone suites' are fixed).
    streams, rate : runtime suite: video streams (default :data:`RUNTIME_STREAMS`) and their
        frame rate (default 30 Hz); the clip must last sizes / (rate streams) seconds.
    """
    if suite not in SUITES:
        raise InputError(f"unknown suite '{suite}', choose from {', '.join(SUITES)}")
    data = Path(data) if data is not None else DEFAULT_DATA
    if not data.is_dir():
        raise InputError(f"mocap folder {data} does not exist; pass --data")
    out = Path(out) if out is not None else DEFAULT_OUT / suite
    out.mkdir(parents=True, exist_ok=True)
    seeds = seeds if seeds is not None else (1 if quick else 3)
    duration = duration if duration is not None else (1.0 if quick else 2.5)
    if suite in ("runtime", "streams", "lone"):
        motions = (motions or [RUNTIME_MOTION])[:1]
    elif motions is None:
        motions = QUICK_MOTIONS if quick else (KENDALL_MOTIONS if suite == "kendall" else MOTIONS)
    paths = [str(resolve_motion(data, m)) for m in motions]
    base = Options()
    doc: dict = {"suite": suite, "quick": quick, "seeds": list(range(seeds)),
                 "motions": [Path(p).stem for p in paths], "duration_s": duration,
                 "options": base.to_dict(), "machine": machine_info(),
                 "command": " ".join(sys.argv), "started": time.strftime("%Y-%m-%d %H:%M:%S")}
    t0 = time.perf_counter()
    if suite in SWEEPS or suite == "ablation":
        if suite == "ablation":
            field, values, label = "noise", ABLATION_NOISE[quick], "2D noise sigma (px)"
            methods = ablation_variants(base)
        else:
            sw = SWEEPS[suite]
            field, values, label = sw.field, sw.quick if quick else sw.values, sw.label
            methods = {m: {} for m in METHODS}
        specs = [{"suite": suite, "motion": p, "setting": v, "methods": methods,
                  "settings": simulation_settings(s, duration, **{field: v})}
                 for v in values for p in paths for s in range(seeds)]
        records = run_jobs(sweep_job, specs, jobs, suite)
        summary = summarise_sweep(records, list(methods), list(values))
        table = sweep_table(summary, label)
        doc.update(field=field, values=list(values), methods=methods)
        title = f"{suite}: {len(paths)} motions x {seeds} seed(s), {duration:g} s clips"
        png = plot_bars(summary, label, out / f"{suite}.png") if suite == "ablation" else \
            plot_sweep(summary, label, title, out / f"{suite}.png")
    elif suite == "kendall":
        specs = [{"motion": p, "settings": simulation_settings(s, duration)}
                 for p in paths for s in range(seeds)]
        records = run_jobs(kendall_job, specs, jobs, suite)
        summary = summarise_kendall(records)
        table = kendall_table(summary)
        png = plot_kendall(summary, out / "kendall.png")
    else:
        specs, sizes_doc = _runtime_specs(suite, paths[0], quick, duration, sizes, streams, rate)
        records = run_jobs(runtime_job, specs, 1, suite, fresh=True)
        # the streams suite's sizes differ in their cameras: no growth against N; the lone
        # suite's growth is its clean sizes'
        summary = {"fits": {}} if suite == "streams" else summarise_runtime(
            [r for r in records if r["detector"] is None])
        table = runtime_table(records, summary)
        doc.update(sizes_doc)
        png = plot_runtime(records, summary, out / f"{suite}.png")
    doc.update(seconds=time.perf_counter() - t0, summary=summary, runs=records, table=table,
               plot=str(png))
    write_results(out, doc)
    logger.info("%s: %d runs in %.0f s -> %s", suite, len(records), doc["seconds"], out)
    return doc


def _runtime_specs(suite: str, motion: str, quick: bool, duration: float,
                   sizes: list[int] | None, streams: int | None, rate: float | None
                   ) -> tuple[list[dict], dict]:
    """The runs of the ``runtime``, ``streams`` or ``lone`` suite (one solve each) and what
    ``results.json`` records of their sizes."""
    if suite == "lone":
        grid = LONE_SIZES[quick]
        return [{"motion": motion, "setting": n,
                 "settings": simulation_settings(0, duration, num_streams=0, lone_photos=n,
                                                 detector=detector)} for n, detector in grid], \
            {"sizes": [list(size) for size in grid]}
    if suite == "streams":
        grid = list(STREAMS_SIZES[quick])
    else:
        streams = streams or RUNTIME_STREAMS
        rate = rate or 30.0
        if streams < 2 or not 0 < rate <= 1000:
            raise InputError(f"--streams must be 2 or more and --rate in (0, 1000], got "
                             f"{streams} and {rate:g}")
        grid = [(n, streams, rate) for n in sizes or RUNTIME_SIZES[quick]]
    seq = load_mocap(motion)
    clip = seq.positions.shape[0] / seq.fps
    n, most, hz = max(grid, key=lambda size: size[0] / (size[1] * size[2]))
    if n / (most * hz) > clip:
        raise InputError(f"{Path(motion).name} is {clip:.1f} s long: {n} images "
                         f"need {n / (most * hz):.1f} s at {most} streams of "
                         f"{hz:g} Hz " + ("(--data: the CMU clips)" if suite == "streams"
                                          else f"(--streams {math.ceil(n / (hz * clip))} "
                                          "or more, or a higher --rate)"))
    specs = [{"motion": motion, "setting": int(n),
              "settings": simulation_settings(0, n / (k * r), num_streams=k, rate=r)}
             for n, k, r in grid]
    if suite == "runtime":
        return specs, {"sizes": [size[0] for size in grid], "num_streams": streams, "rate": rate}
    return specs, {"sizes": [list(size) for size in grid]}
