"""Node rows on horizontal ridges and valleys: the topology mesh's surgery, checked on the mesh itself
(the slices they make possible are checked in test_pipeline and test_report)."""

from __future__ import annotations

import numpy as np
import pytest

from tests.conftest import build_part, write_step
from worker.dst import constants as C
from worker.dst.meshops import edge_defects, signed_volume
from worker.dst.ridges import add_ridge_rows
from worker.dst.step_io import read_step
from worker.dst.topomesh import build_topomesh

CLEARANCE = 1e-4
TOP = 4.1 + CLEARANCE  # the ridge's height in every part below


def _mesh(tmp_path, kind: str, nurbs: bool):
    part = read_step(
        write_step(build_part(kind, clearance=CLEARANCE), tmp_path / f"{kind}.step", nurbs=nurbs)
    )
    return build_topomesh(part.solids[0], deflection=0.01, angular=C.TOPO_ANGULAR_RAD, merge_tol=1e-8)


@pytest.mark.parametrize("nurbs", [False, True])
@pytest.mark.parametrize("kind", ["through_hole", "lying_cylinder", "flat_torus"])
def test_a_ridge_row_keeps_the_mesh_closed_and_every_node_exact(tmp_path, kind, nurbs):
    """Split along the ridge (a plane 0.1 um below it): the ridge then has nodes (new ones, or those
    of a seam edge lying on it: the analytic lying cylinder's); the mesh is still a closed,
    consistently oriented manifold; the new nodes lie on the ridge (its exact height) and on the
    surface at their (u, v) in every triangle; split boundary edges still map to their B-rep edge,
    whose curve passes through both ends of each piece."""
    mesh = _mesh(tmp_path, kind, nurbs)
    n0, volume0 = mesh.n_nodes, signed_volume(mesh.xyz, mesh.tris)
    add_ridge_rows(mesh, np.array([1.1, 4.1]))
    on_ridge = np.abs(mesh.xyz[:, 2] - TOP) < 1e-9
    assert on_ridge.sum() >= 2
    assert edge_defects(mesh.tris, mesh.n_nodes) == (0, 0)
    assert np.array_equal(np.unique(mesh.tris), np.arange(mesh.n_nodes))
    new = np.arange(n0, mesh.n_nodes)
    np.testing.assert_allclose(mesh.xyz[new, 2], TOP, atol=1e-9)
    # the surface at each corner's (u, v) is the node
    for t in np.flatnonzero(np.isin(mesh.tris, new).any(axis=1)).tolist():
        fe = mesh.faces[int(mesh.tri_face[t])]
        for node, (u, v) in zip(mesh.tris[t].tolist(), mesh.tri_uv[t].tolist(), strict=True):
            assert np.linalg.norm(np.subtract(fe.point(u, v), mesh.xyz[node])) < 1e-7
    for (a, b), ei in mesh.edge_of.items():
        if a >= n0 or b >= n0:
            ev = mesh.edges[ei]
            for node in (a, b):
                s = ev.parameter_of(tuple(mesh.xyz[node]))
                q = ev.ad.Value(s)
                assert np.linalg.norm(np.subtract((q.X(), q.Y(), q.Z()), mesh.xyz[node])) < 1e-7
    # nodes moved onto the surface from chords at most a deflection off it: a sliver of volume
    assert abs(signed_volume(mesh.xyz, mesh.tris) - volume0) < 0.1


def test_no_plane_beside_the_ridge_leaves_the_mesh_alone(tmp_path):
    """Planes farther from the ridge than the band (two deflections) change nothing (the same mesh
    gets a row with a plane 0.1 um below the ridge: the first test)."""
    mesh = _mesh(tmp_path, "through_hole", False)
    tris = mesh.tris.copy()
    assert add_ridge_rows(mesh, np.array([4.0, 4.2])) == 0
    assert np.array_equal(mesh.tris, tris)


# A torus (R 15, r 5) turned 10 degrees about x: its height has a maximum, a minimum and two saddles,
# the upper one r - R sin(10 deg) above the centre. Just below that saddle a plane cuts two loops (a
# crescent on each side of the hole), just above it one.
TORUS_R, TORUS_r, TORUS_TILT = 15.0, 5.0, 10.0
TORUS_SADDLE = TORUS_r - TORUS_R * np.sin(np.radians(TORUS_TILT))


