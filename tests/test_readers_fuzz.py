"""Capture / result / mocap / COLMAP readers: every input gives a valid result or one clean
InputError, never another exception, and no array is allocated from a size a file only claims
(hypothesis), plus the regressions of issue 12 and the near-orthonormal rotations of issue 14."""

from __future__ import annotations

import io
import re
import shutil
import struct
import zipfile
from dataclasses import replace
from pathlib import Path

import numpy as np
import pycolmap
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import dloe_sfm
from dloe_sfm import colmap
from dloe_sfm.core.capture import Capture, memory_estimate
from dloe_sfm.errors import InputError
from dloe_sfm.io import (
    load_capture,
    load_result,
    load_truth,
    read_mocap,
    save_capture,
    save_result,
)
from dloe_sfm.resources import check_solve_memory
from dloe_sfm.stages.evaluate import main as evaluate_main
from dloe_sfm.synth import SimulationSettings, load_mocap, simulate
from dloe_sfm.truth import GroundTruth, Simulated

FUZZ = settings(max_examples=60, deadline=None,
                suppress_health_check=[HealthCheck.function_scoped_fixture])


def one_line_error(call) -> object | None:
    """Run ``call``; None when it raised a one-line InputError, else its value."""
    try:
        return call()
    except InputError as e:
        assert "\n" not in str(e) and str(e)
        return None


@pytest.fixture(scope="module")
def simulated(assets_dir) -> Simulated:
    seq = load_mocap(assets_dir / "mocap" / "walking_1.npz")
    return simulate(seq, SimulationSettings(duration=0.5, rate=10.0, num_streams=3))


@pytest.fixture(scope="module")
def capture(simulated) -> Capture:
    return simulated.capture


@pytest.fixture(scope="module")
def truth(simulated) -> GroundTruth:
    return simulated.truth


@pytest.fixture(scope="module")
def capture_bytes(capture, truth, tmp_path_factory) -> bytes:
    path = tmp_path_factory.mktemp("cap") / "capture.npz"
    save_capture(path, capture, truth)
    return path.read_bytes()


def arrays_of(capture: Capture, truth: GroundTruth) -> dict[str, np.ndarray]:
    return {"x": capture.x, "K": capture.K, "R": capture.R, "C": capture.C,
            "stream": capture.stream, "frame": capture.frame,
            "image_names": capture.image_names, **truth.arrays()}


def write_npz(path: Path, arrays: dict[str, np.ndarray]) -> Path:
    with open(path, "wb") as f:
        np.savez_compressed(f, **arrays)
    return path


def npz_with_header(path: Path, arrays: dict, key: str, shape: tuple, payload: bytes) -> Path:
    """An .npz whose member ``key`` declares ``shape`` (float64) but holds ``payload``."""
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as z:
        for k, v in arrays.items():
            with z.open(f"{k}.npy", "w") as f:
                if k == key:
                    np.lib.format.write_array_header_1_0(
                        f, {"descr": "<f8", "fortran_order": False, "shape": shape})
                    f.write(payload)
                else:
                    np.lib.format.write_array(f, np.asarray(v))
    return path


@pytest.fixture
def reads(monkeypatch) -> list[tuple]:
    """Shapes of every array the readers decompress (np.lib.format.read_array calls)."""
    seen: list[tuple] = []
    real = np.lib.format.read_array

    def spy(fp, *args, **kwargs):
        array = real(fp, *args, **kwargs)
        seen.append(array.shape)
        return array

    monkeypatch.setattr(np.lib.format, "read_array", spy)
    return seen


# --- capture files: hypothesis ---

@FUZZ
@given(data=st.data())
def test_corrupted_capture_bytes(capture_bytes, tmp_path, data) -> None:
    raw = bytearray(capture_bytes)
    kind = data.draw(st.sampled_from(["flip", "truncate", "random"]))
    if kind == "flip":
        for pos in data.draw(st.lists(st.integers(0, len(raw) - 1), min_size=1, max_size=8)):
            raw[pos] ^= data.draw(st.integers(1, 255))
    elif kind == "truncate":
        raw = raw[: data.draw(st.integers(0, len(raw) - 1))]
    else:
        raw = bytearray(data.draw(st.binary(max_size=2000)))
    path = tmp_path / "capture.npz"
    path.write_bytes(bytes(raw))
    result = one_line_error(lambda: load_capture(path))
    assert result is None or isinstance(result, Capture)


