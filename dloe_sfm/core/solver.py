"""Alternating convex search for DLOE (Xu & Dunn, ICCV 2019): the entry point.

One subject: :func:`dloe_sfm.core.pipeline.solve_single` (initialise -> events -> per event:
alternate -> robust rounds -> clocks -> assemble), or beyond ``Options.window_images`` images
:func:`dloe_sfm.core.windows.solve_windowed` (overlapping time windows, each solved so, stitched);
several detections per image:
:func:`dloe_sfm.core.multitarget.reconstruct_subjects`, which associates them and then runs the
same pipeline.
"""

from __future__ import annotations

import logging

from .alternation import Progress
from .assess import assess
from .capture import Capture
from .multitarget import reconstruct_subjects
from .options import Options
from .parallel import kept_workers
from .pipeline import solve_single
from .result import Result
from .windows import solve_windowed
from .xstep import BLAS

logger = logging.getLogger("dloe_sfm")


@BLAS.wrap(limits=1, user_api="blas")
def reconstruct(
    capture: Capture, options: Options | None = None, *, progress: Progress | None = None
) -> Result:
    """Estimate every image's 3D points and the images' temporal graph and order.

    ``capture`` must be valid (``Capture.validate``). Returns a new :class:`Result` in world
    units, every image checked and its reconstructability measured (:func:`.assess.assess`).
    ``progress(done, total, info)`` is called after every sweep of every solve (see
    :data:`dloe_sfm.core.alternation.Progress`). The BLAS runs on one thread throughout, as in
    the event workers (``core.parallel``): its threads share blocks too small to gain from
    them, and wait for one another when another process keeps a core busy (docs/method.md,
    "Speed"). Worker processes, once started, serve every later parallel step of the solve
    (``parallel.kept_workers``).
    """
    options = options or Options()
    size = options.window_size(capture.num_images)
    with kept_workers():
        if capture.x.ndim == 4:
            result = reconstruct_subjects(capture, options, progress=progress)
        elif size:
            result = solve_windowed(capture, options, size, size // 10)
        else:
            result = solve_single(capture, options, progress)
    if result.order_ambiguous is not None and result.order_ambiguous.any():
        logger.warning("%d lone photo(s) fit another time on the line as well as their own "
                       "place (a pose seen again): their place in the order is a guess, "
                       "flagged order_ambiguous", int(result.order_ambiguous.sum()))
    return assess(capture, result, lambda1=options.lambda1)
