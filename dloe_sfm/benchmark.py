"""Benchmark DLOE against the paper's baselines on simulated mocap captures (the paper's protocol).

Suites (``dloe-sfm benchmark SUITE``):

- ``noise``, ``rate``, ``missing``, ``density``: mean 3D error (mm) of every method while one
  factor of the capture varies (2D noise, frame rate per stream, missing points, dropped frames).
- ``kendall``: |Kendall tau| of the spectral / MDS / SHP orders from Euclidean and arc distances,
  on the pseudo-triangulated and on the DLOE shapes (the paper's Table 1).
- ``ablation``: DLOE without the S, T or R term at moderate and high noise.
- ``runtime``: time per iteration and per step, and peak memory, against the number of images.

Every suite writes ``results.json`` (every run, settings, seeds, machine, git commit),
``table.md`` and ``<suite>.png`` to ``outputs/benchmark/<suite>/`` and prints the table.
"""

from __future__ import annotations

import argparse
import importlib.resources
import json
import logging
import multiprocessing as mp
import os
import platform
import resource
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import scipy
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from tqdm.auto import tqdm

from .baselines import high_pass_filter, pseudo_triangulation, sedl, trajectory_basis
from .core.capture import Capture
from .core.options import Distance, Embedding, Options
from .core.sequencing import (
    affine_time,
    distance_matrix,
    kendall_tau,
    line_embedding,
    order_from_embedding,
)
from .core.solver import initialise, oracle_reconstruct, reconstruct
from .errors import InputError
from .evaluate import point_errors
from .io import atomic_path
from .synth import SimulationSettings, load_mocap, simulate

logger = logging.getLogger("dloe_sfm")

# the bundled clips (walking_1, jumping_1, basketball_signal_1, package data) run the --quick
# grids and any suite restricted to them with --motions; the full suites take --data (the CMU set)
DEFAULT_DATA = Path(str(importlib.resources.files("dloe_sfm") / "assets" / "mocap"))
DEFAULT_OUT = Path("outputs") / "benchmark"

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
SUITES = [*SWEEPS, "kendall", "ablation", "runtime"]


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


def run_method(name: str, capture: Capture, options: Options) -> tuple[np.ndarray, dict]:
    """Reconstruct ``capture`` with one of :data:`METHODS`; returns (X (N, P, 3), extra facts)."""
    t_true = capture.extras["t_true"]
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


def resolve_motion(data: Path, name: str) -> Path:
    """The mocap file of ``name``: a path, ``data/<name>``, ``data/<name>.npz`` (assets/mocap) or
    ``data/li2018_train_<name>.npz`` (../shared/data/mocap)."""
    for path in (Path(name), data / name, data / f"{name}.npz", data / f"li2018_train_{name}.npz"):
        if path.is_file():
            return path
    raise InputError(f"motion '{name}' not found in {data}")


def _category(motion: str) -> str:
    stem = Path(motion).stem.removeprefix("li2018_train_").rstrip("_0123456789")
    return CATEGORIES.get(stem, stem)


# ---------------------------------------------------------------------------------------------
# jobs (top-level functions so a spawned worker can run them)


def _sweep_job(spec: dict) -> list[dict]:
    """Simulate one capture and reconstruct it with every method (or DLOE variant) of ``spec``."""
    capture = simulate(load_mocap(spec["motion"]), SimulationSettings(**spec["settings"]))
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
            X, extra = run_method(name, capture, base.replace(**overrides))
        except Exception as e:  # one failing method must not sink a long sweep
            logger.warning("%s on %s failed: %s", method, record["motion"], e)
            record["failed"] = f"{type(e).__name__}: {e}"
            records.append(record)
            continue
        record["seconds"] = time.perf_counter() - t0
        record.update(point_errors(X, capture.extras["X_true"], capture.visible))
        record.update(extra)
        records.append(record)
    return records


