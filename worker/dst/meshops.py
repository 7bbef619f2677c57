"""Checks of indexed triangle meshes shared by the topology mesh and the finished DST mesh."""

from __future__ import annotations

import numpy as np


def edge_defects(tris: np.ndarray, n_vertices: int) -> tuple[int, int]:
    """(open, non-manifold) directed-edge counts; both 0 for a closed, consistently oriented 2-manifold.

    A directed edge is open when its reverse is missing, non-manifold when it occurs more than once.
    """
    d = np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]])
    key = d[:, 0] * n_vertices + d[:, 1]
    rkey = d[:, 1] * n_vertices + d[:, 0]
    uniq, counts = np.unique(key, return_counts=True)
    return int((~np.isin(rkey, uniq)).sum()), int((counts > 1).sum())


def signed_volume(xyz: np.ndarray, tris: np.ndarray) -> float:
    """Signed volume (mm^3) enclosed by a closed triangle mesh (divergence theorem); > 0 if outward."""
    a, b, c = xyz[tris[:, 0]], xyz[tris[:, 1]], xyz[tris[:, 2]]
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)
