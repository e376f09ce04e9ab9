"""Capture and result files (docs/interfaces.md), written atomically; output safety."""

from __future__ import annotations

import contextlib
import logging
import math
import os
import re
import shutil
import tempfile
import tokenize
import zipfile
import zlib
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np
import scipy.sparse as sp

from . import __version__
from .core.capture import MIN_IMAGES, OPTIONAL_KEYS, REQUIRED_KEYS, Capture, field_shapes
from .core.result import Result
from .errors import InputError
from .keypoints.base import quoted, shown
from .resources import check_memory
from .truth import GroundTruth

logger = logging.getLogger("dloe_sfm")

MARKER = ".dloe_sfm"
"""File inside every output folder dloe-sfm writes; only such folders are ever replaced."""
_TEMP_PREFIX = ".dloe_sfm-tmp-"
# .dloe_sfm-tmp-<pid>-<random>-<target name>: the pid tells whether its writer still runs
_TEMP_NAME = re.compile(re.escape(_TEMP_PREFIX) + r"(\d+)-[a-z0-9_]+-(.+)", re.DOTALL)
_RESULT_KEYS = ("X", "order", "A_data", "A_indices", "A_indptr", "events")


def _describe(path: Path) -> str:
    return "folder" if path.is_dir() else "file"


def _check_ours(folder: Path, name: Path | str, marker: str = MARKER) -> None:
    """Refuse to replace a folder that holds anything but is not marked as dloe-sfm's (by its
    file ``marker``): no option replaces it, so the message asks for another output path."""
    if not (folder / marker).is_file() and any(folder.iterdir()):
        raise InputError(f"{name}: not written by dloe-sfm (no {marker} file in it), never "
                         "replaced; choose another output path")


def _nearest_existing(path: Path) -> Path:
    while not os.path.lexists(path):
        path = path.parent
    return path


def _is_result_file(path: Path) -> bool:
    """Whether ``path`` is a ``result.npz`` (docs/interfaces.md), judged by its key names."""
    try:
        with zipfile.ZipFile(path) as z:
            names = set(z.namelist())
    except (OSError, zipfile.BadZipFile):
        return False
    return all(f"{k}.npy" in names for k in _RESULT_KEYS)


def check_output(out: Path | str, *, protected: Sequence[Path | str | None] = (),
                 overwrite: bool = False, kind: str = "dir", marker: str = MARKER) -> Path:
    """Check an output path before any work; returns it resolved (symlinks followed).

    ``kind`` is ``"dir"`` (an output folder) or ``"file"`` (a result file). Refused with a
    one-line InputError that says what to do: a path that is, contains or lies inside a
    ``protected`` input (missing ones and None are skipped); a folder without the file
    ``marker`` (``MARKER``, or a command's own output file) unless empty, or a file that is
    not a result file: nothing replaces them, so another path is asked for, not
    ``--overwrite``; an earlier output without ``overwrite``; a location that cannot be
    created or written.
    """
    out = Path(out)
    target = out.resolve()
    for p in protected:
        if p is None or not os.path.lexists(p):
            continue
        source = Path(p).resolve()
        if target == source or (target.exists() and os.path.samefile(target, source)):
            relation = "is"
        elif target in source.parents:
            relation = "contains"
        elif source in target.parents:
            relation = "lies inside"
        else:
            continue
        raise InputError(f"{out}: the output {relation} the input {_describe(source)} {p}; "
                         "choose another output path")
    if os.path.lexists(target):
        if kind == "dir" and not target.is_dir():
            raise InputError(f"{out}: exists and is not a folder; choose another output path")
        if kind == "file" and target.is_dir():
            raise InputError(f"{out}: exists and is a folder; choose another output path")
        if kind == "dir":
            _check_ours(target, out, marker)
        if kind == "file" and not _is_result_file(target):
            raise InputError(f"{out}: exists and is not a dloe-sfm result file, never "
                             "replaced; choose another output path")
        if not overwrite:
            raise InputError(f"{out}: output {_describe(target)} exists "
                             "(use --overwrite to replace it)")
    base = _nearest_existing(target.parent)
    if not base.is_dir():
        raise InputError(f"{out}: cannot create it, {base} is not a folder; choose another "
                         "output path")
    try:
        with tempfile.TemporaryFile(prefix=".dloe_sfm-probe-", dir=base) as probe:
            probe.write(b"x")
            probe.flush()
    except OSError as e:
        raise InputError(f"{out}: cannot write in {base} ({e.strerror or e}); choose a "
                         "writable output path") from None
    return target


