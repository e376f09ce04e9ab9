"""Structure from motion on a folder of images: COLMAP's SIFT, exhaustive matching, mapping."""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from pathlib import Path

import pycolmap

from ..errors import InputError
from ..images import list_images
from ..io import atomic_path
from .common import check_camera_model, quiet_colmap

logger = logging.getLogger("dloe_sfm")

SFM_CAMERA_MODES = ("per_folder", "per_image", "single")


def run_sfm(
    image_dir: Path | str,
    workspace_dir: Path | str,
    *,
    camera_mode: str | None = None,
    camera_model: str = "SIMPLE_RADIAL",
    camera_params: Sequence[float] | Mapping[str, Sequence[float]] | None = None,
    mapper: str = "global",
    max_num_features: int = 4096,
    first_octave: int = 0,
    num_threads: int = -1,
    seed: int | None = None,
    overwrite: bool = False,
) -> Path:
    """COLMAP SfM (SIFT, exhaustive matching, global or incremental mapping) of ``image_dir``
    into a new workspace ``workspace_dir`` (``database.db``, ``sparse/<k>``, ``images`` -> a link
    to ``image_dir``); returns ``workspace_dir``.

    ``camera_mode``: ``per_folder`` (one camera per sub-folder, i.e. per video stream; the
    default when images sit in sub-folders), ``per_image`` (crowd photos; the default otherwise)
    or ``single``. ``camera_params`` (COLMAP order for ``camera_model``; one set for every camera
    or, per image name, the set of that image's camera) fixes known intrinsics: they are then
    not refined (refining them cost accuracy: docs/method.md, "Around the solver").
    ``first_octave`` -1 upsamples the images for SIFT (more matches across wide baselines, slower);
    ``num_threads`` -1 uses every core; ``seed`` (COLMAP's ``random_seed``) makes the mapping
    repeatable. The workspace is built in a temporary sibling and renamed when complete.
    """
    image_dir = Path(image_dir).resolve()
    workspace_dir = Path(workspace_dir)
    if not image_dir.is_dir():
        raise InputError(f"{image_dir}: no such image folder")
    names = list_images(image_dir)
    if len(names) < 2:
        raise InputError(f"{image_dir}: SfM needs at least 2 images, found {len(names)}")
    if workspace_dir.exists() and not overwrite:
        raise InputError(f"{workspace_dir}: workspace exists (pass overwrite=True to replace it)")
    if camera_mode is None:
        camera_mode = "per_folder" if any("/" in n for n in names) else "per_image"
    if camera_mode not in SFM_CAMERA_MODES:
        raise InputError(f"camera_mode '{camera_mode}': expected one of {SFM_CAMERA_MODES}")
    if mapper not in ("global", "incremental"):
        raise InputError(f"mapper '{mapper}': expected 'global' or 'incremental'")
    check_camera_model(camera_model)
    quiet_colmap()
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = camera_model
    if camera_params is not None and not isinstance(camera_params, Mapping):
        reader.camera_params = ",".join(repr(float(v)) for v in camera_params)
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = int(num_threads)
    extraction.sift.max_num_features = int(max_num_features)
    extraction.sift.first_octave = int(first_octave)
    extraction.sift.estimate_affine_shape = True  # wide baselines barely matched without it
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = int(num_threads)
    fixed = camera_params is not None
    with atomic_path(workspace_dir) as tmp:
        tmp.mkdir()
        database = tmp / "database.db"
        logger.info("SfM: extracting features of %d images in %s (%s cameras)", len(names),
                    image_dir, camera_mode)
        pycolmap.extract_features(
            database, image_dir, image_names=names,
            camera_mode=pycolmap.CameraMode.__members__[camera_mode.upper()],
            reader_options=reader, extraction_options=extraction, device=pycolmap.Device.cpu,
        )
        if isinstance(camera_params, Mapping):
            _set_camera_params(database, camera_params)
        logger.info("SfM: exhaustive matching")
        pycolmap.match_exhaustive(database, matching_options=matching, device=pycolmap.Device.cpu)
        (tmp / "sparse").mkdir()
        logger.info("SfM: %s mapping", mapper)
        if mapper == "global":
            options = pycolmap.GlobalPipelineOptions()
            options.mapper.bundle_adjustment.refine_focal_length = not fixed
            options.mapper.bundle_adjustment.refine_extra_params = not fixed
        else:
            options = pycolmap.IncrementalPipelineOptions()
            options.ba_refine_focal_length = not fixed
            options.ba_refine_extra_params = not fixed
            options.mapper.abs_pose_refine_focal_length = not fixed
            options.mapper.abs_pose_refine_extra_params = not fixed
        options.num_threads = int(num_threads)
        if seed is not None:
            options.random_seed = int(seed)
            options.mapper.random_seed = int(seed)
        run = pycolmap.global_mapping if mapper == "global" else pycolmap.incremental_mapping
        models = run(database, image_dir, tmp / "sparse", options=options)
        if not models:
            raise InputError(f"{image_dir}: COLMAP could not register the images (no model)")
        (tmp / "images").symlink_to(image_dir, target_is_directory=True)
        sizes = {k: rec.num_reg_images() for k, rec in models.items()}
        logger.info("SfM: %d model(s), registered images %s of %d", len(models), sizes, len(names))
    return workspace_dir


def _set_camera_params(database: Path, params: Mapping[str, Sequence[float]]) -> None:
    """Give each image's camera in ``database`` the intrinsics ``params[image name]``, known
    (a prior focal length); images sharing a camera must share them."""
    db = pycolmap.Database.open(database)
    try:
        done = {}
        for image in db.read_all_images():
            if image.name not in params:
                raise InputError(f"camera_params: no intrinsics for image {image.name}")
            values = [float(v) for v in params[image.name]]
            if done.setdefault(image.camera_id, values) != values:
                raise InputError(f"camera_params: image {image.name} shares camera "
                                 f"{image.camera_id} with other intrinsics")
            camera = db.read_camera(image.camera_id)
            camera.params = values
            camera.has_prior_focal_length = True
            db.update_camera(camera)
    finally:
        db.close()
