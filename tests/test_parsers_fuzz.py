"""Hostile input for every keypoint parser and ``build_capture``: a valid result or a one-line
InputError, never another exception or a huge allocation (hypothesis), plus the regressions of
issue 12 (deep JSON, wrong JSON types, lying image headers, ids that size arrays, odd CSV)."""

from __future__ import annotations

import csv
import io
import json
import logging
import struct
import tempfile
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dloe_sfm import colmap
from dloe_sfm.errors import InputError
from dloe_sfm.keypoints import Keypoints, Layout, load_layout, match_names, read_keypoints
from dloe_sfm.keypoints.base import MAX_POINTS
from dloe_sfm.observations import build_capture

FUZZ = settings(max_examples=40, deadline=None, database=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])


@pytest.fixture(scope="module")
def ws(tmp_path_factory) -> colmap.Workspace:
    """2 video cameras x 3 frames (``cameraNNNNNN_frameNNNNNN.png``, 1024 x 768)."""
    root = colmap.synthetic_workspace(tmp_path_factory.mktemp("fuzz") / "ws", num_cameras=2,
                                      num_frames=3)
    return colmap.load_workspace(root)


@pytest.fixture(scope="module")
def scratch(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("inputs")


def fresh(scratch: Path) -> Path:
    """A new empty folder for one example."""
    return Path(tempfile.mkdtemp(dir=scratch))


def outcome(call):
    """``call()``'s result, or None when it raised an InputError of exactly one line; any other
    exception propagates (and fails the test)."""
    try:
        return call()
    except InputError as e:
        message = str(e)
        assert message.strip() and len(message.splitlines()) == 1, repr(message)
        return None


def check_keypoints(kp: Keypoints) -> None:
    """(M, P, 3) float arrays; observed = positive score with finite x, y; missing = NaN, 0."""
    assert isinstance(kp, Keypoints) and isinstance(kp.layout, Layout)
    p = kp.layout.num_points
    assert 1 <= p <= MAX_POINTS
    for a, b in kp.layout.edges + kp.layout.symmetric_pairs:
        assert 0 <= a < p and 0 <= b < p
    for arr in kp.points.values():
        assert arr.dtype == np.float64 and arr.ndim == 3 and arr.shape[1:] == (p, 3)
        seen = arr[..., 2] > 0
        assert np.isfinite(arr[seen]).all()
        assert np.isnan(arr[~seen][:, :2]).all() and (arr[~seen][:, 2] == 0).all()


def through(fmt: str, path: Path, ws: colmap.Workspace, person, **options) -> Keypoints | None:
    """``read_keypoints`` and then ``build_capture``: valid results or one-line errors; the
    keypoints (None after an error)."""
    kp = outcome(lambda: read_keypoints(fmt, path, workspace=ws, **options))
    if kp is None:
        return None
    check_keypoints(kp)
    observations = outcome(lambda: build_capture(ws, kp, person=person))
    if observations is not None:
        capture, skipped, unobserved = observations
        capture.validate()
        assert capture.num_points + len(unobserved) == kp.num_points
        assert set(capture.image_names) <= set(ws.image_names)
        assert not set(skipped) & set(capture.image_names)
    return kp


# --- strategies ------------------------------------------------------------------------------
# Each example is either well-formed (valid results reach build_capture) or hostile: then any
# field may be any JSON value, numbers may be NaN / inf / huge, files may be damaged.

SCALARS = (st.none() | st.booleans() | st.integers(-2**70, 2**70)
           | st.floats(allow_nan=True, allow_infinity=True) | st.text(max_size=6))
ANY_JSON = st.recursive(
    SCALARS, lambda c: st.lists(c, max_size=4) | st.dictionaries(st.text(max_size=6), c,
                                                                 max_size=4),
    max_leaves=10,
)
NUMBER = (st.floats(allow_nan=True, allow_infinity=True) | st.integers(-10, 2000)
          | st.sampled_from([1e308, -1e308, 5e-324, -0.0]))
PERSON = st.sampled_from(["auto", "all", "largest", 0, 1])
# whole-file damage: a byte order mark, cut in half, bytes that are not UTF-8, empty
DAMAGE = st.sampled_from(["none", "none", "bom", "cut", "not_utf8", "empty"])


class Fuzz:
    """Strategies of one example: well-formed, or ``hostile``."""

    def __init__(self, hostile: bool) -> None:
        self.hostile = hostile

    def maybe(self, valid: st.SearchStrategy) -> st.SearchStrategy:
        """``valid``; when hostile, sometimes any JSON value in its place."""
        return st.one_of(valid, valid, ANY_JSON) if self.hostile else valid

    def numbers(self, size: int, low: float = 100.0, high: float = 700.0) -> st.SearchStrategy:
        """``size`` numbers in [low, high]; when hostile, also odd numbers or a wrong size."""
        good = st.lists(st.floats(low, high), min_size=size, max_size=size)
        if not self.hostile:
            return good
        return good | st.lists(NUMBER, min_size=size, max_size=size) | st.lists(
            NUMBER, max_size=size + 3)

    def keypoints(self, p: int, columns: int) -> st.SearchStrategy:
        """(x, y[, score]) of p points, flat."""
        point = st.tuples(st.floats(100, 700), st.floats(100, 700),
                          *[st.floats(0.05, 1.0)] * (columns - 2))
        good = st.lists(point, min_size=p, max_size=p).map(
            lambda pts: [v for pt in pts for v in pt])
        return self.maybe(good | self.numbers(columns * p)) if self.hostile else good

    def pairs(self, p: int, base: int = 0) -> st.SearchStrategy:
        """Lists of point index pairs, two different points in base..base + p - 1."""
        good = st.lists(st.lists(st.integers(base, base + p - 1), min_size=2, max_size=2,
                                 unique=True), max_size=3) if p > 1 else st.just([])
        bad = st.lists(st.lists(st.integers(-1, p + 1), min_size=1, max_size=3), max_size=3)
        return self.maybe(good | bad) if self.hostile else good

    def damage(self) -> st.SearchStrategy:
        return DAMAGE if self.hostile else st.sampled_from(["none", "bom"])


def damaged(text: str, how: str) -> bytes:
    data = text.encode()
    return {"bom": b"\xef\xbb\xbf" + data, "cut": data[:len(data) // 2],
            "not_utf8": data[:5] + b"\xff\xfe\x80" + data[5:], "empty": b""}.get(how, data)


def file_names(ws: colmap.Workspace, fuzz: Fuzz) -> st.SearchStrategy:
    """Image stems of ``ws`` (all of them when well-formed); when hostile some of them and odd
    names (unicode, line breaks, a folder)."""
    stems = [Path(n).stem for n in ws.image_names]
    if not fuzz.hostile:
        return st.just(stems)
    return st.lists(st.sampled_from([*stems, "zz", "a\nb", "ü/é", "x\u2028y"]), min_size=1,
                    max_size=len(stems), unique=True)


def openpose_doc(fuzz: Fuzz, p: int) -> st.SearchStrategy:
    person = st.fixed_dictionaries({"pose_keypoints_2d": fuzz.keypoints(p, 3)})
    return fuzz.maybe(st.fixed_dictionaries(
        {"people": fuzz.maybe(st.lists(fuzz.maybe(person), max_size=3))}))


def coco_doc(fuzz: Fuzz, names: list[str], p: int) -> st.SearchStrategy:
    ids = st.integers(0, len(names) - 1)
    images = st.just([{"id": i, "file_name": name} for i, name in enumerate(names)])
    if fuzz.hostile:
        image = st.fixed_dictionaries({"id": fuzz.maybe(ids),
                                       "file_name": fuzz.maybe(st.sampled_from(names))})
        images = images | st.lists(fuzz.maybe(image), max_size=len(names))
    annotation = st.fixed_dictionaries({
        "image_id": fuzz.maybe(ids), "keypoints": fuzz.keypoints(p, 3),
        "category_id": fuzz.maybe(st.just(1)),
    })
    category = st.fixed_dictionaries({
        "id": fuzz.maybe(st.just(1)), "name": fuzz.maybe(st.just("person")),
        "keypoints": fuzz.maybe(st.lists(st.text(max_size=4), min_size=p, max_size=p)),
        "skeleton": fuzz.pairs(p, base=1),
    })
    return fuzz.maybe(st.fixed_dictionaries({
        "images": fuzz.maybe(images),
        "annotations": fuzz.maybe(st.lists(fuzz.maybe(annotation),
                                           min_size=1 if fuzz.hostile else 8, max_size=16)),
        "categories": fuzz.maybe(st.lists(fuzz.maybe(category), min_size=1, max_size=2)),
    }))


def mmpose_doc(fuzz: Fuzz, p: int) -> st.SearchStrategy:
    xy = fuzz.keypoints(p, 2).map(
        lambda flat: [flat[i:i + 2] for i in range(0, len(flat), 2)]
        if isinstance(flat, list) else flat)
    instance = st.fixed_dictionaries({"keypoints": fuzz.maybe(xy)}, optional={
        "keypoint_scores": fuzz.maybe(fuzz.numbers(p, 0.05, 1.0))})
    instances = st.lists(fuzz.maybe(instance), max_size=3)
    keys = st.sampled_from([*map(str, range(p)), *(["x", "-1", "1.5", " 2 "] * fuzz.hostile)])
    meta = st.fixed_dictionaries({
        "keypoint_id2name": fuzz.maybe(st.dictionaries(keys, st.text(max_size=3),
                                                       max_size=p + 1)),
        "skeleton_links": fuzz.pairs(p), "flip_pairs": fuzz.pairs(p),
        "dataset_name": fuzz.maybe(st.just("coco")),
    })
    per_image = fuzz.maybe(instances) | st.fixed_dictionaries(
        {"meta_info": fuzz.maybe(meta), "instance_info": fuzz.maybe(instances)})
    if not fuzz.hostile:
        return per_image
    # a video's frames (keys FILE/<frame>, which match no image of the workspace)
    frame = st.fixed_dictionaries({"frame_id": fuzz.maybe(st.integers(0, 3)),
                                   "instances": fuzz.maybe(instances)})
    return per_image | st.lists(fuzz.maybe(frame), max_size=3)


def write_json(folder: Path, name: str, doc, how: str) -> None:
    file = folder / name
    file.parent.mkdir(parents=True, exist_ok=True)
    file.write_bytes(damaged(json.dumps(doc), how))


# --- property tests --------------------------------------------------------------------------

@pytest.mark.parametrize(("fmt", "counts", "suffix", "doc"), [
    ("openpose", [1, 3, 25], "_keypoints.json", openpose_doc),
    ("mmpose", [1, 3, 17], ".json", mmpose_doc),
])
@FUZZ
@given(data=st.data(), fuzz=st.builds(Fuzz, st.booleans()))
def test_per_image_json_fuzz(ws, scratch, fmt, counts, suffix, doc, data, fuzz) -> None:
    """One JSON file per image (OpenPose, MMPose)."""
    p = data.draw(st.sampled_from(counts), label="points")
    folder = fresh(scratch)
    for name in data.draw(file_names(ws, fuzz), label="files"):
        write_json(folder, f"{name}{suffix}", data.draw(doc(fuzz, p)), data.draw(fuzz.damage()))
    through(fmt, folder, ws, data.draw(PERSON))


@FUZZ
@given(data=st.data(), fuzz=st.builds(Fuzz, st.booleans()))
def test_coco_fuzz(ws, scratch, data, fuzz) -> None:
    p = data.draw(st.sampled_from([1, 4, 17]), label="points")
    names = [*ws.image_names, *(["zz.png", "a\nb.png"] * fuzz.hostile)]
    folder = fresh(scratch)
    write_json(folder, "coco.json", data.draw(coco_doc(fuzz, names, p)),
               data.draw(fuzz.damage()))
    kp = through("coco", folder / "coco.json", ws, data.draw(PERSON))
    assert fuzz.hostile or kp is not None


@FUZZ
@given(data=st.data(), fuzz=st.builds(Fuzz, st.booleans()))
def test_layout_file_fuzz(scratch, data, fuzz) -> None:
    p = data.draw(st.integers(1, 4), label="points")
    doc = data.draw(fuzz.maybe(st.fixed_dictionaries({
        "point_names": fuzz.maybe(st.lists(st.text(max_size=3), min_size=p, max_size=p)),
        "edges": fuzz.pairs(p), "symmetric_pairs": fuzz.pairs(p),
        "name": fuzz.maybe(st.text(max_size=8)),
    })))
    folder = fresh(scratch)
    write_json(folder, "layout.json", doc, data.draw(fuzz.damage()))
    layout = outcome(lambda: load_layout(folder / "layout.json"))
    if layout is not None:
        p = layout.num_points
        assert p >= 1 and all(0 <= i < p for pair in layout.edges for i in pair)
        assert all(0 <= a < p and 0 <= b < p and a != b for a, b in layout.symmetric_pairs)


CSV_COLUMNS = ("image", "point_id", "x", "y", "score", "person")


def csv_cell(kind: str, ws: colmap.Workspace, fuzz: Fuzz) -> st.SearchStrategy:
    good = {"image": st.sampled_from(ws.image_names), "point_id": st.integers(0, 3).map(str),
            "person": st.integers(0, 1).map(str), "score": st.floats(0.05, 1.0).map(repr)
            }.get(kind, st.floats(100, 700).map(repr))
    if not fuzz.hostile:
        return good
    odd_text = st.text(max_size=5) | st.sampled_from(["nan", "inf", "-1", "1e9", "", "٣", "0x1"])
    odd = {"image": st.sampled_from(["zz.png", "a\nb", "ü,é", 'q"q']),
           "point_id": st.integers(-2, 2**40).map(str) | st.sampled_from(
               ["1000000000", "99999"]),
           "person": st.integers(-2, 2**40).map(str) | st.just("999"),
           }.get(kind, NUMBER.map(repr))
    return good | odd | odd_text


@FUZZ
@given(data=st.data(), fuzz=st.builds(Fuzz, st.booleans()))
def test_csv_fuzz(ws, scratch, data, fuzz) -> None:
    header = data.draw(st.permutations(CSV_COLUMNS), label="order")
    if fuzz.hostile:
        header = header[:data.draw(st.integers(3, len(header)), label="columns")]
    else:
        header = [c for c in header if c != "score" or data.draw(st.booleans())]
    key = [header.index(c) for c in ("image", "point_id", "person") if c in header]
    rows = data.draw(st.lists(st.tuples(*(csv_cell(c, ws, fuzz) for c in header)),
                              min_size=0 if fuzz.hostile else 8, max_size=30,
                              unique_by=None if fuzz.hostile else
                              (lambda row: tuple(row[k] for k in key))), label="rows")
    text = io.StringIO()
    writer = csv.writer(text, lineterminator=data.draw(st.sampled_from(["\n", "\r\n", "\r"])))
    writer.writerow([c.upper() if data.draw(st.booleans()) else c for c in header])
    writer.writerows(rows)
    folder = fresh(scratch)
    (folder / "kp.csv").write_bytes(damaged(text.getvalue(), data.draw(fuzz.damage())))
    options = data.draw(st.sampled_from([{}, {"layout": "COCO_17"}])) if fuzz.hostile else {}
    kp = through("csv", folder / "kp.csv", ws, data.draw(PERSON), **options)
    assert fuzz.hostile or kp is not None


def png_bytes(width: int, height: int, pixels: bytes = b"\0" * 16) -> bytes:
    """A PNG whose header claims ``width`` x ``height`` grey pixels, holding ``pixels``."""
    def chunk(kind: bytes, body: bytes) -> bytes:
        return (struct.pack(">I", len(body)) + kind + body
                + struct.pack(">I", zlib.crc32(kind + body)))
    header = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header)
            + chunk(b"IDAT", zlib.compress(pixels)) + chunk(b"IEND", b""))