def check_not_input(out: Path | str, inputs: Sequence[Path | str], what: str = "input file"
                    ) -> None:
    """Refuse an output file ``out`` that is one of ``inputs`` (the same file, whatever the
    path), for the writers that need no more of :func:`check_output`."""
    for p in inputs:
        if os.path.exists(out) and os.path.exists(p) and os.path.samefile(out, p):
            raise InputError(f"{out}: the output is the {what} {p}; choose another output path")


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    return True


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        with contextlib.suppress(OSError):
            path.unlink()


def _remove_stale_temps(path: Path) -> None:
    """Delete our temporaries for ``path`` left by a process that no longer runs (SIGKILL).
    Inside a folder that is itself one of our temporaries there are none (a killed run's
    folder goes as a whole), and the scan is skipped: a folder of N files written one by one
    would cost N^2."""
    if any(part.startswith(_TEMP_PREFIX) for part in path.parent.parts):
        return
    for tmp in path.parent.glob(_TEMP_PREFIX + "*"):
        match = _TEMP_NAME.fullmatch(tmp.name)
        if match and match[2] == path.name and not _pid_alive(int(match[1])):
            logger.info("removing %s, left by an interrupted run", tmp)
            _remove(tmp)


def _temp_sibling(path: Path) -> Path:
    fd, tmp = tempfile.mkstemp(prefix=f"{_TEMP_PREFIX}{os.getpid()}-", suffix=f"-{path.name}",
                               dir=path.parent)
    os.close(fd)
    os.unlink(tmp)
    return Path(tmp)


class _WriteError(InputError):
    """Writing an output failed (disk full, no permission): a bad output location, not a bug."""

    def __init__(self, path: Path, reason: str):
        super().__init__(f"{path}: cannot write it ({reason})")
        self.reason = reason


@contextlib.contextmanager
def atomic_path(path: Path | str, *, mark: bool = False) -> Iterator[Path]:
    """Yield a temporary sibling of ``path`` (file or folder); rename it to ``path`` on success.

    Nothing is left at ``path`` or beside it when the body raises; temporaries of ``path``
    left by a killed run are removed first. An OSError becomes a one-line InputError naming
    ``path``. With ``mark``, a folder written by the body gets the ``MARKER`` file, and an
    existing folder at ``path`` is only replaced when it carries one (or is empty).
    """
    path = Path(path)
    tmp = old = None
    created = []  # folders made for ``path``, nearest first: removed again on failure
    parent = path.parent
    while not os.path.lexists(parent):
        created.append(parent)
        parent = parent.parent
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        _remove_stale_temps(path)
        tmp = _temp_sibling(path)
        yield tmp
        if mark and tmp.is_dir():
            (tmp / MARKER).write_text(f"dloe-sfm {__version__}\n")
        if path.is_dir() and tmp.is_dir():
            if mark:
                _check_ours(path, path)
            old = _temp_sibling(path)  # set aside, so ``path`` is never missing for long
            os.replace(path, old)
        os.replace(tmp, path)
    except _WriteError as e:  # from a nested atomic_path: name the outer path
        raise _WriteError(path, e.reason) from None
    except OSError as e:
        raise _WriteError(path, e.strerror or str(e)) from None
    finally:
        if tmp is not None and os.path.lexists(tmp):
            _remove(tmp)
        if old is not None and os.path.lexists(old):
            if os.path.lexists(path):
                _remove(old)
            else:  # interrupted between the two renames: put the previous output back
                os.replace(old, path)
        if not os.path.lexists(path):
            for folder in created:
                with contextlib.suppress(OSError):
                    folder.rmdir()


