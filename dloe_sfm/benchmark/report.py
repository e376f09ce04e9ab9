"""The benchmark's reports: summaries of the runs, markdown tables, plots, machine facts."""

from __future__ import annotations

import importlib.resources
import json
import os
import platform
import subprocess
from pathlib import Path

import numpy as np
import scipy
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from ..core.options import Distance, Embedding
from ..io import atomic_path
from .suites import STAGES


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


_EMB_NAMES = {Embedding.SPECTRAL: "SR", Embedding.MDS: "MDS", Embedding.SHP: "SHP",
              Embedding.AFFINE: "affine clocks"}
_DIST_NAMES = {Distance.EUCLIDEAN: "Z^E", Distance.ARC: "Z (arc)"}


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
    """Growth exponents (log-log slope against N) of the whole solve, the steps per iteration,
    every stage (``stage_seconds``, ``stage_rise_mb``) and the peak memory."""
    records = sorted(records, key=lambda r: r["num_images"])
    n = np.array([r["num_images"] for r in records], dtype=np.float64)
    series = {key: [r[key] for r in records]
              for key in ("seconds", "per_iteration", "w_step_per_iteration",
                          "d_step_per_iteration", "x_step_per_iteration", "peak_rss_mb")}
    for stage in STAGES:
        series[f"{stage} s"] = [r["stage_seconds"][stage] for r in records]
    out = {"fits": {}}
    for key, values in series.items():
        y = np.array(values)
        if n.size >= 2 and (y > 0).all():
            slope, intercept = fit_exponent(n, y)
            out["fits"][key] = {"exponent": slope, "intercept": intercept}
    return out


def _size(record: dict) -> str:
    """A runtime row's N, and its detector model when the detections were made by one."""
    detector = record.get("detector")
    return f"{record['num_images']}" + (f" ({detector} detector)" if detector else "")


def runtime_table(records: list[dict], summary: dict) -> str:
    """Markdown: per size the steps per iteration, then every stage's seconds and peak-memory
    rise, then the growth exponents (if fitted)."""
    records = sorted(records, key=lambda r: r["num_images"])
    lines = ["| N images | streams | iterations | total s | per iteration s | W-step s/it | "
             "D-step s/it | X-step s/it | peak RSS MB | error mm |", "|---|" + "---|" * 9]
    for r in records:
        lines.append(f"| {_size(r)} | {r['num_streams']} | {r['nit']} | "
                     f"{r['seconds']:.2f} | "
                     f"{r['per_iteration']:.3f} | {r['w_step_per_iteration']:.3f} | "
                     f"{r['d_step_per_iteration']:.4f} | {r['x_step_per_iteration']:.3f} | "
                     f"{r['peak_rss_mb']:.0f} | {r['error_mm']:.2f} |")
    lines += ["", "Stages: seconds (exclusive) / rise of the peak RSS, MB", "",
              "| N images | " + " | ".join(STAGES) + " |", "|---|" + "---|" * len(STAGES)]
    for r in records:
        lines.append(f"| {_size(r)} | " + " | ".join(
            f"{r['stage_seconds'][s]:.2f} s / {r['stage_rise_mb'][s]:.0f}" for s in STAGES)
            + " |")
    if summary["fits"]:
        lines.append("")
        lines.append("Fitted growth exponents (log-log slope against N): " + ", ".join(
            f"{k} {v['exponent']:.2f}" for k, v in summary["fits"].items()))
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
    if summary["fits"]:
        ax.legend(fontsize=8)
    return _save_png(fig, path)


def _git_commit(folder: Path) -> str | None:
    """HEAD of the git checkout that tracks ``folder``'s ``__init__.py``; None otherwise (an
    installed copy, no git)."""
    def git(*args: str) -> str:
        return subprocess.run(["git", "-C", str(folder), *args], capture_output=True, text=True,
                              timeout=10, check=True).stdout.strip()

    try:
        git("ls-files", "--error-unmatch", "__init__.py")
        return git("rev-parse", "HEAD") or None
    except (OSError, subprocess.SubprocessError):
        return None


def machine_info() -> dict:
    """Platform, CPU, library versions and the git commit of the package's checkout (None when
    the package is not in one)."""
    cpu = None
    cpuinfo = Path("/proc/cpuinfo")
    if cpuinfo.is_file():
        for line in cpuinfo.read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    commit = _git_commit(Path(str(importlib.resources.files("dloe_sfm"))))
    return {"platform": platform.platform(), "cpu_count": os.cpu_count(), "cpu_model": cpu,
            "python": platform.python_version(), "numpy": np.__version__,
            "scipy": scipy.__version__, "git_commit": commit}


def write_results(out: Path, doc: dict) -> None:
    """``<out>/results.json`` (the whole document) and ``<out>/table.md`` (its table)."""
    with atomic_path(out / "results.json") as tmp:
        tmp.write_text(json.dumps(doc, indent=1, default=_json_default))
    with atomic_path(out / "table.md") as tmp:
        tmp.write_text(doc["table"] + "\n")


def _json_default(obj):
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")
