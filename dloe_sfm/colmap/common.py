"""What the COLMAP modules share: COLMAP's log level, the check of a camera model name."""

from __future__ import annotations

import logging

import pycolmap

from ..errors import InputError

logger = logging.getLogger("dloe_sfm")


def quiet_colmap() -> None:
    """COLMAP's own (glog) logging: errors only, unless the package logger is at DEBUG."""
    verbose = logger.isEnabledFor(logging.DEBUG)
    level = pycolmap.logging.Level.INFO if verbose else pycolmap.logging.Level.ERROR
    pycolmap.logging.minloglevel = int(level)
    pycolmap.logging.verbose_level = 1 if verbose else 0


def check_camera_model(name: str) -> None:
    """InputError unless ``name`` is a COLMAP camera model (e.g. ``SIMPLE_RADIAL``)."""
    if name not in pycolmap.CameraModelId.__members__ or name == "INVALID":
        raise InputError(f"unknown COLMAP camera model '{name}'")