def save_npz(path: Path | str, **arrays) -> Path:
    """``np.savez_compressed`` to a temporary name, renamed when complete."""
    path = Path(path)
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        np.savez_compressed(f, **arrays)
    return path


NPZ_ERRORS = (OSError, ValueError, EOFError, zipfile.BadZipFile, zlib.error, NotImplementedError,
              SyntaxError, tokenize.TokenError, TypeError)
"""What a damaged zip or .npy member raises while it is read (the last three: numpy parsing a
mangled .npy header)."""
MAX_DEFLATE_RATIO = 1100
"""Deflate compresses at most ~1032:1: a member claiming more holds a lying size."""
SMALL_ARRAY = 1 << 20
"""Elements any key may hold regardless of the other arrays' sizes (histories, scalars)."""
TRUTH_KEYS = ("X_true", "t_true", "event_true", "subject_true", "outlier_true", "swap_true",
              "x_clean", "parents")
"""Ground-truth keys of a capture file read by :func:`load_truth` (written by ``simulate``;
for ``evaluate`` and the benchmarks); any other key is skipped without being decompressed."""
CHECK_KEYS = ("image_status", "status_reason", "residual_px", "neighbour_deviation", "depth_sd",
              "supported")
"""Keys of the per-image checks (``core.assess``) in a result file: (N,) then (N, P)."""
_TEXT_KEYS = ("image_status", "status_reason")
RESULT_KEYS = ("X", "order", "A_data", "A_indices", "A_indptr", "W_data", "W_indices",
               "W_indptr", "D", "events", "embedding", "cost_history", "change_history",
               "seconds", "subject_id", "point_id", "assignment", "outliers", "swaps",
               "outlier_residual_px", "offset_px", "clock", "clock_dropped", "order_ambiguous",
               *CHECK_KEYS)
"""Keys of a result file that are read (``result_arrays``); others are skipped."""
_REAL = "biuf"  # bool, signed / unsigned integers, floats: no objects, strings or complex
_KIND_NAMES = {"b": "bool", "i": "integers", "u": "unsigned integers", "f": "floats",
               "U": "text"}


def _reason(e: BaseException) -> str:
    text = " ".join(str(e).split())
    return text[:200] if text else type(e).__name__


