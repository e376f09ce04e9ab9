"""Shelf: real OpenPose detections of several people, made asynchronous, scored per person.

Data: the Shelf sequence (Belagiannis et al., 5 calibrated cameras, 301 frames, four actors) as
the 4D Association repository ships it (``zhangyux15/4d_association``, ``data/shelf``): the
cameras (``calibration.json``), OpenPose BODY_25 joint candidates and part-affinity scores per
frame and camera (``detection/<camera>.txt``) and 3D ground truth of every actor
(``gt.txt``, SHELF15 joints, metres, with each actor's identity).

1. Per image, OpenPose's own parsing groups the candidates into skeletons (greedy on the affinity
   scores, as ``OpenposeDetection::Associate`` of that repository; skeletons of fewer than 5
   joints dropped): detections grouped per person, identities unknown, in OpenPose's order.
2. Asynchronous capture: of the frames with any actor in the ground truth, frame f is seen by
   camera ``f % 5`` only (one image per instant). Images where the parser found nobody are kept.
3. A COLMAP workspace (PINHOLE cameras, one posed image per frame, no image files) and one
   OpenPose ``<image>_keypoints.json`` per image -> ``dloe-sfm reconstruct`` at default options.
4. Scores against the ground truth. Each detection is given the actor whose projected joints it
   lies nearest (median over the 12 limb joints, within ``--match-px``), else none. Per actor:
   the subject that took most of its detections, the share of its detections that subject took
   (purity), the share of its detected images that subject reconstructs, the mean 3D error over
   the 12 limb joints (ankles, knees, hips, wrists, elbows, shoulders), |Kendall tau| of the
   subject's images against their frames; and, as the reference, the synchronised 5-camera DLT
   of the same detections at every frame.
5. Runs (``--runs``): ``people``, every detection; ``single``, the same capture with only the
   main actor's detections (the one seen in most frames), every other detection removed, empty
   images kept; ``association``, the association step alone (``multitarget.associate``), scored
   in seconds.

    python pipelines/shelf/pipeline.py --data PATH/TO/4d_association/data/shelf --out OUT
"""

from __future__ import annotations

import argparse
import csv
import json
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dloe_sfm.colmap import CameraSpec, ImageSpec, load_workspace, write_model
from dloe_sfm.core import multitarget
from dloe_sfm.core.capture import nearest_rotation
from dloe_sfm.core.events import symmetrised
from dloe_sfm.core.options import Options
from dloe_sfm.core.pipeline import shape_space_graph
from dloe_sfm.core.problem import initialise
from dloe_sfm.core.sequencing import kendall_tau
from dloe_sfm.errors import InputError
from dloe_sfm.io import atomic_path, check_output
from dloe_sfm.keypoints import read_keypoints
from dloe_sfm.observations import build_capture
from dloe_sfm.stages.reconstruct import main as reconstruct_workspace

# OpenPose BODY_25's part-affinity pairs, in the order of the detection files.
PAFS = np.array([
    [1, 9, 10, 8, 8, 12, 13, 1, 2, 3, 2, 1, 5, 6, 5, 1, 0, 0, 15, 16, 14, 19, 14, 11, 22, 11],
    [8, 10, 11, 9, 12, 13, 14, 2, 3, 4, 17, 5, 6, 7, 18, 0, 15, 16, 17, 18, 19, 20, 21, 22, 23,
     24]]).T
JOINTS = 25
MIN_JOINTS = 5  # OpenPose's parsing drops skeletons with fewer joints (jcntThresh)
BODY25_TYPE = 4  # the detection files' skeleton type for BODY_25
# The 12 limb joints of SHELF15 (R ankle, R knee, R hip, L hip, L knee, L ankle, R wrist,
# R elbow, R shoulder, L shoulder, L elbow, L wrist) and the BODY_25 joints that are the same.
SHELF_LIMBS = np.arange(12)
BODY25_LIMBS = np.array([11, 10, 9, 12, 13, 14, 4, 3, 2, 5, 6, 7])
STEP = 5  # one camera per instant: frame f is seen by camera f % STEP


@dataclass
class Camera:
    K: np.ndarray  # (3, 3), pixel (0, 0) = the centre of the top-left pixel
    R: np.ndarray  # (3, 3) world -> camera
    t: np.ndarray  # (3,)
    width: int
    height: int

    def project(self, X: np.ndarray) -> np.ndarray:
        x = (X @ self.R.T + self.t) @ self.K.T
        return x[..., :2] / x[..., 2:]