def marker_image(marker_id: int) -> np.ndarray:
    """ArUco DICT_4X4_50 marker ``marker_id`` on a white 80 x 80 square."""
    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50)
    image = np.full((80, 80), 255, np.uint8)
    image[20:60, 20:60] = cv2.aruco.generateImageMarker(dictionary, marker_id, 40)
    return image


@st.composite
def image_file(draw) -> tuple[str, bytes]:
    """(suffix, bytes): a real small image (noise or a marker), a lying or broken PNG, junk."""
    kind = draw(st.sampled_from(["marker", "marker", "noise", "lying", "truncated", "junk"]))
    if kind in ("noise", "marker"):
        if kind == "marker":
            pixels = marker_image(draw(st.integers(0, 49)))
        else:
            shape = (draw(st.integers(1, 40)), draw(st.integers(1, 40)))
            pixels = np.random.default_rng(draw(st.integers(0, 99))).integers(
                0, 256, shape, dtype=np.uint8)
        suffix = draw(st.sampled_from([".png", ".jpg"]))
        return suffix, cv2.imencode(suffix, pixels)[1].tobytes()
    if kind == "lying":
        size = st.integers(1, 2**31 - 1) | st.integers(1, 64)
        return ".png", png_bytes(draw(size), draw(size))
    if kind == "truncated":
        data = cv2.imencode(".png", marker_image(0))[1].tobytes()
        return ".png", data[:draw(st.integers(0, len(data) - 1))]
    return draw(st.sampled_from([".png", ".jpg"])), draw(st.binary(max_size=64))


