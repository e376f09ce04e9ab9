"""Make the bundled demo workspace ``assets/demo``: a rendered room, moving markers, COLMAP SfM.

Four static cameras film a textured room as unsynchronised videos while eight coloured spheres
move through it. The script renders the frames (a numpy ray caster: true pinhole projection with
mild radial distortion, z-buffered, supersampled), runs pycolmap SfM on them, aligns the model to
the render's world frame, detects the spheres and writes the keypoints and the ground truth. Field
mode (``FieldSettings``, ``--field``: handheld cameras at their own rates) and crowd mode
(``CrowdSettings``, ``--crowd``: lone photos and short bursts from all around) make the
development workspaces of ``pipelines/field`` and ``pipelines/crowd_workspaces``.

Run from the repository root::

    python pipelines/make_demo_assets/pipeline.py --out assets/demo --overwrite
"""

from __future__ import annotations

import argparse
import csv
import logging
import shutil
import string
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pycolmap

from dloe_sfm.colmap import find_model, run_sfm

logger = logging.getLogger("dloe_sfm")

WIDTH, HEIGHT = 640, 480
FOCAL = 500.0
RADIAL_K = -0.03  # SIMPLE_RADIAL k: mild barrel distortion, at most ~8 px in the corners
SUPERSAMPLING = 3  # rays per pixel along each axis
NUM_CAMERAS = 4
NUM_FRAMES = 12
FRAME_PERIOD = 0.125  # s, the same for every camera; camera c starts c/4 of a period late
RING_RADIUS = 3.6  # m, cameras on a ring around the room's centre ...
RING_ANGLES_DEG = (-90.0, -30.0, 30.0, 90.0)  # ... 60 degrees apart
CAMERA_HEIGHT = 1.6
LOOK_AT = (0.0, 0.0, 0.8)
ROOM_HALF_SIZE = 5.0
WALL_HEIGHT = 4.0
MARKER_RADIUS = 0.05  # m; about 12 px across at the room's centre
# Fully saturated marker colours, hue in degrees; the room's textures stay below saturation 0.3.
MARKER_HUES = (0.0, 30.0, 58.0, 120.0, 185.0, 230.0, 275.0, 320.0)
MARKER_NAMES = ("red", "orange", "yellow", "green", "cyan", "blue", "violet", "magenta")
NOISE_SIGMA = 2.0  # sensor noise, grey levels
JPEG_QUALITY = 60
MAX_FEATURES = 2048
SHAPES_PER_M2 = 12
GLYPHS = list(string.ascii_uppercase + string.digits)


@dataclass(kw_only=True)
class RenderCamera:
    """A SIMPLE_RADIAL camera: world-to-camera rotation ``R``, centre ``C``, pixel coordinates
    in COLMAP's convention (centre of the top-left pixel = (0.5, 0.5))."""

    R: np.ndarray
    C: np.ndarray
    f: float = FOCAL
    cx: float = WIDTH / 2
    cy: float = HEIGHT / 2
    k: float = RADIAL_K
    width: int = WIDTH
    height: int = HEIGHT

    def project(self, X: np.ndarray) -> np.ndarray:
        """World points (..., 3) -> COLMAP pixel coordinates (..., 2); NaN behind the camera."""
        cam = (X - self.C) @ self.R.T
        z = cam[..., 2:3]
        xy = np.where(z > 0, cam[..., :2] / np.where(z > 0, z, 1.0), np.nan)
        r2 = (xy**2).sum(axis=-1, keepdims=True)
        return self.f * xy * (1 + self.k * r2) + np.array([self.cx, self.cy])

    def rays(self, ss: int) -> np.ndarray:
        """(H*ss, W*ss, 3) unit world directions of the sub-pixel samples."""
        u = (np.arange(self.width * ss) + 0.5) / ss
        v = (np.arange(self.height * ss) + 0.5) / ss
        xd = (u[None, :] - self.cx) / self.f
        yd = (v[:, None] - self.cy) / self.f
        xd, yd = np.broadcast_arrays(xd, yd)
        x, y = xd.copy(), yd.copy()
        for _ in range(20):  # invert x_d = x (1 + k r^2) by fixed-point iteration
            scale = 1 + self.k * (x**2 + y**2)
            x, y = xd / scale, yd / scale
        cam = np.stack([x, y, np.ones_like(x)], axis=-1)
        world = cam @ self.R  # R^T applied to row vectors
        return (world / np.linalg.norm(world, axis=-1, keepdims=True)).astype(np.float32)


def look_at(C: np.ndarray, target: np.ndarray) -> np.ndarray:
    """World-to-camera rotation of a camera at ``C`` looking at ``target``, world z up."""
    z = target - C
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z])


def ring_cameras() -> list[RenderCamera]:
    target = np.array(LOOK_AT)
    cams = []
    for a in np.deg2rad(RING_ANGLES_DEG):
        C = np.array([RING_RADIUS * np.cos(a), RING_RADIUS * np.sin(a), CAMERA_HEIGHT])
        cams.append(RenderCamera(R=look_at(C, target), C=C))
    return cams


# --------------------------------------------------------------------------- static scene


@dataclass(kw_only=True)
class TexturedQuad:
    """A parallelogram ``origin + s * edge_u + t * edge_v`` (s, t in [0, 1]) with a texture whose
    columns run along ``edge_u`` and rows along ``edge_v``."""

    origin: np.ndarray
    edge_u: np.ndarray
    edge_v: np.ndarray
    texture: np.ndarray  # (h, w, 3) float32 RGB in [0, 1]
    shade: float = 1.0


