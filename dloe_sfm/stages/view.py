"""Play a ``reconstruct`` output folder in open3d's window: the points and skeleton image by
image in estimated order, around the static COLMAP points."""

from __future__ import annotations

import argparse
import ctypes
import ctypes.util
import logging
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..columns import point_colors
from ..errors import InputError
from ..io import NpzReader, atomic_path, check_output

logger = logging.getLogger("dloe_sfm")

UP = {"x": (1, 0, 0), "y": (0, 1, 0), "z": (0, 0, 1),
      "-x": (-1, 0, 0), "-y": (0, -1, 0), "-z": (0, 0, -1)}
# GLFW key codes (open3d's key callbacks)
KEY_SPACE, KEY_RIGHT, KEY_LEFT, KEY_Q = 32, 262, 263, ord("Q")


@dataclass(frozen=True)
class Sequence:
    """A reconstruct output as read back: X (N, P, 3) (NaN = none), order (N,) image indices
    by estimated time, image_names (N,), events (N,), edges (E, 2) columns of X, colors (P, 3)
    uint8, observed (N, P) bool, subject_id (P,) (several people) or None, static_xyz (M, 3),
    static_rgb (M, 3) uint8 or None."""

    X: np.ndarray
    order: np.ndarray
    image_names: np.ndarray
    events: np.ndarray
    edges: np.ndarray
    colors: np.ndarray
    observed: np.ndarray | None
    subject_id: np.ndarray | None
    static_xyz: np.ndarray
    static_rgb: np.ndarray | None


def load_sequence(out: Path) -> Sequence:
    """Read ``out/trajectories.npz`` and ``out/static.ply`` (docs/interfaces.md, "Reconstruct
    outputs")."""
    import open3d as o3d

    out = Path(out)
    if not out.is_dir():
        raise InputError(f"{out}: no such folder (a `dloe-sfm reconstruct` output folder)")
    path = out / "trajectories.npz"
    if not path.is_file():
        raise InputError(f"{out}: no trajectories.npz in it: not a `dloe-sfm reconstruct` "
                         "output folder")
    with NpzReader(path) as npz:
        missing = [k for k in ("X", "order", "image_names", "events") if k not in npz.files]
        if missing:
            raise InputError(f"{path}: missing {', '.join(missing)}")
        arrays = {k: npz.read(k, "U") if k == "image_names" else npz.read(k)
                  for k in ("X", "order", "image_names", "events", "edges", "point_id",
                            "observed", "subject_id") if k in npz.files}
    X = np.asarray(arrays["X"], dtype=np.float64)
    if X.ndim != 3 or X.shape[2] != 3 or X.shape[0] == 0:
        raise InputError(f"{path}: X has shape {X.shape}, expected (N, P, 3) with N > 0")
    n, p = X.shape[:2]
    order = np.asarray(arrays["order"])
    if order.shape != (n,) or not np.array_equal(np.sort(order), np.arange(n)):
        raise InputError(f"{path}: order is not a permutation of the {n} images")
    edges = np.asarray(arrays.get("edges", np.zeros((0, 2))), dtype=np.int64).reshape(-1, 2)
    if edges.size and (edges.min() < 0 or edges.max() >= p):
        raise InputError(f"{path}: edges refer to points outside 0..{p - 1}")
    point_id = np.asarray(arrays.get("point_id", np.arange(p)), dtype=np.int64)
    static_xyz, static_rgb = np.zeros((0, 3)), None
    if (out / "static.ply").is_file():
        cloud = o3d.io.read_point_cloud(str(out / "static.ply"))
        static_xyz = np.asarray(cloud.points)
        if cloud.has_colors():
            static_rgb = np.round(np.asarray(cloud.colors) * 255).astype(np.uint8)
    return Sequence(X=X, order=order, image_names=np.asarray(arrays["image_names"]).astype(str),
                    events=np.asarray(arrays["events"]), edges=edges,
                    colors=point_colors(int(point_id.max()) + 1)[point_id],
                    observed=arrays.get("observed"), subject_id=arrays.get("subject_id"),
                    static_xyz=static_xyz, static_rgb=static_rgb)