def _torus_mesh(tmp_path, deflection=C.TOPO_DEFLECTION_MAX_MM):
    from worker.dst.step_io import orient

    part = read_step(write_step(build_part("torus", major=TORUS_R, minor=TORUS_r), tmp_path / "torus.step"))
    part = orient(part, (TORUS_TILT, 0.0, 0.0))
    return build_topomesh(part.solids[0], deflection=deflection, angular=C.TOPO_ANGULAR_RAD, merge_tol=1e-8)


def _torus_distance(xyz: np.ndarray) -> np.ndarray:
    """Distance of points from the turned torus's surface, in closed form."""
    t = np.radians(TORUS_TILT)
    axis = np.array([0.0, -np.sin(t), np.cos(t)])  # the z axis turned about x
    h = xyz @ axis
    rho = np.linalg.norm(xyz - h[:, None] * axis, axis=1)
    return np.abs(np.hypot(rho - TORUS_R, h) - TORUS_r)


def _loops_at(mesh, z: float) -> int:
    from worker.dst.sections import cut_topology

    return len(cut_topology(mesh, np.array([z]), on_plane_tol=C.ON_PLANE_TOL_MM).loops)


def test_edges_grazing_planes_beside_a_saddle_are_split_on_the_exact_surface(tmp_path):
    """Planes 0.2 um below and above the turned torus's saddle: topology edges near the saddle have
    both ends on one side of a plane while the torus between them passes it, so the coarse mesh's
    section joins the two crescents, or parts the one loop (this mesh errs at one of the planes).
    Split at the exact extreme along each such edge, the mesh's section has the exact number of loops
    at both; the mesh is still a closed, consistently oriented manifold; every new node is on the
    torus (closed form), off the planes, and at its (u, v) in every triangle."""
    from worker.dst.ridges import split_grazed_edges

    mesh = _torus_mesh(tmp_path)
    exact = {TORUS_SADDLE - 2e-4: 2, TORUS_SADDLE + 2e-4: 1}
    before = {z: _loops_at(mesh, z) for z in exact}
    assert before != exact, "the coarse mesh is right at both planes: this test would show nothing"
    n0, volume0 = mesh.n_nodes, signed_volume(mesh.xyz, mesh.tris)
    added = split_grazed_edges(mesh, np.array(sorted(exact)))
    assert {z: _loops_at(mesh, z) for z in exact} == exact
    assert added == mesh.n_nodes - n0 > 0
    assert edge_defects(mesh.tris, mesh.n_nodes) == (0, 0)
    assert np.array_equal(np.unique(mesh.tris), np.arange(mesh.n_nodes))
    new = np.arange(n0, mesh.n_nodes)
    assert _torus_distance(mesh.xyz[new]).max() < 1e-9
    assert (np.abs(mesh.xyz[new, 2, None] - np.array(list(exact))) > 1e-9).all()
    for t in np.flatnonzero(np.isin(mesh.tris, new).any(axis=1)).tolist():
        fe = mesh.faces[int(mesh.tri_face[t])]
        for node, (u, v) in zip(mesh.tris[t].tolist(), mesh.tri_uv[t].tolist(), strict=True):
            assert np.linalg.norm(np.subtract(fe.point(u, v), mesh.xyz[node])) < 1e-7
    assert abs(signed_volume(mesh.xyz, mesh.tris) - volume0) < 0.01


def test_planes_no_edge_grazes_leave_the_mesh_alone(tmp_path):
    """Planes far from the torus's saddles and extremes (and one through the middle, which crosses
    every edge it reaches) split nothing."""
    from worker.dst.ridges import split_grazed_edges

    mesh = _torus_mesh(tmp_path)
    tris = mesh.tris.copy()
    assert split_grazed_edges(mesh, np.array([TORUS_SADDLE - 0.5, 0.0, TORUS_SADDLE + 0.5])) == 0
    assert np.array_equal(mesh.tris, tris)