@settings(FUZZ, max_examples=30)
@given(files=st.lists(image_file(), min_size=1, max_size=3))
def test_aruco_fuzz(scratch, files) -> None:
    folder = fresh(scratch)
    for k, (suffix, data) in enumerate(files):
        (folder / f"image{k}{suffix}").write_bytes(data)
    kp = outcome(lambda: read_keypoints("aruco", folder))
    if kp is not None:
        check_keypoints(kp)
        assert kp.num_points % 4 == 0 and len(kp.points) == len(files)


# --- regressions (issue 12) ------------------------------------------------------------------

def one_line_error(call, match: str) -> str:
    with pytest.raises(InputError, match=match) as info:
        call()
    assert len(str(info.value).splitlines()) == 1
    return str(info.value)


@pytest.mark.parametrize("fmt", ["openpose", "coco", "mmpose", "layout"])
def test_deeply_nested_json(tmp_path, fmt) -> None:
    path = tmp_path / "deep.json"
    path.write_text("[" * 100_000 + "]" * 100_000)
    call = (lambda: load_layout(path)) if fmt == "layout" else \
        (lambda: read_keypoints(fmt, path))
    one_line_error(call, r"deep\.json: JSON nested too deeply")


def coco(tmp_path: Path, **fields) -> Path:
    doc = {"images": [{"id": 1, "file_name": "a.jpg"}],
           "annotations": [{"image_id": 1, "keypoints": [10, 20, 2] * 2}],
           "categories": [{"id": 1, "name": "person", "keypoints": ["l", "r"]}]}
    (tmp_path / "coco.json").write_text(json.dumps(doc | fields))
    return tmp_path / "coco.json"


