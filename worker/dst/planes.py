"""Slicing-plane heights, computed exactly the way slicers compute them (DST.md section 2).

Heights are relative to the part's exact lowest point (slicers drop every part onto the bed). Each
plan carries the slicer's own value in double precision and the float32 value written into the STL:
a ring vertex written as ``float32(plane)`` is exactly on the plane for Cura (integer micrometres
after ``round(z * 1000)``) and for PrusaSlicer (float32 comparison).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from worker.dst.constants import MAX_PLANES
from worker.dst.errors import ResourceLimitExceeded
from worker.dst.params import SliceParams


@dataclass(frozen=True)
class PlanePlan:
    """The planes of one job.

    z : (n,) float64, mm above the part's lowest point, as the slicer computes them
    z32 : (n,) float32, the same heights as written into the STL
    """

    z: np.ndarray
    z32: np.ndarray
    mode: str
    target_slicer: str | None

    @property
    def section_z(self) -> np.ndarray:
        """(n,) float64: the heights at which the exact B-rep is cut (the float32 values, widened)."""
        return self.z32.astype(np.float64)

    def __len__(self) -> int:
        return int(self.z.size)


def plan_planes(*, height: float, params: SliceParams) -> PlanePlan:
    """Return the slicing planes strictly inside ``(0, height)`` for a part of the given height (mm)."""
    h, h0 = params.layer_height, params.h0
    estimate = int(height / h) + 3
    if estimate > MAX_PLANES:
        raise ResourceLimitExceeded(
            f"{estimate} planes for a {height:.1f} mm tall part at {h} mm layers exceeds the limit of "
            f"{MAX_PLANES}; check the file's units or the layer height"
        )
    if params.target_slicer == "cura":
        z = _cura_planes(height=height, h=h, h0=h0, mode=params.mode)
    elif params.target_slicer == "prusa":
        if params.mode != "middle":
            # PrusaSlicer has no slicing-tolerance setting: it always slices mid-layer.
            from worker.dst.errors import InvalidParameters

            raise InvalidParameters("target_slicer 'prusa' only slices in 'middle' mode")
        z = _prusa_planes(height=height, h=h, h0=h0)
    else:
        z = _exact_planes(height=height, h=h, h0=h0, mode=params.mode)
    z = z[(z > 0.0) & (z < height)]
    return PlanePlan(z=z, z32=z.astype(np.float32), mode=params.mode, target_slicer=params.target_slicer)


def _exact_planes(*, height: float, h: float, h0: float, mode: str) -> np.ndarray:
    """Decimal planes: middle ``h0/2, h0 + (k - 1/2) h``; boundary modes ``h0 + (k - 1) h`` (k >= 1)."""
    n = int(np.ceil(max(height - h0, 0.0) / h)) + 2
    k = np.arange(1, n + 1, dtype=np.float64)
    if mode == "middle":
        return np.concatenate([[h0 / 2.0], h0 + (k - 0.5) * h])
    return np.concatenate([[max(0.0, h0 - h)], h0 + (k - 1.0) * h])


def _cura_planes(*, height: float, h: float, h0: float, mode: str) -> np.ndarray:
    """CuraEngine 4.x ``Slicer::buildLayersWithHeight`` in integer micrometres (integer divisions)."""
    h_um, h0_um = int(round(h * 1000)), int(round(h0 * 1000))
    n = int(np.ceil(max(height * 1000 - h0_um, 0) / h_um)) + 2
    k = np.arange(1, n + 1, dtype=np.int64)
    if mode == "middle":
        first, offset = h0_um // 2, h0_um + h_um // 2
    else:
        first, offset = max(0, h0_um - h_um), h0_um
    um = np.concatenate([[first], offset + h_um * (k - 1)])
    return um.astype(np.float64) / 1000.0


def _prusa_planes(*, height: float, h: float, h0: float) -> np.ndarray:
    """PrusaSlicer ``generate_object_layers``: ``print_z`` accumulated in double, ``slice_z`` mid-layer."""
    out = [0.5 * (0.0 + h0)]
    lo = h0
    while lo + 0.5 * h < height:
        hi = lo + h
        out.append(0.5 * (lo + hi))
        lo = hi
    return np.asarray(out, dtype=np.float64)