FIELDS = ("x", "K", "R", "C", "stream", "frame", "image_names", "X_true", "t_true")
DTYPES = (np.float64, np.float32, np.int64, np.uint8, bool, np.complex128, "U5", object)


@FUZZ
@given(data=st.data())
def test_random_fields(capture, truth, tmp_path, data) -> None:
    """A field of random shape, dtype and values (NaN, inf, huge): a valid capture and truth or
    one line."""
    arrays = arrays_of(capture, truth)
    key = data.draw(st.sampled_from(FIELDS))
    n = capture.num_images
    shape = tuple(data.draw(st.lists(st.sampled_from([0, 1, 2, 3, n, 28]), max_size=4)))
    dtype = data.draw(st.sampled_from(DTYPES))
    values = data.draw(st.sampled_from([0.0, 1.0, -1.0, np.nan, np.inf, 1e300]))
    if data.draw(st.booleans()):
        shape = arrays[key].shape
    array = np.full(shape, values if dtype is not object else None, dtype=object)
    if dtype is not object:
        with np.errstate(invalid="ignore", over="ignore"):
            array = np.array(array.tolist() if array.size else array, dtype=np.float64)
            array = array.astype(dtype) if np.dtype(dtype).kind != "U" else array.astype(dtype)
    if data.draw(st.booleans()) and arrays[key].dtype.kind == "f" and array.shape == shape:
        mixed = arrays[key].copy()
        mixed.flat[data.draw(st.integers(0, mixed.size - 1))] = values
        array = mixed
    arrays[key] = array
    path = tmp_path / "capture.npz"
    with open(path, "wb") as f:
        np.savez(f, **arrays)  # allow_pickle: object arrays get written
    result = one_line_error(lambda: (load_capture(path), load_truth(path)))
    assert result is None or (
        isinstance(result[0], Capture) and isinstance(result[1], GroundTruth)
    )


# --- capture files: sizes a file only claims ---

def test_lying_header_is_refused_before_allocation(capture, truth, tmp_path, reads) -> None:
    path = npz_with_header(tmp_path / "c.npz", arrays_of(capture, truth), "x", (10**6, 10**6, 2),
                           bytes(800))
    with pytest.raises(InputError, match=r"c.npz: key 'x' declares shape \(1000000, 1000000, 2\)"):
        load_capture(path)
    assert reads == []  # nothing decompressed, so nothing allocated


def test_lying_zip_directory_is_refused(capture, truth, tmp_path, reads) -> None:
    """The zip directory claims 16 TB uncompressed for 'x' (consistent with its .npy header)."""
    arrays = arrays_of(capture, truth)
    path = npz_with_header(tmp_path / "c.npz", arrays, "x", (10**6, 10**6, 2), bytes(800))
    raw = bytearray(path.read_bytes())
    entry = raw.find(b"PK\x01\x02")
    while entry >= 0:
        name_len = struct.unpack_from("<H", raw, entry + 28)[0]
        if raw[entry + 46: entry + 46 + name_len] == b"x.npy":
            struct.pack_into("<I", raw, entry + 24, 0xFFFFFFF0)  # uncompressed size
        entry = raw.find(b"PK\x01\x02", entry + 4)
    path.write_bytes(bytes(raw))
    with pytest.raises(InputError, match="c.npz: not a readable .npz file|c.npz: key 'x'"):
        load_capture(path)
    assert all(np.prod(s) <= capture.x.size * 2 for s in reads)


def test_large_unread_key_is_never_decompressed(capture, truth, tmp_path, reads) -> None:
    arrays = {**arrays_of(capture, truth), "junk": np.zeros(2**23)}  # 64 MB in ~64 KB
    path = write_npz(tmp_path / "c.npz", arrays)
    load_capture(path)
    loaded = load_truth(path)
    assert (2**23,) not in reads
    assert np.array_equal(loaded.X, truth.X) and np.array_equal(loaded.t, truth.t)


def test_truth_larger_than_the_capture_is_refused(capture, truth, tmp_path, reads) -> None:
    arrays = {**arrays_of(capture, truth), "X_true": np.zeros((capture.num_images, 50_000, 3))}
    with pytest.raises(InputError, match="key 'X_true' declares shape"):
        load_truth(write_npz(tmp_path / "c.npz", arrays))
    assert reads == []


