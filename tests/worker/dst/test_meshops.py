import numpy as np

from worker.dst.meshops import edge_defects, open_edges, signed_volume, split_t_junctions

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
