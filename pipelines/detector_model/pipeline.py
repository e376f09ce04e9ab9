"""Detector error model: OpenPose residuals against synchronised triangulation, fitted for the
simulator (``dloe-sfm simulate --detector openpose``, :mod:`dloe_sfm.synth.detector`).

Data: the Pose2Sim single-trial sample (4 calibrated 60 fps cameras, OpenPose BODY_25B).

1. every joint at every frame triangulated from all cameras (the lab rig's weighted DLT on
   undistorted rays) and reprojected into the ideal pinhole of each camera;
2. residuals = detection - reprojection, divided by the person's height in that image (pixels,
   the y-extent of the reprojected joints) so the model transfers to other image scales, and
   scaled by sqrt(2n / (2n - 3)) for a joint seen in n views (the triangulation absorbs 3 of the
   2n coordinates: residuals are smaller than the detector's errors); joints seen in fewer than 3
   views are left out;
3. fits (per image coordinate): the quantiles of the per-(camera, joint) bias (median residual
   over frames, as the mean of noise this heavy-tailed does not settle in 100 frames, less the
   camera's median over joints, a calibration error), Student-t dof and scale (scipy.stats) of
   the residuals less the bias; the confidences' quantiles per error decile, the miss rate
   (score 0 or absent), the left/right swap rate (pairs with a joint detected much nearer its
   twin's reprojection than its own).

Writes the model JSON (default: the package's ``dloe_sfm/synth/detectors/openpose.json``) and
``--out``: residuals.png (histogram with the t and Gaussian fits, QQ plot), fit.json and
workspace/ (the calibration as a COLMAP model).

    python pipelines/detector_model/pipeline.py --data ../shared/data/pose2sim_single_trial \\
        --out outputs/detector_model
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import warnings
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from scipy import stats

from dloe_sfm.calibration import import_calibration, read_calibration
from dloe_sfm.colmap import load_workspace
from dloe_sfm.errors import InputError
from dloe_sfm.io import atomic_path, check_output
from dloe_sfm.keypoints import LAYOUTS, read_keypoints
from dloe_sfm.observations import select_person
from dloe_sfm.synth import sibling_pipeline

lab_rig = sibling_pipeline(__file__, "lab_rig")
"""The lab rig pipeline (its calibration reading, detections and DLT)."""
LAYOUT = lab_rig.LAYOUT
logger = logging.getLogger("dloe_sfm")

MODEL = Path(__file__).resolve().parents[2] / "dloe_sfm" / "synth" / "detectors" / "openpose.json"
BINS = 10  # error deciles for the confidence model
QUANTILES = np.linspace(0.0, 1.0, 11)
BIAS_QUANTILES = np.linspace(0.0, 1.0, 41)
SWAP_RATIO = 0.5  # a joint is swapped when its twin's reprojection is half as far ...
SWAP_MIN = 2.0  # ... and its own residual is above SWAP_MIN x the median one
OUTLIER_SIGMAS = 5.0  # outliers: beyond this many robust sigmas of a coordinate


def observations(data: Path, tmp: Path) -> dict:
    """Undistorted detections of the largest person ``uv`` (F, V, P, 2) normalised, ``score``
    (F, V, P) (0 = missed), ``person`` (F, V) whether anybody was detected, the cameras' ``K``
    (V, 3, 3) and ``Rt`` (V, 3, 4) from a COLMAP model of the calibration written under
    ``tmp``."""
    calib = data / "calibration" / "Calib.qca.txt"
    serials = [c.name for c in read_calibration(calib)]
    cameras = [lab_rig.camera_folder(s) for s in serials]
    kp = read_keypoints("openpose", data / "pose", layout=LAYOUT)
    frames, dets = lab_rig.detections(kp, cameras)
    model = import_calibration(calib, tmp / "workspace" / "sparse" / "0", {
        s: [lab_rig.image_name(c, int(frames[0]))] for s, c in zip(serials, cameras, strict=True)})
    ws = load_workspace(model.parent.parent)
    names = [lab_rig.image_name(c, int(frames[0])) for c in cameras]
    K = np.stack([ws.pinhole(n) for n in names])
    Rt = np.stack([np.concatenate([ws.rotation(n), -ws.rotation(n) @ ws.centre(n)[:, None]],
                                  axis=1) for n in names])
    num_points = len(kp.layout.point_names)
    uv = np.full((frames.size, len(cameras), num_points, 2), np.nan)
    score = np.zeros((frames.size, len(cameras), num_points))
    person = np.zeros((frames.size, len(cameras)), dtype=bool)
    for v, c in enumerate(cameras):
        for t, f in enumerate(frames):
            people = dets[c][int(f)]
            pts = select_person(people, "largest", 0.0) if len(people) else None
            if pts is None:
                continue
            person[t, v] = True
            s = np.nan_to_num(pts[:, 2])
            pixels = np.where((s > 0)[:, None], pts[:, :2] + 0.5, np.nan)  # OpenPose -> COLMAP
            uv[t, v] = ws.normalised(names[v], pixels)
            score[t, v] = np.where(np.isfinite(uv[t, v]).all(axis=1), np.clip(s, 0, 1), 0.0)
    return {"uv": uv, "score": score, "person": person, "K": K, "Rt": Rt, "frames": frames,
            "cameras": cameras}


def residuals(obs: dict) -> dict:
    """``rel`` (F, V, P, 2): residuals of the detections against the synchronised triangulation
    relative to the height and dof-corrected, NaN where not ``usable`` (F, V, P); ``pixels`` and
    ``proj`` (F, V, P, 2): detections and reprojections in pinhole pixels (from the principal
    point); ``height`` (F, V): the person's height in pixels."""
    uv, score, K, Rt = obs["uv"], obs["score"], obs["K"], obs["Rt"]
    X = lab_rig.triangulate(uv, score, Rt)
    cam = np.einsum("vij,fpj->fvpi", Rt[:, :, :3], X) + Rt[None, :, None, :, 3]
    f = np.stack([K[:, 0, 0], K[:, 1, 1]], axis=1)[None, :, None, :]
    proj = cam[..., :2] / cam[..., 2:3] * f
    pixels = uv * f
    height = np.nanmax(proj[..., 1], axis=2) - np.nanmin(proj[..., 1], axis=2)
    seen = np.isfinite(uv).all(axis=-1) & (score > 0)
    views = seen.sum(axis=1, keepdims=True)  # (F, 1, P)
    factor = np.sqrt(2 * views / np.maximum(2 * views - 3, 1))[..., None]
    usable = seen & (views >= 3) & np.isfinite(proj).all(axis=-1)
    rel = np.where(usable[..., None], (pixels - proj) * factor / height[..., None, None], np.nan)
    return {"rel": rel, "pixels": pixels, "proj": proj, "height": height, "usable": usable}