@pytest.mark.parametrize("damage", ["crc", "deflate", "empty", "text"])
def test_unreadable_npz_is_one_line(capture_bytes, tmp_path, damage) -> None:
    raw = bytearray(capture_bytes)
    if damage == "crc":  # flip a byte of the first member's CRC in the central directory
        raw[raw.find(b"PK\x01\x02") + 16] ^= 0xFF
    elif damage == "deflate":
        raw[len(raw) // 3: len(raw) // 3 + 64] = bytes(64)
    elif damage == "empty":
        raw = bytearray()
    else:
        raw = bytearray(b"image,point_id,x,y\nimg0,0,1,2\n")
    path = tmp_path / "c.npz"
    path.write_bytes(bytes(raw))
    with pytest.raises(InputError, match=r"c.npz: (not a readable \.npz file|key )") as e:
        load_capture(path)
    assert "pickle" not in str(e.value) and "\n" not in str(e.value)


def test_object_arrays_are_refused(capture, truth, tmp_path) -> None:
    arrays = {**arrays_of(capture, truth), "K": np.array([None] * 3, dtype=object)}
    path = tmp_path / "c.npz"
    with open(path, "wb") as f:
        np.savez(f, **arrays)
    with pytest.raises(InputError, match="c.npz: key 'K' holds Python objects"):
        load_capture(path)


# --- capture values (Capture.validate) ---

def test_image_ids_follow_the_images(capture, truth) -> None:
    n = capture.num_images
    ids = {"detection_index": np.arange(n)[:, None].repeat(2, axis=1)}
    with_ids = replace(capture, image_ids=ids).validate()
    idx = np.flatnonzero(capture.stream != 1)
    part, part_truth = with_ids.subset(idx), truth.subset(idx)
    np.testing.assert_array_equal(part.image_ids["detection_index"][:, 0], idx)
    assert part_truth.X.shape[0] == part_truth.t.size == part.num_images
    np.testing.assert_array_equal(part_truth.x_clean, truth.x_clean[idx])
    assert part_truth.parents is truth.parents
    with pytest.raises(InputError, match="image ids 'colmap_frame_id' must have one entry per"):
        replace(capture, image_ids={"colmap_frame_id": np.arange(n - 1)}).validate()


def test_negative_focal_length_is_refused(capture) -> None:
    K = capture.K.copy()
    K[4, 0, 0] *= -1
    with pytest.raises(InputError, match=r"field 'K' has focal lengths \(-\d+, \d+\) for image 4"):
        Capture(x=capture.x, K=K, R=capture.R, C=capture.C, stream=capture.stream,
                frame=capture.frame).validate()


def test_nan_frame_is_refused(capture) -> None:
    frame = capture.frame.astype(float)
    frame[2] = np.nan
    with pytest.raises(InputError, match=r"field 'frame' must hold integers .* nan for image 2"):
        Capture(x=capture.x, K=capture.K, R=capture.R, C=capture.C, stream=capture.stream,
                frame=frame).validate()


def test_rotation_slightly_off_is_projected(capture, log_lines) -> None:
    R = capture.R.copy()
    R[:, 0, 0] += 1e-6
    bad = Capture(x=capture.x, K=capture.K, R=R, C=capture.C, stream=capture.stream,
                  frame=capture.frame)
    fixed = bad.validate("cap")
    assert any(re.fullmatch(r"cap: rotations projected to SO\(3\), largest deviation "
                            r"[1-3](\.\d)?e-06 \(image .*\)", line) for line in log_lines)
    assert np.abs(np.einsum("nij,nkj->nik", fixed.R, fixed.R) - np.eye(3)).max() < 1e-12
    np.testing.assert_allclose(fixed.R, capture.R, atol=2e-6)
    R[3, 1, 2] += 1e-2
    with pytest.raises(InputError, match=r"field 'R' is not a rotation for image 3 .*deviates"):
        Capture(x=capture.x, K=capture.K, R=R, C=capture.C, stream=capture.stream,
                frame=capture.frame).validate()


def test_tiny_captures(capture) -> None:
    """2 images of two streams: one line. 3-8 images (fewer than num_candidates): solved."""
    first = [int(np.flatnonzero(capture.stream == s)[0]) for s in range(3)]
    with pytest.raises(InputError, match="needs at least 3 images"):
        capture.subset(np.array(first[:2])).validate()
    for idx in (first, [*first, first[0] + 1, first[1] + 1]):
        small = capture.subset(np.array(idx)).validate()
        result = dloe_sfm.reconstruct(small, dloe_sfm.Options(max_iterations=5))
        assert sorted(result.order.tolist()) == list(range(len(idx)))
        assert np.isfinite(result.X).all()


# --- memory ---

def test_memory_estimate_and_check(capture, monkeypatch) -> None:
    small, large = memory_estimate(100, 25), memory_estimate(10_000, 25)
    assert large > 50 * small  # the (N, N) arrays dominate
    assert memory_estimate(10_000, 25, num_streams=20) > large
    # with videos the sequencing tables stay at MDS_SAMPLE images: linear in N beyond
    videos = [memory_estimate(n, 28, num_streams=16, num_videos=16) for n in (10_000, 100_000)]
    assert videos[0] < large / 5 and videos[1] < 12 * videos[0]
    options = dloe_sfm.Options()
    monkeypatch.setattr("dloe_sfm.resources.available_memory", lambda: 10 << 20)
    with pytest.raises(InputError, match=r"cap.npz: solving \d+ images x 28 points needs about "
                                         r"[\d.]+ MiB of memory, 10.0 MiB available"):
        check_solve_memory(capture, options, "cap.npz")
    monkeypatch.setattr("dloe_sfm.resources.available_memory", lambda: 1 << 40)
    check_solve_memory(capture, options, "cap.npz")


# --- result / evaluate / simulate inputs ---

@pytest.fixture(scope="module")
def solved(capture, truth, tmp_path_factory) -> tuple[Path, Path]:
    folder = tmp_path_factory.mktemp("solved")
    result = dloe_sfm.reconstruct(capture, dloe_sfm.Options(max_iterations=10))
    return save_capture(folder / "cap.npz", capture, truth), save_result(folder / "res.npz",
                                                                         result)


def test_evaluate_rejects_bad_inputs(solved, tmp_path) -> None:
    cap, res = solved
    assert evaluate_main(res, cap, references=False)["kendall_tau"] > 0.5
    with np.load(res) as d:
        arrays = {k: d[k] for k in d.files}
    for key, value, message in (
        ("order", np.array([None] * 3, dtype=object), "key 'order' holds Python objects"),
        ("order", arrays["order"][::-1] * 0, "key 'order' is not a permutation"),
        ("A_indices", arrays["A_indices"] + 10**6, "not an \\(N, N\\) sparse matrix"),
        ("X", np.zeros((2, 3)), "key 'X' must have shape \\(N, P, 3\\)"),
    ):
        bad = tmp_path / "bad.npz"
        with open(bad, "wb") as f:
            np.savez(f, **{**arrays, key: value})
        with pytest.raises(InputError, match=message):
            evaluate_main(bad, cap, references=False)
        assert load_result(res).X.shape == arrays["X"].shape
    with np.load(cap) as d:
        truth = {k: d[k] for k in d.files}
    for key, value, message in (("t_true", np.zeros(3), "'t_true' must be finite, shape"),
                                ("X_true", np.array([None], dtype=object), "key 'X_true' holds")):
        bad = write_npz(tmp_path / "badcap.npz", {**truth, key: value})
        with pytest.raises(InputError, match=message):
            evaluate_main(res, bad, references=False)


@pytest.mark.parametrize("change, message", [
    ({"positions": np.array([None, 1], dtype=object)}, "key 'positions' holds Python objects"),
    ({"positions": np.zeros((1, 28, 3))}, "key 'positions' must have shape"),
    ({"fps": np.array("x")}, "key 'fps' has dtype"),
    ({"fps": np.array(-5.0)}, "key 'fps' must be a positive number"),
    ({"parents": np.full(28, 99)}, "key 'parents' must hold joint indices"),
])
def test_mocap_inputs(assets_dir, tmp_path, change, message) -> None:
    with np.load(assets_dir / "mocap" / "walking_1.npz") as d:
        arrays = {k: d[k] for k in d.files}
    path = tmp_path / "m.npz"
    with open(path, "wb") as f:
        np.savez(f, **{**arrays, **change})
    with pytest.raises(InputError, match=message):
        read_mocap(path)


# --- COLMAP models ---

@pytest.fixture(scope="module")
def models(tmp_path_factory) -> dict[str, Path]:
    """A small synthetic model as .bin, as .txt, and as a legacy .txt (no rigs / frames)."""
    root = tmp_path_factory.mktemp("colmap")
    colmap.synthetic_workspace(root / "ws", num_cameras=3, num_frames=2, num_points3D=15)
    binary = root / "ws" / "sparse" / "0"
    text, legacy = root / "txt", root / "legacy"
    for folder in (text, legacy):
        folder.mkdir()
        pycolmap.Reconstruction(str(binary)).write_text(str(folder))
    (legacy / "rigs.txt").unlink()
    (legacy / "frames.txt").unlink()
    return {"bin": binary, "txt": text, "legacy": legacy}


def load_copy(src: Path, dest: Path, name: str, content: bytes):
    shutil.rmtree(dest, ignore_errors=True)
    shutil.copytree(src, dest)
    (dest / name).write_bytes(content)
    return one_line_error(lambda: colmap.load_workspace(dest))


@pytest.mark.parametrize("fmt", ["bin", "txt"])
def test_image_name_that_is_not_utf8(models, tmp_path, fmt) -> None:
    """A byte that is no UTF-8 in an image name: pycolmap reads it, Python cannot decode it."""
    src = models[fmt]
    name = "images.txt" if fmt == "txt" else "images.bin"
    raw = (src / name).read_bytes()
    first = colmap.load_workspace(src).image_names[0].encode()
    assert raw.count(first) >= 1
    dest = tmp_path / "m"
    shutil.copytree(src, dest)
    (dest / name).write_bytes(raw.replace(first, b"\x80" + first[1:], 1))
    with pytest.raises(InputError, match="an image name in the COLMAP model is not UTF-8"):
        colmap.load_workspace(dest)


@FUZZ
@given(data=st.data())
def test_corrupted_colmap_models(models, tmp_path, data) -> None:
    fmt = data.draw(st.sampled_from(["bin", "txt", "legacy"]))
    src = models[fmt]
    name = data.draw(st.sampled_from(sorted(p.name for p in src.iterdir())))
    raw = bytearray((src / name).read_bytes())
    kind = data.draw(st.sampled_from(["flip", "truncate", "splice"]))
    if kind == "flip" and raw:
        for pos in data.draw(st.lists(st.integers(0, len(raw) - 1), min_size=1, max_size=6)):
            raw[pos] = data.draw(st.sampled_from([0, 0xFF, ord("-"), ord("9"), ord(" "),
                                                  ord("\n"), raw[pos] ^ 0x40]))
    elif kind == "truncate":
        raw = raw[: data.draw(st.integers(0, max(len(raw) - 1, 0)))]
    else:
        pos = data.draw(st.integers(0, len(raw)))
        raw[pos:pos] = data.draw(st.binary(min_size=1, max_size=16))
    ws = load_copy(src, tmp_path / "m", name, bytes(raw))
    if ws is not None:
        for image in ws.image_names:
            R = ws.rotation(image)
            assert np.abs(R @ R.T - np.eye(3)).max() < 1e-9
            assert np.isfinite(ws.pinhole(image)).all() and ws.pinhole(image)[0, 0] > 0


def edit_line(text: str, startswith: str, field: int, value: str) -> str:
    lines = text.splitlines()
    for i, line in enumerate(lines):
        if line.startswith(startswith):
            parts = line.split()
            parts[field] = value
            lines[i] = " ".join(parts)
            break
    return "\n".join(lines) + "\n"


@pytest.mark.parametrize("value", ["-1280", "0"])
def test_unusable_camera_is_an_error_naming_it(models, tmp_path, value) -> None:
    text = (models["txt"] / "cameras.txt").read_text()
    shutil.copytree(models["txt"], tmp_path / "m")
    (tmp_path / "m" / "cameras.txt").write_text(edit_line(text, "2 ", 4, value))
    with pytest.raises(InputError, match=rf"m: camera 2 \(SIMPLE_RADIAL\) has focal length "
                                         rf"\[{float(value)}\]; it must be positive"):
        colmap.load_workspace(tmp_path / "m")


def test_truncated_and_empty_model_files(models, tmp_path) -> None:
    raw = (models["bin"] / "images.bin").read_bytes()
    with pytest.raises(InputError, match=r"m: cannot read the COLMAP model \(images.bin is "
                                         r"truncated or corrupt"):
        load_copy(models["bin"], tmp_path / "m", "images.bin", raw[: len(raw) // 2]) or \
            colmap.load_workspace(tmp_path / "m")
    shutil.rmtree(tmp_path / "m")
    shutil.copytree(models["txt"], tmp_path / "m")
    (tmp_path / "m" / "images.txt").write_bytes(b"")
    with pytest.raises(InputError, match=r"m: cannot read the COLMAP model"):
        colmap.load_workspace(tmp_path / "m")


def test_colmap_claimed_counts_are_not_allocated(models, tmp_path) -> None:
    """A points3D.bin claiming 2^40 track elements is refused by the walk, not by bad_alloc."""
    raw = bytearray((models["bin"] / "points3D.bin").read_bytes())
    struct.pack_into("<Q", raw, 8 + 43, 2**40)  # first point's track length
    shutil.copytree(models["bin"], tmp_path / "m")
    (tmp_path / "m" / "points3D.bin").write_bytes(bytes(raw))
    with pytest.raises(InputError, match=r"points3D.bin is truncated or corrupt: 1099511627776 "
                                         r"entries declared"):
        colmap.load_workspace(tmp_path / "m")


def test_quaternion_slightly_off_is_projected(models, tmp_path, log_lines) -> None:
    """Legacy text models keep the quaternion as written: 1e-6 off is projected, 1e-2 refused."""
    text = (models["legacy"] / "images.txt").read_text()
    line = next(ln for ln in text.splitlines() if ln and not ln.startswith("#")
                and ln.endswith(".png"))
    parts = line.split()
    reference = colmap.load_workspace(models["legacy"])
    for scale, ok in ((1 + 5e-7, True), (1.01, False)):
        q = [repr(float(v) * scale) for v in parts[1:5]]
        shutil.rmtree(tmp_path / "m", ignore_errors=True)
        shutil.copytree(models["legacy"], tmp_path / "m")
        (tmp_path / "m" / "images.txt").write_text(text.replace(line, " ".join(
            [parts[0], *q, *parts[5:]])))
        if not ok:
            with pytest.raises(InputError, match=rf"m: image '{parts[-1]}' has a rotation "
                                                 r"0.0\d+ from orthonormal"):
                colmap.load_workspace(tmp_path / "m")
            continue
        ws = colmap.load_workspace(tmp_path / "m")
        assert any(re.search(r"m: rotations projected to SO\(3\), largest deviation "
                             r"\d(\.\d)?e-06", line) for line in log_lines)
        R = ws.rotation(parts[-1])
        assert np.abs(R @ R.T - np.eye(3)).max() < 1e-12
        np.testing.assert_allclose(R, reference.rotation(parts[-1]), atol=1e-6)
        np.testing.assert_allclose(ws.centre(parts[-1]), reference.centre(parts[-1]), atol=1e-5)


def test_object_bytes_in_npz_named_like_text(tmp_path) -> None:
    """A pickle inside a zip member is refused by its header, never unpickled."""
    buf = io.BytesIO()
    np.save(buf, np.array([{"a": 1}], dtype=object), allow_pickle=True)
    with zipfile.ZipFile(tmp_path / "c.npz", "w") as z:
        for key in ("x", "K", "R", "C"):
            z.writestr(f"{key}.npy", buf.getvalue())
    with pytest.raises(InputError, match="key 'x' holds Python objects"):
        load_capture(tmp_path / "c.npz")


def test_simulate_settings_and_outputs(assets_dir, tmp_path, solved) -> None:
    from dloe_sfm.stages.simulate import main as simulate_main

    mocap = assets_dir / "mocap" / "walking_1.npz"
    for bad, message in (({"rate": 0.0}, r"--rate must be in \(0, 1000\]"),
                         ({"drop": 1.0}, r"--drop must be in \[0, 1\)"),
                         ({"focal": float("nan")}, "--focal")):
        with pytest.raises(InputError, match=message):
            SimulationSettings(**bad)
    with pytest.raises(InputError, match=r"--outliers must be in \[0, 1\]"):
        simulate_main(mocap, tmp_path / "c.npz", outliers=1.5)
    copy = tmp_path / "m.npz"
    shutil.copy(mocap, copy)
    with pytest.raises(InputError, match="the output is the input mocap file"):
        simulate_main(copy, copy)
    assert copy.read_bytes() == mocap.read_bytes()
    cap, res = solved
    before = res.read_bytes()
    with pytest.raises(InputError, match="the output is the input file"):
        evaluate_main(res, cap, references=False, out=res)
    assert res.read_bytes() == before
