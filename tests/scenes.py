"""Hand-built scenes and input files shared by the tests (a helper module, not a test file):
cameras looking at a point, a toy capture with a result, a walking COCO_18 stick figure filmed by a
synthetic COLMAP workspace, OpenPose files; the command line run in-process."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import scipy.sparse as sp

from dloe_sfm import Capture, Result, cli, colmap
from dloe_sfm.core.capture import project
from dloe_sfm.keypoints import Layout
from dloe_sfm.keypoints.base import LAYOUTS


def look_at(centre: np.ndarray, target: np.ndarray) -> np.ndarray:
    """World-to-camera rotation of a camera at ``centre`` looking at ``target`` (z up)."""
    z = (target - centre) / np.linalg.norm(target - centre)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(z, x), z])


N_PER_STREAM, STREAMS, P = 6, 3, 5
F, W_IMG, H_IMG = 800.0, 640.0, 480.0


TOY_LAYOUT = Layout("toy", ["head", "neck", "hip", "knee", "foot"],
                    [(0, 1), (1, 2), (2, 3), (3, 4)])


def toy_capture() -> tuple[Capture, Result, np.ndarray]:
    """3 cameras on a ring, 18 images at distinct instants, 5 points moving on a helix."""
    rng = np.random.default_rng(0)
    n = N_PER_STREAM * STREAMS
    t = np.linspace(0.0, 1.0, n)
    stream = np.arange(n) % STREAMS
    frame = np.arange(n) // STREAMS
    offsets = np.array([[0, 0, 1.7], [0, 0, 1.5], [0, 0, 1.0], [0.1, 0, 0.5], [0.1, 0, 0.05]])
    centre = np.stack([0.5 * np.cos(2 * np.pi * t), 0.5 * np.sin(2 * np.pi * t), 0 * t], axis=1)
    X = centre[:, None, :] + offsets[None]
    angle = 2 * np.pi * stream / STREAMS
    C = np.stack([4 * np.cos(angle), 4 * np.sin(angle), np.full(n, 1.0)], axis=1)
    R = np.stack([look_at(c, np.array([0.0, 0.0, 1.0])) for c in C])
    K = np.tile(np.array([[F, 0, W_IMG / 2], [0, F, H_IMG / 2], [0, 0, 1]]), (n, 1, 1))
    x = project(X, K, R, C)
    x[4, 2] = np.nan
    confidence = rng.uniform(0.5, 1.0, (n, P))
    confidence[4, 2] = 0.0
    names = np.array([f"cam{s:02d}/{f:04d}.jpg" for s, f in zip(stream, frame, strict=True)])
    capture = Capture(x=x, K=K, R=R, C=C, stream=stream, frame=frame, confidence=confidence,
                      image_names=names)
    order = np.arange(n)[::-1].copy()  # estimated order reversed: rank != index
    chain = sp.diags(np.ones(n - 1), 1, shape=(n, n), format="csr")
    result = Result(
        X=X + 1e-3 * rng.normal(size=X.shape), order=order, A=chain, W=chain, D=np.ones(n),
        events=(np.arange(n) >= 12).astype(np.int64), embedding=t,
        cost_history=np.array([2.0, 1.0]), change_history=np.array([0.5, 1e-4]), nit=2,
        success=True, message="converged", seconds=0.25, timings={"x_step": 0.1},
    )
    return capture, result, X


NUM_CAMERAS, NUM_FRAMES = 4, 15  # 60 images, each at an instant of its own
COCO_LAYOUT = LAYOUTS["COCO_18"]
# a stick figure in COCO_18 order (x right, y forward, z up; model units, about 0.9 tall)
BODY = np.array([
    [0.0, 0.05, 0.85], [0.0, 0.0, 0.75], [-0.15, 0.0, 0.73], [-0.2, 0.0, 0.55], [-0.22, 0.05, 0.4],
    [0.15, 0.0, 0.73], [0.2, 0.0, 0.55], [0.22, 0.05, 0.4], [-0.1, 0.0, 0.4], [-0.1, 0.02, 0.2],
    [-0.1, 0.0, 0.0], [0.1, 0.0, 0.4], [0.1, 0.02, 0.2], [0.1, 0.0, 0.0], [-0.03, 0.08, 0.88],
    [0.03, 0.08, 0.88], [-0.07, 0.04, 0.86], [0.07, 0.04, 0.86],
])
ARMS = [3, 4, 6, 7]


def body_at(t: float) -> np.ndarray:
    """(18, 3) joints at time t in [0, 1]: walking on an arc, turning, swinging its arms."""
    pose = BODY.copy()
    swing = 0.5 * np.sin(2 * np.pi * t)
    for j, sign in zip(ARMS, (1, 1, -1, -1), strict=True):
        d = pose[j] - pose[2 if j < 5 else 5]
        c, s = np.cos(sign * swing), np.sin(sign * swing)
        pose[j] = pose[2 if j < 5 else 5] + [d[0], c * d[1] - s * d[2], s * d[1] + c * d[2]]
    turn = 0.8 * t
    Rz = np.array([[np.cos(turn), -np.sin(turn), 0], [np.sin(turn), np.cos(turn), 0], [0, 0, 1]])
    centre = np.array([0.3 * np.cos(np.pi * t), 0.3 * np.sin(np.pi * t), -0.45])
    return pose @ Rz.T + centre


def image_time(name: str) -> float:
    """Instant of a synthetic image: camera c's frame f is taken at (NUM_CAMERAS f + c) / N."""
    cam, frame = map(int, re.match(r"camera(\d+)_frame(\d+)", name).groups())
    return (NUM_CAMERAS * frame + cam - 1) / (NUM_CAMERAS * NUM_FRAMES - 1)


def write_openpose(folder: Path, ws: colmap.Workspace) -> dict[str, np.ndarray]:
    """One OpenPose file per image (pixel convention (0, 0)); returns the true (18, 3) joints."""
    folder.mkdir()
    truth = {}
    for name in ws.image_names:
        X = body_at(image_time(name))
        uv = ws.project(name, X) - 0.5  # COLMAP (0.5, 0.5) -> OpenPose (0, 0)
        w, h = ws.image_size(name)
        assert np.isfinite(uv).all() and (uv > 0).all() and (uv < [w, h]).all(), name
        values = np.concatenate([uv, np.ones((len(uv), 1))], axis=1).ravel().tolist()
        data = {"version": 1.3, "people": [{"pose_keypoints_2d": values}]}
        (folder / f"{Path(name).stem}_keypoints.json").write_text(json.dumps(data))
        truth[name] = X
    return truth


def openpose_file(path: Path, people: np.ndarray) -> None:
    """An OpenPose file of ``people`` (M, P, 3) (x, y, score); NaN joints written as 0, 0, 0."""
    flat = [np.nan_to_num(p, nan=0.0).ravel().tolist() for p in people]
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps({"version": 1.3, "people": [
        {"person_id": [-1], "pose_keypoints_2d": f, "face_keypoints_2d": []} for f in flat]}))


def run_cli(*args, capsys) -> tuple[int, str]:
    """Exit code and stderr of ``dloe-sfm ARGS``, in this process."""
    try:
        code = cli.main([str(a) for a in args])
    except SystemExit as e:
        code = e.code
    return code, capsys.readouterr().err


def error_line(stderr: str) -> str:
    """The one ``dloe-sfm: error:`` line; the message must not continue on another line."""
    lines = [line for line in re.split(r"[\r\n]", stderr) if line.strip()]
    errors = [i for i, line in enumerate(lines) if ": error: " in line]
    assert len(errors) == 1 and errors[0] == len(lines) - 1, stderr
    return lines[-1]

