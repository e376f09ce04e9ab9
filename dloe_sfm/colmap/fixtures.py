"""A small synthetic COLMAP workspace (``pycolmap.synthesize_dataset``) for tests and examples."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import pycolmap

from ..errors import InputError
from ..io import atomic_path
from .common import check_camera_model, quiet_colmap
from .read import has_model


def synthetic_workspace(
    path: Path | str,
    *,
    num_cameras: int = 3,
    num_frames: int = 4,
    cameras_per_rig: int = 1,
    num_points3D: int = 50,
    camera_model: str = "SIMPLE_RADIAL",
    camera_params: Sequence[float] | None = None,
    seed: int = 0,
) -> Path:
    """A small COLMAP workspace from ``pycolmap.synthesize_dataset`` at ``path/sparse/0``.

    ``num_cameras`` rigs of ``cameras_per_rig`` cameras, each with ``num_frames`` posed images
    named ``cameraNNNNNN_frameNNNNNN.png`` (1024 x 768). Seeded and deterministic. Returns ``path``.
    """
    path = Path(path)
    model_dir = path / "sparse" / "0"
    if has_model(model_dir):
        raise InputError(f"{model_dir}: a COLMAP model is already there")
    check_camera_model(camera_model)
    quiet_colmap()
    options = pycolmap.SyntheticDatasetOptions()
    options.num_rigs = num_cameras
    options.num_cameras_per_rig = cameras_per_rig
    options.num_frames_per_rig = num_frames
    options.num_points3D = num_points3D
    options.camera_model_id = pycolmap.CameraModelId.__members__[camera_model]
    if camera_params is not None:
        options.camera_params = [float(v) for v in camera_params]
    elif camera_model != "SIMPLE_RADIAL":  # options' default params are SIMPLE_RADIAL's
        options.camera_params = pycolmap.Camera.create_from_model_name(
            0, camera_model, 1280.0, options.camera_width, options.camera_height
        ).params.tolist()
    pycolmap.set_random_seed(seed)
    rec = pycolmap.synthesize_dataset(options)
    with atomic_path(model_dir) as tmp:
        tmp.mkdir()
        rec.write(str(tmp))
    return path