def _kendall_job(spec: dict) -> list[dict]:
    """|tau| of every (embedding, distance) order on the initial and the DLOE shapes."""
    capture = simulate(load_mocap(spec["motion"]), SimulationSettings(**spec["settings"]))
    t_true = capture.extras["t_true"]
    options = Options()
    shapes = {"initial": initialise(capture, options), "optimised": reconstruct(capture, options).X}
    records = []
    for stage, X in shapes.items():
        row = {"motion": Path(spec["motion"]).stem, "category": _category(spec["motion"]),
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


def _runtime_job(spec: dict) -> list[dict]:
    """Time one DLOE solve in a fresh process; peak memory before and after the solve."""
    capture = simulate(load_mocap(spec["motion"]), SimulationSettings(**spec["settings"]))
    before = _rss_mb()
    result = reconstruct(capture, Options())
    t = result.timings
    steps = t["w_step"] + t["d_step"] + t["x_step"]
    return [{"target": spec["setting"], "num_images": capture.num_images,
             "num_points": capture.num_points, "nit": result.nit, "seconds": result.seconds,
             "per_iteration": steps / max(result.nit, 1),
             **{f"{k}_per_iteration": t[k] / max(result.nit, 1)
                for k in ("w_step", "d_step", "x_step")},
             "timings": t, "rss_before_mb": before, "peak_rss_mb": _rss_mb(),
             "error_mm": point_errors(result.X, capture.extras["X_true"],
                                      capture.visible)["error_mm"]}]


@contextmanager
def _single_threaded_children() -> Iterator[None]:
    """Spawned workers inherit one BLAS / OpenMP thread each (set before they import numpy)."""
    keys = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")
    old = {k: os.environ.get(k) for k in keys}
    os.environ.update({k: "1" for k in keys})
    try:
        yield
    finally:
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def _run_jobs(job: Callable[[dict], list[dict]], specs: list[dict], jobs: int, desc: str, *,
              fresh: bool = False) -> list[dict]:
    """Run ``job`` on every spec in ``jobs`` spawned single-threaded worker processes.

    With ``fresh`` every spec gets a new process, so its peak memory is its own.
    """
    records: list[dict] = []
    with _single_threaded_children(), mp.get_context("spawn").Pool(
            max(1, jobs), maxtasksperchild=1 if fresh else None) as pool:
        for out in tqdm(pool.imap(job, specs), total=len(specs), desc=desc, unit="run"):
            records += out
    return records


# ---------------------------------------------------------------------------------------------
# summaries, tables, plots


def _stats(values: list[float]) -> dict[str, float]:
    v = np.asarray([x for x in values if np.isfinite(x)], dtype=np.float64)
    if v.size == 0:
        return {"mean": float("nan"), "std": float("nan"), "median": float("nan"),
                "q25": float("nan"), "q75": float("nan"), "count": 0}
    return {"mean": float(v.mean()), "std": float(v.std()), "median": float(np.median(v)),
            "q25": float(np.percentile(v, 25)), "q75": float(np.percentile(v, 75)),
            "count": int(v.size)}


def summarise_sweep(records: list[dict], methods: list[str], values: list[float]
                    ) -> dict[str, dict[str, dict[str, float]]]:
    """{method: {setting: stats of error_mm over motions and seeds}}."""
    out: dict[str, dict[str, dict[str, float]]] = {}
    for m in methods:
        out[m] = {}
        for v in values:
            errs = [r.get("error_mm", np.nan) for r in records
                    if r["method"] == m and r["setting"] == v]
            out[m][f"{v:g}"] = _stats(errs)
            fails = sum(1 for r in records if r["method"] == m and r["setting"] == v
                        and "failed" in r)
            out[m][f"{v:g}"]["failed"] = fails
    return out


def sweep_table(summary: dict, label: str) -> str:
    """Markdown table: one row per method, one column per setting, mean +- std (mm)."""
    settings = list(next(iter(summary.values())))
    lines = [f"| method \\ {label} | " + " | ".join(settings) + " |",
             "|---|" + "---|" * len(settings)]
    for method, row in summary.items():
        cells = []
        for s in settings:
            st = row[s]
            cell = f"{st['mean']:.2f} ± {st['std']:.2f}" if st["count"] else "n/a"
            if st.get("failed"):
                cell += f" ({st['failed']} failed)"
            cells.append(cell)
        lines.append(f"| {method} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _figure(**kwargs) -> Figure:
    fig = Figure(**kwargs)
    FigureCanvasAgg(fig)
    return fig


def _save_png(fig: Figure, path: Path) -> Path:
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100, format="png")
    return path


def plot_sweep(summary: dict, label: str, title: str, path: Path) -> Path:
    """Mean 3D error against the setting, one line per method, interquartile band (log y)."""
    fig = _figure(figsize=(6.4, 4.2), layout="constrained")
    ax = fig.add_subplot()
    for method, row in summary.items():
        xs = np.array([float(s) for s in row])
        mean = np.array([row[s]["mean"] for s in row])
        lo = np.array([row[s]["q25"] for s in row])
        hi = np.array([row[s]["q75"] for s in row])
        (line,) = ax.plot(xs, mean, marker="o", ms=3, label=method)
        ax.fill_between(xs, lo, hi, color=line.get_color(), alpha=0.15, lw=0)
    ax.set_yscale("log")
    ax.set_xlabel(label)
    ax.set_ylabel("mean 3D error (mm)")
    ax.set_title(title, fontsize=10)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7, ncols=2)
    return _save_png(fig, path)