class NpzReader:
    """An ``.npz`` opened without decompressing anything: each array's ``.npy`` header is read
    and checked (dtype, declared size against the zip member) before its data is.

    Every failure is a one-line InputError naming the file and key.
    """

    def __init__(self, path: Path | str):
        self.path = Path(path)
        if not self.path.is_file():
            raise InputError(f"{self.path}: no such file")
        try:
            self._zip = zipfile.ZipFile(self.path)
        except NPZ_ERRORS as e:
            raise self._unreadable(e) from None
        self._members = {
            info.filename[:-4]: info
            for info in self._zip.infolist()
            if info.filename.endswith(".npy") and not info.is_dir()
        }
        self._headers: dict[str, tuple[tuple[int, ...], np.dtype]] = {}

    def __enter__(self) -> NpzReader:
        return self

    def __exit__(self, *exc) -> None:
        self._zip.close()

    @property
    def files(self) -> list[str]:
        return list(self._members)

    def _unreadable(self, e: BaseException, key: str | None = None) -> InputError:
        where = "" if key is None else f"key '{key}': "
        return InputError(f"{self.path}: not a readable .npz file ({where}{_reason(e)})")

    def header(self, key: str, kinds: str = _REAL) -> tuple[tuple[int, ...], np.dtype]:
        """Shape and dtype ``key`` declares, checked: dtype kind in ``kinds`` (numpy's
        ``dtype.kind`` letters), size equal to what the zip member holds."""
        if key not in self._headers:
            info = self._members[key]
            if info.compress_type not in (zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED) or (
                info.compress_type == zipfile.ZIP_STORED and info.file_size != info.compress_size
            ) or info.file_size > MAX_DEFLATE_RATIO * info.compress_size + 4096:
                raise self._unreadable(
                    ValueError("unsupported compression or inconsistent zip directory sizes"),
                    key,
                )
            try:
                with self._zip.open(info) as fp:
                    version = np.lib.format.read_magic(fp)
                    if version == (1, 0):
                        shape, _, dtype = np.lib.format.read_array_header_1_0(fp)
                    elif version == (2, 0):
                        shape, _, dtype = np.lib.format.read_array_header_2_0(fp)
                    else:
                        raise ValueError(f".npy format version {version} is not supported")
                    offset = fp.tell()
            except NPZ_ERRORS as e:
                raise self._unreadable(e, key) from None
            if dtype.hasobject or dtype.fields is not None or dtype.subdtype is not None:
                raise InputError(
                    f"{self.path}: key '{key}' holds Python objects or records "
                    f"(dtype {dtype}), which are not read"
                )
            size = math.prod(shape) * dtype.itemsize
            if size != info.file_size - offset:
                raise InputError(
                    f"{self.path}: key '{key}' declares shape {shape} of {dtype} ({size} bytes) "
                    f"but holds {info.file_size - offset} bytes"
                )
            self._headers[key] = tuple(shape), dtype
        shape, dtype = self._headers[key]
        if dtype.kind not in kinds:
            wanted = ", ".join(_KIND_NAMES[c] for c in kinds)
            raise InputError(f"{self.path}: key '{key}' has dtype {dtype}, expected {wanted}")
        return shape, dtype

    def read(self, key: str, kinds: str = _REAL) -> np.ndarray:
        """The array of ``key``, once its header passed :meth:`header`."""
        self.header(key, kinds)
        try:
            with self._zip.open(self._members[key]) as fp:
                array = np.lib.format.read_array(fp, allow_pickle=False)
                if fp.read(1):  # also reaches the end of the member, where the CRC is checked
                    raise ValueError("data after the array")
        except NPZ_ERRORS as e:
            raise self._unreadable(e, key) from None
        return array


def _sizes(npz: NpzReader, keys: Sequence[str]) -> int:
    return sum(math.prod(s) * d.itemsize for s, d in (npz._headers[k] for k in keys))


def _check_bound(npz: NpzReader, key: str, limit: int, what: str) -> None:
    shape, _ = npz._headers[key]
    if math.prod(shape) > limit:
        raise InputError(
            f"{npz.path}: key '{key}' declares shape {shape}, more than {what} allows"
        )


def _x_shape(npz: NpzReader) -> tuple[int, ...]:
    """The checked header shape of a capture file's ``x``."""
    if "x" not in npz.files:
        raise InputError(f"{npz.path}: missing key(s) 'x'")
    x_shape = npz.header("x", "iuf")[0]
    if len(x_shape) not in (3, 4) or x_shape[-1] != 2:
        raise InputError(
            f"{npz.path}: field 'x' must have shape (N, P, 2) or (N, M, P, 2), got {x_shape}"
        )
    return x_shape