def test_coco_wrong_types(tmp_path) -> None:
    kp = read_keypoints("coco", coco(tmp_path))
    np.testing.assert_array_equal(kp.points["a.jpg"], [[[10, 20, 1], [10, 20, 1]]])
    one_line_error(lambda: read_keypoints("coco", coco(tmp_path, categories=5)),
                   r"coco\.json: 'categories' must be a list, got 5$")
    one_line_error(lambda: read_keypoints("coco", coco(tmp_path, images=[
        {"id": [1], "file_name": "a.jpg"}])), r"images\[0\] 'id' must be an integer or a string")
    one_line_error(lambda: read_keypoints("coco", coco(tmp_path, annotations=[
        {"image_id": [1], "keypoints": [1, 2, 1] * 2}])),
        r"annotation 0: 'image_id' must be an integer or a string, got a list$")
    one_line_error(lambda: read_keypoints("coco", coco(tmp_path, annotations=[
        {"image_id": 1, "keypoints": ["1", 2, 1] * 2}])), "keypoints are not a list of numbers")
    one_line_error(lambda: read_keypoints("coco", coco(tmp_path, annotations=[
        {"image_id": 1, "keypoints": [[10, 20, 2]] * 2}])),
        r"annotation 0: expected a flat list of 2 x 3 numbers, got shape \(2, 3\)$")
    one_line_error(lambda: read_keypoints("coco", coco(tmp_path, categories=[
        {"id": 1, "keypoints": ["l", "r"], "skeleton": [[1, 2, 3]]}])),
        r"'skeleton'\[0\] must be a pair of point indices")
    one_line_error(lambda: read_keypoints("coco", coco(tmp_path, categories=[
        {"id": 1, "keypoints": ["l", "r"], "skeleton": [[1, 1e999]]}])),
        r"'skeleton'\[0\] must be a pair")


