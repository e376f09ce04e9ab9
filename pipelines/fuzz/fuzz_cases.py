"""Cases of the CLI fuzz harness (``pipeline.py``): shared inputs, forged files, and every
hostile or odd input with its expected outcome.

``build_cases()`` lists them; a case's ``setup(Ctx)`` fills its folder and returns the ``Run``
(CLI arguments, output, how to check it). Nothing is written until a setup runs.
"""

from __future__ import annotations

import csv
import hashlib
import io
import json
import os
import pickle
import shutil
import signal
import struct
import subprocess
import sys
import threading
import zipfile
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
DEMO = REPO / "assets" / "demo"
MOCAP = REPO / "assets" / "mocap" / "walking_1.npz"
SIMULATE_ARGS = ["--duration", "1", "--rate", "8", "--num-streams", "3"]  # 24 images x 28 points
FAST = ["--set", "robust_loss=none", "--set", "max_iterations=30"]  # valid solves in seconds


# --------------------------------------------------------------------------------------------
# shared inputs


class Base:
    """Inputs shared by the cases, each built once on first use (thread-safe): the demo
    workspace (binary and text model), its keypoints per image, a simulated capture, a result
    of it, a 2 GB-zeros capture."""

    def __init__(self, root: Path) -> None:
        self.root = root
        self._lock = threading.RLock()  # builds call each other
        self._built: dict[str, object] = {}

    def _once(self, key: str, build: Callable[[], object]):
        with self._lock:
            if key not in self._built:
                self._built[key] = build()
            return self._built[key]

    def demo(self) -> Path:
        def build() -> Path:
            dst = self.root / "demo"
            shutil.copytree(DEMO, dst)
            if tree_hash(dst) != tree_hash(DEMO):
                raise RuntimeError(f"{dst}: copy of {DEMO} differs")
            return dst
        return self._once("demo", build)

    def demo_txt(self) -> Path:
        """The demo workspace with its model as cameras/images/points3D.txt."""
        def build() -> Path:
            import pycolmap

            src = self.demo()
            dst = self.root / "demo_txt"
            shutil.copytree(src, dst)
            model = dst / "sparse" / "0"
            for f in model.iterdir():
                f.unlink()
            pycolmap.Reconstruction(str(src / "sparse" / "0")).write_text(str(model))
            return dst
        return self._once("demo_txt", build)

    def points(self) -> dict[str, np.ndarray]:
        """The demo's keypoints.csv as {image: (8, 3) x, y, score}, NaN / 0 = missing."""
        def build() -> dict[str, np.ndarray]:
            points: dict[str, np.ndarray] = {}
            with open(DEMO / "keypoints.csv", newline="") as f:
                for row in csv.DictReader(f):
                    arr = points.setdefault(row["image"], np.tile([np.nan, np.nan, 0.0], (8, 1)))
                    arr[int(row["point_id"])] = [float(row["x"]), float(row["y"]),
                                                 float(row["score"])]
            return points
        return self._once("points", build)

    def capture(self) -> Path:
        def build() -> Path:
            path = self.root / "capture.npz"
            cli(["simulate", str(MOCAP), "--out", str(path), *SIMULATE_ARGS])
            return path
        return self._once("capture", build)

    def arrays(self) -> dict[str, np.ndarray]:
        def build() -> dict[str, np.ndarray]:
            with np.load(self.capture()) as d:
                return {k: d[k] for k in d.files}
        return dict(self._once("arrays", build))

    def result(self) -> Path:
        def build() -> Path:
            path = self.root / "result.npz"
            cli(["solve", str(self.capture()), "--out", str(path), *FAST])
            return path
        return self._once("result", build)

    def zeros_2gb(self) -> Path:
        """The capture plus a 2 GB float64 zero array in a key nobody reads (~2 MB on disk)."""
        def build() -> Path:
            path = self.root / "zeros_2gb.npz"
            shutil.copy(self.capture(), path)
            count = 2 * 10**9 // 8
            chunk = bytes(2**24)
            with zipfile.ZipFile(path, "a", compression=zipfile.ZIP_DEFLATED) as zf, \
                    zf.open("padding.npy", "w", force_zip64=True) as f:
                f.write(npy_header("<f8", (count,)))
                left = count * 8
                while left:
                    f.write(chunk[:min(left, len(chunk))])
                    left -= min(left, len(chunk))
            return path
        return self._once("zeros_2gb", build)


def cli(argv: list[str]) -> None:
    """Run the CLI to build a shared input; raise with its stderr when it fails."""
    proc = subprocess.run([sys.executable, "-m", "dloe_sfm.cli", *argv], capture_output=True,
                          text=True, env=child_env())
    if proc.returncode != 0:
        raise RuntimeError(f"dloe-sfm {' '.join(argv)}: exit {proc.returncode}: "
                           f"{proc.stderr.strip().splitlines()[-1:]}")


