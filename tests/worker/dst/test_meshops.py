from collections import Counter

import numpy as np
import pytest

from worker.dst.meshops import edge_defects, open_edges, signed_volume, split_t_junctions, unique_ints

# a unit right tetrahedron, outward oriented
XYZ = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
TET = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])


def test_a_closed_oriented_tetrahedron_has_no_defects_and_its_volume():
    assert edge_defects(TET, 4) == (0, 0)
    assert signed_volume(XYZ, TET) == 1.0 / 6.0
    assert signed_volume(XYZ, TET[:, ::-1]) == -1.0 / 6.0


def test_a_missing_face_leaves_its_three_reverse_edges_open():
    assert edge_defects(TET[1:], 4) == (3, 0)


def test_a_flipped_face_makes_its_edges_non_manifold_and_open():
    flipped = TET.copy()
    flipped[0] = flipped[0, ::-1]
    # its 3 edges now repeat those of the neighbours (non-manifold), and their reverses are gone
    assert edge_defects(flipped, 4) == (6, 3)


def test_each_repeated_edge_counts_once_however_often_it_repeats():
    assert edge_defects(np.concatenate([TET, TET[:1]]), 4) == (0, 3)
    assert edge_defects(np.concatenate([TET, TET[:1], TET[:1]]), 4) == (0, 3)
    assert edge_defects(np.empty((0, 3), dtype=np.int64), 0) == (0, 0)


def _torus(n: int, m: int) -> np.ndarray:
    """A closed, consistently oriented n x m grid of triangles on a torus (vertex i * m + j)."""
    i, j = np.meshgrid(np.arange(n), np.arange(m), indexing="ij")
    a, b = i * m + j, ((i + 1) % n) * m + j
    c, d = ((i + 1) % n) * m + (j + 1) % m, i * m + (j + 1) % m
    return np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])


def _counted(tris: np.ndarray) -> tuple[int, int]:
    """``edge_defects`` by counting each directed edge in a dictionary."""
    edges = Counter((int(a), int(b)) for t in tris for a, b in ((t[0], t[1]), (t[1], t[2]), (t[2], t[0])))
    missing = sum(k for (a, b), k in edges.items() if (b, a) not in edges)
    return missing, sum(1 for k in edges.values() if k > 1)


@pytest.mark.parametrize("n_vertices", [600, 60_000])
@pytest.mark.parametrize("change", ["none", "drop", "flip", "repeat", "degenerate", "reorder"])
def test_edge_defects_counts_as_a_dictionary_of_directed_edges_does(change, n_vertices):
    """The quick answer for a closed, oriented mesh (its undirected edges pair up once each way) and
    the full count otherwise agree with counting every directed edge, on a torus of 1,200 triangles
    changed at random places; with edge keys sorted as 32-bit numbers (600 vertices) and as 64-bit
    ones (as if there were 60,000: keys up to 2 n^2 no longer fit in 32 bits)."""
    rng = np.random.default_rng(7)
    tris = _torus(20, 30)
    k = rng.choice(len(tris), size=3, replace=False)
    if change == "drop":
        tris = np.delete(tris, k, axis=0)
    elif change == "flip":
        tris[k] = tris[k, ::-1]
    elif change == "repeat":
        tris = np.concatenate([tris, tris[k[:2]]])
    elif change == "degenerate":  # a corner repeated: its edge a -> a is its own reverse
        tris = np.concatenate([tris, [[tris[k[0], 0], tris[k[0], 0], tris[k[0], 1]]]])
    elif change == "reorder":  # the same closed mesh, triangles and corners in another order
        tris = np.roll(tris[rng.permutation(len(tris))], 1, axis=1)
    expected = _counted(tris)
    assert (expected == (0, 0)) == (change in ("none", "reorder"))
    assert edge_defects(tris, n_vertices) == expected


def test_edges_that_do_not_pair_up_are_counted_whatever_their_keys_parity():
    # two triangles on edge 2 -> 3 the same way: sorted, the doubled key sits where a pair's first
    # would (the quick answer must check the pairs, not the parity alone)
    tris = np.array([[2, 3, 1], [2, 3, 0]])
    assert edge_defects(tris, 4) == _counted(tris) == (6, 1)


def test_unique_ints_is_numpys_unique():
    rng = np.random.default_rng(3)
    for x in (
        rng.integers(-50, 50, size=1000),
        rng.integers(0, 10**12, size=(300, 3)),
        np.arange(5)[::-1],
        np.zeros(0, dtype=np.int64),
    ):
        got = unique_ints(x)
        assert got.dtype == x.dtype
        assert np.array_equal(got, np.unique(x))


def test_open_edges_are_the_directed_edges_whose_reverse_is_missing():
    assert open_edges(TET, 4).shape == (0, 2)
    # without its first face, the three edges around the hole, as the neighbours hold them
    assert sorted(map(tuple, open_edges(TET[1:], 4).tolist())) == [(0, 1), (1, 2), (2, 0)]
    # a repeated edge is not open while its reverse is there; a lone triangle is all border
    assert open_edges(np.concatenate([TET, TET[:1]]), 4).shape == (0, 2)
    assert sorted(map(tuple, open_edges(TET[:1], 4).tolist())) == [(0, 2), (1, 0), (2, 1)]
    assert open_edges(np.empty((0, 3), dtype=np.int64), 0).shape == (0, 2)


def _t_junction(offset: float) -> tuple[np.ndarray, np.ndarray]:
    """The tetrahedron with face (0, 1, 3) split at vertex 4 beside the middle of edge 0-1 (``offset``
    mm off it, in -y: outside), and face (0, 2, 1) not: a T-junction."""
    xyz = np.vstack([XYZ, [[0.5, -offset, 0.0]]])
    tris = np.array([[0, 2, 1], [0, 4, 3], [4, 1, 3], [0, 3, 2], [1, 2, 3]])
    return xyz, tris


def test_a_t_junction_is_closed_by_splitting_the_triangle_whose_edge_it_lies_on():
    xyz, tris = _t_junction(0.0)
    assert edge_defects(tris, 5) == (3, 0)
    out, split = split_t_junctions(xyz, tris, 1e-7)
    assert split == 1
    assert edge_defects(out, 5) == (0, 0)
    assert signed_volume(xyz, out) == 1.0 / 6.0  # the same surface, in one more triangle
    assert sorted(map(tuple, out[-2:].tolist())) == [(1, 4, 2), (4, 0, 2)]


def test_a_vertex_off_the_open_edge_or_a_closed_mesh_is_left_alone():
    xyz, tris = _t_junction(1e-6)  # ten times the tolerance off the edge
    out, split = split_t_junctions(xyz, tris, 1e-7)
    assert split == 0 and out is tris
    out, split = split_t_junctions(XYZ, TET, 1e-7)
    assert split == 0 and out is TET