def read_cameras(path: Path) -> dict[str, Camera]:
    document = json.loads(path.read_text())
    cameras = {}
    for name, cam in document.items():
        RT = np.array(cam["RT"], dtype=float).reshape(3, 4)
        # stored to 7-8 digits: the nearest rotation
        cameras[name] = Camera(np.array(cam["K"], dtype=float).reshape(3, 3),
                               nearest_rotation(RT[:, :3]), RT[:, 3], *map(int, cam["imgSize"]))
    return cameras


def read_detections(path: Path, camera: Camera) -> list[list[np.ndarray]]:
    """Per frame, OpenPose's skeletons: a list of (25, 3) arrays (x, y px, score; 0 = missing)."""
    tokens = path.read_text().split()
    if int(tokens[0]) != BODY25_TYPE:
        raise InputError(f"{path}: skeleton type {tokens[0]}, expected BODY_25 ({BODY25_TYPE})")
    frames, at = int(tokens[1]), 2
    scale = np.array([camera.width - 1, camera.height - 1, 1.0])
    out = []
    for _ in range(frames):
        candidates = []
        for _ in range(JOINTS):
            n = int(tokens[at])
            candidates.append(np.array(tokens[at + 1:at + 1 + 3 * n], dtype=float)
                              .reshape(3, n).T * scale)
            at += 1 + 3 * n
        affinities = []
        for a, b in PAFS:
            size = len(candidates[a]) * len(candidates[b])
            affinities.append(np.array(tokens[at:at + size], dtype=float)
                              .reshape(len(candidates[a]), len(candidates[b])))
            at += size
        out.append(parse_people(candidates, affinities))
    return out


def parse_people(candidates: list[np.ndarray], affinities: list[np.ndarray]) -> list[np.ndarray]:
    """OpenPose's greedy parsing: limbs by decreasing affinity join or merge skeletons."""
    links = sorted(((affinities[k][i, j], k, i, j) for k, (a, b) in enumerate(PAFS)
                    for i in range(len(candidates[a])) for j in range(len(candidates[b]))
                    if candidates[a][i, 2] > 0 and candidates[b][j, 2] > 0
                    and affinities[k][i, j] > 0), reverse=True)
    people: list[np.ndarray] = []  # per skeleton, the candidate index of each joint (-1 none)
    owner = [np.full(len(c), -1) for c in candidates]
    for _, k, i, j in links:
        a, b = PAFS[k]
        pa, pb = owner[a][i], owner[b][j]
        if pa == -1 and pb == -1:
            skeleton = np.full(JOINTS, -1)
            skeleton[a], skeleton[b] = i, j
            owner[a][i] = owner[b][j] = len(people)
            people.append(skeleton)
        elif pa == -1 or pb == -1:
            p, joint, index = (pa, b, j) if pb == -1 else (pb, a, i)
            if people[p][joint] == -1:
                people[p][joint] = index
                owner[joint][index] = p
        elif pa != pb:
            first, second = min(pa, pb), max(pa, pb)
            if not ((people[first] >= 0) & (people[second] >= 0)).any():
                people[first] = np.maximum(people[first], people[second])
                del people[second]
                for o in owner:
                    o[o == second] = first
                    o[o > second] -= 1
    skeletons = []
    for skeleton in people:
        if (skeleton >= 0).sum() < MIN_JOINTS:
            continue
        values = np.zeros((JOINTS, 3))
        for joint in np.flatnonzero(skeleton >= 0):
            values[joint] = candidates[joint][skeleton[joint]]
        skeletons.append(values)
    return skeletons


def read_truth(path: Path) -> list[dict[int, np.ndarray]]:
    """Per frame, {actor id: (15, 3) SHELF15 joints, metres}."""
    tokens = path.read_text().split()
    joints, frames, at = int(tokens[0]), int(tokens[1]), 2
    out = []
    for _ in range(frames):
        count, at = int(tokens[at]), at + 1
        actors = {}
        for _ in range(count):
            actor = int(tokens[at])
            actors[actor] = np.array(tokens[at + 1:at + 1 + 4 * joints], dtype=float) \
                .reshape(4, joints)[:3].T
            at += 1 + 4 * joints
        out.append(actors)
    return out


