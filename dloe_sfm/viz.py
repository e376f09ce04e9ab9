"""Plots (matplotlib, Agg backend) and image overlays (OpenCV) of a reconstruction, as PNG
files, and its animation as a GIF."""

from __future__ import annotations

import io
import logging
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np
import scipy.sparse as sp
from matplotlib import colormaps
from matplotlib.animation import AbstractMovieWriter
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.colors import LogNorm
from matplotlib.figure import Figure
from PIL import Image

from .columns import (
    column_edges,
    column_ids,
    column_labels,
    frame_file_stem,
    point_colors,
    solved_capture,
)
from .core import events as core_events
from .core.bias import per_stream
from .core.capture import Capture
from .core.result import Result
from .io import atomic_path
from .keypoints.base import quoted

if TYPE_CHECKING:
    from .colmap import Workspace

logger = logging.getLogger("dloe_sfm")


def _figure(**kwargs) -> Figure:
    """A figure on the Agg canvas, outside pyplot (no global backend state, nothing to close)."""
    fig = Figure(**kwargs)
    FigureCanvasAgg(fig)
    return fig


def _save(fig: Figure, path: Path | str) -> Path:
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=120, format="png")
    return path


def plot_sequence(result: Result, capture: Capture, path: Path | str) -> Path:
    """Estimated rank of every image against its frame index, one line per stream, and the
    1D embedding (estimated time) in estimated order; a stream's line rises steadily when the
    recovered order agrees with the stream's known frame order."""
    rank = result.rank
    fig = _figure(figsize=(13, 5.2))
    ax_seq, ax_emb = fig.subplots(1, 2)
    streams = np.unique(capture.stream)
    cmap = colormaps["tab10" if streams.size <= 10 else "turbo"]
    for k, s in enumerate(streams):
        idx = np.flatnonzero(capture.stream == s)
        idx = idx[np.argsort(capture.frame[idx])]
        colour = cmap(k % 10) if streams.size <= 10 else cmap(k / max(streams.size - 1, 1))
        if s < 0:
            ax_seq.scatter(np.zeros(idx.size), rank[idx], marker="x", color="k",
                           label=f"lone photos ({idx.size})")
            continue
        ax_seq.plot(capture.frame[idx], rank[idx], "o-", ms=3, lw=1.2, color=colour,
                    label=f"stream {s} ({idx.size})")
        sel = np.isin(result.order, idx)
        ax_emb.scatter(np.flatnonzero(sel), result.embedding[result.order[sel]], s=10,
                       color=colour, label=f"stream {s}")
    ax_seq.set_xlabel("frame index within its stream")
    ax_seq.set_ylabel("estimated rank (0 = earliest)")
    ax_seq.set_title("Recovered order vs. known in-stream order")
    ax_seq.grid(alpha=0.3)
    ax_seq.legend(fontsize=8, loc="best", ncol=1 + streams.size // 12)
    lone = capture.stream[result.order] < 0
    if lone.any():
        ax_emb.scatter(np.flatnonzero(lone), result.embedding[result.order[lone]], s=14,
                       marker="x", color="k", label="lone photos")
    boundaries = np.flatnonzero(np.diff(result.events[result.order]) != 0) + 0.5
    for b in boundaries:
        ax_emb.axvline(b, color="grey", ls="--", lw=0.8)
    ax_emb.set_xlabel("estimated rank")
    ax_emb.set_ylabel("embedding (estimated time)")
    n_events = np.unique(result.events).size
    ax_emb.set_title(f"Embedding in estimated order ({n_events} event{'s' * (n_events > 1)})")
    ax_emb.grid(alpha=0.3)
    if streams.size <= 12:
        ax_emb.legend(fontsize=8, loc="best")
    fig.suptitle(f"Sequencing of {capture.num_images} images from {streams.size} stream(s)")
    fig.tight_layout()
    return _save(fig, path)


def plot_affinity(result: Result, path: Path | str) -> Path:
    """The sparse affinity A = D W with rows and columns in estimated order, log colour scale.

    Drawn from its non-zeros only (never densified); dashed lines separate events.
    """
    n = result.order.size
    A = sp.coo_matrix(sp.csr_matrix(result.A)[result.order][:, result.order])
    keep = A.data > 0
    rows, cols, vals = A.row[keep], A.col[keep], A.data[keep]
    fig = _figure(figsize=(7.2, 6.2))
    ax = fig.subplots()
    marker_size = max(1.0, min(30.0, (300.0 / max(n, 1)) ** 2))
    if vals.size:
        sc = ax.scatter(cols, rows, c=vals, s=marker_size, marker="s", cmap="viridis",
                        norm=LogNorm(vmin=vals.min(), vmax=max(vals.max(), vals.min() * 1.0001)),
                        linewidths=0)
        fig.colorbar(sc, ax=ax, label="affinity A_ij (log scale)")
    for b in np.flatnonzero(np.diff(result.events[result.order]) != 0) + 0.5:
        ax.axhline(b, color="grey", ls="--", lw=0.8)
        ax.axvline(b, color="grey", ls="--", lw=0.8)
    ax.set_xlim(-0.5, n - 0.5)
    ax.set_ylim(n - 0.5, -0.5)
    ax.set_aspect("equal")
    ax.set_xlabel("image j (estimated rank)")
    ax.set_ylabel("image i (estimated rank)")
    ax.set_title(f"Affinity A = D W in estimated order ({vals.size} non-zeros, N = {n})")
    fig.tight_layout()
    return _save(fig, path)


def plot_reconstructability(result: Result, capture: Capture, path: Path | str) -> Path:
    """Per image in estimated order: median depth sd of its observed points and its reprojection
    residual (``core.assess``); ``uncertain`` / ``inconsistent`` images marked."""
    order = result.order
    sd = np.where(capture.visible, result.depth_sd, np.nan)[order]
    seen = np.isfinite(sd).any(axis=1)
    median_sd = np.full(order.size, np.nan)
    median_sd[seen] = np.nanmedian(sd[seen], axis=1)
    status = result.image_status[order]
    fig = _figure(figsize=(9.0, 5.4))
    ax_sd, ax_res = fig.subplots(2, 1, sharex=True)
    rank = np.arange(order.size)
    ax_sd.semilogy(rank, median_sd, ".", color="tab:blue", ms=3)
    ax_sd.set_ylabel("median depth sd (world units)")
    ax_res.plot(rank, result.residual_px[order], ".", color="tab:green", ms=3)
    ax_res.set_ylabel("reprojection residual (px)")
    ax_res.set_xlabel("image (estimated rank)")
    for name, color in (("uncertain", "tab:orange"), ("inconsistent", "tab:red")):
        k = np.flatnonzero(status == name)
        if k.size:
            for ax in (ax_sd, ax_res):
                for r in k:
                    ax.axvline(r, color=color, lw=0.8, alpha=0.6)
            ax_sd.plot([], [], color=color, label=f"{name} ({k.size})")
    if (status != "ok").any():
        ax_sd.legend(loc="upper right", fontsize=8)
    ax_sd.set_title(f"Reconstructability per image ({int((status != 'ok').sum())} of "
                    f"{order.size} flagged)")
    fig.tight_layout()
    return _save(fig, path)


def plot_stream_offsets(result: Result, capture: Capture, path: Path | str,
                        point_names: list[str]) -> Path:
    """The detector offsets taken out (``Result.offset_px``, ``core.bias``): their length in
    pixels per stream (rows, with image counts) and point (columns), the median over each
    stream's images; blank where none was taken out."""
    stream = capture.stream_ids
    ids, offsets = per_stream(result.offset_px, stream)
    size = np.linalg.norm(offsets, axis=2)
    size[size == 0] = np.nan
    streams = np.flatnonzero(np.isfinite(size).any(axis=1))
    size = size[streams]
    fig = _figure(figsize=(min(2.0 + 0.32 * size.shape[1], 16.0),
                           min(1.6 + 0.3 * streams.size, 12.0)))
    ax = fig.subplots()
    shown = ax.imshow(size, aspect="auto", cmap="viridis", interpolation="nearest")
    fig.colorbar(shown, ax=ax, label="offset (px)")
    ax.set_yticks(np.arange(streams.size),
                  [f"stream {ids[s]} ({int((stream == ids[s]).sum())})" for s in streams],
                  fontsize=7)
    ax.set_xticks(np.arange(len(point_names)), point_names, rotation=90, fontsize=6)
    ax.set_title(f"Detector offsets taken out, median {np.nanmedian(size):.2f} px "
                 f"({int(np.isfinite(size).sum())} stream-point pairs)")
    fig.tight_layout()
    return _save(fig, path)


def events_figure(result: Result) -> Figure:
    """The figure of ``plot_events``: every event's images in the 2D spectral embedding of that
    event's graph (``core.events``; the first coordinate orders an event in time, scaled to
    [-1, 1]), events side by side and coloured, each with its own ticks and its name above it;
    the title counts the graph's links between events (0 when they are disjoint)."""
    labels, counts = np.unique(result.events, return_counts=True)
    A = sp.csr_matrix(result.A)
    coo = A.tocoo()
    crossing = int((result.events[coo.row] != result.events[coo.col]).sum())
    cmap = colormaps["tab10" if labels.size <= 10 else "turbo"]
    fig = _figure(figsize=(max(7.2, 2.6 * labels.size), 5.4))
    ax = fig.subplots()
    for k, (event, count) in enumerate(zip(labels.tolist(), counts.tolist(), strict=True)):
        idx = np.flatnonzero(result.events == event)
        xy = np.zeros((idx.size, 2))
        if idx.size > 2:
            xy = core_events.spectral_coordinates(A[idx][:, idx], dim=2)
            xy = (xy - xy.mean(axis=0)) / np.maximum(np.abs(xy - xy.mean(axis=0)).max(axis=0),
                                                      1e-300)
        colour = cmap(k) if labels.size <= 10 else cmap(k / (labels.size - 1))
        ax.scatter(xy[:, 0] + 2.5 * k, xy[:, 1], s=14, color=colour,
                   label=f"event {event} ({count} image{'s' * (count > 1)})")
    # each event's own coordinate (-1, 0, 1) below, its name above
    ticks = [2.5 * k + u for k in range(labels.size) for u in (-1.0, 0.0, 1.0)]
    ax.set_xticks(ticks, ["\u22121", "0", "1"] * labels.size)
    ax.set_xlim(-1.4, 2.5 * (labels.size - 1) + 1.4)
    top = ax.secondary_xaxis("top")
    top.set_xticks([2.5 * k for k in range(labels.size)], [f"event {e}" for e in labels.tolist()])
    ax.set_xlabel("spectral coordinate 1 of each event's graph (its time line)")
    ax.set_ylabel("spectral coordinate 2")
    ax.set_title(f"{labels.size} event{'s' * (labels.size > 1)}, N = {result.events.size}: "
                 f"{crossing} link{'s' * (crossing != 1)} between events")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="best", ncol=1 + labels.size // 12)
    fig.tight_layout()
    return fig


def plot_events(result: Result, path: Path | str) -> Path:
    """``events_figure`` saved as a PNG."""
    return _save(events_figure(result), path)


def _bgr(k: int) -> tuple[int, int, int]:
    """OpenCV BGR colour of the k-th subject (tab10)."""
    r, g, b = (round(255 * c) for c in colormaps["tab10"](k % 10)[:3])
    return b, g, r


def plot_reprojection(image_path: Path | str, observed: np.ndarray, reprojected: np.ndarray,
                      edges: np.ndarray | list[tuple[int, int]], path: Path | str, *,
                      title: str | None = None, max_side: int = 1600,
                      subject_id: np.ndarray | None = None) -> Path:
    """Overlay on the image: observed keypoints (green dots), reprojected 3D points (red
    crosses), their error lines (yellow) and the skeleton through the reprojected points
    (one colour per subject when ``subject_id`` (P,) is given).

    observed (P, 2), reprojected (P, 2): COLMAP pixel coordinates (centre of the top-left pixel
    = (0.5, 0.5)); NaN rows are skipped. edges (E, 2) point indices. The image is cropped to the
    points (with a margin) and scaled so the longer side is about ``max_side`` pixels: a person
    in a large photo stays readable.
    """
    image = cv2.imread(str(image_path), cv2.IMREAD_COLOR)
    if image is None:
        raise OSError(f"{image_path}: cannot read the image")
    # COLMAP's (0.5, 0.5) is the centre of OpenCV's pixel (0, 0)
    obs = np.asarray(observed, dtype=np.float64) - 0.5
    rep = np.asarray(reprojected, dtype=np.float64) - 0.5
    height, width = image.shape[:2]
    pts = np.concatenate([obs, rep])
    pts = pts[np.isfinite(pts).all(axis=1)]
    pts = pts[(pts >= 0).all(axis=1) & (pts[:, 0] < width) & (pts[:, 1] < height)]
    if len(pts):
        margin = max(0.25 * float(np.ptp(pts, axis=0).max()), 20.0)
        x0, y0 = np.maximum(np.floor(pts.min(axis=0) - margin), 0).astype(int)
        x1, y1 = np.minimum(np.ceil(pts.max(axis=0) + margin), [width, height]).astype(int)
        image = image[y0:y1, x0:x1]
        obs, rep = obs - [x0, y0], rep - [x0, y0]
    scale = min(8.0, max_side / max(image.shape[:2]))
    image = cv2.resize(image, None, fx=scale, fy=scale,
                       interpolation=cv2.INTER_AREA if scale < 1 else cv2.INTER_LINEAR)
    obs, rep = obs * scale, rep * scale
    size = max(image.shape[:2])
    thick = max(1, round(size / 600))
    radius = max(3, round(size / 200))

    def pt(v: np.ndarray) -> tuple[int, int]:
        return int(round(v[0])), int(round(v[1]))

    ok_rep = np.isfinite(rep).all(axis=1)
    ok_obs = np.isfinite(obs).all(axis=1)
    for i, j in np.asarray(edges, dtype=np.int64).reshape(-1, 2):
        if ok_rep[i] and ok_rep[j]:
            colour = (255, 160, 60) if subject_id is None else _bgr(int(subject_id[i]))
            cv2.line(image, pt(rep[i]), pt(rep[j]), colour, thick, cv2.LINE_AA)
    for p in range(len(obs)):
        if ok_obs[p] and ok_rep[p]:
            cv2.line(image, pt(obs[p]), pt(rep[p]), (0, 230, 255), thick, cv2.LINE_AA)
    for p in np.flatnonzero(ok_obs):
        cv2.circle(image, pt(obs[p]), radius, (40, 200, 40), -1, cv2.LINE_AA)
    for p in np.flatnonzero(ok_rep):
        cv2.drawMarker(image, pt(rep[p]), (30, 30, 230), cv2.MARKER_CROSS, 3 * radius, thick,
                       cv2.LINE_AA)
    err = np.linalg.norm(np.asarray(observed) - np.asarray(reprojected), axis=1)
    mean = float(np.nanmean(err)) if np.isfinite(err).any() else float("nan")
    lines = [title or Path(image_path).name,
             f"observed (green) vs reprojected (red): mean {mean:.2f} px, "
             f"{int(np.isfinite(err).sum())} points"]
    # title lines on a white band above the image, font shrunk to fit its width
    font, font_scale = cv2.FONT_HERSHEY_SIMPLEX, max(0.5, image.shape[1] / 1600)
    widest = max(cv2.getTextSize(t, font, font_scale, thick)[0][0] for t in lines)
    font_scale *= min(1.0, (image.shape[1] - 20) / widest)
    line_height = int(cv2.getTextSize("Ag", font, font_scale, thick)[0][1] * 1.9) + 4
    band = np.full((line_height * len(lines) + 8, image.shape[1], 3), 255, dtype=np.uint8)
    for k, text in enumerate(lines):
        cv2.putText(band, text, (10, (k + 1) * line_height), font, font_scale, (0, 0, 0), thick,
                    cv2.LINE_AA)
    image = np.concatenate([band, image], axis=0)
    path = Path(path)
    with atomic_path(path) as tmp:
        ok, buf = cv2.imencode(".png", image)
        if not ok:
            raise OSError(f"{path}: OpenCV could not encode the overlay")
        tmp.write_bytes(buf.tobytes())
    return path


def trajectories_figure(X: np.ndarray, order: np.ndarray, *,
                        points: list[int] | None = None, point_names: list[str] | None = None,
                        observed: np.ndarray | None = None, max_points: int = 12,
                        subject_id: np.ndarray | None = None) -> Figure:
    """The figure of ``plot_trajectories``: 3D trajectories of the points along the estimated
    order, one legend entry per point drawn.

    X (N, P, 3) world points, order (N,) image indices by estimated time, observed (N, P) bool,
    subject_id (P,) int: the subject of every point (colour per subject, a line style per point).
    Every point is drawn when P <= ``max_points``; else the ``max_points`` points (split between
    subjects) with the largest robust extent (5th-95th percentile) among the most observed ones
    of their subject (seen in >= 80 % as many images as its best), and the title says how many
    of P are shown. Circles mark the first image, squares the last. The view spans the
    1st-99th percentiles of the drawn positions: outliers beyond it are left out and counted in
    the title.
    """
    X = np.asarray(X, dtype=np.float64)[np.asarray(order)]
    groups = np.zeros(X.shape[1], dtype=np.int64) if subject_id is None else subject_id
    if points is None and X.shape[1] <= max_points:
        points = list(range(X.shape[1]))
    if points is None:
        spread = np.nanpercentile(X, 95, axis=0) - np.nanpercentile(X, 5, axis=0)  # (P, 3)
        score = np.nan_to_num(np.linalg.norm(spread, axis=1))
        seen = None if observed is None else np.asarray(observed).sum(axis=0)
        per_group = max(1, max_points // np.unique(groups).size)
        points = []
        for g in np.unique(groups):
            members = np.flatnonzero(groups == g)
            ranked = score[members].copy()
            if seen is not None:
                ranked[seen[members] < 0.8 * seen[members].max()] = -1.0
            points += members[np.argsort(-ranked)[:per_group]].tolist()
        points = sorted(points)
    tracks = X[:, points].copy()  # (N, k, 3)
    finite = tracks[np.isfinite(tracks).all(axis=2)]
    outliers = 0
    if len(finite):
        low, high = np.percentile(finite, 1, axis=0), np.percentile(finite, 99, axis=0)
        margin = 0.1 * (high - low).max() + 1e-9
        low, high = low - margin, high + margin
        outside = ((tracks < low) | (tracks > high)).any(axis=2)
        outliers = int(outside.sum())
        tracks[outside] = np.nan
    fig = _figure(figsize=(8, 7))
    ax = fig.add_subplot(projection="3d")
    cmap = colormaps["tab10" if len(points) <= 10 or subject_id is not None else "tab20"]
    subjects = np.unique(groups).tolist()
    for k, p in enumerate(points):
        track = tracks[:, k]
        valid = np.flatnonzero(np.isfinite(track).all(axis=1))
        label = point_names[p] if point_names is not None else f"point {p}"
        if not valid.size:
            label += " (no finite position)"
        style = "-"
        colour = cmap(k % cmap.N)
        if subject_id is not None:
            label = f"subject {groups[p]}: {label}"
            colour = cmap(subjects.index(groups[p]) % 10)
            style = ("-", "--", ":", "-.")[int(np.sum(groups[points[:k]] == groups[p])) % 4]
        ax.plot(*track.T, style, color=colour, lw=1.3, label=label)
        if not valid.size:
            continue
        ax.scatter(*track[valid[0]], color=colour, marker="o", s=40)
        ax.scatter(*track[valid[-1]], color=colour, marker="s", s=40)
    if len(finite):
        centre, half = (high + low) / 2, float((high - low).max()) / 2
        ax.set_xlim(centre[0] - half, centre[0] + half)
        ax.set_ylim(centre[1] - half, centre[1] + half)
        ax.set_zlim(centre[2] - half, centre[2] + half)
    ax.set_xlabel("x (model units)")
    ax.set_ylabel("y")
    ax.set_zlabel("z")
    shown = (f"{len(points)} of {X.shape[1]} points (the widest moving)"
             if len(points) < X.shape[1] else f"all {X.shape[1]} points")
    note = f", {outliers} outlying position(s) not drawn" if outliers else ""
    ax.set_title(f"Trajectories along the estimated order: {shown}, {X.shape[0]} images{note}\n"
                 "o = first image, \u25a1 = last image")
    ax.legend(fontsize=8, loc="upper left", ncol=1 + len(points) // 16)
    fig.tight_layout()
    return fig


def plot_trajectories(X: np.ndarray, order: np.ndarray, path: Path | str, **kwargs) -> Path:
    """``trajectories_figure`` (same keyword arguments) saved as a PNG."""
    return _save(trajectories_figure(X, order, **kwargs), path)


class GifWriter(AbstractMovieWriter):
    """Animated GIF through Pillow (as matplotlib's ``PillowWriter``) with one palette for every
    frame, taken from the first, middle and last frames plus the exact ``colors`` (K, 3) uint8
    (at most 128; small marks would otherwise be merged with their surroundings): a pixel
    that did not change keeps its palette index, so each GIF frame stores only what moved
    (smaller and faster to encode than a palette per frame: docs/method.md, "Around the
    solver")."""

    def __init__(self, *, fps: float, colors: np.ndarray | None = None):
        super().__init__(fps=fps)
        self.colors = np.zeros((0, 3), dtype=np.uint8) if colors is None else \
            np.unique(np.asarray(colors, dtype=np.uint8).reshape(-1, 3), axis=0)[:128]

    def setup(self, fig: Figure, outfile: Path | str, dpi: float | None = None) -> None:
        super().setup(fig, outfile, dpi=dpi)
        self.images: list[Image.Image] = []

    def grab_frame(self, **savefig_kwargs) -> None:
        buf = io.BytesIO()
        self.fig.savefig(buf, **{**savefig_kwargs, "format": "rgba", "dpi": self.dpi})
        self.images.append(Image.frombuffer("RGBA", self.frame_size, buf.getbuffer(), "raw",
                                            "RGBA", 0, 1).convert("RGB"))

    def finish(self) -> None:
        picks = [self.images[k] for k in sorted({0, len(self.images) // 2, len(self.images) - 1})]
        width, height = self.frame_size
        mosaic = Image.new("RGB", (width, height * len(picks)))
        for k, image in enumerate(picks):
            mosaic.paste(image, (0, k * height))
        scene = mosaic.quantize(colors=256 - len(self.colors), method=Image.Quantize.MEDIANCUT)
        palette = Image.new("P", (1, 1))
        palette.putpalette(scene.getpalette()[:3 * (256 - len(self.colors))]
                           + self.colors.ravel().tolist())
        frames = [image.quantize(palette=palette, dither=Image.Dither.NONE)
                  for image in self.images]
        frames[0].save(self.outfile, format="GIF", save_all=True, append_images=frames[1:],
                       duration=round(1000 / self.fps), loop=0)


def scene_box(X: np.ndarray, *, margin: float = 0.15) -> tuple[np.ndarray, float]:
    """Centre (3,) and half side of a cube around the dynamic points X (..., 3): their
    1st-99th percentiles per axis (a stray point does not stretch it) plus ``margin`` of the
    largest side on each side; the unit cube at 0 when no position is finite."""
    finite = np.asarray(X, dtype=np.float64).reshape(-1, 3)
    finite = finite[np.isfinite(finite).all(axis=1)]
    if not len(finite):
        return np.zeros(3), 1.0
    low, high = np.percentile(finite, 1, axis=0), np.percentile(finite, 99, axis=0)
    side = max(float((high - low).max()), 1e-9)
    return (low + high) / 2, side * (0.5 + margin)


def crop_static(xyz: np.ndarray, rgb: np.ndarray | None, centre: np.ndarray, half: float, *,
                max_points: int) -> tuple[np.ndarray, np.ndarray | None]:
    """The static points xyz (M, 3) (colours rgb (M, 3) uint8) inside the cube ``centre`` +-
    ``half``, at most ``max_points`` of them (a fixed random subset, seed 0)."""
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    keep = np.flatnonzero((np.abs(xyz - centre) <= half).all(axis=1))
    if keep.size > max_points:
        keep = np.sort(np.random.default_rng(0).choice(keep, max_points, replace=False))
    return xyz[keep], None if rgb is None else np.asarray(rgb)[keep]


def animation_frames(num_images: int, max_frames: int) -> np.ndarray:
    """The ranks drawn by ``animate``: all of them, or ``max_frames`` evenly spread."""
    if num_images <= max_frames:
        return np.arange(num_images)
    return np.unique(np.linspace(0, num_images - 1, max_frames).round().astype(np.int64))


def animate(X: np.ndarray, order: np.ndarray, path: Path | str, *,
            image_names: np.ndarray | None = None, events: np.ndarray | None = None,
            edges: np.ndarray | None = None, colors: np.ndarray | None = None,
            subject_id: np.ndarray | None = None, observed: np.ndarray | None = None,
            static_xyz: np.ndarray | None = None, static_rgb: np.ndarray | None = None,
            up: np.ndarray | None = None, max_frames: int = 150, width_px: int = 640,
            fps: float = 10.0, max_static: int = 3000, trail: int = 8) -> Path:
    """Animated GIF of the points and skeleton image by image in estimated order, around the
    static points, on fixed equal-aspect axes.

    X (N, P, 3) world points (NaN = none), order (N,) image indices by estimated time,
    image_names (N,), events (N,) int, edges (E, 2) columns of X (``columns.column_edges``),
    colors (P, 3) uint8 (``columns.point_colors``; default tab10), subject_id (P,) int (a
    marker shape per subject), observed (N, P) bool (filled: detected, hollow: estimated),
    static_xyz (M, 3) / static_rgb (M, 3) uint8: COLMAP's points, those in the cube of
    ``scene_box`` (at most ``max_static``) drawn; a thin trail follows every point through
    the ``trail`` images before (of its event). ``up`` (3,): the world's up direction
    (e.g. the cameras' mean), its nearest axis drawn vertical; default z. At most
    ``max_frames`` frames (``animation_frames``), ``width_px`` wide, ``fps`` frames a second.
    """
    X = np.asarray(X, dtype=np.float64)
    order = np.asarray(order)
    events = None if events is None else np.asarray(events)
    n, p = X.shape[:2]
    centre, half = scene_box(X)
    drawn = np.where((np.abs(X - centre) <= half).all(axis=2, keepdims=True), X, np.nan)
    colors = (np.asarray(colors, dtype=np.float64) / 255.0 if colors is not None
              else np.array([colormaps["tab10"](k % 10)[:3] for k in range(p)]))
    subjects = np.zeros(p, dtype=np.int64) if subject_id is None else np.asarray(subject_id)
    markers = "o^sDvp<>h*"
    marker_of = {s: markers[k % len(markers)] for k, s in enumerate(np.unique(subjects))}
    edges = np.zeros((0, 2), dtype=np.int64) if edges is None else np.asarray(edges).reshape(-1, 2)

    height_px = int(round(0.875 * width_px))
    fig = _figure(figsize=(width_px / 100, height_px / 100), dpi=100)
    ax = fig.add_subplot(projection="3d", computed_zorder=False)
    ax.set_position((-0.04, -0.04, 1.08, 1.0))
    axis = 2 if up is None else int(np.argmax(np.abs(up)))
    ax.view_init(elev=18, azim=-60, vertical_axis="xyz"[axis])
    # up along -axis: that axis and the next one reversed, a half turn (no mirror image)
    flipped = (axis, (axis + 1) % 3) if up is not None and up[axis] < 0 else ()
    for k, setter in enumerate((ax.set_xlim, ax.set_ylim, ax.set_zlim)):
        low, high = centre[k] - half, centre[k] + half
        setter((high, low) if k in flipped else (low, high))
    ax.set_box_aspect((1, 1, 1))
    # axis names but no tick labels: text is most of a 3D frame's drawing time
    ax.set(xlabel="x", ylabel="y", zlabel="z", xticklabels=[], yticklabels=[], zticklabels=[])
    if static_xyz is not None and len(static_xyz):
        xyz, rgb = crop_static(static_xyz, static_rgb, centre, half, max_points=max_static)
        ax.scatter(*xyz.T, s=2.5, c="0.6" if rgb is None else rgb / 255.0, alpha=0.7,
                   depthshade=False, linewidths=0, zorder=1)
    trails = [ax.plot([], [], [], "-", lw=0.8, alpha=0.6, color=colors[k], zorder=2)[0]
              for k in range(p if trail > 0 else 0)]
    bones = [ax.plot([], [], [], "-", lw=2.0, color=colors[a], zorder=2)[0] for a, _ in edges]
    dots = [ax.plot([], [], [], ls="none", marker=marker_of[subjects[k]], ms=6, mew=1.2,
                    color=colors[k], zorder=3)[0] for k in range(p)]
    title = fig.text(0.5, 0.965, "", ha="center", va="top", fontsize=10)
    if observed is not None:
        fig.text(0.5, 0.925, "filled: detected in the image, hollow: estimated", ha="center",
                 va="top", fontsize=7, color="0.3")

    path = Path(path)
    writer = GifWriter(fps=fps, colors=np.round(255 * colors))
    with atomic_path(path) as tmp, writer.saving(fig, tmp, dpi=100):
        for rank in animation_frames(n, max_frames).tolist():
            i = int(order[rank])
            recent = order[max(rank - trail, 0):rank + 1]
            if events is not None:  # a trail never crosses into another event
                recent = recent[events[recent] == events[i]]
            for k, line in enumerate(trails):
                line.set_data_3d(*drawn[recent, k].T)
            for line, (a, b) in zip(bones, edges.tolist(), strict=True):
                line.set_data_3d(*drawn[i, [a, b]].T)
            for k, dot in enumerate(dots):
                dot.set_data_3d(*drawn[i, k:k + 1].T)
                seen = observed is None or bool(observed[i, k])
                dot.set_markerfacecolor(colors[k] if seen else "none")
            name = "" if image_names is None else f"{image_names[i]}   "
            event = "" if events is None else f"   event {int(events[i])}"
            title.set_text(f"{name}rank {rank} / {n - 1}{event}")
            writer.grab_frame()
    return path


def readable_images(workspace: Workspace, names: Sequence[str]) -> list[str]:
    """The ``names`` whose file in the workspace's image folder OpenCV can read (judged by its
    header, without decoding it), for the overlays; the others are named in one warning
    (keypoints and a calibration without image files, or empty placeholders, are normal
    input: only the overlays need pixels)."""
    folder = workspace.image_dir
    readable = [] if folder is None else [
        n for n in names if (folder / n).is_file() and cv2.haveImageReader(str(folder / n))]
    if len(readable) < len(names):
        missing = [n for n in names if n not in set(readable)]
        where = (f"{workspace.model_dir}: no image folder" if folder is None
                 else f"{folder}: no readable image file")
        logger.warning("%s for %d of %d image(s) (%s): no reprojection overlay on them%s",
                       where, len(missing), len(names),
                       ", ".join(quoted(n) for n in missing[:3])
                       + (f" and {len(missing) - 3} more" if len(missing) > 3 else ""),
                       "" if readable else "; the other plots are written")
    return readable


def write_plots(folder: Path, capture: Capture, result: Result, *,
                workspace: Workspace | None = None,
                edges: np.ndarray | None = None, point_names: list[str] | None = None,
                num_overlays: int = 4, overlay_images: Sequence[str] | None = None
                ) -> list[Path]:
    """Sequence, affinity, event and trajectory plots, the detector offsets taken out (when
    any), the animation (``animation.gif``, with the workspace's static points), plus
    reprojection overlays on ``num_overlays`` images
    spread over the estimated order among ``overlay_images`` (names of images with a readable
    file; default ``readable_images``, which warns about the others). ``edges`` (E, 2)
    and ``point_names`` (P,) are the layout's (point ids); with several subjects, skeletons
    and trajectories are drawn per subject."""
    capture = solved_capture(capture, result)
    subject_id, point_id = column_ids(result)
    subjects = None if result.subject_id is None else subject_id
    edges = column_edges(edges if edges is not None else [], subject_id, point_id)
    folder.mkdir(parents=True, exist_ok=True)
    written = [
        plot_sequence(result, capture, folder / "sequence.png"),
        plot_affinity(result, folder / "affinity.png"),
        plot_events(result, folder / "events.png"),
        *([] if result.image_status is None else
          [plot_reconstructability(result, capture, folder / "reconstructability.png")]),
        *([] if result.offset_px is None else
          [plot_stream_offsets(result, capture, folder / "stream_offsets.png",
                               column_labels(result, point_names))]),
        plot_trajectories(result.X, result.order, folder / "trajectories.png",
                          point_names=None if point_names is None else
                          [point_names[j] for j in point_id],
                          observed=capture.visible, subject_id=subjects),
        animate(result.X, result.order, folder / "animation.gif",
                image_names=capture.image_names, events=result.events, edges=edges,
                colors=point_colors(int(point_id.max()) + 1)[point_id], subject_id=subjects,
                observed=capture.visible,
                static_xyz=None if workspace is None else workspace.static_xyz,
                static_rgb=None if workspace is None else workspace.static_rgb,
                up=-capture.R[:, 1].mean(axis=0)),  # image up is -y of the camera
    ]
    if workspace is None or num_overlays <= 0:
        return written
    if overlay_images is None:
        overlay_images = readable_images(workspace, capture.image_names)
    readable = np.isin(capture.image_names, list(overlay_images))
    if not readable.any():
        return written

    detected = capture if result.offset_px is None else replace(  # the user's own detections
        capture, x=capture.x + result.offset_px)
    rays = detected.rays()
    candidates = result.order[readable[result.order]]
    picks = candidates[np.linspace(0, candidates.size - 1, num_overlays).round().astype(int)]
    for i in dict.fromkeys(picks.tolist()):
        name = str(capture.image_names[i])
        image_path = Path(workspace.image_dir) / name
        # any point on the observed ray projects to the observed (distorted) pixel
        observed = np.full((capture.num_points, 2), np.nan)
        vis = capture.visible[i]
        if vis.any():
            observed[vis] = workspace.project(name, capture.C[i] + rays[i, vis])
        reprojected = workspace.project(name, result.X[i])
        rank = int(result.rank[i])
        written.append(plot_reprojection(
            image_path, observed, reprojected, edges,
            folder / "overlays" / f"{frame_file_stem(rank, name, capture.num_images)}.png",
            title=f"{name} (rank {rank})", subject_id=subjects,
        ))
    return written