def child_env() -> dict[str, str]:
    """One BLAS thread per run (the cases run in parallel); same for reruns."""
    env = dict(os.environ)
    env.update(OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", MKL_NUM_THREADS="1")
    return env


# --------------------------------------------------------------------------------------------
# file forging


def npy_header(descr: str, shape: tuple[int, ...]) -> bytes:
    """An .npy version 1.0 header declaring ``descr`` and ``shape`` (no data)."""
    text = repr({"descr": descr, "fortran_order": False, "shape": shape})
    pad = 64 - (10 + len(text) + 1) % 64
    text = text + " " * pad + "\n"
    return b"\x93NUMPY\x01\x00" + struct.pack("<H", len(text)) + text.encode("latin1")


def save(path: Path, arrays: dict[str, np.ndarray], *, compressed: bool = True) -> Path:
    """An .npz of ``arrays`` (object arrays allowed: they are pickled, as a hostile file would)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "wb") as f:
        (np.savez_compressed if compressed else np.savez)(f, **arrays)
    return path


def member_span(path: Path, name: str) -> tuple[int, int]:
    """Byte offset and length of member ``name``'s (possibly compressed) data in a zip file."""
    with zipfile.ZipFile(path) as zf:
        info = zf.getinfo(name)
    with open(path, "rb") as f:
        f.seek(info.header_offset + 26)
        name_len, extra_len = struct.unpack("<HH", f.read(4))
    return info.header_offset + 30 + name_len + extra_len, info.compress_size


def flip_bits(path: Path, offsets: list[int], mask: int = 0x01) -> None:
    data = bytearray(path.read_bytes())
    for o in offsets:
        data[o] ^= mask
    path.write_bytes(bytes(data))


def lying_npz(path: Path, arrays: dict[str, np.ndarray], key: str,
              shape: tuple[int, ...]) -> Path:
    """``arrays`` with member ``key`` replaced by a header declaring ``shape`` float64 and 16
    bytes of data."""
    save(path, {k: v for k, v in arrays.items() if k != key})
    with zipfile.ZipFile(path, "a", compression=zipfile.ZIP_DEFLATED) as zf:
        zf.writestr(f"{key}.npy", npy_header("<f8", shape) + bytes(16))
    return path


def png_header(width: int, height: int) -> bytes:
    """A PNG signature and IHDR chunk (valid CRC) claiming width x height, then an empty IDAT."""
    import zlib

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(
            ">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    ihdr = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr)
            + chunk(b"IDAT", zlib.compress(b"\x00" * 1000)) + chunk(b"IEND", b""))


def nested(depth: int) -> str:
    return "[" * depth + "]" * depth


# --------------------------------------------------------------------------------------------
# cases


@dataclass
class Run:
    """What a case runs: CLI arguments, the output it may write and how to check it."""

    argv: list[str]
    out: Path | None = None
    kind: str | None = None  # "dir" (reconstruct / demo), "npz" (solve / simulate), "json"
    replaced: bool = False  # out exists before and may be replaced (our own previous output)
    pre: list[list[str]] = field(default_factory=list)  # CLI runs that make the inputs
    cwd: Path | None = None
    extra_inputs: list[Path] = field(default_factory=list)  # inputs outside the case folder
    interrupt: int | None = None  # signal sent to the run once its output's temp sibling appears
    pre_kill: list[str] | None = None  # a run SIGKILLed that way first (leaves its temp behind)


@dataclass
class Case:
    name: str
    expect: str  # "error" (exit 2), "ok" (exit 0), "either" (0 or 2: the issue leaves it open)
    # or "sigterm" (exit 143 after SIGTERM, one line)
    group: str
    setup: Callable[[Ctx], Run]
    quick: bool = False  # in the --quick subset
    rerun: bool = False  # rerun into a fresh --out and compare the arrays


@dataclass
class Ctx:
    """A case's folder and helpers to fill it."""

    dir: Path
    base: Base

    def ws(self, model: str = "bin", name: str = "ws") -> Path:
        src = self.base.demo() if model == "bin" else self.base.demo_txt()
        dst = self.dir / name
        shutil.copytree(src, dst, symlinks=True)
        return dst

    def capture(self, name: str = "capture.npz", *, drop: tuple[str, ...] = (),
                compressed: bool = True, **changes) -> Path:
        arrays = {k: v for k, v in self.base.arrays().items() if k not in drop}
        arrays.update(changes)
        return save(self.dir / name, arrays, compressed=compressed)

    def write(self, name: str, content: bytes | str) -> Path:
        path = self.dir / name
        path.parent.mkdir(parents=True, exist_ok=True)
        if isinstance(content, str):
            path.write_bytes(content.encode("utf-8"))
        else:
            path.write_bytes(content)
        return path

    def json(self, name: str, obj) -> Path:
        return self.write(name, json.dumps(obj))

    def mocap(self, name: str = "mocap.npz", **changes) -> Path:
        with np.load(MOCAP) as d:
            arrays = {k: d[k] for k in d.files}
        arrays.update(changes)
        return save(self.dir / name, arrays)


def rec(ws: Path, kp: Path | None, fmt: str, out: Path, *more: str) -> list[str]:
    keypoints = [] if kp is None else ["--keypoints", str(kp)]
    return ["reconstruct", str(ws), *keypoints, "--format", fmt, "--out", str(out), *more]


def csv_text(points: dict[str, np.ndarray], names: dict[str, str] | None = None) -> str:
    lines = ["image,point_id,x,y,score"]
    for image, arr in points.items():
        name = (names or {}).get(image, image)
        for j, (x, y, s) in enumerate(arr.tolist()):
            if s > 0:
                lines.append(f"{name},{j},{x!r},{y!r},{s!r}")
    return "\n".join(lines) + "\n"


def openpose_files(c: Ctx, folder: str = "openpose") -> Path:
    for image, arr in c.base.points().items():
        values = np.where(arr[:, 2:] > 0, arr, 0.0).ravel().tolist()
        c.json(f"{folder}/{Path(image).with_suffix('')}_keypoints.json",
               {"version": 1.3, "people": [{"person_id": [-1], "pose_keypoints_2d": values}]})
    return c.dir / folder


def coco_doc(c: Ctx) -> dict:
    images, annotations = [], []
    for i, (image, arr) in enumerate(c.base.points().items()):
        images.append({"id": i + 1, "file_name": image, "width": 640, "height": 480})
        values = np.where(arr[:, 2:] > 0, arr, 0.0).ravel().tolist()
        annotations.append({"id": i + 1, "image_id": i + 1, "category_id": 1,
                            "keypoints": values, "num_keypoints": int((arr[:, 2] > 0).sum())})
    category = {"id": 1, "name": "markers", "keypoints": [f"m{j}" for j in range(8)],
                "skeleton": [[5, 6], [6, 7]]}
    return {"images": images, "annotations": annotations, "categories": [category]}


def mmpose_instances(arr: np.ndarray) -> list[dict]:
    return [{"keypoints": np.nan_to_num(arr[:, :2]).tolist(),
             "keypoint_scores": arr[:, 2].tolist(), "bbox": [[0, 0, 640, 480]],
             "bbox_score": 1.0}]


MMPOSE_META = {"dataset_name": "markers", "keypoint_id2name": {str(j): f"m{j}" for j in range(8)},
               "skeleton_links": [[4, 5], [5, 6]], "flip_pairs": []}


def mmpose_files(c: Ctx, *, meta: bool = False, folder: str = "mmpose") -> Path:
    for image, arr in c.base.points().items():
        doc = mmpose_instances(arr)
        if meta:
            doc = {"meta_info": MMPOSE_META, "instance_info": doc}
        c.json(f"{folder}/{Path(image).with_suffix('')}.json", doc)
    return c.dir / folder


def edit_line(path: Path, startswith: str, edit: Callable[[list[str]], list[str]]) -> None:
    """Apply ``edit`` to the fields of the first non-comment line of a COLMAP text file whose
    first field is ``startswith`` (any line when empty)."""
    lines = path.read_text().splitlines()
    for i, line in enumerate(lines):
        if line.startswith("#") or not line.strip():
            continue
        if not startswith or line.split()[0] == startswith:
            lines[i] = " ".join(edit(line.split()))
            break
    path.write_text("\n".join(lines) + "\n")


def edited_model(edit: Callable[[Path], None], model: str = "bin"):
    """A CSV reconstruction of a workspace whose `sparse/0` model `edit` has mangled."""
    def setup(c: Ctx) -> Run:
        ws = c.ws(model)
        edit(ws / "sparse" / "0")
        return Run(rec(ws, ws / "keypoints.csv", "csv", c.dir / "out", "--no-plots"),
                   out=c.dir / "out", kind="dir")
    return setup


def build_cases() -> list[Case]:
    """Every case (names unique); nothing is written until a case's ``setup`` runs."""
    cases: list[Case] = []

    def add(name: str, expect: str, group: str, quick: bool = False, rerun: bool = False):
        def deco(setup: Callable[[Ctx], Run]) -> Callable[[Ctx], Run]:
            cases.append(Case(name, expect, group, setup, quick=quick, rerun=rerun))
            return setup
        return deco

    _output_safety(add)
    _cameras(add)
    _corrupt_files(add)
    _hostile_npz(add)
    _evaluate_simulate(add)
    _keypoints(add)
    _options(add)
    return cases


# ---- output safety


def _output_safety(add) -> None:
    def csv_run(out_of: Callable[[Path, Ctx], Path], *more: str, replaced: bool = False,
                kind: str = "dir", cwd_ws: bool = False):
        def setup(c: Ctx) -> Run:
            ws = c.ws()
            out = out_of(ws, c)
            return Run(rec(ws, ws / "keypoints.csv", "csv", out, "--no-plots", *more), out=out,
                       kind=kind, replaced=replaced, cwd=ws if cwd_ws else None)
        return setup

    targets = {
        "workspace": lambda ws, c: ws,
        "model": lambda ws, c: ws / "sparse" / "0",
        "sparse": lambda ws, c: ws / "sparse",
        "images": lambda ws, c: ws / "images",
        "image_subfolder": lambda ws, c: ws / "images" / "cam0",
        "keypoints_file": lambda ws, c: ws / "keypoints.csv",
        "ground_truth_file": lambda ws, c: ws / "ground_truth.npz",
        "image_file": lambda ws, c: ws / "images" / "cam0" / "000.jpg",
        "model_file": lambda ws, c: ws / "sparse" / "0" / "images.bin",
        "images_via_dotdot": lambda ws, c: ws / "sparse" / ".." / "images",
    }
    for name, out_of in targets.items():
        quick = name in ("workspace", "model")
        add(f"out_is_{name}", "error", "output")(csv_run(out_of))
        add(f"out_is_{name}_overwrite", "error", "output", quick=quick)(
            csv_run(out_of, "--overwrite"))
    add("out_inside_images", "error", "output", quick=True)(
        csv_run(lambda ws, c: ws / "images" / "cam0" / "dloe"))
    add("out_inside_model", "error", "output")(csv_run(lambda ws, c: ws / "sparse" / "0" / "out"))
    add("out_dot_in_workspace_overwrite", "error", "output")(
        csv_run(lambda ws, c: Path("."), "--overwrite", cwd_ws=True))

    def parent_file(ws: Path, c: Ctx) -> Path:
        return c.write("notes.txt", "a user's file\n") / "out"
    add("out_parent_is_file", "error", "output", quick=True)(csv_run(parent_file))
    add("out_parent_is_keypoints_file", "error", "output")(
        csv_run(lambda ws, c: ws / "keypoints.csv" / "out"))

    def existing_file(ws: Path, c: Ctx) -> Path:
        return c.write("results.txt", "a user's file\n")
    add("out_is_existing_file", "error", "output")(csv_run(existing_file))
    add("out_is_existing_file_overwrite", "error", "output")(csv_run(existing_file, "--overwrite"))

    def symlink_to(target: str) -> Callable[[Path, Ctx], Path]:
        def out_of(ws: Path, c: Ctx) -> Path:
            link = c.dir / "link"
            link.symlink_to(ws / target if target else ws, target_is_directory=True)
            return link
        return out_of
    add("out_symlink_to_images_overwrite", "error", "output")(
        csv_run(symlink_to("images"), "--overwrite"))
    add("out_symlink_to_workspace_overwrite", "error", "output")(
        csv_run(symlink_to(""), "--overwrite"))

    def containing(ws: Path, c: Ctx) -> Path:
        return c.dir  # the case folder holds the workspace
    add("out_contains_workspace_overwrite", "error", "output")(csv_run(containing, "--overwrite"))

    def foreign(ws: Path, c: Ctx) -> Path:
        c.write("mine/thesis.tex", "\\documentclass{article}\n")
        c.write("mine/data/points.csv", "1,2,3\n")
        return c.dir / "mine"
    add("out_foreign_folder", "error", "output")(csv_run(foreign))
    add("out_foreign_folder_overwrite", "error", "output", quick=True)(
        csv_run(foreign, "--overwrite"))

    def foreign_report(ws: Path, c: Ctx) -> Path:
        c.write("mine/report.json", "{}\n")  # looks like ours, is not
        c.write("mine/thesis.tex", "\\documentclass{article}\n")
        return c.dir / "mine"
    add("out_foreign_folder_with_report_json_overwrite", "error", "output")(
        csv_run(foreign_report, "--overwrite"))

    def empty_dir(ws: Path, c: Ctx) -> Path:
        (c.dir / "empty").mkdir()
        return c.dir / "empty"
    add("out_empty_folder_overwrite", "either", "output")(
        csv_run(empty_dir, "--overwrite", replaced=True))
    add("out_inside_workspace", "ok", "output")(csv_run(lambda ws, c: ws / "dloe_out"))
    add("out_nested_new_folders", "ok", "output")(
        csv_run(lambda ws, c: c.dir / "a" / "b" / "c" / "out"))

    def previous(c: Ctx, overwrite: bool) -> Run:
        ws = c.ws()
        out = c.dir / "out"
        argv = rec(ws, ws / "keypoints.csv", "csv", out, "--no-plots")
        return Run(argv + (["--overwrite"] if overwrite else []), out=out, kind="dir",
                   replaced=overwrite, pre=[argv])
    add("out_own_previous_overwrite", "ok", "output", quick=True, rerun=True)(
        lambda c: previous(c, True))

    def killed(c: Ctx, sig: int | None) -> Run:
        ws = c.ws()
        out = c.dir / "out"
        argv = rec(ws, ws / "keypoints.csv", "csv", out)  # with plots: a long export
        if sig is None:
            return Run(argv, out=out, kind="dir", pre_kill=argv)
        return Run(argv, out=out, kind="dir", interrupt=sig)
    add("sigterm_during_export", "sigterm", "output", quick=True)(
        lambda c: killed(c, signal.SIGTERM))
    add("sigkill_during_export_then_rerun", "ok", "output")(lambda c: killed(c, None))
    add("out_own_previous_no_overwrite", "error", "output")(lambda c: previous(c, False))

    # dloe-sfm demo writes from the repository's assets/demo (checked unchanged)
    def demo(out_of: Callable[[Ctx], Path], *, pre: bool = False, replaced: bool = False):
        def setup(c: Ctx) -> Run:
            out = out_of(c)
            argv = ["demo", "--out", str(out), "--no-plots"]
            return Run(argv, out=out, kind="dir", replaced=replaced, pre=[argv] if pre else [],
                       extra_inputs=[DEMO])
        return setup
    add("demo_out_foreign_folder", "error", "output", quick=True)(
        demo(lambda c: foreign(c.dir, c)))
    add("demo_out_is_file", "error", "output")(demo(lambda c: existing_file(c.dir, c)))
    add("demo_out_parent_is_file", "error", "output")(demo(lambda c: parent_file(c.dir, c)))
    add("demo_out_own_previous", "ok", "output")(
        demo(lambda c: c.dir / "out", pre=True, replaced=True))
    add("demo_fresh_out", "ok", "output", rerun=True)(demo(lambda c: c.dir / "out"))

    def solve(out_of: Callable[[Ctx, Path], Path], *more: str, pre: bool = False,
              replaced: bool = False):
        def setup(c: Ctx) -> Run:
            cap = c.capture()
            out = out_of(c, cap)
            argv = ["solve", str(cap), "--out", str(out), *FAST]
            return Run(argv + list(more), out=out, kind="npz", replaced=replaced,
                       pre=[argv] if pre else [])
        return setup
    add("solve_out_is_capture", "error", "output", quick=True)(solve(lambda c, cap: cap))
    add("solve_out_is_capture_overwrite", "error", "output")(
        solve(lambda c, cap: cap, "--overwrite"))
    add("solve_out_is_foreign_file", "error", "output")(
        solve(lambda c, cap: c.write("notes.npz", b"my notes")))
    add("solve_out_is_folder", "error", "output")(
        solve(lambda c, cap: foreign(c.dir, c)))
    add("solve_out_is_folder_overwrite", "error", "output")(
        solve(lambda c, cap: foreign(c.dir, c), "--overwrite"))
    add("solve_out_parent_is_file", "error", "output")(
        solve(lambda c, cap: parent_file(c.dir, c)))
    add("solve_out_own_previous_overwrite", "ok", "output")(
        solve(lambda c, cap: c.dir / "result.npz", "--overwrite", pre=True, replaced=True))
    add("solve_out_own_previous_no_overwrite", "error", "output")(
        solve(lambda c, cap: c.dir / "result.npz", pre=True))
    add("solve_out_nested_new_folders", "ok", "output")(
        solve(lambda c, cap: c.dir / "a" / "b" / "result.npz"))
    add("solve_capture", "ok", "output", quick=True, rerun=True)(
        solve(lambda c, cap: c.dir / "result.npz"))

    def simulate(out_of: Callable[[Ctx, Path], Path]):
        def setup(c: Ctx) -> Run:
            mocap = c.mocap()
            out = out_of(c, mocap)
            return Run(["simulate", str(mocap), "--out", str(out), *SIMULATE_ARGS], out=out,
                       kind="npz")
        return setup
    add("simulate_out_is_mocap", "error", "output")(simulate(lambda c, m: m))
    add("simulate_out_parent_is_file", "error", "output")(
        simulate(lambda c, m: parent_file(c.dir, c)))
    add("simulate_out_is_folder", "error", "output")(simulate(lambda c, m: foreign(c.dir, c)))
    add("simulate_capture", "ok", "output", rerun=True)(simulate(lambda c, m: c.dir / "cap.npz"))

    def evaluate(out_of: Callable[[Ctx, Path, Path], Path | None]):
        def setup(c: Ctx) -> Run:
            result = c.dir / "result.npz"
            shutil.copy(c.base.result(), result)
            cap = c.capture()
            out = out_of(c, result, cap)
            return Run(["evaluate", str(result), str(cap), "--json", str(out)], out=out,
                       kind="json")
        return setup
    add("evaluate_json_is_result", "error", "output")(evaluate(lambda c, r, cap: r))
    add("evaluate_json_is_capture", "error", "output")(evaluate(lambda c, r, cap: cap))
    add("evaluate_json_parent_is_file", "error", "output")(
        evaluate(lambda c, r, cap: parent_file(c.dir, c)))
    add("evaluate_result", "ok", "output", quick=True)(
        evaluate(lambda c, r, cap: c.dir / "scores.json"))

    if hasattr(os, "geteuid") and os.geteuid() != 0:  # root writes anywhere
        def read_only(ws: Path, c: Ctx) -> Path:
            folder = c.dir / "locked"
            folder.mkdir()
            folder.chmod(0o555)
            return folder / "out"
        add("out_parent_read_only", "error", "output")(csv_run(read_only))


# ---- cameras


def _cameras(add) -> None:
    def txt_camera(param: int, value: str):
        def edit(f: list[str]) -> list[str]:
            f[4 + param] = value
            return f
        return edited_model(lambda m: edit_line(m / "cameras.txt", "", edit), "txt")

    # SIMPLE_RADIAL: f, cx, cy, k
    for name, param, value in [("negative_focal", 0, "-500"), ("zero_focal", 0, "0"),
                               ("nan_focal", 0, "nan"), ("inf_focal", 0, "inf"),
                               ("nan_principal_point", 1, "nan"), ("inf_principal_point", 2,
                                                                   "-inf"),
                               ("nan_distortion", 3, "nan")]:
        add(f"cameras_txt_{name}", "error", "cameras", quick=name == "negative_focal")(
            txt_camera(param, value))

    add("cameras_txt_unknown_model", "error", "cameras")(edited_model(
        lambda m: edit_line(m / "cameras.txt", "", lambda f: [f[0], "FISHEYE_FOO", *f[2:]]),
        "txt"))
    add("cameras_txt_missing_param", "error", "cameras")(edited_model(
        lambda m: edit_line(m / "cameras.txt", "", lambda f: f[:-1]), "txt"))
    add("cameras_txt_param_not_a_number", "error", "cameras")(edited_model(
        lambda m: edit_line(m / "cameras.txt", "", lambda f: [*f[:4], "five", *f[5:]]),
        "txt"))

    def bin_focal(value: float):
        def edit(model: Path) -> None:
            # cameras.bin: count u64, then id u32, model i32, width u64, height u64, params f64
            data = bytearray((model / "cameras.bin").read_bytes())
            data[32:40] = struct.pack("<d", value)
            (model / "cameras.bin").write_bytes(bytes(data))
        return edit
    add("cameras_bin_negative_focal", "error", "cameras")(
        edited_model(bin_focal(-500.0)))
    add("cameras_bin_zero_focal", "error", "cameras")(edited_model(bin_focal(0.0)))
    add("cameras_bin_nan_focal", "error", "cameras")(edited_model(bin_focal(float("nan"))))
    add("model_txt", "ok", "cameras", rerun=True)(edited_model(lambda m: None, "txt"))

    def capture_K(edit: Callable[[np.ndarray], None]):
        def setup(c: Ctx) -> Run:
            K = c.base.arrays()["K"].copy()
            edit(K)
            cap = c.capture(K=K)
            return Run(["solve", str(cap), "--out", str(c.dir / "r.npz"), *FAST],
                       out=c.dir / "r.npz", kind="npz")
        return setup

    def setter(index, value: float) -> Callable[[np.ndarray], None]:
        def edit(K: np.ndarray) -> None:
            K[index] = value
        return edit
    add("capture_K_negative_focal", "error", "cameras", quick=True)(
        capture_K(setter((slice(None), 0, 0), -1000.0)))
    add("capture_K_negative_focal_one_image", "error", "cameras")(
        capture_K(setter((3, 1, 1), -1000.0)))
    add("capture_K_zero_focal", "error", "cameras")(capture_K(setter((0, 0, 0), 0.0)))
    add("capture_K_nan_focal", "error", "cameras")(capture_K(setter((0, 0, 0), np.nan)))
    add("capture_K_nan_principal_point", "error", "cameras")(capture_K(setter((0, 0, 2), np.nan)))
    add("capture_K_inf_principal_point", "error", "cameras")(capture_K(setter((1, 1, 2), np.inf)))
    add("capture_K_last_row_zero", "error", "cameras")(capture_K(setter((0, 2), 0.0)))


# ---- corrupt files


def _corrupt_files(add) -> None:
    def solve_file(make: Callable[[Ctx], Path]):
        def setup(c: Ctx) -> Run:
            cap = make(c)
            return Run(["solve", str(cap), "--out", str(c.dir / "r.npz"), *FAST],
                       out=c.dir / "r.npz", kind="npz")
        return setup

    def from_capture(mangle: Callable[[bytes], bytes], compressed: bool = True):
        def make(c: Ctx) -> Path:
            path = c.capture(compressed=compressed)
            path.write_bytes(mangle(path.read_bytes()))
            return path
        return make

    add("npz_zero_bytes", "error", "corrupt", quick=True)(
        solve_file(lambda c: c.write("capture.npz", b"")))
    add("npz_truncated_half", "error", "corrupt")(
        solve_file(from_capture(lambda b: b[:len(b) // 2])))
    add("npz_truncated_10_bytes", "error", "corrupt")(solve_file(from_capture(lambda b: b[:10])))
    add("npz_missing_last_byte", "error", "corrupt")(solve_file(from_capture(lambda b: b[:-1])))
    add("npz_text", "error", "corrupt")(
        solve_file(lambda c: c.write("capture.npz", "x,K,R,C\n1,2,3,4\n")))
    add("npz_random_bytes", "error", "corrupt")(solve_file(
        lambda c: c.write("capture.npz", np.random.default_rng(0).bytes(5000))))
    add("npz_is_npy", "error", "corrupt")(solve_file(
        lambda c: c.write("capture.npz", npy_bytes(c.base.arrays()["x"]))))
    add("npz_is_pickle", "error", "corrupt")(solve_file(
        lambda c: c.write("capture.npz", pickle.dumps(c.base.arrays()))))
    add("npz_empty_zip", "error", "corrupt")(solve_file(
        lambda c: c.write("capture.npz", empty_zip())))
    add("npz_member_garbage", "error", "corrupt")(solve_file(lambda c: garbage_member(c)))
    add("npz_is_folder", "error", "corrupt")(solve_file(lambda c: mkdir(c.dir / "capture.npz")))
    add("npz_missing", "error", "corrupt")(solve_file(lambda c: c.dir / "nothing.npz"))

    def crc_mismatch(c: Ctx) -> Path:
        path = c.capture(compressed=False)
        start, size = member_span(path, "x.npy")
        flip_bits(path, [start + size - 8])  # a data byte: only the CRC notices
        return path
    add("npz_crc_mismatch", "error", "corrupt", quick=True)(solve_file(crc_mismatch))

    def corrupt_deflate(c: Ctx) -> Path:
        path = c.capture()
        start, size = member_span(path, "x.npy")
        data = bytearray(path.read_bytes())
        data[start + size // 3:start + size // 3 + 16] = b"\xff" * 16
        path.write_bytes(bytes(data))
        return path
    add("npz_corrupt_deflate", "error", "corrupt")(solve_file(corrupt_deflate))

    def bitflip(seed: int):
        def make(c: Ctx) -> Path:
            path = c.capture()
            start, size = member_span(path, "x.npy")
            rng = np.random.default_rng(seed)
            flip_bits(path, [start + int(rng.integers(size))], 1 << int(rng.integers(8)))
            return path
        return make
    for seed in range(4):
        add(f"npz_bitflip_x_{seed}", "error", "corrupt")(solve_file(bitflip(seed)))

    def header_flip(c: Ctx) -> Path:
        path = c.capture(compressed=False)
        start, _ = member_span(path, "x.npy")
        data = path.read_bytes()
        flip_bits(path, [data.index(b"<f8", start) + 2])  # '<f8' -> '<f9'
        return path
    add("npz_header_bitflip", "error", "corrupt")(solve_file(header_flip))

    def cut(name: str, keep: Callable[[int], int]) -> Callable[[Path], None]:
        def mangle(model: Path) -> None:
            data = (model / name).read_bytes()
            (model / name).write_bytes(data[:keep(len(data))])
        return mangle

    def overwrite(name: str, offset: int, data: bytes) -> Callable[[Path], None]:
        def mangle(model: Path) -> None:
            raw = bytearray((model / name).read_bytes())
            raw[offset:offset + len(data)] = data
            (model / name).write_bytes(bytes(raw))
        return mangle

    add("images_bin_truncated_half", "error", "corrupt", quick=True)(
        edited_model(cut("images.bin", lambda n: n // 2)))
    add("images_bin_missing_last_byte", "error", "corrupt")(
        edited_model(cut("images.bin", lambda n: n - 1)))
    add("images_bin_zero_bytes", "error", "corrupt")(edited_model(cut("images.bin", lambda n: 0)))
    add("images_bin_huge_count", "error", "corrupt")(
        edited_model(overwrite("images.bin", 0, struct.pack("<Q", 2**62))))
    add("cameras_bin_zero_bytes", "error", "corrupt")(edited_model(cut("cameras.bin", lambda n: 0)))
    add("cameras_bin_truncated", "error", "corrupt")(
        edited_model(cut("cameras.bin", lambda n: n - 20)))
    add("cameras_bin_huge_count", "error", "corrupt")(
        edited_model(overwrite("cameras.bin", 0, struct.pack("<Q", 2**40))))
    add("points3D_bin_truncated", "error", "corrupt")(
        edited_model(cut("points3D.bin", lambda n: n // 3)))
    add("points3D_bin_garbage", "error", "corrupt")(edited_model(
        lambda m: (m / "points3D.bin").write_bytes(np.random.default_rng(1).bytes(4096))))
    add("images_txt_emptied", "error", "corrupt", quick=True)(
        edited_model(lambda m: (m / "images.txt").write_text(""), "txt"))
    add("images_txt_garbage_line", "error", "corrupt")(edited_model(
        lambda m: edit_line(m / "images.txt", "", lambda f: ["1", "one", "two"]), "txt"))
    add("cameras_txt_garbage", "error", "corrupt")(edited_model(
        lambda m: (m / "cameras.txt").write_text("this is not a camera\n"), "txt"))
    add("points3D_txt_garbage", "error", "corrupt")(edited_model(
        lambda m: (m / "points3D.txt").write_text("1 2 3 x y z\n\x00\x01\x02\n"), "txt"))
    add("model_missing_images_bin", "error", "corrupt")(
        edited_model(lambda m: (m / "images.bin").unlink()))
    add("model_folder_empty", "error", "corrupt")(
        edited_model(lambda m: [f.unlink() for f in m.iterdir()]))

    def workspace_arg(make: Callable[[Ctx], Path]):
        def setup(c: Ctx) -> Run:
            ws = make(c)
            kp = c.write("keypoints.csv", (DEMO / "keypoints.csv").read_text())
            return Run(rec(ws, kp, "csv", c.dir / "out"), out=c.dir / "out", kind="dir")
        return setup
    add("workspace_missing", "error", "corrupt")(workspace_arg(lambda c: c.dir / "nowhere"))
    add("workspace_is_file", "error", "corrupt")(
        workspace_arg(lambda c: c.write("ws.txt", "not a workspace")))
    add("workspace_images_only", "error", "corrupt")(workspace_arg(
        lambda c: (shutil.rmtree(c.ws() / "sparse"), c.dir / "ws")[1]))

    def keypoints_csv(content: Callable[[Ctx], bytes | str]):
        def setup(c: Ctx) -> Run:
            ws = c.ws()
            kp = c.write("kp.csv", content(c))
            return Run(rec(ws, kp, "csv", c.dir / "out", "--no-plots"), out=c.dir / "out",
                       kind="dir")
        return setup
    add("csv_zero_bytes", "error", "corrupt")(keypoints_csv(lambda c: b""))
    add("csv_binary_garbage", "error", "corrupt")(
        keypoints_csv(lambda c: np.random.default_rng(2).bytes(3000)))
    add("csv_truncated_mid_row", "error", "corrupt")(
        keypoints_csv(lambda c: (DEMO / "keypoints.csv").read_bytes()[:5017]))
    add("csv_not_utf8", "error", "corrupt")(keypoints_csv(
        lambda c: (DEMO / "keypoints.csv").read_bytes().replace(b"cam0/000.jpg", b"cam\xff.jpg")))
    add("csv_header_only", "error", "corrupt")(keypoints_csv(lambda c: "image,point_id,x,y\n"))


def npy_bytes(arr: np.ndarray) -> bytes:
    f = io.BytesIO()
    np.save(f, arr)
    return f.getvalue()


def empty_zip() -> bytes:
    f = io.BytesIO()
    with zipfile.ZipFile(f, "w"):
        pass
    return f.getvalue()


def garbage_member(c: Ctx) -> Path:
    path = c.capture(drop=("x",))
    with zipfile.ZipFile(path, "a") as zf:
        zf.writestr("x.npy", b"this is no array")
    return path


def mkdir(path: Path) -> Path:
    path.mkdir(parents=True)
    return path


# ---- hostile npz


def _hostile_npz(add) -> None:
    def solve_with(*, drop: tuple[str, ...] = (), more: tuple[str, ...] = (), **changes):
        def setup(c: Ctx) -> Run:
            arrays = c.base.arrays()
            values = {k: v(arrays) if callable(v) else v for k, v in changes.items()}
            cap = c.capture(drop=drop, **values)
            return Run(["solve", str(cap), "--out", str(c.dir / "r.npz"), *FAST, *more],
                       out=c.dir / "r.npz", kind="npz")
        return setup

    def obj(a: dict) -> np.ndarray:
        return np.array([{"x": 1}, None, "text"], dtype=object)

    add("npz_object_x", "error", "hostile", quick=True)(solve_with(x=obj))
    add("npz_object_image_names", "error", "hostile")(
        solve_with(image_names=lambda a: a["image_names"].astype(object)))

    def lying(key: str, shape: tuple[int, ...]):
        def setup(c: Ctx) -> Run:
            cap = lying_npz(c.dir / "capture.npz", c.base.arrays(), key, shape)
            return Run(["solve", str(cap), "--out", str(c.dir / "r.npz"), *FAST],
                       out=c.dir / "r.npz", kind="npz")
        return setup
    add("npz_lying_header_x", "error", "hostile", quick=True)(lying("x", (10**6, 10**6, 2)))
    add("npz_lying_header_K", "error", "hostile")(lying("K", (10**9, 3, 3)))
    add("npz_lying_header_confidence", "error", "hostile")(lying("confidence", (10**6, 10**6)))

    def zeros(c: Ctx) -> Run:
        cap = c.dir / "capture.npz"
        shutil.copy(c.base.zeros_2gb(), cap)
        return Run(["solve", str(cap), "--out", str(c.dir / "r.npz"), *FAST],
                   out=c.dir / "r.npz", kind="npz")
    add("npz_2gb_zeros_in_unread_key", "ok", "hostile", quick=True)(zeros)

    def dtype(key: str, kind) -> Callable[[dict], np.ndarray]:
        return lambda a: a[key].astype(kind)
    add("npz_x_strings", "error", "hostile")(solve_with(x=dtype("x", str)))
    add("npz_x_complex", "error", "hostile")(solve_with(x=dtype("x", complex)))
    add("npz_x_bool", "error", "hostile")(solve_with(x=dtype("x", bool)))
    add("npz_K_bytes", "error", "hostile")(solve_with(K=dtype("K", "S8")))
    add("npz_x_structured", "error", "hostile")(solve_with(
        x=lambda a: np.zeros(a["x"].shape[:2], dtype=[("u", "f8"), ("v", "f8")])))
    add("npz_x_datetime", "error", "hostile")(
        solve_with(x=lambda a: np.zeros(a["x"].shape, dtype="datetime64[s]")))
    add("npz_frame_fractional", "error", "hostile")(
        solve_with(frame=lambda a: a["frame"] + 0.5))
    add("npz_stream_fractional", "error", "hostile")(
        solve_with(stream=lambda a: a["stream"] + 0.25))

    def with_nan(key: str, index=(0,), value: float = np.nan) -> Callable[[dict], np.ndarray]:
        def make(a: dict) -> np.ndarray:
            arr = a[key].astype(np.float64)
            arr[index] = value
            return arr
        return make
    for key in ("K", "R", "C", "frame", "stream"):
        add(f"npz_nan_in_{key}", "error", "hostile", quick=key == "frame")(
            solve_with(**{key: with_nan(key)}))
    add("npz_inf_in_x", "error", "hostile")(solve_with(x=with_nan("x", (0, 0, 0), np.inf)))
    add("npz_inf_in_C", "error", "hostile")(solve_with(C=with_nan("C", (2, 1), -np.inf)))
    add("npz_x_all_nan", "error", "hostile")(solve_with(x=lambda a: np.full_like(a["x"], np.nan)))
    add("npz_confidence_nan_is_unseen", "ok", "hostile")(solve_with(  # 1 in 5, scattered
        confidence=lambda a: np.where(np.add.outer(*map(np.arange, a["x"].shape[:2])) % 5 == 0,
                                      np.nan, 1.0)))
    add("npz_confidence_negative", "error", "hostile")(
        solve_with(confidence=lambda a: -np.ones(a["x"].shape[:2])))

    def two_images(a: dict) -> dict:
        pick = [int(np.flatnonzero(a["stream"] == s)[0]) for s in np.unique(a["stream"])[:2]]
        return {k: a[k][pick] for k in ("x", "K", "R", "C", "stream", "frame", "image_names")}

    def subset(pick: Callable[[dict], dict]):
        def setup(c: Ctx) -> Run:
            cap = save(c.dir / "capture.npz", pick(c.base.arrays()))
            return Run(["solve", str(cap), "--out", str(c.dir / "r.npz"), *FAST],
                       out=c.dir / "r.npz", kind="npz")
        return setup
    add("npz_two_images_two_streams", "either", "hostile")(subset(two_images))
    add("npz_one_image", "error", "hostile")(
        subset(lambda a: {k: a[k][:1] for k in ("x", "K", "R", "C")}))
    add("npz_zero_images", "error", "hostile")(
        subset(lambda a: {k: a[k][:0] for k in ("x", "K", "R", "C")}))
    add("npz_zero_points", "error", "hostile")(
        subset(lambda a: {"x": a["x"][:, :0], **{k: a[k] for k in ("K", "R", "C")}}))

    def rotated(eps: float) -> Callable[[dict], np.ndarray]:
        def make(a: dict) -> np.ndarray:
            R = a["R"].copy()
            R += eps * np.random.default_rng(3).standard_normal(R.shape)
            return R
        return make
    add("npz_R_1e-6_off_orthonormal", "ok", "hostile", quick=True)(solve_with(R=rotated(1e-6)))
    add("npz_R_1e-1_off_orthonormal", "error", "hostile")(solve_with(R=rotated(1e-1)))
    add("npz_R_reflection", "error", "hostile")(solve_with(R=lambda a: -a["R"]))
    add("npz_K_one_short", "error", "hostile")(solve_with(K=lambda a: a["K"][:-1]))
    add("npz_x_three_columns", "error", "hostile")(
        solve_with(x=lambda a: np.concatenate([a["x"], a["x"][..., :1]], axis=-1)))
    add("npz_x_flat", "error", "hostile")(solve_with(x=lambda a: a["x"].ravel()))
    add("npz_x_scalar", "error", "hostile")(solve_with(x=lambda a: np.float64(3.0)))
    add("npz_stream_one_short", "error", "hostile")(solve_with(stream=lambda a: a["stream"][:-1]))
    add("npz_image_names_one_short", "error", "hostile")(
        solve_with(image_names=lambda a: a["image_names"][:-1]))
    add("npz_missing_R", "error", "hostile")(solve_with(drop=("R",)))
    add("npz_confidence_wrong_shape", "error", "hostile")(
        solve_with(confidence=lambda a: np.ones((3, 3))))
    add("npz_symmetric_pairs_out_of_range", "error", "hostile")(
        solve_with(symmetric_pairs=np.array([[0, 1000]])))
    add("npz_symmetric_pairs_three_columns", "error", "hostile")(
        solve_with(symmetric_pairs=np.array([[0, 1, 2]])))
    add("npz_duplicate_frames_in_stream", "either", "hostile")(
        solve_with(frame=lambda a: np.zeros_like(a["frame"])))


# ---- evaluate and simulate with bad inputs


def _evaluate_simulate(add) -> None:
    def evaluate(result: Callable[[Ctx], Path], capture: Callable[[Ctx], Path] | None = None):
        def setup(c: Ctx) -> Run:
            r = result(c)
            cap = capture(c) if capture else c.capture()
            return Run(["evaluate", str(r), str(cap)])
        return setup

    def result_with(**changes):
        def make(c: Ctx) -> Path:
            with np.load(c.base.result()) as d:
                arrays = {k: d[k] for k in d.files}
            arrays.update({k: v(arrays) if callable(v) else v for k, v in changes.items()})
            return save(c.dir / "result.npz", arrays)
        return make

    add("evaluate_object_X", "error", "evaluate")(
        evaluate(result_with(X=np.array([None, {"a": 1}], dtype=object))))
    add("evaluate_object_X_true", "error", "evaluate")(evaluate(
        result_with(), lambda c: c.capture(X_true=np.array([None], dtype=object))))
    add("evaluate_result_zero_bytes", "error", "evaluate")(
        evaluate(lambda c: c.write("result.npz", b"")))
    add("evaluate_result_text", "error", "evaluate")(
        evaluate(lambda c: c.write("result.npz", "X,order\n")))
    add("evaluate_result_missing", "error", "evaluate")(evaluate(lambda c: c.dir / "none.npz"))
    add("evaluate_capture_without_truth", "error", "evaluate")(
        evaluate(result_with(), lambda c: c.capture(drop=("X_true", "t_true"))))
    add("evaluate_result_of_other_size", "error", "evaluate")(
        evaluate(result_with(X=lambda a: a["X"][:-2], order=lambda a: a["order"][:-2])))
    add("evaluate_order_out_of_range", "error", "evaluate")(
        evaluate(result_with(order=lambda a: a["order"] + 1000)))
    add("evaluate_order_wrong_length", "error", "evaluate")(
        evaluate(result_with(order=lambda a: a["order"][:3])))
    add("evaluate_lying_header_X", "error", "evaluate")(evaluate(lambda c: lying_result(c)))
    add("evaluate_nan_t_true", "error", "evaluate")(evaluate(
        result_with(), lambda c: c.capture(t_true=np.full_like(c.base.arrays()["t_true"], np.nan))))

    def simulate(mocap: Callable[[Ctx], Path], *more: str):
        def setup(c: Ctx) -> Run:
            m = mocap(c)
            out = c.dir / "cap.npz"
            return Run(["simulate", str(m), "--out", str(out), *SIMULATE_ARGS, *more], out=out,
                       kind="npz")
        return setup

    def positions(make: Callable[[np.ndarray], np.ndarray]) -> Callable[[Ctx], Path]:
        def build(c: Ctx) -> Path:
            with np.load(MOCAP) as d:
                p = d["positions"]
            return c.mocap(positions=make(p))
        return build

    add("simulate_object_positions", "error", "simulate", quick=True)(
        simulate(lambda c: c.mocap(positions=np.array([None, 1], dtype=object))))
    add("simulate_lying_header_positions", "error", "simulate")(simulate(
        lambda c: lying_npz(c.dir / "mocap.npz", mocap_arrays(), "positions",
                            (10**6, 10**6, 3))))
    add("simulate_mocap_zero_bytes", "error", "simulate")(
        simulate(lambda c: c.write("mocap.npz", b"")))
    add("simulate_mocap_text", "error", "simulate")(
        simulate(lambda c: c.write("mocap.npz", "positions\n")))
    add("simulate_mocap_missing", "error", "simulate")(simulate(lambda c: c.dir / "none.npz"))
    add("simulate_positions_2d", "error", "simulate")(simulate(positions(lambda p: p[..., :2])))
    add("simulate_positions_all_nan", "error", "simulate")(
        simulate(positions(lambda p: np.full_like(p, np.nan))))
    add("simulate_positions_one_frame", "error", "simulate")(simulate(positions(lambda p: p[:1])))
    add("simulate_positions_strings", "error", "simulate")(
        simulate(positions(lambda p: p.astype(str))))
    for name, fps in [("zero", 0.0), ("negative", -120.0), ("nan", np.nan), ("inf", np.inf)]:
        add(f"simulate_fps_{name}", "error", "simulate")(
            simulate(lambda c, fps=fps: c.mocap(fps=np.float32(fps))))
    add("simulate_fps_array", "error", "simulate")(
        simulate(lambda c: c.mocap(fps=np.array([120.0, 60.0]))))
    add("simulate_parents_out_of_range", "error", "simulate")(
        simulate(lambda c: c.mocap(parents=np.full(28, 500, dtype=np.int16))))
    for option, value in [("rate", "0"), ("rate", "-8"), ("rate", "nan"), ("num-streams", "0"),
                          ("num-streams", "-2"), ("noise", "-1"), ("noise", "nan"),
                          ("missing", "1.5"), ("missing", "-0.1"), ("drop", "1"),
                          ("duration", "0"), ("duration", "-1"), ("image-size", "0"),
                          ("focal", "-1000"), ("focal", "nan"), ("radius", "-3"),
                          ("outliers", "2"), ("swaps", "-1"), ("gap", "nan"), ("start", "1e9")]:
        add(f"simulate_{option}_{value}".replace("-", "_").replace(".", "p"), "error",
            "simulate")(simulate(lambda c: c.mocap(), f"--{option}={value}"))


def mocap_arrays() -> dict[str, np.ndarray]:
    with np.load(MOCAP) as d:
        return {k: d[k] for k in d.files}


def lying_result(c: Ctx) -> Path:
    with np.load(c.base.result()) as d:
        arrays = {k: d[k] for k in d.files}
    return lying_npz(c.dir / "result.npz", arrays, "X", (10**6, 10**6, 3))


# ---- keypoint files


def _keypoints(add) -> None:
    def run_kp(make: Callable[[Ctx, Path], tuple[Path | None, str]], *more: str,
               model: str = "bin", plots: bool = False):
        def setup(c: Ctx) -> Run:
            ws = c.ws(model)
            kp, fmt = make(c, ws)
            out = c.dir / "out"
            return Run(rec(ws, kp, fmt, out, *more, *([] if plots else ["--no-plots"])),
                       out=out, kind="dir")
        return setup

    def csv_of(text: Callable[[Ctx], str | bytes]):
        return lambda c, ws: (c.write("kp.csv", text(c)), "csv")

    # valid: every format, odd but legal encodings and names
    add("kp_csv", "ok", "keypoints", quick=True, rerun=True)(
        run_kp(lambda c, ws: (ws / "keypoints.csv", "csv"), plots=True))
    add("kp_openpose", "ok", "keypoints", rerun=True)(
        run_kp(lambda c, ws: (openpose_files(c), "openpose")))
    add("kp_coco", "ok", "keypoints")(run_kp(lambda c, ws: (c.json("coco.json", coco_doc(c)),
                                                             "coco")))
    add("kp_mmpose", "ok", "keypoints")(run_kp(lambda c, ws: (mmpose_files(c), "mmpose")))
    add("kp_mmpose_meta_info", "ok", "keypoints")(
        run_kp(lambda c, ws: (mmpose_files(c, meta=True), "mmpose")))
    add("kp_csv_bom", "ok", "keypoints", quick=True)(
        run_kp(csv_of(lambda c: "\ufeff" + (DEMO / "keypoints.csv").read_text())))
    add("kp_csv_crlf", "ok", "keypoints")(
        run_kp(csv_of(lambda c: (DEMO / "keypoints.csv").read_text().replace("\n", "\r\n"))))
    add("kp_csv_bom_crlf", "ok", "keypoints")(run_kp(csv_of(
        lambda c: "\ufeff" + (DEMO / "keypoints.csv").read_text().replace("\n", "\r\n"))))
    add("kp_person_index_0", "ok", "keypoints")(
        run_kp(lambda c, ws: (ws / "keypoints.csv", "csv"), "--person", "0"))

    def unicode_names(c: Ctx, ws: Path) -> tuple[Path, str]:
        rename = {name: name.replace("cam", "kämérà_ü").replace("/", "/ß_")
                  for name in c.base.points()}
        images = ws / "sparse" / "0" / "images.txt"
        images.write_text("\n".join(
            " ".join([*f.split(" ")[:-1], rename.get(f.split(" ")[-1], f.split(" ")[-1])])
            if f and not f.startswith("#") and f.split(" ")[-1] in rename else f
            for f in images.read_text().split("\n")))
        for old, new in rename.items():
            (ws / "images" / new).parent.mkdir(parents=True, exist_ok=True)
            (ws / "images" / old).rename(ws / "images" / new)
        return c.write("kp.csv", csv_text(c.base.points(), rename)), "csv"
    add("kp_unicode_names", "ok", "keypoints", quick=True, rerun=True)(
        run_kp(unicode_names, model="txt"))

    # csv
    def rows(edit: Callable[[list[str]], list[str]]):
        def text(c: Ctx) -> str:
            lines = (DEMO / "keypoints.csv").read_text().splitlines()
            return "\n".join(edit(lines)) + "\n"
        return csv_of(text)

    def row0(value: str, column: int):
        def edit(lines: list[str]) -> list[str]:
            fields = lines[1].split(",")
            fields[column] = value
            return [lines[0], ",".join(fields), *lines[2:]]
        return edit

    add("csv_point_id_1e9", "error", "keypoints", quick=True)(run_kp(rows(row0("1000000000", 1))))
    add("csv_point_id_2e63", "error", "keypoints")(
        run_kp(rows(row0("9223372036854775808", 1))))
    add("csv_point_id_negative", "error", "keypoints")(run_kp(rows(row0("-1", 1))))
    add("csv_point_id_float", "error", "keypoints")(run_kp(rows(row0("1.5", 1))))
    add("csv_x_nan", "error", "keypoints")(run_kp(rows(row0("nan", 2))))
    add("csv_y_inf", "error", "keypoints")(run_kp(rows(row0("inf", 3))))
    add("csv_score_text", "error", "keypoints")(run_kp(rows(row0("high", 4))))
    add("csv_person_column_1e7", "error", "keypoints")(run_kp(rows(
        lambda lines: [lines[0] + ",person", *(f"{ln},{10**7 if i == 0 else 0}"
                                               for i, ln in enumerate(lines[1:]))])))
    add("person_option_1e7", "error", "keypoints")(
        run_kp(lambda c, ws: (ws / "keypoints.csv", "csv"), "--person", "10000000"))
    add("person_option_huge", "error", "keypoints")(
        run_kp(lambda c, ws: (ws / "keypoints.csv", "csv"), "--person", "9" * 30))
    add("csv_missing_column", "error", "keypoints")(
        run_kp(rows(lambda lines: [ln.rsplit(",", 2)[0] for ln in lines])))
    add("csv_field_count", "error", "keypoints")(
        run_kp(rows(lambda lines: [*lines[:5], lines[5] + ",7", *lines[6:]])))
    add("csv_duplicate_row", "error", "keypoints")(
        run_kp(rows(lambda lines: [*lines, lines[3]])))
    add("csv_one_image", "error", "keypoints")(
        run_kp(rows(lambda lines: [ln for ln in lines if not ln.startswith("cam")
                                   or ln.startswith("cam0/000.jpg")])))
    add("csv_names_not_in_model", "error", "keypoints", quick=True)(
        run_kp(rows(lambda lines: [lines[0], *(ln.replace("cam", "camera_x") for ln in
                                               lines[1:])])))
    add("csv_newline_in_image_name", "error", "keypoints", quick=True)(run_kp(rows(
        lambda lines: [lines[0], '"cam0/000.jpg\ndloe-sfm: error: all good",0,1,2,1',
                       *lines[1:]])))
    add("csv_carriage_return_in_image_name", "error", "keypoints")(run_kp(rows(
        lambda lines: [lines[0], '"nope\rdloe-sfm: error: all good",0,1,2,1', *lines[1:]])))
    add("csv_escape_codes_in_image_name", "error", "keypoints")(run_kp(rows(
        lambda lines: [lines[0], "\x1b[2J\x1b[31mnope\x07,0,1,2,1", *lines[1:]])))
    add("csv_unclosed_quote", "error", "keypoints")(
        run_kp(rows(lambda lines: [*lines, '"cam0/000.jpg,0,1,2,1'])))

    # openpose
    def openpose_with(mutate: Callable[[Ctx, Path], None]):
        def make(c: Ctx, ws: Path) -> tuple[Path, str]:
            folder = openpose_files(c)
            mutate(c, folder)
            return folder, "openpose"
        return make

    first = "cam0/000_keypoints.json"

    def replace_first(content: Callable[[dict], object]):
        def mutate(c: Ctx, folder: Path) -> None:
            doc = json.loads((folder / first).read_text())
            value = content(doc)
            (folder / first).write_text(value if isinstance(value, str) else json.dumps(value))
        return mutate

    add("openpose_deep_nesting", "error", "keypoints", quick=True)(
        run_kp(openpose_with(replace_first(lambda d: nested(100000)))))
    add("openpose_people_not_list", "error", "keypoints")(
        run_kp(openpose_with(replace_first(lambda d: {"people": 5}))))
    add("openpose_person_is_int", "error", "keypoints")(
        run_kp(openpose_with(replace_first(lambda d: {"people": [7]}))))
    add("openpose_values_strings", "error", "keypoints")(run_kp(openpose_with(replace_first(
        lambda d: {"people": [{"pose_keypoints_2d": ["a"] * 24}]}))))
    add("openpose_values_nested_dicts", "error", "keypoints")(run_kp(openpose_with(replace_first(
        lambda d: {"people": [{"pose_keypoints_2d": [{"x": 1}] * 24}]}))))
    add("openpose_length_not_3k", "error", "keypoints")(run_kp(openpose_with(replace_first(
        lambda d: {"people": [{"pose_keypoints_2d": [1.0] * 23}]}))))
    add("openpose_top_level_list", "error", "keypoints")(
        run_kp(openpose_with(replace_first(lambda d: [d]))))
    add("openpose_json_nan", "error", "keypoints")(run_kp(openpose_with(replace_first(
        lambda d: '{"people": [{"pose_keypoints_2d": [NaN, NaN, 1' + ", 1" * 21 + "]}]}"))))
    add("openpose_number_1e400", "error", "keypoints")(run_kp(openpose_with(replace_first(
        lambda d: json.dumps({"people": [{"pose_keypoints_2d": [1e300] * 24}]}).replace(
            "1e+300", "1e400")))))
    add("openpose_not_utf8", "error", "keypoints")(run_kp(openpose_with(
        lambda c, f: (f / first).write_bytes(b'{"people": [], "n\xff": 1}'))))
    add("openpose_empty_folder", "error", "keypoints")(
        run_kp(lambda c, ws: (mkdir(c.dir / "openpose"), "openpose")))
    add("openpose_names_not_in_model", "error", "keypoints")(run_kp(openpose_with(
        lambda c, f: (f / "cam0").rename(f / "elsewhere"))))
    add("openpose_no_people_anywhere", "error", "keypoints")(run_kp(openpose_with(
        lambda c, f: [p.write_text('{"people": []}') for p in f.rglob("*.json")])))
    add("openpose_same_key_twice", "error", "keypoints")(run_kp(openpose_with(
        lambda c, f: shutil.copy(f / first, f / "cam0" / "000.json"))))

    # coco
    def coco_with(mutate: Callable[[dict], object]):
        def make(c: Ctx, ws: Path) -> tuple[Path, str]:
            doc = coco_doc(c)
            value = mutate(doc)
            doc = doc if value is None else value
            return c.write("coco.json", doc if isinstance(doc, str) else json.dumps(doc)), "coco"
        return make

    def set_path(*path_value):
        *path, value = path_value

        def mutate(doc: dict) -> None:
            target = doc
            for p in path[:-1]:
                target = target[p]
            target[path[-1]] = value
        return mutate

    add("coco_deep_nesting", "error", "keypoints")(run_kp(coco_with(lambda d: nested(100000))))
    add("coco_categories_int", "error", "keypoints", quick=True)(
        run_kp(coco_with(set_path("categories", 5))))
    add("coco_image_id_list", "error", "keypoints")(
        run_kp(coco_with(set_path("annotations", 0, "image_id", [1, 2]))))
    add("coco_image_entry_id_list", "error", "keypoints")(
        run_kp(coco_with(set_path("images", 0, "id", [1, 2]))))
    add("coco_annotations_dict", "error", "keypoints")(
        run_kp(coco_with(set_path("annotations", {"a": 1}))))
    add("coco_image_without_file_name", "error", "keypoints")(
        run_kp(coco_with(lambda d: d["images"][0].pop("file_name") and None)))
    add("coco_file_name_int", "error", "keypoints")(
        run_kp(coco_with(set_path("images", 0, "file_name", 12))))
    add("coco_keypoints_string", "error", "keypoints")(
        run_kp(coco_with(set_path("annotations", 0, "keypoints", "1 2 3"))))
    add("coco_keypoints_nested", "error", "keypoints")(
        run_kp(coco_with(set_path("annotations", 0, "keypoints", [[[1, 2, 3]]] * 8))))
    add("coco_image_id_unknown", "error", "keypoints")(
        run_kp(coco_with(set_path("annotations", 0, "image_id", 9999))))
    add("coco_category_keypoints_int", "error", "keypoints")(
        run_kp(coco_with(set_path("categories", 0, "keypoints", 8))))
    add("coco_skeleton_three_element_links", "error", "keypoints")(
        run_kp(coco_with(set_path("categories", 0, "skeleton", [[1, 2, 3]]))))
    add("coco_skeleton_out_of_range", "error", "keypoints")(
        run_kp(coco_with(set_path("categories", 0, "skeleton", [[1, 99]]))))
    add("coco_file_name_newline", "error", "keypoints")(run_kp(coco_with(
        set_path("images", 0, "file_name", "x.jpg\ndloe-sfm: error: all good"))))
    add("coco_top_level_list", "error", "keypoints")(run_kp(coco_with(lambda d: [d])))

    # mmpose
    def mmpose_with(mutate: Callable[[dict], object], meta: bool = True):
        def make(c: Ctx, ws: Path) -> tuple[Path, str]:
            folder = mmpose_files(c, meta=meta)
            file = folder / "cam0" / "000.json"
            doc = json.loads(file.read_text())
            value = mutate(doc)
            doc = doc if value is None else value
            file.write_text(doc if isinstance(doc, str) else json.dumps(doc))
            return folder, "mmpose"
        return make

    add("mmpose_deep_nesting", "error", "keypoints")(run_kp(mmpose_with(lambda d: nested(100000))))
    add("mmpose_id2name_non_integer_keys", "error", "keypoints", quick=True)(run_kp(mmpose_with(
        set_path("meta_info", "keypoint_id2name", {f"j{j}": f"m{j}" for j in range(8)}))))
    add("mmpose_skeleton_three_element_links", "error", "keypoints")(
        run_kp(mmpose_with(set_path("meta_info", "skeleton_links", [[1, 2, 3]]))))
    add("mmpose_flip_pairs_out_of_range", "error", "keypoints")(
        run_kp(mmpose_with(set_path("meta_info", "flip_pairs", [[0, 50]]))))
    add("mmpose_keypoints_strings", "error", "keypoints")(
        run_kp(mmpose_with(set_path("instance_info", 0, "keypoints", [["a", "b"]] * 8))))
    add("mmpose_scores_wrong_length", "error", "keypoints")(
        run_kp(mmpose_with(set_path("instance_info", 0, "keypoint_scores", [1.0] * 3))))
    add("mmpose_instances_not_list", "error", "keypoints")(
        run_kp(mmpose_with(set_path("instance_info", 7))))
    add("mmpose_frame_id_list", "error", "keypoints")(run_kp(mmpose_with(
        lambda d: [{"frame_id": [1], "instances": d["instance_info"]}])))
    add("mmpose_instance_is_string", "error", "keypoints")(
        run_kp(mmpose_with(set_path("instance_info", ["abc"]))))

    # aruco: markers from the workspace's own images
    def aruco(mutate: Callable[[Ctx, Path], Path | None]):
        def make(c: Ctx, ws: Path) -> tuple[Path | None, str]:
            return mutate(c, ws), "aruco"
        return make

    def bomb(c: Ctx, ws: Path) -> None:
        (ws / "images" / "cam0" / "000.jpg").unlink()
        (ws / "images" / "cam0" / "000.png").write_bytes(png_header(100000, 100000))
    add("aruco_png_claims_100000_px", "error", "keypoints", quick=True)(run_kp(aruco(bomb)))

    def bomb_folder(c: Ctx, ws: Path) -> Path:
        c.write("markers/cam0/000.png", png_header(100000, 100000))
        return c.dir / "markers"
    add("aruco_png_claims_100000_px_keypoints_folder", "error", "keypoints")(
        run_kp(aruco(bomb_folder)))
    def zero_byte_image(c: Ctx, ws: Path) -> None:
        (ws / "images" / "cam0" / "001.jpg").write_bytes(b"")
    add("aruco_zero_byte_image", "error", "keypoints")(run_kp(aruco(zero_byte_image)))
    add("aruco_text_as_png", "error", "keypoints")(run_kp(aruco(
        lambda c, ws: c.write("markers/cam0/000.png", "not an image\n").parent.parent)))
    add("aruco_no_markers_in_images", "error", "keypoints")(run_kp(aruco(lambda c, ws: None)))

    # layout, stream pattern, scores, format mismatches
    def layout(content: str | None, spec: str | None = None):
        def setup(c: Ctx) -> Run:
            ws = c.ws()
            value = spec if content is None else str(c.write("layout.json", content))
            return Run(rec(ws, ws / "keypoints.csv", "csv", c.dir / "out", "--no-plots",
                           "--layout", value), out=c.dir / "out", kind="dir")
        return setup
    names = [f"m{j}" for j in range(8)]
    add("layout_edges_out_of_range", "error", "keypoints")(
        layout(json.dumps({"point_names": names, "edges": [[0, 40]]})))
    add("layout_size_mismatch", "error", "keypoints")(
        layout(json.dumps({"point_names": names[:5]})))
    add("layout_deep_nesting", "error", "keypoints")(layout(nested(100000)))
    add("layout_edges_strings", "error", "keypoints")(
        layout(json.dumps({"point_names": names, "edges": "0-1"})))
    add("layout_unknown_name", "error", "keypoints")(layout(None, "BODY_99"))
    add("layout_missing_file", "error", "keypoints")(layout(None, "nothing.json"))

    def more_args(*args: str):
        return run_kp(lambda c, ws: (ws / "keypoints.csv", "csv"), *args)
    add("stream_pattern_invalid_regex", "error", "keypoints")(more_args("--stream-pattern", "(["))
    add("stream_pattern_without_groups", "error", "keypoints")(
        more_args("--stream-pattern", "cam"))
    add("stream_pattern_matches_nothing", "error", "keypoints")(
        more_args("--stream-pattern", r"(?P<stream>zzz\d)/(?P<frame>\d+)"))
    add("min_score_nan", "error", "keypoints")(more_args("--min-score", "nan"))
    add("min_score_above_every_score", "error", "keypoints")(more_args("--min-score", "2"))
    add("format_csv_on_json", "error", "keypoints")(
        run_kp(lambda c, ws: (c.json("coco.json", coco_doc(c)), "csv")))
    add("format_openpose_on_csv", "error", "keypoints")(
        run_kp(lambda c, ws: (ws / "keypoints.csv", "openpose")))
    add("format_coco_on_folder", "error", "keypoints")(
        run_kp(lambda c, ws: (openpose_files(c), "coco")))
    add("keypoints_missing", "error", "keypoints")(
        run_kp(lambda c, ws: (c.dir / "nothing.csv", "csv")))
    add("keypoints_dev_null", "error", "keypoints")(run_kp(lambda c, ws: (Path(os.devnull),
                                                                          "csv")))
    add("keypoints_none_for_csv", "error", "keypoints")(run_kp(lambda c, ws: (None, "csv")))


# ---- solver options (--set) and config files


OPTION_ERRORS = [
    "num_candidates=0", "num_candidates=-3", "num_candidates=1000000000", "num_candidates=2.5",
    "max_iterations=0", "max_iterations=-1", "min_ray_angle=90", "min_ray_angle=-1",
    "min_ray_angle=nan", "noise_px=-5", "noise_px=nan", "noise_px=inf", "omega=nan", "omega=-1",
    "tolerance=nan", "tolerance=-1", "cost_tolerance=nan", "lambda1=-1", "lambda1=nan",
    "lambda1=inf", "lambda2=-1", "lambda2=nan", "lambda3=-1", "ridge=-1", "prior_weight=5",
    "prior_weight=-0.1", "prior_weight=nan", "end_degree=-1", "end_degree=nan",
    "soft_iterations=-5", "robust_iterations=-1", "robust_scale_px=-1", "robust_scale_px=nan",
    "degree_floor=5", "degree_floor=-1", "resequence_every=0", "resequence_every=-1",
    "no_such_option=1", "embedding=afine", "distance=arcc", "robust_loss=cauchyy",
    "stream_clocks=sometimes", "fixed_degree=maybe", "num_candidates", "=5", "noise_px=",
    "noise_px=1e999",
]
OPTION_VALID = ["noise_px=3", "embedding=SHP", "stream_clocks=true", "lambda2=inf",
                " noise_px = 2 "]
TOML_ERRORS = {
    "solver_is_int": "solver = 5\n",
    "list_value": "noise_px = [1, 2]\n",
    "inline_table_value": "noise_px = {a = 1}\n",
    "string_for_number": 'noise_px = "abc"\n',
    "bool_for_number": "noise_px = true\n",
    "float_for_int": "num_candidates = 2.5\n",
    "nan_value": "noise_px = nan\n",
    "datetime_value": "noise_px = 1979-05-27T07:32:00Z\n",
    "unknown_key": "[solver]\nno_such_option = 1\n",
    "out_of_range_in_table": "[solver]\nprior_weight = 5\n",
    "invalid_toml": "noise_px = = 3\n[solver\n",
    "deep_nested_arrays": f"noise_px = {nested(5000)}\n",
}


def _options(add) -> None:
    def solve(*args: str, config: str | bytes | None = None, folder: bool = False):
        def setup(c: Ctx) -> Run:
            cap = c.capture()
            extra: list[str] = []
            if config is not None:
                extra = ["--config", str(c.write("options.toml", config))]
            elif folder:
                extra = ["--config", str(mkdir(c.dir / "options.toml"))]
            return Run(["solve", str(cap), "--out", str(c.dir / "r.npz"), *FAST, *args, *extra],
                       out=c.dir / "r.npz", kind="npz")
        return setup

    def slug(text: str) -> str:
        out = text.strip().replace("=", "_eq_").replace(".", "p").replace("-", "minus")
        return out.replace(" ", "") or "empty"

    for item in OPTION_ERRORS:
        quick = item == "num_candidates=0"
        add(f"set_{slug(item)}", "error", "options", quick=quick)(solve("--set", item))
    for item in OPTION_VALID:
        add(f"set_valid_{slug(item)}", "ok", "options")(solve("--set", item))
    for name, text in TOML_ERRORS.items():
        add(f"toml_{name}", "error", "options", quick=name == "solver_is_int")(
            solve(config=text))
    add("toml_not_utf8", "error", "options")(solve(config=b"noise_px = 3 # \xff\xfe\n"))
    add("toml_is_folder", "error", "options")(solve(folder=True))
    add("toml_missing", "error", "options")(
        lambda c: Run(["solve", str(c.capture()), "--out", str(c.dir / "r.npz"), "--config",
                       str(c.dir / "none.toml")], out=c.dir / "r.npz", kind="npz"))
    add("toml_empty", "ok", "options")(solve(config=""))
    add("toml_solver_table", "ok", "options")(
        solve(config="[solver]\nnoise_px = 2.0\nembedding = 'affine'\n"))

    def rec_options(*args: str, config: str | None = None):
        def setup(c: Ctx) -> Run:
            ws = c.ws()
            extra = [] if config is None else ["--config", str(c.write("o.toml", config))]
            return Run(rec(ws, ws / "keypoints.csv", "csv", c.dir / "out", "--no-plots", *args,
                           *extra), out=c.dir / "out", kind="dir")
        return setup
    add("reconstruct_set_num_candidates_0", "error", "options")(
        rec_options("--set", "num_candidates=0"))
    add("reconstruct_set_min_ray_angle_90", "error", "options")(
        rec_options("--set", "min_ray_angle=90"))
    add("reconstruct_toml_invalid", "error", "options")(rec_options(config="a = = 1\n"))


def tree_hash(root: Path, exclude: Callable[[Path], bool] = lambda p: False) -> dict[str, str]:
    """{relative path: sha256 / 'dir' / 'link -> target'} of everything below ``root`` (or of
    the file ``root``), symlinks not followed."""
    root = Path(root)
    if not root.exists() and not root.is_symlink():
        return {}
    if root.is_file() and not root.is_symlink():
        return {".": file_hash(root)}
    out: dict[str, str] = {}
    for folder, dirs, files in os.walk(root):
        for name in sorted(dirs + files):
            path = Path(folder) / name
            if exclude(path):
                if name in dirs:
                    dirs.remove(name)
                continue
            rel = str(path.relative_to(root))
            if path.is_symlink():
                out[rel] = f"link -> {os.readlink(path)}"
            elif path.is_dir():
                out[rel] = "dir"
            else:
                out[rel] = file_hash(path)
    return out


def file_hash(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()