def write_gif(seq: Sequence, path: Path, *, fps: float, up: str) -> Path:
    """The animation of ``viz.animate`` from a read-back output."""
    from .. import viz

    return viz.animate(seq.X, seq.order, path, image_names=seq.image_names, events=seq.events,
                       edges=seq.edges, colors=seq.colors, subject_id=seq.subject_id,
                       observed=seq.observed, static_xyz=seq.static_xyz,
                       static_rgb=seq.static_rgb, up=np.array(UP[up], dtype=np.float64), fps=fps)


def display_problem() -> str | None:
    """Why no window can open here, or None. Linux only (elsewhere there is a desktop): no
    ``DISPLAY`` / ``WAYLAND_DISPLAY``, a Wayland socket that is not there, or an X server that
    does not answer (asked through libX11 when it is installed). open3d checks none of this:
    it falls back to an invisible offscreen window and would play to nobody."""
    if not sys.platform.startswith("linux"):
        return None
    wayland, x11 = os.environ.get("WAYLAND_DISPLAY"), os.environ.get("DISPLAY")
    if not (wayland or x11):
        return "no display to open a window on"
    if wayland:
        socket = Path(os.environ.get("XDG_RUNTIME_DIR", "/run/user/nobody"), wayland)
        if socket.exists():
            return None
        if not x11:
            return f"no display to open a window on (no Wayland socket {socket})"
    library = ctypes.util.find_library("X11")
    if library is None:
        return None
    xlib = ctypes.CDLL(library)
    xlib.XOpenDisplay.argtypes, xlib.XOpenDisplay.restype = [ctypes.c_char_p], ctypes.c_void_p
    xlib.XCloseDisplay.argtypes = [ctypes.c_void_p]
    handle = xlib.XOpenDisplay(None)
    if not handle:
        return f"cannot connect to the X display {x11}"
    xlib.XCloseDisplay(handle)
    return None


def _output_file(path: Path, option: str, magic: bytes, *, overwrite: bool,
                 protected: list[Path]) -> Path:
    """Check the image file an option writes: its suffix is the format; an existing one is
    only replaced with ``overwrite`` and when it is an image of that format (``magic``)."""
    suffix = {b"GIF8": ".gif", b"\x89PNG": ".png"}[magic]
    if path.suffix.lower() != suffix:
        raise InputError(f"{path}: {option} needs a file name ending in {suffix}")
    if path.is_file():
        with open(path, "rb") as f:
            if f.read(len(magic)) != magic:
                raise InputError(f"{path}: exists and is not a {suffix} image, never replaced; "
                                 f"choose another {option} file")
        if not overwrite:
            raise InputError(f"{path}: output file exists (use --overwrite to replace it)")
        return path
    return check_output(path, protected=protected, kind="file")


def _no_window(out: Path, reason: str) -> InputError:
    gif = out / "plots" / "animation.gif"
    where = (f"the animation is in {gif}" if gif.is_file() else
             f"write the animation with `dloe-sfm view {out} --save-gif FILE.gif`")
    return InputError(f"{reason}; {where}")