def load_capture(path: Path | str, *, validate: bool = True) -> Capture:
    """Read a ``capture.npz``: its fields only (the ground truth: :func:`load_truth`; other
    keys are not read). Every array's header is checked against the others' before any data is
    decompressed."""
    path = Path(path)
    with NpzReader(path) as npz:
        missing = [k for k in REQUIRED_KEYS if k not in npz.files]
        if missing:
            raise InputError(f"{path}: missing key(s) {', '.join(repr(k) for k in missing)}")
        keys = [k for k in (*REQUIRED_KEYS, *OPTIONAL_KEYS) if k in npz.files]
        kinds = {k: "iuf" for k in keys} | {"image_names": "iuU", "symmetric_pairs": "iu"}
        for k in keys:
            npz.header(k, kinds[k])
        x_shape = _x_shape(npz)
        for k, shape in field_shapes(x_shape).items():
            if k in keys and npz._headers[k][0] != shape:
                raise InputError(
                    f"{path}: field '{k}' must have shape {shape}, got {npz._headers[k][0]}"
                )
        if "symmetric_pairs" in keys:
            _check_bound(npz, "symmetric_pairs", x_shape[-2] ** 2 + SMALL_ARRAY, "field 'x'")
        check_memory(_sizes(npz, keys), f"{path}: reading it")
        fields = {k: npz.read(k, kinds[k]) for k in keys}
    if "symmetric_pairs" in fields and fields["symmetric_pairs"].size % 2:
        raise InputError(f"{path}: field 'symmetric_pairs' must have shape (K, 2)")
    capture = Capture(**fields)
    return capture.validate(str(path)) if validate else capture


def without_empty_images(capture: Capture, source: Path | str) -> tuple[Capture, np.ndarray]:
    """``capture`` (checked with ``validate(empty_images=True)``) without the images that
    observe no point (the detector found nobody), checked again, and the (N',) indices of the
    images kept. The images left out are named in one warning; fewer than ``MIN_IMAGES`` left
    is an InputError naming ``source``."""
    observing = capture.visible.reshape(capture.num_images, -1).any(axis=1)
    if observing.all():
        return capture, np.arange(capture.num_images)
    kept = np.flatnonzero(observing)
    if kept.size < MIN_IMAGES:
        raise InputError(f"{shown(source)}: only {kept.size} of {capture.num_images} images "
                         f"observe a point, at least {MIN_IMAGES} needed")
    empty = capture.image_names[~observing].tolist()
    logger.warning("%s: %d image(s) observe no point (the detector found nobody), skipped: %s",
                   shown(source), len(empty), ", ".join(quoted(n) for n in empty[:5])
                   + (f" and {len(empty) - 5} more" if len(empty) > 5 else ""))
    return capture.subset(kept).validate(shown(source)), kept


def load_truth(path: Path | str) -> GroundTruth:
    """Read the ground truth of a ``capture.npz`` (the keys ``TRUTH_KEYS``; ``X_true`` and
    ``t_true`` required), headers checked against ``x`` before any data is decompressed.
    Shapes and values are checked where the truth is used (``evaluate``)."""
    path = Path(path)
    with NpzReader(path) as npz:
        for k in ("X_true", "t_true"):
            if k not in npz.files:
                raise InputError(f"{path}: missing ground-truth key '{k}'")
        x_shape = _x_shape(npz)
        keys = [k for k in TRUTH_KEYS if k in npz.files]
        for k in keys:
            npz.header(k)
            _check_bound(npz, k, 2 * math.prod(x_shape) + SMALL_ARRAY, f"field 'x' {x_shape}")
        check_memory(_sizes(npz, keys), f"{path}: reading it")
        return GroundTruth.from_arrays({k: npz.read(k) for k in keys})


def read_mocap(path: Path | str) -> tuple[np.ndarray, float, np.ndarray | None]:
    """``positions`` (T, J, 3) float64, ``fps`` and ``parents`` (J,) int64 (None when absent) of
    a mocap ``.npz``, checked (T >= 2 finite frames, fps > 0, parents in -1..J-1)."""
    path = Path(path)
    with NpzReader(path) as npz:
        for key in ("positions", "fps"):
            if key not in npz.files:
                raise InputError(f"{path}: missing key '{key}'")
        shape, _ = npz.header("positions", "iuf")
        if len(shape) != 3 or shape[0] < 2 or shape[1] < 1 or shape[2] != 3:
            raise InputError(f"{path}: key 'positions' must have shape (T >= 2, J, 3), got {shape}")
        if math.prod(npz.header("fps", "iuf")[0]) != 1:
            raise InputError(f"{path}: key 'fps' must be one number")
        if "parents" in npz.files and npz.header("parents", "iu")[0] != shape[1:2]:
            raise InputError(f"{path}: key 'parents' must have shape ({shape[1]},)")
        positions = npz.read("positions", "iuf").astype(np.float64)
        fps = float(npz.read("fps", "iuf").ravel()[0])
        parents = npz.read("parents", "iu").astype(np.int64) if "parents" in npz.files else None
    if not np.isfinite(positions).all():
        raise InputError(f"{path}: key 'positions' is not finite")
    if not (math.isfinite(fps) and fps > 0):
        raise InputError(f"{path}: key 'fps' must be a positive number, got {fps}")
    if parents is not None and ((parents < -1) | (parents >= shape[1])).any():
        raise InputError(f"{path}: key 'parents' must hold joint indices in -1..{shape[1] - 1}")
    return positions, fps, parents


