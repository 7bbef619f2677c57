"""Runs: the pieces of section curves that the sampler places its points along.

A run is a piece of a section curve inside one face between two exact end points (its loop's
corners, or the crossings of a pinned loop), with a seed path from the topology mesh in the face's
(u, v), parametrised by arc length: ``sampling`` finds the runs, ``refine`` samples them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# A run whose exact end lies more than this many topology deflections from its topology crossing has
# its points checked against the face's trim (the ordinary gap is within one deflection)
SUSPECT_DEFLECTIONS = 5.0
GAP_SPAN_REL = 1e-6  # a seed interval this small (relative to its run) cannot hold another exact point
GAP_POINT = -3  # (vertex id placeholder of a point added next to a run's end: ``RunEnds._gap_end_points``)
# (vertex id placeholder of a point where a run's curve leaves its face's trim for good before the
# corner at the run's end: ``FaceLimits._trim_borders``)
BRIDGE_POINT = -4


@dataclass
class Run:
    """A piece of a section curve inside one face, parametrised by arc length along a seed path."""

    face: int
    s: np.ndarray  # (k,) arc length of the seed path, 0 .. length
    uv: np.ndarray  # (k, 2) seed path in the face's (u, v)
    max_step: float  # Newton trust region in (u, v)
    start: int  # vertex id of the exact start point
    end: int  # vertex id of the exact end point
    n_seg: int  # initial number of segments
    zc: float  # world height of the plane, mm
    plane: int  # plane index
    # exact ends far from their topology crossings, with the distance they moved: points near them are
    # checked against the face's trim
    moved: tuple[tuple[np.ndarray, float], ...] = ()
    # the seed path is a trace along the exact curve (``_excursion_runs``): a point placed by arc length
    # along it is on the right piece of the curve even where it projects beyond its segment's chord
    traced: bool = False
    # an end vertex off the face's curve gets the curve's nearest point next to it (``_add_gap_points``;
    # the runs of free loops: a pinned loop's kept triangles take its segments' points as they are)
    gap_ends: bool = False