class _Player:
    """open3d callbacks: advance at ``fps``, space = pause, arrows = step, Q = quit."""

    def __init__(self, vis, seq: Sequence, *, fps: float, max_frames: int | None,
                 screenshot: Path | None):
        import open3d as o3d

        from .. import viz

        self.o3d, self.vis, self.seq = o3d, vis, seq
        self.period, self.max_frames, self.screenshot = 1.0 / fps, max_frames, screenshot
        self.rank, self.shown, self.paused, self.next_time = 0, 0, False, 0.0
        centre, half = viz.scene_box(seq.X)
        self.centre, self.half = centre, half
        sphere = o3d.geometry.TriangleMesh.create_sphere(radius=0.03 * half, resolution=8)
        self.sphere_v = np.asarray(sphere.vertices)
        self.sphere_t = np.asarray(sphere.triangles)
        self.points = o3d.geometry.TriangleMesh()
        self.bones = o3d.geometry.LineSet()

    def _frame_geometry(self) -> None:
        """Spheres at the current image's points (darker when estimated, not detected) and
        its skeleton."""
        o3d, seq = self.o3d, self.seq
        i = int(seq.order[self.rank])
        X = seq.X[i]
        ok = np.flatnonzero(np.isfinite(X).all(axis=1))
        shade = np.ones(len(X)) if seq.observed is None else np.where(seq.observed[i], 1.0, 0.45)
        nv = len(self.sphere_v)
        self.points.vertices = o3d.utility.Vector3dVector(
            (X[ok, None, :] + self.sphere_v[None]).reshape(-1, 3))
        self.points.triangles = o3d.utility.Vector3iVector(
            (self.sphere_t[None] + nv * np.arange(ok.size)[:, None, None]).reshape(-1, 3))
        rgb = seq.colors[ok] / 255.0 * shade[ok, None]
        self.points.vertex_colors = o3d.utility.Vector3dVector(np.repeat(rgb, nv, axis=0))
        self.points.compute_vertex_normals()
        edges = seq.edges[np.isfinite(X[seq.edges]).all(axis=(1, 2))] if seq.edges.size else \
            seq.edges
        self.bones.points = o3d.utility.Vector3dVector(np.nan_to_num(X))
        self.bones.lines = o3d.utility.Vector2iVector(edges.astype(np.int32))
        self.bones.colors = o3d.utility.Vector3dVector(seq.colors[edges[:, 0]] / 255.0)

    def add_geometry(self, up: np.ndarray) -> None:
        """The points' cube (``viz.scene_box``, light grey: the view fits it), the first
        frame, static points in a cube three times as large, the view."""
        from .. import viz

        o3d, seq, vis = self.o3d, self.seq, self.vis
        cube = o3d.geometry.LineSet.create_from_axis_aligned_bounding_box(
            o3d.geometry.AxisAlignedBoundingBox(self.centre - self.half, self.centre + self.half))
        cube.paint_uniform_color((0.8, 0.8, 0.8))
        vis.add_geometry(cube)
        self._frame_geometry()
        vis.add_geometry(self.points, reset_bounding_box=False)
        if seq.edges.size:
            vis.add_geometry(self.bones, reset_bounding_box=False)
        xyz, rgb = viz.crop_static(seq.static_xyz, seq.static_rgb, self.centre, 3 * self.half,
                                   max_points=200_000)
        if len(xyz):
            cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(xyz))
            if rgb is not None:
                cloud.colors = o3d.utility.Vector3dVector(rgb / 255.0)
            vis.add_geometry(cloud, reset_bounding_box=False)
        vis.get_render_option().point_size = 2.0
        # matplotlib's default 3D view (azimuth -60 deg, elevation 18 deg) about ``up``
        side = np.eye(3)[(int(np.argmax(np.abs(up))) + 1) % 3]
        side2 = np.cross(up, side)
        az, el = np.radians(-60.0), np.radians(18.0)
        front = np.cos(el) * (np.cos(az) * side + np.sin(az) * side2) + np.sin(el) * up
        view = vis.get_view_control()
        view.set_lookat(self.centre)
        view.set_up(up)
        view.set_front(front)
        view.set_zoom(1.0)

    def show(self, rank: int) -> str:
        """Draw the image of estimated rank ``rank`` (wrapping around); returns its caption."""
        self.rank = rank % self.seq.order.size
        self._frame_geometry()
        self.vis.update_geometry(self.points)
        if self.seq.edges.size:
            self.vis.update_geometry(self.bones)
        i = int(self.seq.order[self.rank])
        return (f"rank {self.rank} / {self.seq.order.size - 1}: {self.seq.image_names[i]} "
                f"(event {int(self.seq.events[i])})")

    def tick(self, vis) -> bool:
        now = time.monotonic()
        if self.paused or now < self.next_time:
            return False
        self.next_time = now + self.period
        self.shown += 1
        if self.max_frames is not None and self.shown > self.max_frames:
            self.quit(vis)
            return False
        if self.shown > 1:
            logger.debug("%s", self.show(self.rank + 1))
        return True

    def toggle(self, vis) -> bool:
        self.paused = not self.paused
        logger.info("%s", "paused (arrows: step, space: play)" if self.paused else "playing")
        return False

    def step(self, delta: int):
        def callback(vis) -> bool:
            self.paused = True
            logger.info("%s", self.show(self.rank + delta))
            return True
        return callback

    def quit(self, vis) -> bool:
        if self.screenshot is not None:
            with atomic_path(self.screenshot) as tmp:
                vis.capture_screen_image(str(tmp), True)
        vis.close()
        return False