def procedural_texture(rng: np.random.Generator, h: int, w: int, texel: float) -> np.ndarray:
    """A non-repetitive, low-saturation RGB texture (h, w, 3) in [0, 1].

    Smooth multi-octave noise under random shapes and text whose sizes are drawn in metres
    (``texel`` metres per texel), so every viewing distance finds SIFT-sized structure.
    """
    base_hue = rng.uniform(0, 180)
    img = np.zeros((h, w), np.float32)
    for octave in range(2, 7):
        grid = rng.normal(size=(2**octave // 2 + 2, 2**octave + 2)).astype(np.float32)
        img += cv2.resize(grid, (w, h), interpolation=cv2.INTER_CUBIC) / octave
    value = 140 + 60 * img / (np.abs(img).max() + 1e-6)
    hsv = np.stack(
        [np.full((h, w), base_hue, np.float32), np.full((h, w), 50, np.float32), value], axis=-1
    )
    canvas = cv2.cvtColor(np.clip(hsv, 0, 255).astype(np.uint8), cv2.COLOR_HSV2RGB_FULL)

    def colour() -> tuple[int, ...]:
        hue = (base_hue + rng.normal(0, 25)) % 256
        pix = np.uint8([[[hue, rng.uniform(0, 70), rng.uniform(20, 245)]]])
        return tuple(int(c) for c in cv2.cvtColor(pix, cv2.COLOR_HSV2RGB_FULL)[0, 0])

    area = h * w * texel**2
    for _ in range(int(SHAPES_PER_M2 * area)):
        size = np.exp(rng.uniform(np.log(0.05), np.log(0.6))) / texel
        cx, cy = int(rng.uniform(0, w)), int(rng.uniform(0, h))
        kind = rng.integers(5)
        if kind == 0:
            cv2.circle(canvas, (cx, cy), max(int(size / 2), 1), colour(), -1, cv2.LINE_AA)
        elif kind == 1:
            half = np.array([size, size * rng.uniform(0.3, 1.0)]) / 2
            box = cv2.boxPoints(((cx, cy), tuple(2 * half), rng.uniform(0, 180)))
            cv2.fillPoly(canvas, [box.astype(np.int32)], colour(), cv2.LINE_AA)
        elif kind == 2:
            n = rng.integers(3, 7)
            pts = np.array([cx, cy]) + rng.normal(0, size / 2, size=(n, 2))
            cv2.fillPoly(canvas, [pts.astype(np.int32)], colour(), cv2.LINE_AA)
        elif kind == 3:
            end = np.array([cx, cy]) + rng.normal(0, size, 2)
            thickness = max(int(size / 15), 1)
            cv2.line(canvas, (cx, cy), tuple(int(e) for e in end), colour(), thickness, cv2.LINE_AA)
        else:
            text = "".join(rng.choice(GLYPHS, rng.integers(2, 7)))
            scale = size / 30
            cv2.putText(canvas, text, (cx, cy), int(rng.integers(0, 8)), scale, colour(),
                        max(int(scale * 2), 1), cv2.LINE_AA)
    canvas = cv2.GaussianBlur(canvas, (0, 0), 0.6)
    return canvas.astype(np.float32) / 255.0


def room(rng: np.random.Generator) -> list[TexturedQuad]:
    """Floor, four walls and a few boxes; world z up, metres."""
    s, hgt = ROOM_HALF_SIZE, WALL_HEIGHT
    ex, ey, ez = np.eye(3)
    quads = [TexturedQuad(origin=np.array([-s, -s, 0.0]), edge_u=2 * s * ex, edge_v=2 * s * ey,
                          texture=procedural_texture(rng, 1000, 1000, 2 * s / 1000))]
    corners = [np.array([-s, -s, 0.0]), np.array([s, -s, 0.0]), np.array([s, s, 0.0]),
               np.array([-s, s, 0.0])]
    for i, shade in enumerate((0.92, 0.85, 0.95, 0.88)):
        a, b = corners[i], corners[(i + 1) % 4]
        quads.append(TexturedQuad(origin=a, edge_u=b - a, edge_v=hgt * ez, shade=shade,
                                  texture=procedural_texture(rng, 400, 1000, 2 * s / 1000)))
    light = np.array([0.3, 0.5, 1.0]) / np.linalg.norm([0.3, 0.5, 1.0])
    for centre, size, yaw in (((-1.9, 1.4), (0.8, 0.6, 0.7), 20.0),
                              ((-1.0, -2.4), (0.7, 0.7, 0.9), -35.0),
                              ((-3.0, -0.4), (1.0, 0.5, 0.5), 60.0),
                              ((1.3, 0.1), (0.5, 0.5, 0.45), 5.0)):
        c, si = np.cos(np.deg2rad(yaw)), np.sin(np.deg2rad(yaw))
        axes = [np.array([c, si, 0.0]) * size[0], np.array([-si, c, 0.0]) * size[1], ez * size[2]]
        low = np.array([*centre, 0.0]) - axes[0] / 2 - axes[1] / 2
        faces = [(low, axes[0], axes[2]), (low, axes[2], axes[1]),
                 (low + axes[1], axes[2], axes[0]), (low + axes[0], axes[1], axes[2]),
                 (low + axes[2], axes[0], axes[1])]
        for origin, eu, ev in faces:
            normal = np.cross(eu, ev)
            normal /= np.linalg.norm(normal)
            if normal @ (np.array([*centre, size[2] / 2]) - origin) > 0:
                normal = -normal
            res = 0.005  # metres per texel
            tex = procedural_texture(rng, int(np.linalg.norm(ev) / res),
                                     int(np.linalg.norm(eu) / res), res)
            quads.append(TexturedQuad(origin=origin, edge_u=eu, edge_v=ev, texture=tex,
                                      shade=0.6 + 0.4 * max(normal @ light, 0.0)))
    return quads


def quad_window(q: TexturedQuad, cam: RenderCamera, plane: np.ndarray
                ) -> tuple[slice, slice] | None:
    """Rows and columns of the samples whose rays can hit ``q`` (None: none can).

    ``plane`` (H', W', 2) holds each sample's ray on the undistorted image plane (z = 1, camera
    frame). The part of the quad in front of the camera projects there to a polygon (straight
    edges stay straight before the lens distortion); the samples inside its bounding box, widened
    by 1e-3 (about a sample), are the only ones that can hit it.
    """
    corners = q.origin + np.array([[0, 0], [1, 0], [1, 1], [0, 1]]) @ np.stack([q.edge_u, q.edge_v])
    local = (corners - cam.C) @ cam.R.T
    near = 1e-6  # m: the polygon clipped to z >= near
    front = []
    for a, b in zip(local, np.roll(local, -1, axis=0), strict=True):
        if a[2] > near:
            front.append(a)
        if (a[2] > near) != (b[2] > near):
            front.append(a + (near - a[2]) / (b[2] - a[2]) * (b - a))
    if not front:
        return None
    xy = np.array(front)[:, :2] / np.array(front)[:, 2:]
    lo, hi = xy.min(axis=0) - 1e-3, xy.max(axis=0) + 1e-3
    inside = ((plane >= lo) & (plane <= hi)).all(axis=-1)
    rows, cols = np.flatnonzero(inside.any(axis=1)), np.flatnonzero(inside.any(axis=0))
    if rows.size == 0:
        return None
    return slice(rows[0], rows[-1] + 1), slice(cols[0], cols[-1] + 1)


def render_static(quads: list[TexturedQuad], cam: RenderCamera, all_rays: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Ray-cast the room: (H', W', 3) float32 RGB and (H', W') distance along each unit ray.

    Each quad is cast only on the samples of its ``quad_window``: the same image, bit for bit,
    as casting every sample (a ray outside the window misses the quad), 5-15 x faster.
    """
    shape = all_rays.shape[:2]
    all_depth = np.full(shape, np.inf, np.float32)
    all_rgb = np.zeros((*shape, 3), np.float32)
    local = all_rays @ cam.R.T.astype(np.float32)
    plane = local[..., :2] / local[..., 2:]
    for q in quads:
        window = quad_window(q, cam, plane)
        if window is None:
            continue
        rays, depth, rgb = all_rays[window], all_depth[window], all_rgb[window]  # views
        normal = np.cross(q.edge_u, q.edge_v)
        denom = rays @ normal.astype(np.float32)
        with np.errstate(divide="ignore", invalid="ignore"):
            dist = ((q.origin - cam.C) @ normal) / denom
        hit = cam.C.astype(np.float32) + dist[..., None] * rays - q.origin.astype(np.float32)
        # Coordinates along the two edges through the dual basis (edges need not be orthogonal).
        gram = np.array([[q.edge_u @ q.edge_u, q.edge_u @ q.edge_v],
                         [q.edge_u @ q.edge_v, q.edge_v @ q.edge_v]])
        dual = np.linalg.solve(gram, np.stack([q.edge_u, q.edge_v])).astype(np.float32)
        s, t = np.moveaxis(hit @ dual.T, -1, 0)
        ok = (dist > 0) & (dist < depth) & (s >= 0) & (s <= 1) & (t >= 0) & (t <= 1)
        th, tw = q.texture.shape[:2]
        map_x = (s * tw - 0.5).astype(np.float32)
        map_y = ((1 - t) * th - 0.5).astype(np.float32)  # texture row 0 at the top edge
        colour = cv2.remap(q.texture, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
        rgb[ok] = q.shade * colour[ok]
        depth[ok] = dist[ok]
    sky = ~np.isfinite(all_depth)
    all_rgb[sky] = (0.75, 0.8, 0.85)
    return all_rgb, all_depth


# --------------------------------------------------------------------------- moving markers


def marker_positions(t: float) -> np.ndarray:
    """(P, 3) true marker centres at time ``t`` (s): a spinning rigid tetrahedron (4), a waving
    two-link arm (shoulder, elbow, wrist) and a bouncing ball."""
    tetra = np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]]) / np.sqrt(3) * 0.4
    axis = np.array([0.3, 0.2, 1.0]) / np.linalg.norm([0.3, 0.2, 1.0])
    angle = 2.5 * t
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    rot = np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K
    centre = np.array([0.35 * np.sin(0.9 * t), 0.25 * np.cos(0.7 * t) - 0.25, 1.3])
    body = centre + tetra @ rot.T

    shoulder = np.array([-0.8 + 0.1 * np.sin(1.3 * t), 0.7, 1.5])
    heading = np.deg2rad(30.0) + 0.4 * t  # the arm's vertical plane turns slowly
    plane = np.array([np.cos(heading), np.sin(heading), 0.0])
    up = np.array([0.0, 0.0, 1.0])
    upper = -0.3 + 0.7 * np.sin(2 * np.pi * 0.55 * t)
    fore = upper + 0.9 + 0.6 * np.sin(2 * np.pi * 0.55 * t + 1.0)
    elbow = shoulder + 0.45 * (np.cos(upper) * plane + np.sin(upper) * up)
    wrist = elbow + 0.4 * (np.cos(fore) * plane + np.sin(fore) * up)

    bounce = 1.1 * np.abs(np.sin(np.pi * (t + 0.3) / 1.0))
    ball = np.array([0.9 - 0.6 * t, -0.9 + 0.9 * t, MARKER_RADIUS + bounce])
    return np.vstack([body, shoulder, elbow, wrist, ball])


def marker_rgb() -> np.ndarray:
    """(P, 3) float RGB of the fully saturated marker colours."""
    hsv = np.uint8([[[h / 360 * 255, 255, 255] for h in MARKER_HUES]])
    return cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB_FULL)[0].astype(np.float32) / 255


def render_markers(rgb: np.ndarray, depth: np.ndarray, rays: np.ndarray, cam: RenderCamera,
                   X: np.ndarray, colours: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Z-buffer the spheres into a copy of the static render (H', W', 3).

    Returns the image and the (P,) visible fraction of each sphere's silhouette (0 = hidden or
    out of view); ray-sphere intersection per sample, so occlusion is exact.
    """
    ss = rays.shape[0] // cam.height
    out, zbuf = rgb.copy(), depth.copy()
    owner = np.full(depth.shape, -1, np.int32)
    silhouette = np.zeros(len(X))
    light = np.array([0.3, 0.5, 1.0]) / np.linalg.norm([0.3, 0.5, 1.0])
    pix = cam.project(X)
    dist = np.linalg.norm(X - cam.C, axis=1)
    for p in np.argsort(-dist):  # far to near, the z-buffer decides anyway
        if not np.isfinite(pix[p]).all():
            continue
        r_pix = 1.5 * cam.f * MARKER_RADIUS / dist[p] + 3  # generous silhouette bound
        u0, u1 = (np.array([pix[p, 0] - r_pix, pix[p, 0] + r_pix]) * ss).astype(int)
        v0, v1 = (np.array([pix[p, 1] - r_pix, pix[p, 1] + r_pix]) * ss).astype(int)
        u0, v0 = max(u0, 0), max(v0, 0)
        u1, v1 = min(u1, cam.width * ss), min(v1, cam.height * ss)
        if u1 <= u0 or v1 <= v0:
            continue
        d = rays[v0:v1, u0:u1].astype(np.float64)
        oc = cam.C - X[p]
        b = d @ oc
        disc = b**2 - (oc @ oc - MARKER_RADIUS**2)
        inside = disc > 0
        t = -b - np.sqrt(np.maximum(disc, 0))
        silhouette[p] = inside.sum()
        front = inside & (t > 0) & (t < zbuf[v0:v1, u0:u1])
        normal = (cam.C + t[..., None] * d - X[p]) / MARKER_RADIUS
        shade = 0.6 + 0.4 * np.clip(normal @ light, 0, 1)
        out[v0:v1, u0:u1][front] = (shade[..., None] * colours[p])[front]
        zbuf[v0:v1, u0:u1][front] = t[front]
        owner[v0:v1, u0:u1][front] = p
    visible = np.bincount(owner[owner >= 0], minlength=len(X))
    with np.errstate(invalid="ignore", divide="ignore"):
        fraction = np.where(silhouette > 0, visible / silhouette, 0.0)
    return out, fraction


def downsample(rgb: np.ndarray, ss: int) -> np.ndarray:
    """Box-filter the supersampled render (H*ss, W*ss, 3) to (H, W, 3)."""
    height, width = rgb.shape[0] // ss, rgb.shape[1] // ss
    return rgb.reshape(height, ss, width, ss, 3).mean(axis=(1, 3))


# --------------------------------------------------------------------------- marker detection


def detect_markers(bgr: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Find each coloured sphere: (P, 2) centres in pixels with (0, 0) = centre of the top-left
    pixel (NaN = not found) and (P,) scores in [0, 1].

    HSV threshold on the marker's hue, largest connected component, then a centroid weighted by
    saturation over the component grown by one pixel, so anti-aliased rim pixels count by
    coverage. The score is the weighted area over the area of the component's enclosing circle:
    about 1 for a whole disc, lower when the sphere is partly hidden (its centroid is then biased).
    """
    hsv = cv2.cvtColor(bgr, cv2.COLOR_BGR2HSV_FULL).astype(np.float32)
    hue, sat, val = hsv[..., 0] * 360 / 256, hsv[..., 1] / 255, hsv[..., 2] / 255
    centres = np.full((len(MARKER_HUES), 2), np.nan)
    scores = np.zeros(len(MARKER_HUES))
    for p, h in enumerate(MARKER_HUES):
        dh = np.abs((hue - h + 180) % 360 - 180)
        core = ((dh < 12) & (sat > 0.55) & (val > 0.3)).astype(np.uint8)
        n, labels, stats, _ = cv2.connectedComponentsWithStats(core, connectivity=8)
        if n < 2:
            continue
        best = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
        if stats[best, cv2.CC_STAT_AREA] < 4:
            continue
        blob = (labels == best).astype(np.uint8)
        region = cv2.dilate(blob, np.ones((3, 3), np.uint8)).astype(bool) & (dh < 30)
        weight = np.clip((sat - 0.3) / 0.6, 0, 1) * region
        ys, xs = np.nonzero(weight)
        w = weight[ys, xs]
        centres[p] = (xs @ w / w.sum(), ys @ w / w.sum())
        _, radius = cv2.minEnclosingCircle(np.column_stack(np.nonzero(blob)).astype(np.float32))
        scores[p] = min(w.sum() / (np.pi * (radius + 0.5) ** 2), 1.0)
    return centres, scores


# --------------------------------------------------------------------------- SfM


def sfm_model(images: Path, work: Path, seed: int,
              intrinsics: tuple[float, ...] | dict[str, tuple[float, ...]]
              ) -> pycolmap.Reconstruction:
    """``dloe_sfm.colmap.run_sfm`` into ``work/sfm``: one COLMAP camera per camera folder with the
    true intrinsics held fixed (``intrinsics``: f, cx, cy, k shared by every camera, or per image
    name), a pose per image, exhaustive matching, global mapping; returns the largest model."""
    workspace = run_sfm(
        images, work / "sfm", camera_mode="per_folder", camera_model="SIMPLE_RADIAL",
        camera_params=intrinsics, mapper="global",
        max_num_features=MAX_FEATURES,
        # Upsampled first octave: 2-3x the matches across the 60 degree baselines and a third of
        # the rotation error of first_octave = 0, for 2-3x the extraction and matching time.
        first_octave=-1, num_threads=2, seed=seed,
    )
    return pycolmap.Reconstruction(find_model(workspace))


def align_to_truth(rec: pycolmap.Reconstruction, names: list[str], centres: np.ndarray
                   ) -> None:
    """Move the model into the render's world frame (metres) by the Sim3 of its camera centres."""
    ransac = pycolmap.RANSACOptions()
    ransac.max_error = 0.1
    ransac.random_seed = 0
    sim3 = pycolmap.align_reconstruction_to_locations(rec, names, centres, 3, ransac)
    if sim3 is None:
        raise RuntimeError("could not align the model to the true camera centres")
    rec.transform(sim3)


def without_unused_points2D(rec: pycolmap.Reconstruction, max_points3D: int | None = None
                            ) -> pycolmap.Reconstruction:
    """The registered images with only the keypoints that observe a 3D point.

    Keypoints without a 3D point are three quarters of ``images.bin`` and nothing downstream
    reads them; dropping them keeps the bundled model small. ``max_points3D`` keeps only that
    many 3D points, the longest tracks, ties broken by position (the static scene is only drawn
    in plots).
    """
    points = rec.points3D
    by_length = sorted(points, key=lambda i: (-points[i].track.length(), *points[i].xyz))
    keep = set(by_length[:max_points3D])
    out = pycolmap.Reconstruction()
    for camera in rec.cameras.values():
        out.add_camera_with_trivial_rig(camera)
    new_index = {}
    for image_id in rec.reg_image_ids():
        image = rec.image(image_id)
        used = [i for i, p in enumerate(image.points2D)
                if p.has_point3D() and p.point3D_id in keep]
        new_index.update({(image_id, i): j for j, i in enumerate(used)})
        keypoints = np.array([image.points2D[i].xy for i in used]).reshape(-1, 2)
        out.add_image_with_trivial_frame(
            pycolmap.Image(name=image.name, keypoints=keypoints, camera_id=image.camera_id,
                           image_id=image_id),
            image.cam_from_world(),
        )
    for point_id, point in rec.points3D.items():
        if point_id not in keep:
            continue
        track = pycolmap.Track([
            pycolmap.TrackElement(el.image_id, new_index[el.image_id, el.point2D_idx])
            for el in point.track.elements
        ])
        out.add_point3D(point.xyz, track, point.color)
    out.update_point_3d_errors()
    return out


def rotation_angle_deg(Ra: np.ndarray, Rb: np.ndarray) -> np.ndarray:
    """Angles (deg) of the relative rotations of two stacks (N, 3, 3)."""
    cos = (np.einsum("nij,nij->n", Ra, Rb) - 1) / 2
    return np.rad2deg(np.arccos(np.clip(cos, -1, 1)))


# --------------------------------------------------------------------------- the pipeline


@dataclass(kw_only=True)
class FieldSettings:
    """Field mode: handheld cameras, each at its own frame rate, starting at random times.

    The number of cameras, their places on the ring, rates, start times and shake are drawn from
    the seed (a generator of its own, so the room and the sensor noise are the demo's for the
    same seed). Each camera films from its start until ``duration``; every frame has its own pose:
    the base pose on the ring moved by a smooth random motion (three random sinusoids of
    0.3-1.5 Hz per axis) of ``shake_m`` RMS per axis for the centre and ``shake_deg`` RMS per
    axis for the orientation.
    """

    cameras: tuple[int, int] = (4, 6)  # drawn in [min, max]
    rates_hz: tuple[float, float] = (8.0, 12.0)  # drawn uniformly: non-commensurate
    max_start: float = 0.2  # s, start times drawn in [0, max_start]
    duration: float = 1.2  # s
    arc_deg: float = 180.0  # the cameras share this arc of the ring, jittered evenly
    shake_m: float = 0.03
    shake_deg: float = 2.0
    width: int = 480
    height: int = 360
    supersampling: int = 2  # rays per pixel along each axis
    max_points3D: int | None = None  # of the written model (None: all), to keep assets/ small


def demo_shots() -> list[list[tuple[float, RenderCamera]]]:
    """The demo's frames per camera, (time, camera): static cameras at one rate, staggered."""
    return [[((k + c / NUM_CAMERAS) * FRAME_PERIOD, cam) for k in range(NUM_FRAMES)]
            for c, cam in enumerate(ring_cameras())]


def rotation_exp(w: np.ndarray) -> np.ndarray:
    """Rotation matrix of the rotation vector ``w`` (3,) in radians (Rodrigues)."""
    angle = np.linalg.norm(w)
    if angle == 0:
        return np.eye(3)
    a = w / angle
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


def wobble(rng: np.random.Generator, t: np.ndarray, rms: float) -> np.ndarray:
    """(len(t), 3) smooth random motion: three random sinusoids per axis, ``rms`` per axis."""
    freq = rng.uniform(0.3, 1.5, (3, 3))
    phase = rng.uniform(0, 2 * np.pi, (3, 3))
    weight = rng.normal(size=(3, 3))
    motion = (weight * np.sin(2 * np.pi * freq * t[:, None, None] + phase)).sum(axis=1)
    return rms * motion / np.sqrt((weight**2).sum(axis=0) / 2)


def handheld(rng: np.random.Generator, t: np.ndarray, C: np.ndarray, R: np.ndarray, *,
             shake_m: float, shake_deg: float, f: float, width: int, height: int
             ) -> list[tuple[float, RenderCamera]]:
    """Frames at times ``t`` of a camera held by hand at the pose ``R``, ``C``: every frame its
    own pose, moved by a smooth random motion (``wobble``) of ``shake_m`` RMS per axis for the
    centre and ``shake_deg`` RMS per axis for the orientation."""
    centres = C + wobble(rng, t, shake_m)
    turns = wobble(rng, t, np.deg2rad(shake_deg))
    return [(float(tk), RenderCamera(R=rotation_exp(w) @ R, C=Ck, f=f, cx=width / 2,
                                     cy=height / 2, width=width, height=height))
            for tk, Ck, w in zip(t, centres, turns, strict=True)]


def field_shots(field: FieldSettings, seed: int) -> list[list[tuple[float, RenderCamera]]]:
    """Field mode's frames per camera, (time, camera), every frame its own handheld pose."""
    rng = np.random.default_rng([seed, 1])
    n = int(rng.integers(field.cameras[0], field.cameras[1] + 1))
    spacing = field.arc_deg / n
    angles = np.deg2rad(-field.arc_deg / 2 + spacing * (np.arange(n) + 0.5
                                                        + rng.uniform(-0.2, 0.2, n)))
    rates = rng.uniform(*field.rates_hz, n)
    starts = rng.uniform(0, field.max_start, n)
    target = np.array(LOOK_AT)
    shots = []
    for a, rate, start in zip(angles, rates, starts, strict=True):
        t = start + np.arange(int(np.ceil((field.duration - start) * rate))) / rate
        base = np.array([RING_RADIUS * np.cos(a), RING_RADIUS * np.sin(a), CAMERA_HEIGHT])
        shots.append(handheld(rng, t, base, look_at(base, target), shake_m=field.shake_m,
                              shake_deg=field.shake_deg, f=FOCAL * (field.width / WIDTH),
                              width=field.width, height=field.height))
    return shots


@dataclass(kw_only=True)
class CrowdSettings:
    """Crowd mode: many people around the scene, each taking a lone photo or a short burst.

    Drawn from the seed (a generator of its own, so the room and the sensor noise are the demo's
    for the same seed): the number of cameras; for each, its place (azimuth all around the
    room's centre, spaced evenly with a jitter of 0.4 spacing, distance, height), its aim (the
    room's centre moved by ``aim_m`` RMS per axis), its focal length (``zoom`` times the base
    focal length, the demo's field of view), a lone photo with probability ``lone_fraction``
    else a burst of ``burst`` images at a rate in ``rates_hz`` (cut to the images that fit in
    ``window``), and the time of its first image (uniform, every image within ``window``).
    Every image has its own handheld pose (``handheld``).
    """

    cameras: tuple[int, int] = (24, 40)  # drawn in [min, max]
    lone_fraction: float = 0.25  # of the cameras, one image each
    burst: tuple[int, int] = (2, 5)  # images of the other cameras, drawn in [min, max]
    rates_hz: tuple[float, float] = (1.0, 3.0)  # of the bursts, drawn uniformly
    window: float = 3.0  # s: every image in [0, window] (a burst cut to what fits in it)
    distance_m: tuple[float, float] = (2.2, 4.4)  # from the room's centre (walls at 5 m)
    height_m: tuple[float, float] = (1.3, 1.9)
    zoom: tuple[float, float] = (0.8, 1.4)  # focal length over the base one, drawn uniformly
    aim_m: float = 0.3
    shake_m: float = 0.03
    shake_deg: float = 2.0
    width: int = 480
    height: int = 360
    supersampling: int = 2  # rays per pixel along each axis
    max_points3D: int | None = None  # of the written model (None: all), to keep assets/ small


def crowd_shots(crowd: CrowdSettings, seed: int) -> list[list[tuple[float, RenderCamera]]]:
    """Crowd mode's images per camera, (time, camera), every image its own handheld pose."""
    rng = np.random.default_rng([seed, 2])
    n = int(rng.integers(crowd.cameras[0], crowd.cameras[1] + 1))
    angles = 2 * np.pi * (rng.uniform() + np.arange(n) + rng.uniform(-0.4, 0.4, n)) / n
    distances = rng.uniform(*crowd.distance_m, n)
    heights = rng.uniform(*crowd.height_m, n)
    focals = FOCAL * (crowd.width / WIDTH) * rng.uniform(*crowd.zoom, n)
    counts = np.where(rng.uniform(size=n) < crowd.lone_fraction, 1,
                      rng.integers(crowd.burst[0], crowd.burst[1] + 1, n))
    rates = rng.uniform(*crowd.rates_hz, n)
    counts = np.minimum(counts, 1 + np.floor(crowd.window * rates).astype(int))  # in the window
    starts = rng.uniform(0, 1, n) * (crowd.window - (counts - 1) / rates)
    aims = np.array(LOOK_AT) + rng.normal(0, crowd.aim_m, (n, 3))
    shots = []
    for a, r, z, f, count, rate, start, aim in zip(angles, distances, heights, focals, counts,
                                                    rates, starts, aims, strict=True):
        base = np.array([r * np.cos(a), r * np.sin(a), z])
        shots.append(handheld(rng, start + np.arange(count) / rate, base, look_at(base, aim),
                              shake_m=crowd.shake_m, shake_deg=crowd.shake_deg, f=f,
                              width=crowd.width, height=crowd.height))
    return shots


def render_frames(images: Path, seed: int, mode: FieldSettings | CrowdSettings | None = None
                  ) -> tuple[dict[str, np.ndarray], list[RenderCamera]]:
    """Render every camera's frames as JPEGs under ``images/cam<c>/<k>.jpg``; returns the truth
    per image in name order (names, stream, frame, t, X, visible fraction; in field and crowd
    mode also the stream's frame rate, NaN for a lone photo) and the camera of each image."""
    rng = np.random.default_rng(seed)
    quads = room(rng)
    if mode is None:
        shots = demo_shots()
    else:
        shots = (field_shots if isinstance(mode, FieldSettings) else crowd_shots)(mode, seed)
    ss = SUPERSAMPLING if mode is None else mode.supersampling
    colours = marker_rgb()
    # Full-resolution chroma: 4:2:0 subsampling doubles the marker detection error.
    jpeg = [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY,
            cv2.IMWRITE_JPEG_SAMPLING_FACTOR, cv2.IMWRITE_JPEG_SAMPLING_FACTOR_444]
    rows = []
    for c, frames in enumerate(shots):
        (images / f"cam{c}").mkdir(parents=True, exist_ok=True)
        rate = 1 / (frames[1][0] - frames[0][0]) if len(frames) > 1 else np.nan
        seen = None
        for k, (t, cam) in enumerate(frames):
            if cam is not seen:  # a static camera renders the room once
                rays = cam.rays(ss)
                static, depth = render_static(quads, cam, rays)
                seen = cam
            X = marker_positions(t)
            img, fraction = render_markers(static, depth, rays, cam, X, colours)
            img = downsample(img, ss) * 255
            img += rng.normal(0, NOISE_SIGMA, img.shape)
            name = f"cam{c}/{k:03d}.jpg"
            bgr = np.clip(img + 0.5, 0, 255).astype(np.uint8)[..., ::-1]
            cv2.imwrite(str(images / name), bgr, jpeg)
            rows.append((name, c, k, t, X, fraction, rate, cam))
        logger.info("rendered camera %d (%d frames)", c, len(frames))
    rows.sort(key=lambda r: r[0])
    truth = {
        "image_names": np.array([r[0] for r in rows]),
        "stream": np.array([r[1] for r in rows], np.int64),
        "frame": np.array([r[2] for r in rows], np.int64),
        "t_true": np.array([r[3] for r in rows]),
        "X_true": np.stack([r[4] for r in rows]),
        "visible_fraction": np.stack([r[5] for r in rows]),
    }
    if mode is not None:
        truth["frame_rate"] = np.array([r[6] for r in rows])
    return truth, [r[7] for r in rows]


def write_keypoints(path: Path, images: Path, names: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Detect the markers in the written JPEGs and write ``image,point_id,x,y,score`` rows.

    Returns the detections (N, P, 2) (NaN = not found) and scores (N, P).
    """
    found = np.full((len(names), len(MARKER_HUES), 2), np.nan)
    scores = np.zeros((len(names), len(MARKER_HUES)))
    with open(path, "w", newline="") as f:
        out = csv.writer(f)
        out.writerow(["image", "point_id", "x", "y", "score"])
        for n, name in enumerate(names):
            found[n], scores[n] = detect_markers(cv2.imread(str(images / name)))
            for p in np.flatnonzero(np.isfinite(found[n, :, 0])):
                out.writerow([name, p, f"{found[n, p, 0]:.3f}", f"{found[n, p, 1]:.3f}",
                              f"{scores[n, p]:.3f}"])
    return found, scores


def main(out: Path, *, seed: int = 0, overwrite: bool = False,
         field: FieldSettings | None = None, crowd: CrowdSettings | None = None) -> Path:
    """Build the demo workspace at ``out`` (with ``field``, a field workspace: handheld
    cameras at their own rates; with ``crowd``, a crowd workspace: lone photos and short
    bursts from all around); returns ``out``."""
    if field is not None and crowd is not None:
        raise ValueError("field and crowd mode exclude each other")
    mode = field or crowd
    out = Path(out)
    if out.exists() and not overwrite:
        logger.info("%s exists, pass overwrite=True to rebuild it", out)
        return out
    start = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        stage = Path(tmp) / "demo"
        images = stage / "images"
        truth, views = render_frames(images, seed, mode)
        names = [str(n) for n in truth["image_names"]]
        rendered = time.perf_counter()
        intrinsics = {n: (v.f, v.cx, v.cy, v.k) for n, v in zip(names, views, strict=True)}
        shared = set(intrinsics.values())
        rec = sfm_model(images, Path(tmp), seed, shared.pop() if len(shared) == 1 else intrinsics)
        mapped = time.perf_counter()

        C_all = np.stack([v.C for v in views])
        align_to_truth(rec, names, C_all)
        registered = {rec.image(i).name: rec.image(i) for i in rec.reg_image_ids()}
        keep = np.array([n in registered for n in names])
        truth = {k: v[keep] for k, v in truth.items()}
        views = [v for v, kept in zip(views, keep, strict=True) if kept]
        names = [str(n) for n in truth["image_names"]]
        R_true = np.stack([v.R for v in views])
        C_true = C_all[keep]
        R_est = np.stack([registered[n].cam_from_world().rotation.matrix() for n in names])
        C_est = np.stack([registered[n].projection_center() for n in names])
        (stage / "sparse" / "0").mkdir(parents=True)
        without_unused_points2D(rec, None if mode is None else mode.max_points3D).write(
            stage / "sparse" / "0")

        found, scores = write_keypoints(stage / "keypoints.csv", images, truth["image_names"])
        x_true = np.stack([v.project(X) for v, X in zip(views, truth["X_true"],
                                                        strict=True)]) - 0.5
        x_true[truth["visible_fraction"] == 0] = np.nan
        np.savez_compressed(
            stage / "ground_truth.npz", **truth, x_true=x_true, R_true=R_true, C_true=C_true,
            camera_params=np.array([[v.f, v.cx, v.cy, v.k] for v in views]),
            marker_names=np.array(MARKER_NAMES),
        )

        err = np.linalg.norm(found - x_true, axis=2)
        x_model = np.array([[registered[n].project_point(X) for X in Xs]
                            for n, Xs in zip(names, truth["X_true"], strict=True)]) - 0.5
        model_err = np.linalg.norm(found - x_model, axis=2)
        whole = truth["visible_fraction"] > 0.99
        stats = {
            "seconds_render": rendered - start,
            "seconds_sfm": mapped - rendered,
            "seconds_total": time.perf_counter() - start,
            "images": len(keep),
            "registered": int(keep.sum()),
            "points3D": rec.num_points3D(),
            "mean_track_length": rec.compute_mean_track_length(),
            "reprojection_px": rec.compute_mean_reprojection_error(),
            "centre_error_m": np.linalg.norm(C_est - C_true, axis=1),
            "rotation_error_deg": rotation_angle_deg(R_est, R_true),
            "detections": int(np.isfinite(found[..., 0]).sum()),
            "visible": int((truth["visible_fraction"] > 0).sum()),
            "false_detections": int((np.isfinite(found[..., 0])
                                     & ~np.isfinite(x_true[..., 0])).sum()),
            "error_whole": err[whole & np.isfinite(err)],
            "error_all": err[np.isfinite(err)],
            "error_model": model_err[np.isfinite(model_err)],
            "images_bytes": sum(f.stat().st_size for f in images.rglob("*.jpg")),
        }
        if mode is not None:
            stats.update(field_stats(truth, views))
        (stage / "README.md").write_text(
            readme(stats) if mode is None else field_readme(stats, field, seed) if crowd is None
            else crowd_readme(stats, crowd, seed))
        if out.exists():
            shutil.rmtree(out)
        out.parent.mkdir(parents=True, exist_ok=True)
        shutil.copytree(stage, out)
    logger.info("wrote %s in %.0f s", out, time.perf_counter() - start)
    return out


def measured(stats: dict) -> str:
    """The README's section of the statistics measured on this build."""
    whole, every, model = stats["error_whole"], stats["error_all"], stats["error_model"]
    centre, rot = stats["centre_error_m"], stats["rotation_error_deg"]
    return "## Measured on this build\n" + "\n".join([
        f"- Generator run time: {stats['seconds_total']:.0f} s on 2 CPU cores "
        f"({stats['seconds_render']:.0f} s rendering, {stats['seconds_sfm']:.0f} s SfM); "
        f"images {stats['images_bytes'] / 1e6:.1f} MB.",
        f"- Registered images: {stats['registered']} / {stats['images']}; "
        f"3D points: {stats['points3D']}; mean track length {stats['mean_track_length']:.1f}.",
        f"- Mean reprojection error: {stats['reprojection_px']:.3f} px.",
        f"- Camera centres after alignment: mean {centre.mean() * 1000:.1f} mm, "
        f"max {centre.max() * 1000:.1f} mm; rotations: mean {rot.mean():.3f} deg, "
        f"max {rot.max():.3f} deg.",
        f"- Marker detections: {stats['detections']} of {stats['visible']} visible markers, "
        f"{stats['false_detections']} of hidden ones.",
        f"- Detection vs the true centre projected by the true camera: "
        f"median {np.median(whole):.3f} px, max {whole.max():.2f} px for the {whole.size} "
        f"wholly visible markers (silhouette > 99 % unoccluded); "
        f"median {np.median(every):.3f} px, max {every.max():.2f} px for all.",
        f"- Detection vs the true centre projected by the aligned COLMAP model (what a "
        f"reconstruction from this workspace sees): median {np.median(model):.3f} px, "
        f"max {model.max():.2f} px.",
    ]) + "\n"


def readme(stats: dict) -> str:
    """The workspace's README with the measured statistics of this build."""
    return f"""# Demo workspace: four unsynchronised cameras, eight moving markers

A rendered COLMAP workspace for `dloe-sfm demo`. Four static cameras (640x480, f = {FOCAL:g} px,
SIMPLE_RADIAL k = {RADIAL_K:g}) stand {RING_RADIUS:g} m from the centre of a textured 10 m x 10 m
room, 60 degrees apart, and each films {NUM_FRAMES} frames at {1 / FRAME_PERIOD:g} frames/s; camera
c starts c/4 of a frame period late, so no two cameras share an instant. Eight coloured spheres
(radius {MARKER_RADIUS * 100:g} cm) move through the room: a spinning rigid tetrahedron (points
0-3), a waving arm (4 shoulder, 5 elbow, 6 wrist) and a bouncing ball (7).

Made by `pipelines/make_demo_assets/pipeline.py` (numpy ray caster, then pycolmap feature
extraction with one camera per folder and the true intrinsics held fixed, exhaustive matching,
global mapping); regenerate from the repository root with

    python pipelines/make_demo_assets/pipeline.py --out assets/demo --overwrite

## Contents
- `images/cam<c>/<k>.jpg`: frame k of camera c (one folder = one stream, frame order = name order).
- `sparse/0/`: the COLMAP model (binary), moved by a similarity into the render's world frame
  (metres, z up) using the true camera centres.
- `keypoints.csv`: `image,point_id,x,y,score`, one row per detected marker. `image` is the COLMAP
  image name; `x, y` are pixels with (0, 0) = the centre of the top-left pixel (COLMAP's
  coordinates minus 0.5), distorted as in the image; `score` in [0, 1] is the detected area over
  the area of its enclosing circle (low = partly hidden, centroid likely biased).
  Detector: HSV threshold, largest connected component, saturation-weighted centroid.
- `ground_truth.npz`, rows in image-name order (registered images only): `image_names` (N,),
  `stream`, `frame` (N,), `t_true` (N,) seconds, `X_true` (N, P, 3) metres, `R_true` (N, 3, 3)
  world-to-camera, `C_true` (N, 3), `camera_params` (N, 4) = f, cx, cy, k (COLMAP pixels),
  `x_true` (N, P, 2) projected marker centres in the keypoint convention (NaN = hidden or out of
  view), `visible_fraction` (N, P) of each sphere's silhouette, `marker_names` (P,).

{measured(stats)}"""


def field_stats(truth: dict[str, np.ndarray], views: list[RenderCamera]) -> dict:
    """Per camera of a field or crowd workspace: frame rate (NaN for a lone photo), start time,
    frames, spread of the poses, distance from the room's centre, azimuth and focal length."""
    cameras = []
    for c in np.unique(truth["stream"]):
        sel = np.flatnonzero(truth["stream"] == c)
        C = np.stack([views[i].C for i in sel])
        R = np.stack([views[i].R for i in sel])
        mean_R = np.linalg.svd(R.mean(axis=0))
        mean_R = mean_R[0] @ mean_R[2]
        cameras.append({
            "camera": int(c), "rate_hz": float(truth["frame_rate"][sel[0]]),
            "start_s": float(truth["t_true"][sel].min()), "frames": len(sel),
            "centre_rms_mm": 1000 * float(np.sqrt(((C - C.mean(axis=0)) ** 2).sum(axis=1).mean())),
            "rotation_rms_deg": float(np.sqrt((rotation_angle_deg(R, mean_R[None]) ** 2).mean())),
            "distance_m": float(np.linalg.norm(C.mean(axis=0)[:2])),
            "azimuth_deg": float(np.rad2deg(np.arctan2(*C.mean(axis=0)[1::-1]))),
            "focal_px": float(views[sel[0]].f),
        })
    return {"cameras": cameras}


def field_readme(stats: dict, field: FieldSettings, seed: int) -> str:
    """The README of a field workspace with the drawn cameras and the measured statistics."""
    rows = "\n".join(
        f"| cam{c['camera']} | {c['rate_hz']:.3f} | {c['start_s'] * 1000:.0f} | {c['frames']} "
        f"| {c['centre_rms_mm']:.0f} | {c['rotation_rms_deg']:.1f} |" for c in stats["cameras"])
    f = FOCAL * field.width / WIDTH
    flags = (f"--cameras {field.cameras[0]} {field.cameras[1]} --duration {field.duration:g} "
             + ("" if field.max_points3D is None else f"--max-points3d {field.max_points3D} "))
    return f"""# Field workspace: handheld cameras at their own frame rates, eight moving markers

A rendered COLMAP workspace like `assets/demo` (same room, markers, detector and SfM), in field
mode (`FieldSettings` of `pipelines/make_demo_assets/pipeline.py`, seed {seed}):
{len(stats["cameras"])} handheld cameras ({field.width}x{field.height}, f = {f:g} px,
SIMPLE_RADIAL k = {RADIAL_K:g}) on a {field.arc_deg:g} degree arc of the {RING_RADIUS:g} m
ring, each at its own frame rate (drawn in {field.rates_hz[0]:g}-{field.rates_hz[1]:g} Hz),
starting at a random time in [0, {field.max_start:g}] s and filming until {field.duration:g} s.
Every frame has its own
pose: the base pose moved by a smooth random motion of {field.shake_m * 100:g} cm RMS per axis
(centre) and {field.shake_deg:g} degrees RMS per axis (orientation). One COLMAP camera per folder
(shared intrinsics, held fixed at the true ones), one pose per image. Made by

    python pipelines/make_demo_assets/pipeline.py --field --seed {seed} {flags}--out DIR

| camera | rate (Hz) | start (ms) | frames | centre spread RMS (mm) | rotation spread RMS (deg) |
|---|---|---|---|---|---|
{rows}

Files as in `assets/demo` (see its README); `ground_truth.npz` has in addition `frame_rate` (N,),
the frame rate of each image's camera in Hz, and `R_true`, `C_true` differ from image to image.

{measured(stats)}"""


def crowd_readme(stats: dict, crowd: CrowdSettings, seed: int) -> str:
    """The README of a crowd workspace with the drawn cameras and the measured statistics."""
    cams = stats["cameras"]
    rows = "\n".join(
        f"| cam{c['camera']} | {c['frames']} | "
        + ("lone photo" if c["frames"] == 1 else f"{c['rate_hz']:.2f}")
        + f" | {c['start_s'] * 1000:.0f} | {c['azimuth_deg']:.0f} | {c['distance_m']:.2f} "
        f"| {c['focal_px']:.0f} | {c['centre_rms_mm']:.0f} | {c['rotation_rms_deg']:.1f} |"
        for c in cams)
    lone = sum(c["frames"] == 1 for c in cams)
    f = FOCAL * (crowd.width / WIDTH)
    flags = (f"--cameras {crowd.cameras[0]} {crowd.cameras[1]} "
             f"--lone-fraction {crowd.lone_fraction:g} --burst {crowd.burst[0]} {crowd.burst[1]} "
             f"--window {crowd.window:g} "
             f"--size {crowd.width} {crowd.height} "
             + ("" if crowd.max_points3D is None else f"--max-points3d {crowd.max_points3D} "))
    lo_hi = {key: "-".join(f"{v:g}" for v in getattr(crowd, key))
             for key in ("distance_m", "height_m", "zoom", "burst", "rates_hz")}
    table_head = ("| camera | images | rate (Hz) | first image (ms) | azimuth (deg) | distance (m) "
                  "| f (px) | centre spread RMS (mm) | rotation spread RMS (deg) |")
    return f"""# Crowd workspace: lone photos and short bursts from all around, eight moving markers

A rendered COLMAP workspace like `assets/demo` (same room, markers, detector and SfM), in crowd
mode (`CrowdSettings` of `pipelines/make_demo_assets/pipeline.py`, seed {seed}): {len(cams)}
handheld cameras ({crowd.width}x{crowd.height}, SIMPLE_RADIAL k = {RADIAL_K:g}) all around the
room's centre (azimuths spaced evenly with a jitter), {lo_hi["distance_m"]} m from it and
{lo_hi["height_m"]} m high, each aimed at the centre moved by {crowd.aim_m * 100:g} cm RMS per
axis, each with its own focal length ({lo_hi["zoom"]} x {f:g} px). {lone} of them took a lone
photo, the others a burst of {lo_hi["burst"]} images at {lo_hi["rates_hz"]} Hz, all within
{crowd.window:g} s (a burst cut to what fits), the first image of each at a random time. Every
image has its own pose: the camera's pose moved by a smooth random motion of
{crowd.shake_m * 100:g} cm RMS per axis (centre) and {crowd.shake_deg:g} degrees RMS per axis
(orientation). One COLMAP camera per folder (its true
intrinsics, held fixed), one pose per image: a folder with one image is a lone photo, the others
are streams. Made by

    python pipelines/make_demo_assets/pipeline.py --crowd --seed {seed} {flags}--out DIR

{table_head}
|---|---|---|---|---|---|---|---|---|
{rows}

Files as in `assets/demo` (see its README), registered images only; `ground_truth.npz` has in
addition `frame_rate` (N,), the burst rate of each image's camera in Hz (NaN for a lone photo),
`R_true`, `C_true` differ from image to image and `camera_params` from camera to camera.

{measured(stats)}"""


if __name__ == "__main__":
    parser = argparse.ArgumentParser(allow_abbrev=False, description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("assets/demo"))
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--overwrite", action="store_true")
    modes = parser.add_mutually_exclusive_group()
    modes.add_argument("--field", action="store_true",
                       help="field mode: handheld cameras at their own rates (FieldSettings)")
    modes.add_argument("--crowd", action="store_true",
                       help="crowd mode: lone photos and short bursts from all around "
                       "(CrowdSettings)")
    parser.add_argument("--cameras", type=int, nargs=2, metavar=("MIN", "MAX"),
                        help="field / crowd mode: number of cameras drawn in [MIN, MAX] "
                        "(default 4 6 / 24 40)")
    parser.add_argument("--duration", type=float, metavar="S",
                        help="field mode: the cameras film until S seconds (default 1.2)")
    parser.add_argument("--lone-fraction", type=float, metavar="P",
                        help="crowd mode: probability of a lone photo per camera (default 0.25)")
    parser.add_argument("--burst", type=int, nargs=2, metavar=("MIN", "MAX"),
                        help="crowd mode: images of a burst drawn in [MIN, MAX] (default 2 5)")
    parser.add_argument("--window", type=float, metavar="S",
                        help="crowd mode: every image in [0, S] seconds (default 3)")
    parser.add_argument("--size", type=int, nargs=2, metavar=("W", "H"),
                        help="field / crowd mode: image size (default 480 360; f scales with W)")
    parser.add_argument("--max-points3d", type=int, metavar="M",
                        help="field / crowd mode: write only the M 3D points of the longest "
                        "tracks")
    args = parser.parse_args()
    logging.basicConfig(format="[%(asctime)s %(name)s %(levelname)s] %(message)s",
                        datefmt="%Y/%m/%d %H:%M:%S", level=logging.INFO)
    given = {key: value for key, value in (
        ("cameras", args.cameras and tuple(args.cameras)), ("duration", args.duration),
        ("lone_fraction", args.lone_fraction), ("burst", args.burst and tuple(args.burst)),
        ("window", args.window),
        ("width", args.size and args.size[0]), ("height", args.size and args.size[1]),
    ) if value is not None}
    field = FieldSettings(**given, max_points3D=args.max_points3d) if args.field else None
    crowd = CrowdSettings(**given, max_points3D=args.max_points3d) if args.crowd else None
    main(args.out, seed=args.seed, overwrite=args.overwrite, field=field, crowd=crowd)
