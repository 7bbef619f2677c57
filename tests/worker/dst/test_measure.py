"""Measuring one mesh in ranges of planes (``measure``): the ranges share the work and each range's
cut is the whole mesh's cut at its planes."""

from __future__ import annotations

import numpy as np
import trimesh

from worker.dst.cuts import cut_mesh
from worker.dst.measure import Placed, plane_ranges


def test_plane_ranges_cover_every_plane_once_in_about_equal_work():
    cost = np.array([5.0, 1, 1, 1, 1, 1, 0, 0, 10, 1, 1, 1])
    ranges = plane_ranges(cost, chunk=8.0)
    assert ranges[0][0] == 0 and ranges[-1][1] == len(cost)
    assert all(a[1] == b[0] for a, b in zip(ranges[:-1], ranges[1:], strict=True))  # no gaps, no overlaps
    assert all(j0 < j1 for j0, j1 in ranges)
    assert len(ranges) == 3  # 23 units of work in chunks of about 8
    assert plane_ranges(cost, chunk=np.inf) == [(0, len(cost))]
    assert plane_ranges(np.zeros(0), chunk=1.0) == [(0, 0)]


def test_a_range_of_planes_is_cut_from_its_own_triangles_as_the_whole_mesh_is_cut():
    """``Placed.cut`` (a report piece: the triangles its planes cross, their crossed planes taken
    from the whole mesh's) gives, plane for plane, the cut of the whole mesh, planes through
    vertices included."""
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=10.0)
    v, t = np.asarray(sphere.vertices), np.asarray(sphere.faces)
    heights = np.unique(np.concatenate([np.linspace(-9.5, 9.5, 23), v[::37, 2]]))  # some through vertices
    placed = Placed(v, t, heights)
    for j0, j1 in [(0, len(heights)), (0, 5), (7, 8), (11, len(heights)), (3, 3)]:
        piece, whole = placed.cut(heights, j0, j1), cut_mesh(v, t, heights[j0:j1])
        assert np.array_equal(piece.loops, whole.loops) and np.array_equal(
            piece.open_chains, whole.open_chains
        )
        for j in range(j1 - j0):
            a, b = piece.seg[piece.seg_plane == j], whole.seg[whole.seg_plane == j]
            assert np.array_equal(np.unique(a.reshape(-1, 4), axis=0), np.unique(b.reshape(-1, 4), axis=0))
        assert piece.loops.sum() == (j1 - j0)  # a sphere: one loop a plane