def summarise_kendall(records: list[dict]) -> dict[str, dict[str, dict[str, float]]]:
    """{'category / stage': {'embedding / distance': stats of |tau|}}."""
    out: dict[str, dict[str, dict[str, float]]] = {}
    cats = [c for c in ("linear", "non-linear", "repeating") if any(r["category"] == c
                                                                    for r in records)]
    for cat in cats:
        for stage in ("initial", "optimised"):
            row = out.setdefault(f"{cat} / {stage}", {})
            for emb in _EMB_NAMES:
                for dist in Distance if emb is not Embedding.AFFINE else (Distance.ARC,):
                    taus = [r["kendall_tau"] for r in records if r["category"] == cat
                            and r["stage"] == stage and r["embedding"] == emb.value
                            and r["distance"] == dist.value]
                    row[f"{_EMB_NAMES[emb]} {_DIST_NAMES[dist]}"] = _stats(taus)
    return out


_EMB_NAMES = {Embedding.SPECTRAL: "SR", Embedding.MDS: "MDS", Embedding.SHP: "SHP",
              Embedding.AFFINE: "affine clocks"}
_DIST_NAMES = {Distance.EUCLIDEAN: "Z^E", Distance.ARC: "Z (arc)"}


def kendall_table(summary: dict) -> str:
    cols = list(next(iter(summary.values())))
    lines = ["| motion / shapes | " + " | ".join(cols) + " |", "|---|" + "---|" * len(cols)]
    for name, row in summary.items():
        lines.append(f"| {name} | " + " | ".join(f"{row[c]['mean']:.3f}" for c in cols) + " |")
    return "\n".join(lines)


def plot_kendall(summary: dict, path: Path) -> Path:
    """Grouped bars of mean |tau| per (category, shapes), one bar per (embedding, distance)."""
    fig = _figure(figsize=(7.5, 3.8), layout="constrained")
    ax = fig.add_subplot()
    rows = list(summary)
    cols = list(summary[rows[0]])
    width = 0.8 / len(cols)
    for k, c in enumerate(cols):
        ax.bar(np.arange(len(rows)) + k * width, [summary[r][c]["mean"] for r in rows], width,
               label=c)
    ax.set_xticks(np.arange(len(rows)) + 0.4 - width / 2, [r.replace(" / ", "\n") for r in rows],
                  fontsize=7)
    ax.set_ylabel("|Kendall tau|")
    ax.set_ylim(0, 1.05)
    ax.legend(fontsize=7, ncols=3)
    ax.grid(True, axis="y", alpha=0.3)
    return _save_png(fig, path)


