"""The package that touches pycolmap, one module per job.

- ``read``: find, check and read a COLMAP workspace (``load_workspace`` -> ``Workspace``).
- ``write``: write a model of posed images from plain values (``write_model``).
- ``fixtures``: a small synthetic workspace for tests and examples (``synthetic_workspace``).
- ``sfm``: structure from motion on a folder of images (``run_sfm``).

Pixel convention here is COLMAP's: the centre of the top-left pixel is (0.5, 0.5). Image file
names (suffixes, natural order) are in ``dloe_sfm.images``, which needs no pycolmap.
"""

from .fixtures import synthetic_workspace
from .read import MODEL_FILES, Workspace, find_model, load_workspace
from .sfm import SFM_CAMERA_MODES, run_sfm
from .write import CameraSpec, ImageSpec, write_model

__all__ = [
    "MODEL_FILES", "SFM_CAMERA_MODES", "CameraSpec", "ImageSpec", "Workspace", "find_model",
    "load_workspace", "run_sfm", "synthetic_workspace", "write_model",
]