def save_capture(path: Path | str, capture: Capture, truth: GroundTruth | None = None) -> Path:
    """Write a ``capture.npz``: the capture's fields and, with ``truth``, its keys
    (``X_true``, ``t_true``, ...: ``truth.FILE_KEYS``)."""
    arrays = {k: getattr(capture, k) for k in (*REQUIRED_KEYS, *OPTIONAL_KEYS)}
    arrays = {k: v for k, v in arrays.items() if v is not None}
    if truth is not None:
        arrays.update(truth.arrays())
    return save_npz(path, **arrays)


def result_arrays(result: Result) -> dict[str, np.ndarray]:
    """The arrays of a result file (docs/interfaces.md; plus W, D, embedding for convenience)."""
    A = sp.csr_matrix(result.A)
    W = sp.csr_matrix(result.W)
    return {
        "X": result.X,
        "order": result.order.astype(np.int64),
        "A_data": A.data,
        "A_indices": A.indices.astype(np.int64),
        "A_indptr": A.indptr.astype(np.int64),
        "W_data": W.data,
        "W_indices": W.indices.astype(np.int64),
        "W_indptr": W.indptr.astype(np.int64),
        "D": result.D,
        "events": result.events.astype(np.int64),
        "embedding": result.embedding,
        "cost_history": np.asarray(result.cost_history, dtype=np.float64),
        "change_history": np.asarray(result.change_history, dtype=np.float64),
        "seconds": np.float64(result.seconds),
        **{
            k: np.asarray(v)
            for k in ("subject_id", "point_id", "assignment", "outliers", "swaps")
            if (v := getattr(result, k)) is not None and np.size(v)
        },
        **({"outlier_residual_px": result.outlier_residual_px} if result.outliers.size else {}),
        **({} if result.offset_px is None else {"offset_px": result.offset_px}),
        **{k: v for k in ("clock", "clock_dropped", "order_ambiguous")
           if (v := getattr(result, k)) is not None},
        **({} if result.image_status is None else
           {k: np.asarray(getattr(result, k)).astype(str) if k in _TEXT_KEYS
            else np.asarray(getattr(result, k)) for k in CHECK_KEYS}),
    }


def save_result(path: Path | str, result: Result, *, skipped_images: Sequence[str] = ()
                ) -> Path:
    """Write a ``result.npz``; ``skipped_images``: names of the capture's images left out of
    the solve (``without_empty_images``), key ``skipped_images`` when not empty."""
    skipped = {"skipped_images": np.asarray(skipped_images, dtype=str)} if skipped_images else {}
    return save_npz(path, **result_arrays(result), **skipped)