def plot_bars(summary: dict, label: str, path: Path) -> Path:
    """Ablation: bars of mean error per variant and setting, with std whiskers."""
    fig = _figure(figsize=(6.4, 3.8), layout="constrained")
    ax = fig.add_subplot()
    variants = list(summary)
    settings = list(summary[variants[0]])
    width = 0.8 / len(variants)
    for k, v in enumerate(variants):
        ax.bar(np.arange(len(settings)) + k * width, [summary[v][s]["mean"] for s in settings],
               width, yerr=[summary[v][s]["std"] for s in settings], capsize=2, label=v)
    ax.set_xticks(np.arange(len(settings)) + 0.4 - width / 2, settings)
    ax.set_xlabel(label)
    ax.set_ylabel("mean 3D error (mm)")
    ax.legend(fontsize=7)
    ax.grid(True, axis="y", alpha=0.3)
    return _save_png(fig, path)


def fit_exponent(n: np.ndarray, y: np.ndarray) -> tuple[float, float]:
    """Least-squares line of log y against log n: (slope = growth exponent, intercept)."""
    slope, intercept = np.polyfit(np.log(n), np.log(y), 1)
    return float(slope), float(intercept)


def summarise_runtime(records: list[dict]) -> dict:
    records = sorted(records, key=lambda r: r["num_images"])
    n = np.array([r["num_images"] for r in records], dtype=np.float64)
    out = {"fits": {}}
    for key in ("seconds", "per_iteration", "w_step_per_iteration", "d_step_per_iteration",
                "x_step_per_iteration", "peak_rss_mb"):
        y = np.array([r[key] for r in records])
        if n.size >= 2 and (y > 0).all():
            slope, intercept = fit_exponent(n, y)
            out["fits"][key] = {"exponent": slope, "intercept": intercept}
    return out


def runtime_table(records: list[dict], summary: dict) -> str:
    lines = ["| N images | iterations | total s | per iteration s | W-step s/it | D-step s/it | "
             "X-step s/it | peak RSS MB | error mm |", "|---|" + "---|" * 8]
    for r in sorted(records, key=lambda r: r["num_images"]):
        lines.append(f"| {r['num_images']} | {r['nit']} | {r['seconds']:.2f} | "
                     f"{r['per_iteration']:.3f} | {r['w_step_per_iteration']:.3f} | "
                     f"{r['d_step_per_iteration']:.4f} | {r['x_step_per_iteration']:.3f} | "
                     f"{r['peak_rss_mb']:.0f} | {r['error_mm']:.2f} |")
    fits = summary["fits"]
    lines.append("")
    lines.append("Fitted growth exponents (log-log slope against N): " + ", ".join(
        f"{k} {v['exponent']:.2f}" for k, v in fits.items()))
    return "\n".join(lines)


def plot_runtime(records: list[dict], summary: dict, path: Path) -> Path:
    records = sorted(records, key=lambda r: r["num_images"])
    n = np.array([r["num_images"] for r in records], dtype=np.float64)
    fig = _figure(figsize=(6.4, 4.2), layout="constrained")
    ax = fig.add_subplot()
    for key, name in (("seconds", "total"), ("per_iteration", "per iteration"),
                      ("w_step_per_iteration", "W-step / it"),
                      ("x_step_per_iteration", "X-step / it")):
        y = np.array([r[key] for r in records])
        (line,) = ax.loglog(n, y, "o", ms=4)
        if key in summary["fits"]:
            f = summary["fits"][key]
            ax.loglog(n, np.exp(f["intercept"]) * n ** f["exponent"], "-", color=line.get_color(),
                      label=f"{name}: N^{f['exponent']:.2f}")
    ax.set_xlabel("number of images N")
    ax.set_ylabel("seconds")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    return _save_png(fig, path)


# ---------------------------------------------------------------------------------------------
# machine and provenance


def machine_info() -> dict:
    """Platform, CPU, library versions and the repository's git commit (None outside git)."""
    cpu = None
    cpuinfo = Path("/proc/cpuinfo")
    if cpuinfo.is_file():
        for line in cpuinfo.read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    try:
        commit = subprocess.run(["git", "rev-parse", "HEAD"], cwd=Path(__file__).parent,
                                capture_output=True, text=True, timeout=10,
                                check=True).stdout.strip() or None
    except (OSError, subprocess.SubprocessError):
        commit = None
    return {"platform": platform.platform(), "cpu_count": os.cpu_count(), "cpu_model": cpu,
            "python": platform.python_version(), "numpy": np.__version__,
            "scipy": scipy.__version__, "git_commit": commit}