def main(out: Path, *, fps: float = 10.0, up: str = "z", save_gif: Path | None = None,
         overwrite: bool = False, max_frames: int | None = None,
         screenshot: Path | None = None) -> Path | None:
    """Play ``out`` (a ``reconstruct`` output folder) in an open3d window, looping, until the
    window is closed (or after ``max_frames`` frames), with a PNG of the last view at
    ``screenshot``; with ``save_gif``, write the animation there instead (no window) and
    return its path. ``up``: the world axis drawn vertical (``UP``). No display, or a window
    open3d cannot create: InputError pointing to ``out/plots/animation.gif``."""
    out = Path(out)
    if not (fps > 0 and np.isfinite(fps)):
        raise InputError(f"--fps: must be a positive number, got {fps}")
    if max_frames is not None and max_frames < 1:
        raise InputError(f"--frames: must be at least 1, got {max_frames}")
    if up not in UP:
        raise InputError(f"--up: one of {', '.join(UP)}, got {up!r}")
    seq = load_sequence(out)
    inputs = [out / "trajectories.npz", out / "static.ply"]
    if save_gif is not None:
        _output_file(Path(save_gif), "--save-gif", b"GIF8", overwrite=overwrite, protected=inputs)
        return write_gif(seq, Path(save_gif), fps=fps, up=up)
    if screenshot is not None:
        _output_file(Path(screenshot), "--screenshot", b"\x89PNG", overwrite=overwrite,
                     protected=inputs)
    problem = display_problem()
    if problem is not None:
        raise _no_window(out, problem)
    import open3d as o3d

    vis = o3d.visualization.VisualizerWithKeyCallback()
    if not vis.create_window(window_name=f"dloe-sfm view {out}", width=1024, height=768):
        raise _no_window(out, "open3d could not open a window (no OpenGL context on display "
                              f"{os.environ.get('DISPLAY') or os.environ.get('WAYLAND_DISPLAY')})")
    try:
        player = _Player(vis, seq, fps=fps, max_frames=max_frames, screenshot=screenshot)
        player.add_geometry(np.array(UP[up], dtype=np.float64))
        vis.register_animation_callback(player.tick)
        vis.register_key_callback(KEY_SPACE, player.toggle)
        vis.register_key_callback(KEY_RIGHT, player.step(1))
        vis.register_key_callback(KEY_LEFT, player.step(-1))
        vis.register_key_callback(KEY_Q, player.quit)
        logger.info("%s: %d images; space: pause / play, arrows: step, Q: quit", out,
                    seq.order.size)
        vis.run()
    finally:
        vis.destroy_window()
    return None


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("out", type=Path, help="a `dloe-sfm reconstruct` output folder")
    parser.add_argument("--fps", type=float, default=10.0, help="images a second (default 10)")
    parser.add_argument("--up", choices=list(UP), default="z",
                        help="world axis drawn vertical (default z)")
    parser.add_argument("--save-gif", type=Path, metavar="FILE.gif",
                        help="write the animation to this GIF instead of opening a window")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace an existing GIF at --save-gif (PNG at --screenshot)")
    parser.add_argument("--frames", type=int, metavar="N",
                        help="close the window after N frames (default: play until closed)")
    parser.add_argument("--screenshot", type=Path, metavar="FILE.png",
                        help="save the window's last view as a PNG when it closes")


def run(args: argparse.Namespace) -> int:
    main(args.out, fps=args.fps, up=args.up, save_gif=args.save_gif, overwrite=args.overwrite,
         max_frames=args.frames, screenshot=args.screenshot)
    return 0


if __name__ == "__main__":
    from ..cli import run_stage

    sys.exit(run_stage(__name__))