def match_actors(skeletons: list[np.ndarray], actors: dict[int, np.ndarray], camera: Camera,
                 max_px: float) -> list[int]:
    """Each skeleton's actor: the nearest projected ground truth (median limb-joint distance)
    within ``max_px``, each actor at most once (greedy on the distance); -1 = none."""
    pairs = []
    for s, skeleton in enumerate(skeletons):
        seen = skeleton[BODY25_LIMBS, 2] > 0
        for actor, X in actors.items():
            if seen.sum() >= 3:
                d = np.linalg.norm(camera.project(X[SHELF_LIMBS])[seen]
                                   - skeleton[BODY25_LIMBS, :2][seen], axis=1)
                pairs.append((float(np.median(d)), s, actor))
    matched = [-1] * len(skeletons)
    taken = set()
    for d, s, actor in sorted(pairs):
        if d <= max_px and matched[s] == -1 and actor not in taken:
            matched[s] = actor
            taken.add(actor)
    return matched


def triangulate(cameras: list[Camera], skeletons: list[np.ndarray]) -> np.ndarray:
    """Score-weighted DLT of each limb joint seen by >= 2 cameras; (12, 3), NaN = unseen."""
    X = np.full((len(BODY25_LIMBS), 3), np.nan)
    matrices = [cam.K @ np.hstack([cam.R, cam.t[:, None]]) for cam in cameras]
    for k, joint in enumerate(BODY25_LIMBS):
        rows = []
        for P, skeleton in zip(matrices, skeletons, strict=True):
            x, y, w = skeleton[joint]
            if w > 0:
                rows += [w * (x * P[2] - P[0]), w * (y * P[2] - P[1])]
        if len(rows) >= 4:
            v = np.linalg.svd(np.array(rows))[2][-1]
            X[k] = v[:3] / v[3]
    return X


@dataclass
class Shelf:
    cameras: list[Camera]
    skeletons: list[list[list[np.ndarray]]]  # [camera][frame]: OpenPose's skeletons in its order
    actors: list[list[list[int]]]  # [camera][frame]: each skeleton's actor (-1 none)
    truth: list[dict[int, np.ndarray]]  # [frame]: {actor: (15, 3)}

    def seen(self, camera: int, frame: int, actor: int) -> np.ndarray:
        """The actor's skeleton in that view, or zeros (unseen)."""
        actors = self.actors[camera][frame]
        return self.skeletons[camera][frame][actors.index(actor)] if actor in actors \
            else np.zeros((JOINTS, 3))


def read_shelf(data: Path, max_px: float) -> Shelf:
    by_name = read_cameras(data / "calibration.json")
    names = sorted(by_name, key=int)
    cameras = [by_name[n] for n in names]
    skeletons = [read_detections(data / "detection" / f"{n}.txt", c)
                 for n, c in zip(names, cameras, strict=True)]
    truth = read_truth(data / "gt.txt")
    actors = [[match_actors(s, truth[f], cameras[c], max_px) for f, s in enumerate(per_frame)]
              for c, per_frame in enumerate(skeletons)]
    return Shelf(cameras, skeletons, actors, truth)


def ray_distance(a: tuple[np.ndarray, np.ndarray], b: tuple[np.ndarray, np.ndarray]) -> float:
    """Shortest distance between two rays (centre, unit direction), as lines."""
    (ca, da), (cb, db) = a, b
    n = np.cross(da, db)
    return float(abs((cb - ca) @ n) / max(np.linalg.norm(n), 1e-12))