def test_a_grazed_edge_whose_node_has_a_stale_uv_is_split_at_the_same_exact_point(tmp_path):
    """A node on a B-rep edge carries the (u, v) of the edge's curve on the face, which a sloppy file
    puts off the node (boxed_sphere: up to 0.06 mm). The surface along the stored (u, v) is then
    not the edge's profile, and its extreme can be a point elsewhere (that made a turned boxed_sphere
    fail its mesh check). Here the ends of the torus's grazed edges get a (u, v) 0.05 mm off in
    every triangle: each end is projected back, and the splits are the same exact points."""
    from worker.dst.ridges import split_grazed_edges

    planes = np.array([TORUS_SADDLE - 2e-4, TORUS_SADDLE + 2e-4])
    clean = _torus_mesh(tmp_path)
    n0 = clean.n_nodes
    split_grazed_edges(clean, planes)
    # the nodes the new ones were put between: the ends of the split edges
    new = np.arange(n0, clean.n_nodes)
    ends = np.unique(clean.tris[np.isin(clean.tris, new).any(axis=1)])
    ends = ends[ends < n0]
    mesh = _torus_mesh(tmp_path)
    fe = mesh.faces[0]
    for node in ends.tolist():
        tri, corner = np.nonzero(mesh.tris == node)
        uv = mesh.tri_uv[tri[0], corner[0]]
        pu = np.subtract(fe.point(uv[0] + 1e-6, uv[1]), fe.point(*uv)) / 1e-6
        mesh.tri_uv[tri, corner, 0] += 0.05 / np.linalg.norm(pu)  # 0.05 mm along u
    assert split_grazed_edges(mesh, planes) == len(new)
    np.testing.assert_allclose(mesh.xyz[n0:], clean.xyz[n0:], atol=1e-9)
    assert {z: _loops_at(mesh, z) for z in planes} == {planes[0]: 2, planes[1]: 1}


def test_a_closed_edges_extreme_just_across_its_seam_from_its_vertex_is_split_exactly(tmp_path):
    """A cylinder turned so that its top circle's highest point lies 1 degree past the circle's seam
    vertex (a node of the topology mesh), between that node and its neighbour. The vertex's curve
    parameter is either end of the closed edge, here the far one: the span to the neighbour was
    taken for the long way round and skipped, and a plane 0.05 um below the highest point (both
    nodes 0.4 um and more below it) lost its sliver of the section. The span runs to the seam's
    near end: the edge is split at its exact highest point (closed form), and the mesh stays a
    closed, consistently oriented manifold."""
    import build123d as bd

    from worker.dst.ridges import split_grazed_edges
    from worker.dst.step_io import orient

    part = read_step(write_step(bd.Cylinder(5.0, 10.0), tmp_path / "cylinder.step", nurbs=False))
    # turned 0.5 degrees about x and -30 about y: the top circle's height, R (b cos t + a sin t) +
    # const, is highest at t = atan(a / b), about 1 degree (t = 0 at its seam vertex)
    part = orient(part, (0.5, -30.0, 0.0))
    mesh = build_topomesh(part.solids[0], deflection=0.01, angular=C.TOPO_ANGULAR_RAD, merge_tol=1e-8)
    top = max(
        (ei for ei, ev in enumerate(mesh.edges) if ev.closed),
        key=lambda ei: mesh.edges[ei].point(mesh.edges[ei].s0)[2],
    )
    ev = mesh.edges[top]
    # the exact highest point: the circle's centre plus its radius along its plane's steepest rise
    circ = ev.ad.Circle()
    centre, normal = np.array(circ.Location().Coord()), np.array(circ.Axis().Direction().Coord())
    rise = np.array([0.0, 0.0, 1.0]) - normal[2] * normal
    peak = centre + circ.Radius() * rise / np.linalg.norm(rise)
    s_top = ev.parameter_of(tuple(peak))
    seam = int(np.argmin(np.linalg.norm(mesh.xyz - ev.point(ev.s0), axis=1)))
    (after,) = [
        b if a == seam else a
        for (a, b), ei in mesh.edge_of.items()
        if ei == top and seam in (a, b) and ev.parameter_of(tuple(mesh.xyz[b if a == seam else a])) < np.pi
    ]
    s_seam, s_after = ev.parameter_of(tuple(mesh.xyz[seam])), ev.parameter_of(tuple(mesh.xyz[after]))
    assert ev.s0 < s_top < s_after, "the highest point is not between the seam vertex and its neighbour"
    assert s_seam == ev.s1, "the seam vertex's parameter is the near end: this test would show nothing"
    assert peak[2] - max(mesh.xyz[seam, 2], mesh.xyz[after, 2]) > 4e-7
    n0 = mesh.n_nodes
    assert split_grazed_edges(mesh, np.array([peak[2] - 5e-8])) >= 1
    nearest = np.linalg.norm(mesh.xyz[n0:] - peak, axis=1).min()
    assert nearest < 1e-9, nearest
    assert edge_defects(mesh.tris, mesh.n_nodes) == (0, 0)
    assert np.array_equal(np.unique(mesh.tris), np.arange(mesh.n_nodes))


