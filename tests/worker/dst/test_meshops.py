import numpy as np

from worker.dst.meshops import edge_defects, open_edges, signed_volume

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