def unannotated_seen(shelf: Shelf, joint: int = 1, max_m: float = 0.15) -> tuple[int, int]:
    """(detections matching no annotated actor, those of them whose ``joint`` ray passes within
    ``max_m`` of a detection's in at least two other cameras at the same frame): people the
    annotation leaves out, where both are close."""
    def ray(c: int, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        cam = shelf.cameras[c]
        d = cam.R.T @ np.linalg.solve(cam.K, [x[0], x[1], 1.0])
        return -cam.R.T @ cam.t, d / np.linalg.norm(d)

    rays = [[[ray(c, s[joint]) if s[joint, 2] > 0 else None for s in skeletons]
             for skeletons in per_frame] for c, per_frame in enumerate(shelf.skeletons)]
    total = seen = 0
    for c, per_frame in enumerate(rays):
        for f, frame_rays in enumerate(per_frame):
            for r, actor in zip(frame_rays, shelf.actors[c][f], strict=True):
                if actor != -1 or r is None:
                    continue
                total += 1
                views = sum(any(other is not None and ray_distance(r, other) < max_m
                                for other in rays[o][f])
                            for o in range(len(rays)) if o != c)
                seen += views >= 2
    return total, seen


@dataclass
class Capture:
    names: list[str]  # image names, cam<c>/<frame>.jpg
    frames: np.ndarray  # (N,)
    cameras: np.ndarray  # (N,) camera index

    def views(self) -> zip:
        """(name, frame, camera) of every image."""
        return zip(self.names, self.frames, self.cameras, strict=True)


def asynchronous(shelf: Shelf) -> Capture:
    """The frames with any actor in the ground truth, frame f seen by camera f % STEP."""
    frames = np.array([f for f, actors in enumerate(shelf.truth) if actors])
    cams = frames % STEP
    return Capture([f"cam{c}/{f:04d}.jpg" for f, c in zip(frames, cams, strict=True)], frames, cams)


def write_inputs(folder: Path, shelf: Shelf, capture: Capture, keep: int | None = None) -> None:
    """``folder/workspace`` (COLMAP model) and ``folder/openpose``; ``keep``: only that actor's
    detections (the others removed, empty images kept)."""
    cameras = shelf.cameras
    specs = [CameraSpec(model="PINHOLE", width=c.width, height=c.height,
                        params=np.array([c.K[0, 0], c.K[1, 1], c.K[0, 2] + 0.5,
                                         c.K[1, 2] + 0.5])) for c in cameras]
    images = [ImageSpec(name=name, camera=int(c), R=cameras[c].R, C=-cameras[c].R.T @ cameras[c].t)
              for name, c in zip(capture.names, capture.cameras, strict=True)]
    write_model(folder / "workspace" / "sparse" / "0", specs, images)
    for name, f, c in capture.views():
        people = [s for s, a in zip(shelf.skeletons[c][f], shelf.actors[c][f], strict=True)
                  if keep is None or a == keep]
        file = folder / "openpose" / f"{name.removesuffix('.jpg')}_keypoints.json"
        file.parent.mkdir(parents=True, exist_ok=True)
        file.write_text(json.dumps({"people": [{"pose_keypoints_2d": p.ravel().tolist()}
                                               for p in people]}))


def run_stage(folder: Path, overrides: list[str]) -> dict:
    tic = time.perf_counter()
    out = reconstruct_workspace(folder / "workspace", folder / "openpose", "openpose",
                                folder / "reconstruction", overrides=overrides, plots=False)
    seconds = time.perf_counter() - tic
    with np.load(out / "trajectories.npz") as npz:
        traj = {k: npz[k] for k in npz.files}
    with open(out / "sequence.csv", newline="") as f:
        rank = {r["image"]: int(r["rank"]) for r in csv.DictReader(f)}
    report = json.loads((out / "report.json").read_text())
    return {"traj": traj, "rank": rank, "report": report, "seconds": seconds}


def score_actor(shelf: Shelf, capture: Capture, out: dict, actor: int) -> dict:
    """The actor's subject (the one that took most of its detections), purity, the share of its
    detected images reconstructed, the mean 3D error over the 12 limb joints, |tau| of those
    images against their frames; the synchronised DLT's error on the same images."""
    traj = out["traj"]
    row_of = {str(n): i for i, n in enumerate(traj["image_names"])}
    P = traj["X"].shape[1]
    subject_id = traj.get("subject_id", np.zeros(P, dtype=int))
    point_id = traj.get("point_id", np.arange(P))
    detected, taken = [], []
    for n, (name, f, c) in enumerate(capture.views()):
        if actor in shelf.actors[c][f]:
            detected.append(n)
            m = shelf.actors[c][f].index(actor)
            if name not in row_of:
                taken.append(-1)
            elif "detection_subject" in traj:
                found = traj["detection_subject"][row_of[name]]
                taken.append(int(found[m]) if m < found.size else -1)
            else:
                taken.append(0)
    taken_arr = np.array(taken, dtype=int)
    counts = np.bincount(taken_arr[taken_arr >= 0], minlength=1)
    subject = int(np.argmax(counts)) if counts.sum() else -1
    column_of = {int(point_id[k]): k for k in np.flatnonzero(subject_id == subject)}
    errors, frames, ranks, reference = [], [], [], []
    for n in detected:
        f, name = capture.frames[n], capture.names[n]
        gt = shelf.truth[f][actor][SHELF_LIMBS]
        X_sync = triangulate(shelf.cameras, [shelf.seen(c, f, actor)
                                             for c in range(len(shelf.cameras))])
        reference.append(np.nanmean(np.linalg.norm(X_sync - gt, axis=1)))
        if subject < 0 or name not in row_of:
            continue
        X = np.array([traj["X"][row_of[name], column_of[j]] if j in column_of
                      else np.full(3, np.nan) for j in BODY25_LIMBS])
        if np.isfinite(X).all(axis=1).sum() < len(BODY25_LIMBS) // 2:
            continue
        errors.append(np.nanmean(np.linalg.norm(X - gt, axis=1)))
        frames.append(f)
        ranks.append(out["rank"][name])
    tau = kendall_tau(np.argsort(ranks), np.array(frames)) if len(frames) > 2 else None
    return {"actor": actor, "images_detected": len(detected), "subject": subject,
            "purity": float((taken_arr == subject).mean()) if taken else 0.0,
            "reconstructed": len(errors) / max(len(detected), 1),
            "error_mm": 1000 * float(np.mean(errors)) if errors else None, "tau": tau,
            "sync_dlt_mm": 1000 * float(np.nanmean(reference)) if reference else None}


def association(folder: Path, shelf: Shelf, capture: Capture, actors: list[int]) -> dict:
    """The association alone (``multitarget.associate``, the stage's steps 1-3, seconds instead
    of minutes): subjects, and per actor the share of its detections in its commonest subject;
    and how often the proxy graph's strongest link of an annotated detection goes to a
    detection of the same actor (of those whose strongest link is annotated)."""
    ws = load_workspace(folder / "workspace")
    caught = build_capture(ws, read_keypoints("openpose", folder / "openpose", workspace=ws),
                           person="all").capture
    frame_camera = {name: (f, c) for name, f, c in capture.views()}
    actor = np.full(caught.x.shape[:2], -2)  # -2: no detection in that slot
    for n, name in enumerate(caught.image_names):
        f, c = frame_camera[str(name)]
        for m, k in enumerate(caught.image_ids["detection_index"][n]):
            if k >= 0:
                actor[n, m] = shelf.actors[c][f][k]
    tic = time.perf_counter()
    assignment = multitarget.associate(caught, Options())
    seconds = time.perf_counter() - tic
    proxies, source, slot = multitarget.proxy_capture(caught)
    G = symmetrised(shape_space_graph(proxies, Options(), initialise(proxies, Options())))
    truth = actor[source, slot]
    strongest = np.array([row.indices[np.argmax(row.data)] if row.nnz else -1
                          for row in (G.getrow(i) for i in range(G.shape[0]))])
    linked = (truth >= 0) & (strongest >= 0)
    linked[linked] &= truth[strongest[linked]] >= 0
    shares = {}
    for a in actors:
        mine = assignment[actor == a]
        counts = np.bincount(mine[mine >= 0], minlength=1)
        shares[a] = float(counts.max() / max(mine.size, 1))
    return {"seconds": seconds, "subjects": int(assignment.max()) + 1,
            "largest_share": shares,
            "strongest_link_same_actor": [int((truth[strongest[linked]] == truth[linked]).sum()),
                                          int(linked.sum())]}


def describe(run: str, row: dict) -> str:
    error = "-" if row["error_mm"] is None else f"{row['error_mm']:.1f}"
    tau = "-" if row["tau"] is None else f"{row['tau']:.3f}"
    return (f"{run:6s} actor {row['actor']}: {row['images_detected']:3d} images detected, "
            f"subject {row['subject']}, purity {row['purity']:.3f}, reconstructed "
            f"{100 * row['reconstructed']:.1f} %, {error} mm (sync. 5-camera DLT "
            f"{row['sync_dlt_mm']:.1f}), |tau| {tau}")


RUNS = ("people", "single", "association")


def main(data: Path, out_dir: Path, *, runs: tuple[str, ...] = RUNS[:2],
         max_px: float = 40.0, overrides: list[str] | None = None,
         overwrite: bool = False) -> dict:
    overrides = overrides or []
    data = Path(data)
    out_dir = check_output(Path(out_dir), protected=[data], overwrite=overwrite)
    shelf = read_shelf(data, max_px)
    capture = asynchronous(shelf)
    seen = np.bincount([a for _, f, c in capture.views()
                        for a in shelf.actors[c][f] if a >= 0])
    main_actors = [int(a) for a in np.argsort(-seen)[:2]]
    empty = sum(not shelf.skeletons[c][f] for _, f, c in capture.views())
    detections = sum(len(shelf.skeletons[c][f]) for _, f, c in capture.views())
    unmatched = sum(a == -1 for _, f, c in capture.views() for a in shelf.actors[c][f])
    print(f"{len(capture.names)} images, {empty} without a detection, {detections} "
          f"detections ({unmatched} of no actor); detected images per actor "
          f"{dict(enumerate(seen.tolist()))}", flush=True)
    total, seen_elsewhere = unannotated_seen(shelf)
    print(f"of all {total} detections of no annotated actor with a neck, {seen_elsewhere} are "
          "seen by two other cameras at the same frame (neck rays within 15 cm)", flush=True)
    document = {"data": str(data.resolve()), "images": len(capture.names), "empty_images": empty,
                "unmatched_detections": unmatched, "match_px": max_px, "overrides": overrides,
                "unannotated_necks": total, "unannotated_necks_seen_elsewhere": seen_elsewhere,
                "runs": {}}
    with atomic_path(out_dir, mark=True) as tmp:
        tmp.mkdir()
        for run in runs:
            keep = main_actors[0] if run == "single" else None
            write_inputs(tmp / run, shelf, capture, keep)
            if run == "association":
                document["runs"][run] = found = association(tmp / run, shelf, capture,
                                                            main_actors)
                same, linked = found["strongest_link_same_actor"]
                shares = ", ".join(f"actor {a} {v:.3f}" for a, v in found["largest_share"].items())
                print(f"association: {found['subjects']} subjects; share of each main actor's "
                      f"detections in its commonest subject: {shares}; the "
                      f"strongest link goes to the same actor for {same} of {linked} annotated "
                      f"detections; {found['seconds']:.1f} s", flush=True)
                continue
            out = run_stage(tmp / run, overrides)
            rows = [score_actor(shelf, capture, out, a)
                    for a in (main_actors[:1] if run == "single" else main_actors)]
            for row in rows:
                print(describe(run, row), flush=True)
            report = out["report"]
            summary = {"seconds": out["seconds"], "subjects": report.get("subjects", 1),
                       "events": report.get("events"),
                       "detections_left_out": report.get("detections_left_out", {}).get("count"),
                       "actors": rows}
            print(f"{run:6s} {summary['subjects']} subject(s), {summary['events']} event(s), "
                  f"{summary['detections_left_out']} detections left out, "
                  f"{out['seconds']:.1f} s", flush=True)
            document["runs"][run] = summary
        (tmp / "results.json").write_text(json.dumps(document, indent=2))
    return document


if __name__ == "__main__":
    from dloe_sfm.cli import setup_logging

    parser = argparse.ArgumentParser(allow_abbrev=False, description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, required=True,
                        help="the Shelf folder of zhangyux15/4d_association (data/shelf)")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--runs", nargs="+", default=list(RUNS[:2]), choices=RUNS,
                        help="association: the association step alone, scored (seconds)")
    parser.add_argument("--match-px", type=float, default=40.0,
                        help="largest median distance of a detection to its actor's projection")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="a solver option (default: the package's defaults)")
    parser.add_argument("--overwrite", action="store_true")
    parser.add_argument("--verbose", "-v", action="store_true", help="the stage's logs")
    args = parser.parse_args()
    setup_logging(quiet=not args.verbose)
    try:
        main(args.data, args.out, runs=tuple(args.runs), max_px=args.match_px,
             overrides=args.set, overwrite=args.overwrite)
    except InputError as e:
        parser.exit(2, f"{parser.prog}: error: {e}\n")
