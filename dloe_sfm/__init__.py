"""dloe_sfm: dynamic points from asynchronous crowd imagery, on top of COLMAP (DLOE, ICCV 2019)."""

import logging

from .core.capture import Capture
from .core.options import Clocks, Distance, Embedding, Options
from .core.result import Result
from .core.solver import reconstruct
from .errors import InputError

__version__ = "0.1.0"
__all__ = [
    "Capture", "Clocks", "Distance", "Embedding", "InputError", "Options", "Result", "reconstruct"
]

logger = logging.getLogger("dloe_sfm")
if not logger.handlers:
    _handler = logging.StreamHandler()
    _handler.setFormatter(
        logging.Formatter("[%(asctime)s %(name)s %(levelname)s] %(message)s", "%Y/%m/%d %H:%M:%S")
    )
    logger.addHandler(_handler)
    logger.setLevel(logging.INFO)
    logger.propagate = False