@pytest.mark.parametrize("nurbs", [False, True])
def test_a_new_node_on_a_b_rep_edge_splits_the_mesh_edge_there(tmp_path, nurbs):
    """``lowest._make_node`` where an extreme lies on a B-rep edge between two of its nodes (the
    middle of the highest mesh edge along an edge of ``cut_cap``): one new node at the exact point,
    the mesh edge split into two pieces that both map to the B-rep edge, the mesh still closed,
    every corner of the triangles around the new node on its face at its (u, v); no node moves."""
    from worker.dst.lowest import _make_node

    part = read_step(write_step(build_part("cut_cap", offset=0.3), tmp_path / "cap.step", nurbs=nurbs))
    mesh = build_topomesh(part.solids[0], deflection=0.02, angular=C.TOPO_ANGULAR_RAD, merge_tol=1e-8)
    (a, b), ei = max(mesh.edge_of.items(), key=lambda kv: mesh.xyz[list(kv[0]), 2].min())
    ev = mesh.edges[ei]
    s = 0.5 * (ev.parameter_of(tuple(mesh.xyz[a])) + ev.parameter_of(tuple(mesh.xyz[b])))
    p = np.array(ev.point(s))
    before, n0 = mesh.xyz.copy(), mesh.n_nodes
    got = _make_node(mesh, ("edge", ei, s), p, sign=-1.0)
    assert mesh.n_nodes == n0 + 1
    np.testing.assert_array_equal(mesh.xyz[:n0], before)
    np.testing.assert_array_equal(got, p)
    np.testing.assert_array_equal(mesh.xyz[n0], p)
    assert (a, b) not in mesh.edge_of
    assert mesh.edge_of[(min(a, n0), max(a, n0))] == ei == mesh.edge_of[(min(b, n0), max(b, n0))]
    assert edge_defects(mesh.tris, mesh.n_nodes) == (0, 0)
    around = np.flatnonzero((mesh.tris == n0).any(axis=1))
    assert len(np.unique(mesh.tri_face[around])) == 2  # both faces of the edge
    for t in around.tolist():
        fe = mesh.faces[int(mesh.tri_face[t])]
        for node, (u, v) in zip(mesh.tris[t].tolist(), mesh.tri_uv[t].tolist(), strict=True):
            assert np.linalg.norm(np.subtract(fe.point(u, v), mesh.xyz[node])) < 1e-6


def test_a_split_point_off_its_edge_across_the_surface_is_not_taken_for_a_graze():
    """A split point belongs to its edge when it lies off it along the surface's normal (the surface
    rising over the chord: up to a quarter of the edge's length, a 90-degree arc's sag), not when it
    lies off it across the surface by more than the band: on a flat wall with an uneven (u, v)
    parametrisation the profile of a (u, v) segment bows within the wall (trj3_s1-al-214: a point
    0.15 mm above a long edge, where the mesh's section of the wall is the exact one). A point on a
    B-rep edge's curve (no normal) must lie within the band."""
    from worker.dst.ridges import _along_edge

    band = 0.04
    a, b = np.array([[0.0, 0.0, 0.0]]), np.array([[0.0, 10.0, 0.0]])
    wall, ridge, none = np.array([[1.0, 0.0, 0.0]]), np.array([[0.0, 0.0, 1.0]]), np.full((1, 3), np.nan)
    cases = [
        ((0.0, 5.0, 0.15), wall, False),  # up the wall from the edge: the parametrisation's bow
        ((0.0, 5.0, 0.03), wall, True),  # within the band
        ((0.1, 5.0, 0.0), wall, True),  # out of the wall: the surface over the chord
        ((0.0, 5.0, 0.24), ridge, True),  # trj7's ridge, 0.24 mm over its 8.5 mm edge
        ((0.0, 5.0, 2.6), ridge, False),  # beyond a quarter of the edge's length
        ((0.0, 9.9, 2.4), ridge, True),  # off its end: measured from the nearest point of the edge
        ((0.0, 5.0, 0.03), none, True),
        ((0.0, 5.0, 0.24), none, False),
    ]
    for p, normal, expected in cases:
        assert _along_edge(np.array([p]), normal, a, b, band).tolist() == [expected], (p, normal)