# ---------------------------------------------------------------------------------------------
# the stage


def _settings(seed: int, duration: float, **changes) -> dict:
    return asdict(SimulationSettings(duration=duration, seed=seed, **changes))


def main(suite: str, *, out: Path | None = None, data: Path | None = None, quick: bool = False,
         seeds: int | None = None, motions: list[str] | None = None, jobs: int = 1,
         duration: float | None = None, sizes: list[int] | None = None) -> dict:
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
    sizes : runtime suite: target numbers of images.
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
    if suite == "runtime":
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
                  "settings": _settings(s, duration, **{field: v})}
                 for v in values for p in paths for s in range(seeds)]
        records = _run_jobs(_sweep_job, specs, jobs, suite)
        summary = summarise_sweep(records, list(methods), list(values))
        table = sweep_table(summary, label)
        doc.update(field=field, values=list(values), methods=methods)
        title = f"{suite}: {len(paths)} motions x {seeds} seed(s), {duration:g} s clips"
        png = plot_bars(summary, label, out / f"{suite}.png") if suite == "ablation" else \
            plot_sweep(summary, label, title, out / f"{suite}.png")
    elif suite == "kendall":
        specs = [{"motion": p, "settings": _settings(s, duration)}
                 for p in paths for s in range(seeds)]
        records = _run_jobs(_kendall_job, specs, jobs, suite)
        summary = summarise_kendall(records)
        table = kendall_table(summary)
        png = plot_kendall(summary, out / "kendall.png")
    else:
        sizes = sizes or list(RUNTIME_SIZES[quick])
        settings = SimulationSettings(num_streams=8, rate=30.0)
        per_second = settings.num_streams * settings.rate
        specs = [{"motion": paths[0], "setting": int(n),
                  "settings": _settings(0, n / per_second, num_streams=8,
                                        rate=30.0)} for n in sizes]
        records = _run_jobs(_runtime_job, specs, 1, suite, fresh=True)
        summary = summarise_runtime(records)
        table = runtime_table(records, summary)
        doc.update(sizes=list(sizes), num_streams=8, rate=30.0)
        png = plot_runtime(records, summary, out / "runtime.png")
    doc.update(seconds=time.perf_counter() - t0, summary=summary, runs=records, table=table,
               plot=str(png))
    with atomic_path(out / "results.json") as tmp:
        tmp.write_text(json.dumps(doc, indent=1, default=_json_default))
    with atomic_path(out / "table.md") as tmp:
        tmp.write_text(table + "\n")
    logger.info("%s: %d runs in %.0f s -> %s", suite, len(records), doc["seconds"], out)
    return doc


def _json_default(obj):
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("suite", choices=SUITES, help="which benchmark to run")
    parser.add_argument("--quick", action="store_true",
                        help="reduced grid: 2 motions, 1 seed, 2 settings, 1 s clips")
    parser.add_argument("--out", type=Path, help="output folder (default outputs/benchmark/SUITE)")
    parser.add_argument("--data", type=Path,
                        help="mocap folder (default ../shared/data/mocap beside the repo, else the "
                             "bundled assets/mocap clips)")
    parser.add_argument("--seeds", type=int, help="seeds per setting (default 3, quick 1)")
    parser.add_argument("--motions", nargs="+", help="motion names, e.g. walking_1 soccer_2")
    parser.add_argument("--jobs", type=int, default=1,
                        help="parallel worker processes, each single-threaded (default 1)")
    parser.add_argument("--duration", type=float, help="clip length, s (default 2.5, quick 1)")
    parser.add_argument("--sizes", type=int, nargs="+", help="runtime suite: numbers of images")


def run(args: argparse.Namespace) -> int:
    jobs = max(1, min(args.jobs, os.cpu_count() or 1))
    doc = main(args.suite, out=args.out, data=args.data, quick=args.quick, seeds=args.seeds,
               motions=args.motions, jobs=jobs, duration=args.duration, sizes=args.sizes)
    print(doc["table"])
    return 0


if __name__ == "__main__":
    from .cli import run_stage

    sys.exit(run_stage(__name__))
