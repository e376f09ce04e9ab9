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

# a library only adds a NullHandler; the command line (``cli.setup_logging``) shows the logs
logging.getLogger("dloe_sfm").addHandler(logging.NullHandler())
