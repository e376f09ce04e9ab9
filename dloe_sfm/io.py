"""Capture and result files (INTERFACES.md sections 1 and 2), written atomically."""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
import zipfile
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import scipy.sparse as sp

from .core.capture import OPTIONAL_KEYS, REQUIRED_KEYS, Capture
from .core.result import Result
from .errors import InputError


@contextlib.contextmanager
def atomic_path(path: Path | str) -> Iterator[Path]:
    """Yield a temporary sibling of ``path`` (file or folder); rename it to ``path`` on success.

    Nothing is left at ``path`` or beside it when the body raises.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(
        prefix=f".{path.name}.", suffix=".tmp" + path.suffix, dir=path.parent
    )
    os.close(fd)
    os.unlink(tmp)
    tmp = Path(tmp)
    try:
        yield tmp
        if path.is_dir() and tmp.is_dir():
            shutil.rmtree(path)
        os.replace(tmp, path)
    finally:
        if tmp.is_dir():
            shutil.rmtree(tmp, ignore_errors=True)
        elif tmp.exists():
            tmp.unlink()


def save_npz(path: Path | str, **arrays) -> Path:
    """``np.savez_compressed`` to a temporary name, renamed when complete."""
    path = Path(path)
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        np.savez_compressed(f, **arrays)
    return path


def _open_npz(path: Path) -> np.lib.npyio.NpzFile:
    if not path.exists():
        raise InputError(f"{path}: no such file")
    try:
        return np.load(path, allow_pickle=False)
    except (OSError, ValueError, zipfile.BadZipFile) as e:
        raise InputError(f"{path}: not a readable .npz file ({e})") from None


def load_capture(path: Path | str, *, validate: bool = True) -> Capture:
    """Read a ``capture.npz``; unknown keys (e.g. ground truth) go to ``Capture.extras``."""
    path = Path(path)
    with _open_npz(path) as data:
        missing = [k for k in REQUIRED_KEYS if k not in data.files]
        if missing:
            raise InputError(f"{path}: missing key(s) {', '.join(repr(k) for k in missing)}")
        try:
            arrays = {k: data[k] for k in data.files}
        except ValueError as e:
            raise InputError(f"{path}: cannot read an array ({e})") from None
    fields = {k: arrays.pop(k) for k in (*REQUIRED_KEYS, *OPTIONAL_KEYS) if k in arrays}
    for k, v in fields.items():
        if k != "image_names" and not np.issubdtype(v.dtype, np.number):
            raise InputError(f"{path}: field '{k}' must be numeric, got dtype {v.dtype}")
    capture = Capture(**fields, extras=arrays)
    return capture.validate(str(path)) if validate else capture


def save_capture(path: Path | str, capture: Capture, **extra: np.ndarray) -> Path:
    """Write a ``capture.npz`` (extras such as ``X_true`` / ``t_true`` ride along)."""
    arrays = {k: getattr(capture, k) for k in (*REQUIRED_KEYS, *OPTIONAL_KEYS)}
    arrays = {k: v for k, v in arrays.items() if v is not None}
    arrays.update(capture.extras)
    arrays.update(extra)
    return save_npz(path, **arrays)


def result_arrays(result: Result) -> dict[str, np.ndarray]:
    """The arrays of INTERFACES.md section 2 (plus W, D, embedding for convenience)."""
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
    }


def save_result(path: Path | str, result: Result) -> Path:
    return save_npz(path, **result_arrays(result))


def load_result(path: Path | str) -> dict[str, np.ndarray]:
    """Read a ``result.npz`` into a dict; ``A`` (and ``W`` when present) as CSR matrices."""
    path = Path(path)
    with _open_npz(path) as data:
        missing = [
            k for k in ("X", "order", "A_data", "A_indices", "A_indptr") if k not in data.files
        ]
        if missing:
            raise InputError(f"{path}: not a result file, missing key(s) {', '.join(missing)}")
        out = {k: data[k] for k in data.files}
    n = out["X"].shape[0]
    for name in ("A", "W"):
        if f"{name}_data" in out:
            out[name] = sp.csr_matrix(
                (out.pop(f"{name}_data"), out.pop(f"{name}_indices"), out.pop(f"{name}_indptr")),
                shape=(n, n),
            )
    return out