def mmpose(tmp_path: Path, **meta) -> Path:
    instance = {"keypoints": [[1.0, 2.0], [3.0, 4.0]], "keypoint_scores": [0.9, 0.8]}
    doc = {"meta_info": {"keypoint_id2name": {"0": "l", "1": "r"}} | meta,
           "instance_info": [instance]}
    (tmp_path / "frame.json").write_text(json.dumps(doc))
    return tmp_path / "frame.json"


def test_mmpose_meta_info_types(tmp_path) -> None:
    assert read_keypoints("mmpose", mmpose(tmp_path)).layout.point_names == ["l", "r"]
    one_line_error(lambda: read_keypoints("mmpose", mmpose(tmp_path, keypoint_id2name={
        "nose": "l", "1": "r"})), r"frame\.json: meta_info 'keypoint_id2name' key 'nose' is not")
    one_line_error(lambda: read_keypoints("mmpose", mmpose(tmp_path, skeleton_links=[
        [0, 1, 1]])), r"meta_info 'skeleton_links'\[0\] must be a pair of point indices")
    one_line_error(lambda: read_keypoints("mmpose", mmpose(tmp_path, flip_pairs=[[0, 5]])),
                   r"'flip_pairs'\[0\] \(0, 5\) out of range 0\.\.1")