def fit(obs: dict, res: dict, pairs: np.ndarray) -> dict:
    """The model's parameters and the figures describing the fit."""
    rel, usable, score = res["rel"], res["usable"], obs["score"]
    count = usable.sum(axis=0)  # (V, P)
    with np.errstate(invalid="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # joints seen in too few frames
        typical = np.nanmedian(np.where(count[None, ..., None] >= 10, rel, np.nan), axis=0)
    offset = np.nanmedian(typical, axis=1, keepdims=True)  # (V, 1, 2): the camera's calibration
    bias = (typical - offset)[np.isfinite(typical)]  # per (camera, joint) and coordinate
    bias_dof, _, bias_scale = stats.t.fit(bias, floc=0.0)
    noise = (rel - np.nan_to_num(typical)[None])[usable].ravel()
    dof, _, scale = stats.t.fit(noise, floc=0.0)
    sigma = 1.4826 * float(np.median(np.abs(noise)))
    error = np.linalg.norm(rel - offset[None], axis=-1)[usable]  # bias + noise, relative
    edges = np.quantile(error, np.linspace(0, 1, BINS + 1))
    which = np.clip(np.searchsorted(edges, error, side="right") - 1, 0, BINS - 1)
    conf = score[usable]
    conf_quantiles = [np.quantile(conf[which == b], QUANTILES).tolist() for b in range(BINS)]
    rho = float(stats.spearmanr(conf, error).statistic)

    detected = obs["person"][..., None] & np.ones_like(score, dtype=bool)
    miss_rate = float((score[detected] == 0).mean())

    proj, pixels, height = res["proj"], res["pixels"], res["height"][..., None]

    def flipped(j: np.ndarray, k: np.ndarray) -> np.ndarray:
        """Detections of joints ``j`` much nearer the reprojection of their twins ``k``."""
        own = np.linalg.norm(pixels[..., j, :] - proj[..., j, :], axis=-1) / height
        other = np.linalg.norm(pixels[..., j, :] - proj[..., k, :], axis=-1) / height
        return usable[..., j] & (other < SWAP_RATIO * own) & (own > SWAP_MIN * np.median(error))

    a, b = pairs[:, 0], pairs[:, 1]
    both = usable[..., a] & usable[..., b]
    swapped = both & (flipped(a, b) | flipped(b, a))
    swap_rate = float(swapped.sum() / both.sum())

    gauss = stats.norm(scale=sigma)
    t_dist = stats.t(dof, scale=scale)
    tail = OUTLIER_SIGMAS * sigma
    return {
        "residual": {"distribution": "student_t", "dof": float(dof), "scale": float(scale),
                     "per": "image coordinate, relative to the person's height in pixels"},
        "bias": {"distribution": "empirical", "quantiles": BIAS_QUANTILES.tolist(),
                 "values": np.quantile(bias, BIAS_QUANTILES).tolist(),
                 "per": "image coordinate of a (camera, joint), relative to the person's height"},
        "confidence": {"error_edges": edges.tolist(), "quantiles": QUANTILES.tolist(),
                       "score_quantiles": conf_quantiles},
        "miss_rate": miss_rate,
        "swap_rate": swap_rate,
        "outlier_threshold": float(np.sqrt(2) * tail),
        "figures": {
            "observations": int(usable.sum()),
            "relative_error": {"median": float(np.median(error)),
                               "p90": float(np.quantile(error, 0.9)),
                               "p99": float(np.quantile(error, 0.99))},
            "median_height_px": float(np.nanmedian(res["height"])),
            "robust_sigma": sigma,
            "camera_offset_std": float(np.std(offset)),
            "bias_std": float(np.std(bias)),
            "bias_robust_sigma": 1.4826 * float(np.median(np.abs(bias))),
            "bias_student_t": {"dof": float(bias_dof), "scale": float(bias_scale)},
            "beyond_5_sigma": {"real": float((np.abs(noise) > tail).mean()),
                               "student_t": float(2 * t_dist.sf(tail)),
                               "gaussian": float(2 * gauss.sf(tail))},
            "coordinate_p99": {"real": float(np.quantile(np.abs(noise), 0.99)),
                               "student_t": float(t_dist.ppf(0.995)),
                               "gaussian": float(gauss.ppf(0.995))},
            "spearman_confidence_error": rho,
            "swaps": int(swapped.sum()), "pairs_seen": int(both.sum()),
            "images_without_person": int((~obs["person"]).sum()),
            "misses": int((score[detected] == 0).sum()), "joints_in_images": int(detected.sum()),
        },
        "_noise": noise,
    }


def plot(noise: np.ndarray, model: dict, path: Path) -> None:
    """Histogram (log scale) with the Student-t and Gaussian fits, and a QQ plot against the t."""
    dof, scale = model["residual"]["dof"], model["residual"]["scale"]
    sigma = model["figures"]["robust_sigma"]
    fig = Figure(figsize=(11, 4.5))
    FigureCanvasAgg(fig)
    ax, qq = fig.subplots(1, 2)
    lim = float(np.quantile(np.abs(noise), 0.998))
    grid = np.linspace(-lim, lim, 400)
    ax.hist(noise, bins=100, range=(-lim, lim), density=True, color="0.7", label="OpenPose")
    ax.plot(grid, stats.t.pdf(grid, dof, scale=scale), label=f"Student-t (dof {dof:.2f})")
    ax.plot(grid, stats.norm.pdf(grid, scale=sigma), "--", label="Gaussian (robust sigma)")
    ax.set_yscale("log")
    ax.set_ylim(0.5 / (noise.size * 2 * lim / 100), 3 * stats.t.pdf(0, dof, scale=scale))
    ax.set_xlabel("residual / person height (one coordinate, bias removed)")
    ax.legend()
    probs = (np.arange(noise.size) + 0.5) / noise.size
    qq.plot(stats.t.ppf(probs, dof, scale=scale), np.sort(noise), ".", ms=2)
    qq.plot([-lim, lim], [-lim, lim], "k:")
    qq.set_xlim(-lim, lim)
    qq.set_ylim(-lim, lim)
    qq.set_xlabel("Student-t quantile")
    qq.set_ylabel("residual quantile")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def rounded(value: object) -> object:
    """``value`` with every float to 6 significant digits (a small, readable JSON)."""
    if isinstance(value, float):
        return float(f"{value:.6g}")
    if isinstance(value, dict):
        return {k: rounded(v) for k, v in value.items()}
    if isinstance(value, list):
        return [rounded(v) for v in value]
    return value


def run(data: Path, out: Path, model_path: Path = MODEL, *, overwrite: bool = False) -> dict:
    data, out = Path(data), Path(out)
    out = check_output(out, protected=[data], overwrite=overwrite)
    with atomic_path(out, mark=True) as tmp:
        tmp.mkdir()
        obs = observations(data, tmp)
        res = residuals(obs)
        pairs = np.array(LAYOUTS[LAYOUT].symmetric_pairs, dtype=np.int64)
        model = fit(obs, res, pairs)
        noise = model.pop("_noise")
        model = {
            "name": "openpose",
            "provenance": {
                "detector": f"OpenPose {LAYOUT} (Pose2Sim 0.8.4 single-trial sample)",
                "data": f"{len(obs['cameras'])} calibrated 60 fps cameras, "
                        f"{obs['frames'].size} frames, 1088 x 1920 px",
                "method": "residuals of the detections against the synchronised DLT "
                          "triangulation of all cameras, reprojected in the ideal pinhole, "
                          "relative to the person's height in each image",
                "fitted_by": "pipelines/detector_model/pipeline.py",
            },
            **rounded(model),
        }
        plot(noise, model, tmp / "residuals.png")
        with open(tmp / "fit.json", "w") as f:
            json.dump(model, f, indent=2)
    with atomic_path(model_path) as tmp_model, open(tmp_model, "w") as f:
        json.dump(model, f, indent=2)
        f.write("\n")
    logger.info("model in %s; residual plots in %s", model_path, out)
    print(json.dumps({k: model[k] for k in ("residual", "bias", "miss_rate", "swap_rate",
                                             "figures")}, indent=2))
    return model


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(allow_abbrev=False, description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, required=True, help="pose2sim_single_trial folder")
    parser.add_argument("--out", type=Path, required=True, help="output folder (plots, fit)")
    parser.add_argument("--model", type=Path, default=MODEL, help="model JSON to write")
    parser.add_argument("--overwrite", action="store_true")
    args = parser.parse_args(argv)
    try:
        run(args.data, args.out, args.model, overwrite=args.overwrite)
    except InputError as e:
        parser.exit(2, f"{parser.prog}: error: {e}\n")
    return 0


if __name__ == "__main__":
    from dloe_sfm.cli import setup_logging

    setup_logging()
    sys.exit(main())