def load_result(path: Path | str) -> Result:
    """Read a ``result.npz`` (the keys of ``RESULT_KEYS``) as a :class:`Result`. Headers are
    checked against ``X`` before any data is read. What the file lacks: ``W`` all zero, ``D``,
    ``events``, ``embedding`` and the histories empty, ``seconds`` NaN, the other fields their
    defaults; ``nit``, ``success`` and ``message`` are not stored (0, True, "")."""
    path = Path(path)
    with NpzReader(path) as npz:
        missing = [
            k for k in ("X", "order", "A_data", "A_indices", "A_indptr") if k not in npz.files
        ]
        if missing:
            raise InputError(f"{path}: not a result file, missing key(s) {', '.join(missing)}")
        keys = [k for k in RESULT_KEYS if k in npz.files]
        if any(k in keys for k in CHECK_KEYS) and not all(k in keys for k in CHECK_KEYS):
            raise InputError(f"{path}: keys {', '.join(CHECK_KEYS)} must be given together")
        integer = {"order", "events", "A_indices", "A_indptr", "W_indices", "W_indptr",
                   "subject_id", "point_id", "assignment", "outliers", "swaps"}
        kinds = {k: "U" if k in _TEXT_KEYS else "iu" if k in integer else _REAL for k in keys}
        for k in keys:
            npz.header(k, kinds[k])
        X_shape = npz._headers["X"][0]
        if len(X_shape) != 3 or X_shape[-1] != 3:
            raise InputError(f"{path}: key 'X' must have shape (N, P, 3), got {X_shape}")
        n = X_shape[0]
        expected = {"order": (n,), "events": (n,), "A_indptr": (n + 1,), "W_indptr": (n + 1,),
                    **{k: (n,) for k in CHECK_KEYS[:4]},
                    **{k: tuple(X_shape[:2]) for k in CHECK_KEYS[4:]},
                    "offset_px": (*X_shape[:2], 2), "clock": (n,), "clock_dropped": (n,),
                    "order_ambiguous": (n,)}
        for k in keys:
            shape = npz._headers[k][0]
            if k in expected and shape != expected[k]:
                raise InputError(f"{path}: key '{k}' must have shape {expected[k]}, got {shape}")
            if k[2:] in ("data", "indices") and len(shape) != 1:
                raise InputError(f"{path}: key '{k}' must be one-dimensional, got {shape}")
            _check_bound(npz, k, n * n if k[2:] in ("data", "indices")
                         else 4 * math.prod(X_shape) + SMALL_ARRAY, f"key 'X' {X_shape}")
        check_memory(_sizes(npz, keys), f"{path}: reading it")
        out = {k: npz.read(k, kinds[k]) for k in keys}
    if not np.array_equal(np.sort(out["order"]), np.arange(n)):
        raise InputError(f"{path}: key 'order' is not a permutation of the {n} images")
    for name in ("A", "W"):
        if f"{name}_data" in out and f"{name}_indices" in out and f"{name}_indptr" in out:
            try:
                M = sp.csr_matrix(
                    (out.pop(f"{name}_data"), out.pop(f"{name}_indices"),
                     out.pop(f"{name}_indptr")), shape=(n, n),
                )
                M.check_format(full_check=True)
            except ValueError as e:
                raise InputError(
                    f"{path}: keys '{name}_data', '{name}_indices', '{name}_indptr' are not "
                    f"an (N, N) sparse matrix ({_reason(e)})"
                ) from None
            out[name] = M
    seconds = out.get("seconds", np.float64(np.nan))
    if seconds.size != 1:
        raise InputError(f"{path}: key 'seconds' must be one number, got shape {seconds.shape}")
    empty = np.zeros(0)
    optional = {k: out[k] for k in ("subject_id", "point_id", "assignment", "outliers", "swaps",
                                    "outlier_residual_px", "offset_px", "clock",
                                    "clock_dropped", "order_ambiguous", *CHECK_KEYS)
                if k in out}
    for k in ("supported", "order_ambiguous"):
        if k in optional:
            optional[k] = optional[k].astype(bool)
    return Result(
        X=out["X"], order=out["order"], A=out["A"], W=out.get("W", sp.csr_matrix((n, n))),
        D=out.get("D", empty), events=out.get("events", np.zeros(0, dtype=np.int64)),
        embedding=out.get("embedding", empty), cost_history=out.get("cost_history", empty),
        change_history=out.get("change_history", empty), nit=0, success=True, message="",
        seconds=float(seconds.ravel()[0]), **optional,
    )