@pytest.mark.parametrize(("size", "match"), [
    ((100_000, 100_000), r"big\.png: image larger than"),
    ((13_000, 12_000), r"big\.png: image of 13000 x 12000 pixels, more than"),
])
def test_aruco_checks_the_header_before_decoding(tmp_path, size, match) -> None:
    (tmp_path / "big.png").write_bytes(png_bytes(*size))
    one_line_error(lambda: read_keypoints("aruco", tmp_path), match)


def test_aruco_unreadable_image(tmp_path) -> None:
    (tmp_path / "bad.jpg").write_bytes(b"not an image")
    one_line_error(lambda: read_keypoints("aruco", tmp_path), r"bad\.jpg: cannot read the image")


CSV_HEADER = "image,point_id,x,y,score,person\n"


@pytest.mark.parametrize(("rows", "match"), [
    ("a.png,0,1,2,1,0\na.png,1000000000,1,2,1,0\n",
     r"kp\.csv:3: point_id 1000000000 out of range 0\.\.99999$"),
    ("a.png,0,1,2,1,10000000\n", r"kp\.csv:2: person 10000000 out of range 0\.\.999"),
    ("a.png,99999,1,2,1,999\n", r"kp\.csv: 1 rows spread over 1000 detections of 100000 points"),
    ("a.png,1e9,1,2,1,0\n", r"kp\.csv:2: column 'point_id' is not an integer \('1e9'\)"),
    ("a.png,0,nan,2,1,0\n", r"kp\.csv:2: column 'x' is NaN or infinite"),
])
def test_csv_ids_are_bounded_before_allocation(tmp_path, rows, match) -> None:
    (tmp_path / "kp.csv").write_text(CSV_HEADER + rows)
    one_line_error(lambda: read_keypoints("csv", tmp_path / "kp.csv"), match)