def test_the_quarter_point_look_reaches_a_parabolas_extreme_exactly():
    """``_farthest``: the largest ``-sign * z`` of the parabola through three heights at 0, 1/2, 1, and
    its sag: the vertex where the parabola bulges that way inside [0, 1], else the higher end."""
    from worker.dst.ridges import _farthest

    t = np.linspace(0.0, 1.0, 100_001)
    for c2, c1, c0 in [
        (-3.0, 2.0, 0.5),
        (2.0, -1.0, 0.0),
        (-1.0, 3.0, 0.0),
        (0.0, 1.0, -2.0),
        (4.0, -4.0, 1.0),
    ]:
        z = c2 * t**2 + c1 * t + c0
        heights = [np.array([c2 * x**2 + c1 * x + c0]) for x in (0.0, 0.5, 1.0)]
        for sign in (-1.0, 1.0):
            reach, sag = _farthest(*heights, np.array([sign]))
            assert reach[0] == pytest.approx((-sign * z).max(), abs=1e-9), (c2, c1, c0, sign)
            assert sag[0] == pytest.approx(abs(c2) / 4.0)


def test_an_edge_crossing_a_plane_is_split_where_the_surface_passes_the_next_one(tmp_path):
    """An edge whose ends lie either side of one plane, while the surface along it rises past the next
    plane beyond its higher end (trj7_b1-ec-214's top plane: edges across a ridge crossing the planes
    below): the mesh's section at that plane misses the surface's part beyond it. Planes chosen on
    the turned torus's mesh for its inner edge that bulges most over its higher end: that edge is split
    at the exact extreme of the surface along it (on the torus, beyond the plane), and the mesh is
    still a closed, consistently oriented manifold."""
    from worker.dst.ridges import BAND_DEFLECTIONS, split_grazed_edges

    mesh = _torus_mesh(tmp_path)
    fe = mesh.faces[0]
    brep = {(min(a, b), max(a, b)) for a, b in mesh.edge_of}
    best = None  # (rise over the higher end, a, b, exact highest point)
    for t in range(len(mesh.tris)):
        for i in range(3):
            a, b = int(mesh.tris[t, i]), int(mesh.tris[t, (i + 1) % 3])
            za, zb = mesh.xyz[a, 2], mesh.xyz[b, 2]
            if a > b or (a, b) in brep or abs(za - zb) < 1e-3:
                continue
            (ua, va), (ub, vb) = mesh.tri_uv[t, i], mesh.tri_uv[t, (i + 1) % 3]
            x = fe.height_extreme_on_uv_segment(ua, va, ub, vb, -1.0)
            top = np.array(fe.point(ua + x * (ub - ua), va + x * (vb - va)))
            rise = top[2] - max(za, zb)
            if 0.05 < x < 0.95 and (best is None or rise > best[0]):
                best = (rise, a, b, top)
    rise, a, b, top = best
    assert 1e-4 < rise < BAND_DEFLECTIONS * mesh.deflection, rise
    lo, hi = sorted((mesh.xyz[a, 2], mesh.xyz[b, 2]))
    planes = np.array([0.5 * (lo + hi), hi + 0.5 * rise])  # the edge crosses the first, not the second
    n0 = mesh.n_nodes
    split_grazed_edges(mesh, planes)
    edges = {
        tuple(sorted(e))
        for e in np.vstack([mesh.tris[:, [0, 1]], mesh.tris[:, [1, 2]], mesh.tris[:, [2, 0]]]).tolist()
    }
    assert (a, b) not in edges
    (new,) = [
        k
        for k in range(n0, mesh.n_nodes)
        if (min(a, k), max(a, k)) in edges and (min(b, k), max(b, k)) in edges
    ]
    assert np.linalg.norm(mesh.xyz[new] - top) < 1e-6
    assert _torus_distance(mesh.xyz[new][None])[0] < 1e-9 and mesh.xyz[new, 2] > planes[1]
    assert edge_defects(mesh.tris, mesh.n_nodes) == (0, 0)
