"""Baselines the paper compares DLOE with (docs/method.md, "Baselines").

Every function takes a :class:`~dloe_sfm.core.capture.Capture` (plus the ground-truth times or
instants a baseline needs) and returns the (N, P, 3) shapes in world units. Like the core, this
package is numpy / scipy only and does no I/O. The two DLOE references live elsewhere:
``dloe_sfm.evaluate.oracle_reconstruct`` (DLOE with ground-truth sequencing) and ``reconstruct``
with ``Options(prior_weight=0, spectral_prior=False, stream_clocks="off")`` (DLOE without any
sequencing).
"""

from .high_pass import difference_matrix, high_pass_filter, solve_on_rays
from .sedl import sedl, symmetric_candidates
from .trajectory_basis import dct_basis, select_num_bases, trajectory_basis
from .triangulation import pseudo_triangulation, triangulate_instants

__all__ = [
    "dct_basis",
    "difference_matrix",
    "high_pass_filter",
    "pseudo_triangulation",
    "sedl",
    "select_num_bases",
    "solve_on_rays",
    "symmetric_candidates",
    "trajectory_basis",
    "triangulate_instants",
]