def test_csv_odd_but_valid_text(tmp_path) -> None:
    """A byte order mark, CRLF, upper-case headers and unicode names read as plain CSV."""
    rows = ["image,point_id,x,y", "Kamera_ü/0012.jpg,0,1,2", "Kamera_ü/0012.jpg,1,3,4"]
    (tmp_path / "plain.csv").write_text("\n".join(rows) + "\n", encoding="utf-8")
    (tmp_path / "odd.csv").write_bytes(
        b"\xef\xbb\xbf" + "\r\n".join([rows[0].upper(), *rows[1:]]).encode() + b"\r\n")
    plain = read_keypoints("csv", tmp_path / "plain.csv")
    odd = read_keypoints("csv", tmp_path / "odd.csv")
    assert list(odd.points) == ["Kamera_ü/0012.jpg"]
    name = "Kamera_ü/0012.jpg"
    np.testing.assert_array_equal(odd.points[name], plain.points[name])
    assert match_names(["Kamera_ü/12"], ["Kamera_ü/0012.jpg"], "kp") == {
        "Kamera_ü/12": "Kamera_ü/0012.jpg"}


def test_a_line_break_in_a_name_stays_escaped(ws, tmp_path) -> None:
    name = ws.image_names[0]
    (tmp_path / "kp.csv").write_text(
        f'{CSV_HEADER}"{name}\ndloe-sfm: error: all good",0,1,2,1,0\n{name},0,1,2,1,0\n')
    kp = read_keypoints("csv", tmp_path / "kp.csv", workspace=ws)
    message = one_line_error(lambda: build_capture(ws, kp), "not in the COLMAP model")
    assert "\\ndloe-sfm: error: all good'" in message
    (tmp_path / "kp.csv").write_text(f'{CSV_HEADER}"a\nb",0,1,2,1,0\n"a\nb",0,1,2,1,0\n')
    one_line_error(lambda: read_keypoints("csv", tmp_path / "kp.csv"),
                   r"kp\.csv:4: point 0 of person 0 in 'a\\nb' given twice")


def test_a_stem_shared_by_several_images_matches_none() -> None:
    """Keypoints of an image the model does not have (cam9) are unmatched, not 'ambiguous'."""
    names = ["cam0/003.jpg", "cam1/003.jpg", "cam2/003.jpg"]
    assert match_names(["cam9/003.jpg", "cam1/003"], names, "kp") == {
        "cam9/003.jpg": "cam9/003.jpg", "cam1/003": "cam1/003.jpg"}


@pytest.mark.parametrize(("content", "match"), [
    (b"", r"kp\.json: malformed JSON at line 1"),
    (b'{"people": [\xff]}', r"kp\.json: not a UTF-8 text file"),
    (b"[]", r"kp\.json: not OpenPose output"),
    (b'{"people": {"a": 1}}', r"kp\.json: not OpenPose output"),
    (b'{"people": [{"pose_keypoints_2d": [true, 1, 1]}]}', "keypoints are not a list of numbers"),
    (b'{"people": [{"pose_keypoints_2d": [1, 1]}]}', r"not 3 x joints \(2\)"),
    (b'{"people": [{"pose_keypoints_2d": []}]}', r"0 points per detection \(expected 1\.\."),
    (b'{"people": [{"pose_keypoints_2d": [1, 2, 1e999]}]}', "NaN or infinite"),
    (b'\xef\xbb\xbf{"people": [{"pose_keypoints_2d": [1, 2, 1]}]}', None),
])
def test_openpose_bad_files(tmp_path, content, match) -> None:
    (tmp_path / "kp.json").write_bytes(content)
    if match is None:
        kp = read_keypoints("openpose", tmp_path / "kp.json")
        np.testing.assert_array_equal(kp.points["kp"], [[[1, 2, 1]]])
    else:
        one_line_error(lambda: read_keypoints("openpose", tmp_path / "kp.json"), match)


def test_a_folder_where_a_file_is_expected(tmp_path) -> None:
    (tmp_path / "dir.json").mkdir()
    (tmp_path / "dir.csv").mkdir()
    one_line_error(lambda: read_keypoints("coco", tmp_path / "dir.json"), r"dir\.json: cannot read")
    one_line_error(lambda: read_keypoints("csv", tmp_path / "dir.csv"), r"dir\.csv: cannot read")
    one_line_error(lambda: read_keypoints("openpose", tmp_path), "no .json files in the folder")


def projected_openpose(ws: colmap.Workspace, folder: Path, X: np.ndarray,
                       people: dict[str, int]) -> Path:
    """OpenPose files of every image: X (P, 3) projected, ``people[name]`` times (default 1)."""
    for name in ws.image_names:
        uv = ws.project(name, X) - 0.5
        person = np.column_stack([uv, np.ones(len(X))]).ravel().tolist()
        doc = {"people": [{"pose_keypoints_2d": person}] * people.get(name, 1)}
        (folder / f"{Path(name).stem}_keypoints.json").write_text(json.dumps(doc))
    return folder


def test_images_without_detections_are_skipped_and_listed(ws, tmp_path, caplog) -> None:
    X = ws.static_xyz[:5]
    nobody = [ws.image_names[0], ws.image_names[4]]  # one image of each camera
    folder = projected_openpose(ws, tmp_path, X, dict.fromkeys(nobody, 0))
    low = ws.image_names[1]  # a detection whose every score is below min_score
    doc = json.loads((folder / f"{Path(low).stem}_keypoints.json").read_text())
    doc["people"][0]["pose_keypoints_2d"][2::3] = [0.1] * len(X)
    (folder / f"{Path(low).stem}_keypoints.json").write_text(json.dumps(doc))
    kp = read_keypoints("openpose", folder, workspace=ws)
    logger = logging.getLogger("dloe_sfm")  # may not propagate to caplog's root handler
    logger.addHandler(caplog.handler)
    try:
        capture, skipped_images, _ = build_capture(ws, kp, min_score=0.5)
    finally:
        logger.removeHandler(caplog.handler)
    skipped = sorted([*nobody, low])
    assert sorted(skipped_images) == skipped
    assert sorted(capture.image_names) == sorted(set(ws.image_names) - set(skipped))
    # one record (seen once or twice: by our handler and by the root's when it propagates)
    warnings = list({r for r in caplog.records if r.levelno == logging.WARNING})
    assert len(warnings) == 1 and all(n in warnings[0].getMessage() for n in skipped)
    # nothing left: an error, not an empty capture
    one_line_error(lambda: build_capture(ws, kp, min_score=2.0),
                   "no usable observation in any registered image")
    one_line_error(lambda: build_capture(ws, kp, min_score=float("nan")),
                   "min_score must be a finite number, got nan")


def test_person_index_beyond_every_image(ws, tmp_path) -> None:
    two = [ws.image_names[1], ws.image_names[2], ws.image_names[5]]  # of both cameras
    folder = projected_openpose(ws, tmp_path, ws.static_xyz[:5], dict.fromkeys(two, 2))
    kp = read_keypoints("openpose", folder, workspace=ws)
    # images with fewer detections than the index are left out
    assert list(build_capture(ws, kp, person=1).capture.image_names) == two
    one_line_error(lambda: build_capture(ws, kp, person=10_000_000),
                   r"person index 10000000: no image holds more than 2 detection\(s\)")


def test_absurd_pixels_are_not_observations(ws, tmp_path) -> None:
    X = ws.static_xyz[:5]
    folder = projected_openpose(ws, tmp_path, X, {})
    name = ws.image_names[3]
    doc = json.loads((folder / f"{Path(name).stem}_keypoints.json").read_text())
    doc["people"][0]["pose_keypoints_2d"][0:2] = [1e308, -1e308]
    (folder / f"{Path(name).stem}_keypoints.json").write_text(json.dumps(doc))
    capture = build_capture(ws, read_keypoints("openpose", folder, workspace=ws)).capture
    i = list(capture.image_names).index(name)
    assert np.isnan(capture.x[i, 0]).all() and np.isfinite(capture.x[i, 1:]).all()
    assert np.isfinite(capture.x[np.arange(capture.num_images) != i]).all()
