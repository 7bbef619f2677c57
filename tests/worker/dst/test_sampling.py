"""The ring sampler's own fallbacks, on a cone whose exact sections are closed-form circles."""

from __future__ import annotations

import math

import numpy as np
import pytest
from OCP.GeomAbs import GeomAbs_Cone, GeomAbs_Plane

from worker.dst import constants as C
from worker.dst.chords import point_segment_distance
from worker.dst.pipeline import bbox_diagonal, topo_deflection
from worker.dst.sampler_records import VertexPool
from worker.dst.sampling import RingSampler, ring_passes
from worker.dst.sections import cut_topology
from worker.dst.step_io import read_step
from worker.dst.topomesh import build_topomesh

RADIUS, HEIGHT = 10.0, 20.0  # the conftest cone: base radius 10 at z = 0, apex at z = 20
Z = 5.0  # the plane: the section is the circle of radius 7.5 about the axis
R_Z = RADIUS * (1.0 - Z / HEIGHT)


def _topomesh_of(path):
    """The topology mesh of the part in ``path`` (its one solid) at the build's settings."""
    part = read_step(path)
    diag, _ = bbox_diagonal(part)
    return build_topomesh(
        part.solids[0],
        deflection=topo_deflection(diag),
        angular=C.TOPO_ANGULAR_RAD,
        merge_tol=C.MERGE_TOL_REL * diag,
    )


@pytest.fixture(scope="module")
def cone_sampler(tmp_path_factory):
    from tests.conftest import build_part, write_step

    path = write_step(
        build_part("cone", radius=RADIUS, height=HEIGHT),
        tmp_path_factory.mktemp("c") / "cone.step",
        nurbs=False,
    )
    mesh = _topomesh_of(path)
    world = np.array([Z])
    topo = cut_topology(mesh, world, on_plane_tol=C.ON_PLANE_TOL_MM, noise_tol=np.zeros(1))
    sampler = RingSampler(mesh, topo, VertexPool(), segment_length=1.0, chord_error=0.01)
    kinds = [f.ad.GetType() for f in mesh.faces]
    return sampler, kinds.index(GeomAbs_Cone), kinds.index(GeomAbs_Plane)


def _on_circle(angle: float) -> np.ndarray:
    return np.array([R_Z * math.cos(angle), R_Z * math.sin(angle), Z])


def test_midpoints_the_seed_path_left_off_their_segment_are_solved_from_the_chord(cone_sampler):
    """A seed path through a pole of the face's parametrisation (the cone's apex) can put a
    segment's midpoint next to an end, or find none: the segment would pass the chord check
    unseen. Such midpoints are solved again from the chord's middle, onto the exact section (the
    circle, at the chord's middle); one that still cannot be placed (here: the plane does not meet
    the face named) is counted, not passed silently; a midpoint in its segment's middle is left as
    it is. A segment within the chord budget whatever its arc has an off-middle midpoint solved
    again too (measured where it was, on another piece of the curve, it would fail the segment and
    its parts without end: ec_soapbox-A turned 35 degrees); one not found is dropped, not counted.
    A run traced along the exact curve (the tip of a tongue beyond the chord across it) keeps its
    midpoints wherever they project."""
    sampler, cone, base = cone_sampler
    a0, a1 = 0.3, 1.1  # a 5.8 mm chord of the 7.5 mm circle (sag 0.6 mm)
    pa, pb = _on_circle(a0), _on_circle(a1)
    near_end = pa + 0.02 * (pb - pa)  # where a stray seed path left it
    middle = _on_circle(0.5 * (a0 + a1))
    short_b = _on_circle(a0 + 0.001)  # a 7.5 um segment: within the 0.01 mm budget as any arc
    cases = [  # face, midpoint, found, segment end b
        (cone, near_end, True, pb),
        (cone, np.full(3, np.nan), False, pb),
        (base, near_end, True, pb),
        (cone, middle, True, pb),
        (cone, pa, True, short_b),
        (base, pa, True, short_b),
        (cone, _on_circle(a0 + 0.0005), True, short_b),
        (cone, near_end, True, pb),  # traced
    ]
    face = np.array([c[0] for c in cases])
    mid = np.array([c[1] for c in cases])
    mid_ok = np.array([c[2] for c in cases])
    seg_a = np.repeat(pa[None], len(cases), axis=0)
    seg_b = np.array([c[3] for c in cases])
    length = np.linalg.norm(seg_b - seg_a, axis=1)
    before = sampler.stats.unchecked_segments
    mid_uv = np.full((len(cases), 2), -7.0)
    sampler._midpoints_off_the_path(
        # face, plane height, Newton step, and a seed path's (u, v) at the chord's start (none here:
        # the start's (u, v) found from (0, 0))
        (face, np.full(len(cases), Z), np.full(len(cases), 1.0), np.zeros((len(cases), 2))),
        mid,
        mid_ok,
        seg_a,
        seg_b,
        length,
        np.arange(len(cases)) == len(cases) - 1,
        mid_uv,
    )
    # the first two: on the exact circle, at the chord's middle (the arc's midpoint), with the face
    # parameters of where they now are
    for i in (0, 1):
        assert mid_ok[i]
        assert math.hypot(mid[i, 0], mid[i, 1]) == pytest.approx(R_Z, abs=1e-6)
        assert mid[i, 2] == pytest.approx(Z, abs=C.LEVEL_TOL_MM)
        assert math.atan2(mid[i, 1], mid[i, 0]) == pytest.approx(0.5 * (a0 + a1), abs=1e-6)
        at = sampler.mesh.faces[cone].ad.Value(*mid_uv[i])
        assert np.allclose(at.Coord(), mid[i], atol=1e-9)
    np.testing.assert_array_equal(mid_uv[[2, 3, 6, 7]], -7.0)  # the others' are left as they were
    # the one on the base face: no point of that face on the plane, counted
    assert sampler.stats.unchecked_segments == before + 1
    np.testing.assert_array_equal(mid[2], near_end)
    # already in the middle: untouched
    np.testing.assert_array_equal(mid[3], middle)
    np.testing.assert_array_equal(mid[6], _on_circle(a0 + 0.0005))
    # within the budget, its midpoint at an end: solved at the middle; on the wrong face: dropped
    assert mid_ok[4] and math.atan2(mid[4, 1], mid[4, 0]) == pytest.approx(a0 + 0.0005, abs=1e-7)
    assert math.hypot(mid[4, 0], mid[4, 1]) == pytest.approx(R_Z, abs=1e-6)
    assert not mid_ok[5]
    # traced: untouched
    assert mid_ok[7]
    np.testing.assert_array_equal(mid[7], near_end)


def test_a_crossing_whose_root_lies_beyond_its_face_is_dropped_from_the_ring(tmp_path):
    """A thin curved face (the end of a tube 0.002 mm thick: an annulus on the plane y = -5) has
    topology triangles whose inner edges, chords from one circle to the other, leave the face: the
    root of such an edge at a plane lies on the plane's extension inside the hole, off the B-rep
    (0.0128 and 0.039 mm at z = 2.3 and 22.1 before the fix). It is dropped onto a ring neighbour:
    every vertex of the mesh on the end face lies on the annulus (between its two circles), and the
    mesh stays closed."""
    from build123d import Align, Box, Cylinder, Pos, Rot

    from tests.conftest import write_step
    from worker.dst.meshops import edge_defects
    from worker.dst.params import SliceParams
    from worker.dst.pipeline import slice_step

    r_in, thick, axis_z = 10.0, 0.002, 12.13
    block = Box(30, 10, 30, align=(Align.CENTER, Align.MIN, Align.MIN))
    tube_end = Pos(0, -2.5, axis_z) * Rot(90, 0, 0) * Cylinder(r_in + thick, 5)  # y from -5 to 0
    hole = Pos(0, 0, axis_z) * Rot(90, 0, 0) * Cylinder(r_in, 30)
    path = write_step(block + tube_end - hole, tmp_path / "tube.step", nurbs=False)
    mesh = slice_step(path, SliceParams(layer_height=0.2))

    open_e, dup = edge_defects(mesh.triangles, len(mesh.vertices))
    assert open_e == 0 and dup == 0
    v = mesh.vertices[np.unique(mesh.triangles)]
    z = v[:, 2] + mesh.z_offset
    end = np.abs(v[:, 1] + 5.0) < 1e-7
    r = np.hypot(v[end, 0], z[end] - axis_z)
    assert end.sum() > 100
    assert r.min() > r_in - 1e-6, r.min() - r_in
    assert r.max() < r_in + thick + 1e-6, r.max() - r_in - thick
    assert mesh.stats["off_trim_crossings"] >= 2  # dropped, and counted


def test_a_crossing_whose_nodes_stored_uv_is_off_the_node_is_solved_from_the_nodes_own(tmp_path):
    """A node on a B-rep edge carries the (u, v) of the edge's curve on the face, which a sloppy
    file can put farther from the node than its tolerance says (``trj3_s1-al-214`` turned (78.4,
    32.6, -18.9): 0.37 mm, the surface there on the other side of the plane from the node, and the
    job failed with "no exact point of face 6"). Here a cone's seam node gets a stored (u, v) whose
    surface point lies as far below the plane as the node lies above it: the crossing is still the
    exact point between the two nodes' own (u, v), on the circle and on the topology edge's span."""
    from tests.conftest import build_part, write_step

    path = write_step(build_part("cone", radius=RADIUS, height=HEIGHT), tmp_path / "cone.step", nurbs=False)
    mesh = _topomesh_of(path)
    topo = cut_topology(mesh, np.array([Z]), on_plane_tol=C.ON_PLANE_TOL_MM, noise_tol=np.zeros(1))
    sampler = RingSampler(mesh, topo, VertexPool(), segment_length=1.0, chord_error=0.01)
    on_edge = sampler._on_brep_edge
    # a crossing on a topology edge (not itself a B-rep edge) from a seam node above the plane
    c = next(
        c
        for c in range(len(topo.cross_edge))
        if topo.cross_node[c] < 0
        and (a_b := tuple(int(x) for x in topo.edges[topo.cross_edge[c]])) not in mesh.edge_of
        and any(on_edge[n] and mesh.xyz[n, 2] > Z for n in a_b)
    )
    a, b = (int(x) for x in topo.edges[topo.cross_edge[c]])
    node = a if on_edge[a] and mesh.xyz[a, 2] > Z else b
    t = int(topo.edge_tris[topo.cross_edge[c], 0])
    corner = mesh.tris[t].tolist().index(node)
    face = mesh.faces[int(mesh.tri_face[t])]
    u, v = mesh.tri_uv[t, corner]
    # the (u, v) along the cone's generatrix at the node's height mirrored in the plane
    grad = np.subtract(face.point(u, v + 1e-3), face.point(u, v))[2] / 1e-3
    mesh.tri_uv[t, corner, 1] = v - 2.0 * (mesh.xyz[node, 2] - Z) / grad
    assert face.point(*mesh.tri_uv[t, corner])[2] < Z  # the stored ends no longer bracket the plane

    vid = sampler.crossing(c)
    p = sampler.pool.xyz[vid]
    assert abs(math.hypot(p[0], p[1]) - R_Z) < 1e-9 and p[2] == Z
    lo, hi = np.minimum(mesh.xyz[a, :2], mesh.xyz[b, :2]), np.maximum(mesh.xyz[a, :2], mesh.xyz[b, :2])
    assert np.all(p[:2] > lo - 1e-6) and np.all(p[:2] < hi + 1e-6), (p, mesh.xyz[a], mesh.xyz[b])
    assert sampler.stats.fallbacks == 0  # found by its bracket, not Newton from a seed


def _tangent(angle: float) -> tuple[float, float]:
    return (-math.sin(angle), math.cos(angle))  # counter-clockwise: the cone's material on the left


def test_a_trace_follows_the_section_curve_in_the_loops_direction(cone_sampler):
    """``FaceEval.trace_level`` walks the exact section (here the circle of radius 7.5) in the
    loops' direction, material on the left (counter-clockwise round the cone), to a target ahead
    of it; a target behind it is reached the long way round; a target whose curve runs the other
    way (the far side of a narrow tongue, as near but not on this side) is never taken for it."""
    from worker.dst.exact import ExactFailure

    sampler, cone, _ = cone_sampler
    ev = sampler.mesh.faces[cone]
    u, v = ev.uv_near(tuple(_on_circle(0.2)), (0.0, 0.0))
    assert ev.section_direction(u, v) == pytest.approx(_tangent(0.2), abs=1e-9)

    def angles(target: float, step: float = 1.0, direction=None) -> np.ndarray:
        pts = ev.trace_level(
            u,
            v,
            Z,
            tuple(_on_circle(target)[:2]),
            direction or _tangent(target),
            step=step,
            max_length=60.0,
        )
        xy = np.array(pts)[:, :2]
        assert np.hypot(xy[:, 0], xy[:, 1]) == pytest.approx(R_Z, abs=1e-9)  # on the section
        for x, y, pu, pv in pts:  # and the (u, v) given is the point's
            assert ev.point(pu, pv) == pytest.approx((x, y, Z), abs=1e-9)
        return np.unwrap(np.concatenate([[0.2], np.arctan2(xy[:, 1], xy[:, 0])]))[1:]

    ahead = angles(1.4, step=0.3)
    assert (np.diff(ahead) > 0).all() and 0.2 < ahead[0] and ahead[-1] < 1.4
    assert R_Z * (1.4 - ahead[-1]) <= 0.3 + 1e-9  # the target within the last step
    behind = angles(0.1)
    assert (np.diff(behind) > 0).all() and behind[-1] > 0.1 + 2 * math.pi - 1.0 / R_Z - 1e-9
    with pytest.raises(ExactFailure, match="did not arrive"):
        angles(1.4, direction=tuple(-c for c in _tangent(1.4)))


def test_a_trace_to_its_own_start_goes_once_round(cone_sampler):
    """With ``min_length`` the start is not taken for the target at once (without, that hangs on the
    rounding of the start's own distance): the trace goes once round the closed section (the circle
    of radius 7.5) and stops within a step of where it began, as a pinned cap's ring is traced
    (``RingSampler.traced_loop``)."""
    sampler, cone, _ = cone_sampler
    ev = sampler.mesh.faces[cone]
    u, v = ev.uv_near(tuple(_on_circle(0.2)), (0.0, 0.0))
    start = tuple(_on_circle(0.2)[:2])
    pts = ev.trace_level(u, v, Z, start, _tangent(0.2), step=0.5, max_length=60.0, min_length=1e-9)
    xy = np.array(pts)[:, :2]
    assert np.hypot(xy[:, 0], xy[:, 1]) == pytest.approx(R_Z, abs=1e-9)
    turn = np.unwrap(np.concatenate([[0.2], np.arctan2(xy[:, 1], xy[:, 0])]))
    assert (np.diff(turn) > 0).all()
    assert 2 * math.pi - 0.5 / R_Z - 1e-9 <= turn[-1] - 0.2 < 2 * math.pi


@pytest.fixture(scope="module")
def cube_side():
    """The side x = 5 of a 10 mm cube, where the section z = 2 is the line y = -5 .. 5: the face,
    (u, v) of its point y = -4 and the section's direction there."""
    from build123d import Box
    from OCP.BRepAdaptor import BRepAdaptor_Surface

    from worker.dst.exact import FaceEval

    face = Box(10, 10, 10).faces().sort_by_distance((5, 0, 0))[0]
    ev = FaceEval(BRepAdaptor_Surface(face.wrapped))
    u, v = ev.uv_near((5.0, -4.0, 2.0), (0.0, 0.0))
    return ev, u, v, ev.section_direction(u, v)


def test_a_trace_stops_where_its_face_ends(cube_side):
    """A trace may not leave its face's trim (beyond it lies the surface's extension, not the
    B-rep)."""
    from worker.dst.exact import ExactFailure

    ev, u, v, direction = cube_side
    assert direction == pytest.approx((0.0, 1.0), abs=1e-12)  # material (x < 5) on the left
    pts = ev.trace_level(u, v, 2.0, (5.0, 4.0), direction, step=0.5, max_length=20.0)
    xy = np.array(pts)[:, :2]
    np.testing.assert_allclose(xy[:, 0], 5.0, atol=1e-12)
    assert (np.diff(xy[:, 1]) > 0).all() and xy[0, 1] > -4.0 and 3.5 <= xy[-1, 1] < 4.0
    with pytest.raises(ExactFailure, match="left the face"):
        ev.trace_level(u, v, 2.0, (5.0, 7.0), direction, step=0.5, max_length=20.0)


def test_a_trace_arrives_at_a_target_on_its_faces_edge(cube_side):
    """A stretch traced to a corner ends on its face's edge: the trace arrives there (a target
    within a step ahead is never stepped past, so no step leaves the face first), whatever the step;
    a target beyond the edge is not reached."""
    from worker.dst.exact import ExactFailure

    ev, u, v, direction = cube_side
    for step in (0.3, 0.7, 1.3, 2.5, 4.0):
        pts = ev.trace_level(u, v, 2.0, (5.0, 5.0), direction, step=step, max_length=20.0)
        y = np.array(pts)[:, 1]
        assert (np.diff(y) > 0).all() and 5.0 - step - 1e-9 <= y[-1] < 5.0
    with pytest.raises(ExactFailure, match="left the face"):  # a target beyond the edge: not reached
        ev.trace_level(u, v, 2.0, (5.0, 6.5), direction, step=0.7, max_length=20.0)


@pytest.fixture(scope="module")
def box_sampler(tmp_path_factory):
    """A sampler of the 10 mm cube's section z = 2 (four faces, their corners at x, y = +-5)."""
    from build123d import Box

    from tests.conftest import write_step

    mesh = _topomesh_of(write_step(Box(10, 10, 10), tmp_path_factory.mktemp("b") / "box.step", nurbs=False))
    z = float(mesh.xyz[:, 2].min()) + 2.0
    topo = cut_topology(mesh, np.array([z]), on_plane_tol=C.ON_PLANE_TOL_MM, noise_tol=np.zeros(1))
    return mesh, topo, z


def test_a_ring_passing_a_run_out_of_order_is_traced_again_between_its_corners(box_sampler):
    """A ring that passes the section of one face back and forth (as the report's reference did on
    parts turned so that a plane nearly touches a rounded edge: M6-1x12-countersunk-screw's U-shaped
    section passed four times, its perimeter 17% long) is traced again from the corner before to the
    corner after; a vertex where the ring turns back outside its face (a spur onto the surface's
    extension) is dropped first. The result passes every side once, in order, within budget."""
    mesh, topo, z = box_sampler
    sampler = RingSampler(
        mesh, topo, VertexPool(), segment_length=1.0, chord_error=0.01, keep_crossings=False
    )
    lo = mesh.xyz[:, :2].min(axis=0)
    hi = mesh.xyz[:, :2].max(axis=0)
    mid = 0.5 * (lo + hi)

    def face_at(x: float, y: float) -> int:  # the side face through (x, y, z)
        for k, f in enumerate(mesh.faces):
            if f.ad.GetType() != GeomAbs_Plane or abs(f.ad.Plane().Axis().Direction().Z()) > 0.5:
                continue
            uv = f.uv_near((x, y, z), (0.0, 0.0))
            if f.contains(*uv, tol=1e-6) and np.linalg.norm(np.subtract(f.point(*uv), (x, y, z))) < 1e-9:
                return k
        raise AssertionError(f"no side face through ({x}, {y})")

    x1 = hi[0]
    # along the side x = x1 (loops run counter-clockwise: +y there) twice over y = -2 .. 3 (the
    # trace from y = 3 cannot reach y = -2: it runs on, off the face), then a spur past its far
    # corner (y beyond hi, on the plane's extension) and back
    side_y = [-3.0, -1.0, 1.0, 3.0, -2.0, 0.0, 2.0, 4.0, hi[1] + 0.5, 4.2]
    corners = [(x1, lo[1]), (x1, hi[1]), (lo[0], hi[1]), (lo[0], lo[1])]
    ids = [sampler.pool.add((x, y, z), 0) for x, y in corners]
    sampler.corner_vids.update(ids)
    side = [sampler.pool.add((x1, mid[1] + y, z), 0) for y in side_y]
    ring = [ids[0], *side, ids[1], ids[2], ids[3]]
    f_side = face_at(x1, mid[1])
    face_of = {v: f_side for v in [ids[0], *side]}
    face_of[ids[1]] = face_at(mid[0], hi[1])
    face_of[ids[2]] = face_at(lo[0], mid[1])
    face_of[ids[3]] = face_at(mid[0], lo[1])
    li = 0
    rings = {li: ring}
    sampler._replace_excursions(rings, face_of)
    out = sampler.pool.xyz[rings[li]]
    assert sampler.stats.spur_vertices == 1
    on_side = out[np.abs(out[:, 0] - x1) < 1e-9]
    assert (np.diff(on_side[:, 1]) > 0).all()  # once along the side, in order, corner to corner
    assert on_side[0, 1] == pytest.approx(lo[1]) and on_side[-1, 1] == pytest.approx(hi[1])
    assert np.diff(on_side[:, 1]).max() <= 1.0 + 1e-9  # the segment budget
    assert len(out) == len(on_side) + 2  # the other two corners as they were


def test_stretches_to_trace_again_cluster_round_the_ring_and_replace_its_vertices():
    from worker.dst.traces import _clusters, _splice

    # segments 3, 4 and 10 are one stretch (gap 6 <= 8), 30 another; 60 joins 3 round the end
    assert _clusters([3, 4, 10, 30], 64, 8) == [(3, 11), (30, 31)]
    assert _clusters([3, 4, 10, 60], 64, 8) == [(60, 75)]
    assert _clusters([0, 5], 6, 8) == []  # a stretch must leave a vertex out
    ring = list(range(10))
    # vertices 3, 4 replaced by 100, 101; 9 and 0 (the stretch 8 -> 11 = 1 wraps) by 200
    assert _splice(ring, [(2, 5, [100, 101]), (8, 11, [200])]) == [1, 2, 100, 101, 5, 6, 7, 8, 200]
    assert _splice(ring, [(4, 5, [7])]) == [0, 1, 2, 3, 4, 7, 5, 6, 7, 8, 9]


def test_a_trace_round_a_loop_smaller_than_the_segment_budget_is_not_taken(cone_sampler):
    """A pinned ring whose two crossings came out of order (the second a little behind the first)
    has a trace from one to the other go the long way round, along the ring's other segments: that
    trace fails, however small the loop is against the segment budget (trj4_k1_top-pe-214 at
    z = 1.3: round a 2.3 mm hole, all of it within the 0.8 mm budget of the trace's ends, three laps
    spliced into one ring). A trace along a piece the ring skips is taken."""
    from worker.dst.traces import _segments_beside

    base, cone, _ = cone_sampler
    budget = 4.0 * R_Z  # every point of the circle within the budget of any other
    sampler = RingSampler(base.mesh, base.topo, VertexPool(), segment_length=budget, chord_error=0.01)
    # the circle within the chord budget (0.0023 mm sag), but for two points out of order (0.55 before
    # 0.5) and a piece it skips (from 3.0 to 4.5: its chord 2 mm inside the circle)
    angles = [a for a in np.arange(0.0, 2 * math.pi - 0.01, 0.05) if not 3.0 < a < 4.5]
    angles[10], angles[11] = angles[11], angles[10]
    ring = [sampler.pool.add(tuple(_on_circle(a)), 0) for a in angles]
    p = sampler.pool.xyz[ring, :2]

    def traced(i: int, j: int):
        return sampler._traced_run(cone, ring[i], ring[j], Z, 0, elsewhere=_segments_beside(p, i, j))

    failures = sampler.stats.excursion_failures
    assert angles[10] > angles[11] and traced(10, 11) is None  # round the circle, along the ring
    assert sampler.stats.excursion_failures == failures + 1
    k = angles.index(next(a for a in angles if a >= 4.5)) - 1  # the ring's chord 3.0 -> 4.5
    run = traced(k, k + 1)
    assert run is not None and run.traced
    assert run.s[-1] == pytest.approx(R_Z * (angles[k + 1] - angles[k]), rel=0.01)


def test_a_surface_kink_the_curve_does_not_cross_between_the_runs_ends_is_no_ring_vertex(tmp_path):
    """A run is split at the exact point where its section crosses a C0 line of its face (a corner
    inside one B-spline face), found where the run's seed path crosses that line. An exact end solved
    past the line (boxed_sphere at z = 0.1: a rounded corner's C0 line 0.03 mm beyond the crossing)
    leaves the line's point outside the run, and the ring stepped back to it and forth again, a bow
    tie: no such point then. Where the curve crosses the line between the ends, it is the corner."""
    from tests.conftest import kinked_prism, write_step
    from worker.dst.runs import Run

    corners = [(0.0, 0.0), (20.0, 0.0), (26.0, 9.0), (12.0, 15.0), (-3.0, 7.0)]
    mesh = _topomesh_of(write_step(kinked_prism(corners, 5.0), tmp_path / "kinked.step"))
    z = float(mesh.xyz[:, 2].min()) + 2.5
    topo = cut_topology(mesh, np.array([z]), on_plane_tol=C.ON_PLANE_TOL_MM, noise_tol=np.zeros(1))
    sampler = RingSampler(mesh, topo, VertexPool(), segment_length=1.0, chord_error=0.01)
    (wall,) = [k for k, f in enumerate(mesh.faces) if sampler._surface_kinks(k)[0].size]
    ev = mesh.faces[wall]

    def run_to(end_xy, seed_end_xy) -> Run:
        """The run from (18, 0) to ``end_xy`` on the wall, its seed path ending at ``seed_end_xy``."""
        a, b = (18.0, 0.0, z), (*end_xy, z)
        uv_a = ev.uv_near(a, (0.0, 0.0))
        uv = np.array([uv_a, ev.uv_near((*seed_end_xy, z), uv_a)])
        s = np.array([0.0, float(np.hypot(b[0] - a[0], b[1] - a[1]))])
        va, vb = sampler.pool.add(a, 0), sampler.pool.add(b, 0)
        return Run(wall, s, uv, 1.0, va, vb, 1, z, 0)

    beyond = (21.0, 1.5)  # on the wall's next piece, past its C0 line at (20, 0)
    assert sampler._kink_points(run_to((19.97, 0.0), beyond)) == []  # both ends before the line
    (kink,) = sampler._kink_points(run_to(beyond, beyond))
    assert sampler.pool.xyz[kink[2]] == pytest.approx((20.0, 0.0, z), abs=1e-9)
    assert kink[2] in sampler.corner_vids


def test_only_gaps_left_in_the_final_rings_are_counted(cone_sampler):
    """A segment kept over budget (no exact point between its ends) is a gap of the mesh only if it
    is still a ring segment at the end: one that a later trace re-sampled (r103ec turned: the
    zigzag across a tongue's neck, 0.26 mm, reported as the build's longest gap) is not counted."""
    base, _, _ = cone_sampler
    sampler = RingSampler(base.mesh, base.topo, VertexPool(), segment_length=1.0, chord_error=0.01)
    angles = np.linspace(0.0, 2.0 * math.pi, 8, endpoint=False)
    ring = [sampler.pool.add(tuple(_on_circle(a)), 0) for a in angles]
    xyz = sampler.pool.xyz
    kept, gone = (ring[0], ring[1]), (ring[2], ring[5])  # a ring segment; a chord across the ring
    pa, pb = xyz[[kept[0], gone[0]]], xyz[[kept[1], gone[1]]]
    length = np.linalg.norm(pb - pa, axis=1)
    sampler._record_gaps(np.array([True, True]), length, pa, pb, np.full(2, 3), np.zeros(2, dtype=int))
    assert sampler.stats.tolerance_gaps == 2 and sampler.stats.max_gap_mm == pytest.approx(length[1])
    sampler.settle_gaps([ring])
    assert sampler.stats.tolerance_gaps == 1
    assert sampler.stats.max_gap_mm == pytest.approx(length[0])
    a, b = (np.round(xyz[v, :2], 4).tolist() for v in kept)
    assert sampler.stats.max_gap_at == f"face 1, from {a} to {b}" and sampler.stats.max_gap_plane == 3
    sampler.settle_gaps([ring[::-1]])  # either way round
    assert sampler.stats.tolerance_gaps == 1
    sampler.settle_gaps([ring[:2] + ring[3:]])
    assert sampler.stats.tolerance_gaps == 1  # (ring[0] -> ring[1] still there)
    sampler.settle_gaps([[ring[0], *ring[2:]]])
    assert (
        sampler.stats.tolerance_gaps == 0 and sampler.stats.max_gap_mm == 0.0 and not sampler.stats.max_gap_at
    )
    assert sampler.stats.max_gap_plane == -1


def test_a_point_between_two_others_along_the_section_is_told_from_one_beyond_them(cone_sampler):
    """``RingSampler._between_neighbours``: a point of the section (the circle of radius 7.5, run
    counter-clockwise, the loops' direction) lies between two others where a trace from the first
    to the second passes it: 0.5 rad lies between 0.2 and 0.9, -0.2 and 1.2 do not; from 0.9 to 0.2
    the curve runs the long way round, through 1.2 and not 0.5 (within the trace's reach)."""
    sampler, cone, _ = cone_sampler
    ev = sampler.mesh.faces[cone]

    def between(a: float, lo: float, hi: float, reach: float = 0.0) -> bool:
        u, v = ev.uv_near(tuple(_on_circle(a)), (0.0, 0.0))
        ends = (tuple(_on_circle(lo)[:2]), tuple(_on_circle(hi)[:2]))
        return sampler._between_neighbours(ev, u, v, Z, *ends, 0.1, reach)

    assert between(0.5, 0.2, 0.9)
    assert not between(-0.2, 0.2, 0.9)
    assert not between(1.2, 0.2, 0.9)
    assert not between(1.2, 0.9, 0.2)  # the long way round is beyond the trace's reach
    assert between(1.2, 0.9, 0.2, reach=12.0)
    assert not between(0.5, 0.9, 0.2, reach=12.0)


def _bending_curve(k0: float, k1: float, length: float, at: np.ndarray) -> np.ndarray:
    """Points (len(at), 3) at arc lengths ``at`` of a plane curve at z = Z whose curvature goes
    linearly from ``k0`` to ``k1`` along ``length`` (a circle where they are equal), in closed form
    for its tangent angle and by a fine quadrature for its position."""
    s = np.linspace(0.0, length, 200_001)
    angle = k0 * s + 0.5 * (k1 - k0) * s**2 / length
    step = np.diff(s)
    mid = 0.5 * (angle[1:] + angle[:-1])
    x = np.concatenate([[0.0], np.cumsum(np.cos(mid) * step)])
    y = np.concatenate([[0.0], np.cumsum(np.sin(mid) * step)])
    return np.column_stack([np.interp(at, s, x), np.interp(at, s, y), np.full(len(at), Z)])


def test_a_segment_within_the_halving_budget_is_kept_as_its_halves_where_they_are_parabolic(cone_sampler):
    """``_halves`` (the report's reference): a segment 1.5-2.4x the chord (0.01 mm) from its curve
    is kept as its two halves, each checked at its own midpoint (the segment's quarter point). An
    arc of a circle: both halves pass (a quarter of the distance each), no point more. A bend whose
    curvature grows 5x along the segment: each half passes a one-sample check (0.004 and 0.008 mm)
    but lies a third off a quarter of the segment's distance (a parabola's halves lie at a quarter),
    so both are checked again as any segment, between their own ends. A segment one of whose quarter
    points was not found on it is checked again whole, its midpoint not kept."""
    sampler, _, _ = cone_sampler
    e = sampler.chord
    length = 0.8
    at = length * np.array([0.0, 0.25, 0.5, 0.75, 1.0])
    curves = [
        _bending_curve(0.25, 0.25, length, at),
        _bending_curve(0.1, 0.5, length, at),
        _bending_curve(0.25, 0.25, length, at),
    ]
    pts = np.stack(curves)  # (3 segments, 5 points, 3)
    sag = [float(point_segment_distance(p[2:3], p[0:1], p[4:5])[0]) for p in pts]
    assert all(1.5 * e < s < 2.5 * e for s in sag)
    n = len(pts)
    pending = (np.array([0, 1, 2]), np.zeros(n), np.full(n, length), pts[:, 0], pts[:, 4])
    q_ok = np.array([[True, True], [True, True], [True, False]])
    before = sampler.stats.halved_segments
    kept, again = sampler._halves(
        pending, np.arange(n), pts[:, 2], np.full(n, 0.5 * length), pts[:, [1, 3]], q_ok
    )
    assert kept.tolist() == [True, True, False]
    assert sampler.stats.halved_segments == before + 2
    ri, sa, sb, pa, pb = again
    # the bending segment's two halves, then the third segment whole
    assert ri.tolist() == [1, 1, 2]
    np.testing.assert_allclose(np.column_stack([sa, sb]), [[0.0, 0.4], [0.4, 0.8], [0.0, 0.8]])
    np.testing.assert_array_equal(pa, [pts[1, 0], pts[1, 2], pts[2, 0]])
    np.testing.assert_array_equal(pb, [pts[1, 2], pts[1, 4], pts[2, 4]])
    # the arc's halves are within the chord everywhere (dense points of the exact arc)
    dense = _bending_curve(0.25, 0.25, length, np.linspace(0.0, length, 2001))
    half_a = point_segment_distance(
        dense[:1001], np.repeat(pts[0, :1], 1001, 0), np.repeat(pts[0, 2:3], 1001, 0)
    )
    assert half_a.max() < e


def test_a_runs_end_tangent_is_its_faces_section_tangent_at_the_corner(cone_sampler):
    """``_end_tangents``: each run's start and end vertex placed on the run's own face from its seed
    path's ends (here seeds 0.05 off in (u, v)), and the section's tangent there (either sense): on
    the cone at z = 5, the circle's tangent at each point; NaN for a vertex off its face."""
    from worker.dst.runs import Run

    sampler, cone, _ = cone_sampler
    ev = sampler.mesh.faces[cone]
    angles = (0.3, 2.0, 4.1)
    points = [_on_circle(a) for a in angles] + [_on_circle(5.0) * np.array([1.05, 1.05, 1.0])]
    vids = [sampler.pool.add(tuple(p), 0) for p in points]
    seeds = [np.array(ev.uv_near(tuple(_on_circle(a)), (0.0, 0.0))) + 0.05 for a in (*angles, 5.0)]
    runs = [
        Run(cone, np.array([0.0, 1.0]), np.array([seeds[i], seeds[j]]), 0.5, vids[i], vids[j], 1, Z, 0)
        for i, j in ((0, 1), (2, 3))
    ]
    got = sampler._end_tangents([runs[0], runs[0], runs[1], runs[1]], np.array([0, 1, 0, 1]))[0]
    for t, a in zip(got, angles, strict=False):
        assert abs(t[0] * _tangent(a)[1] - t[1] * _tangent(a)[0]) < 1e-9  # parallel
        assert np.hypot(*t) == pytest.approx(1.0)
    assert np.isnan(got[3]).all()  # 0.37 mm off the cone


def test_a_run_end_off_its_faces_curve_gets_the_curves_nearest_point_next_to_it(cone_sampler):
    """A run's end vertex that lies off its face's section curve (a corner on an edge the face meets
    only within the file's tolerance: here 0.02 mm outside the circle of radius 7.5, at a 0.01 mm
    chord budget) joins the curve where the curve comes nearest it: that point (the circle's, at the
    vertex's angle) is added next to the vertex (``stats.gap_ends``), and the arc from it on is within
    the budget of the ring (the runs of free loops). A sampler without ``gap_ends`` (the report's
    reference) adds none: its segment checks split the end segment over and over towards that
    point instead."""
    from worker.dst.runs import Run

    sampler, cone, _ = cone_sampler
    plain = RingSampler(
        sampler.mesh, sampler.topo, VertexPool(), segment_length=1.0, chord_error=0.01, gap_ends=False
    )
    ev = sampler.mesh.faces[cone]
    a0, a1, off = 0.3, 0.9, 0.02
    start = _on_circle(a0) * np.array([1.0 + off / R_Z, 1.0 + off / R_Z, 1.0])
    uv = np.array([ev.uv_near(tuple(_on_circle(a)), (0.0, 0.0)) for a in (a0, a1)])
    foot = _on_circle(a0)
    rings = []
    for s in (sampler, plain):
        vids = [s.pool.add(tuple(start), 0), s.pool.add(tuple(_on_circle(a1)), 0)]
        before = s.stats.gap_ends
        run = Run(cone, np.array([0.0, R_Z * (a1 - a0)]), uv, 0.5, *vids, 1, Z, 0, gap_ends=True)
        (ids,) = s._sample_runs([run])
        assert ids[0] == vids[0] and ids[-1] == vids[1]
        rings.append(s.pool.xyz[ids])
        assert s.stats.gap_ends == before + (s is sampler)
    ring, piled = rings
    np.testing.assert_allclose(ring[1], foot, atol=1e-6)
    arc = np.array([_on_circle(a) for a in np.linspace(a0, a1, 4001)])
    d = np.min(
        [
            point_segment_distance(arc, np.broadcast_to(p, arc.shape), np.broadcast_to(q, arc.shape))
            for p, q in zip(ring[1:-1], ring[2:], strict=True)
        ],
        axis=0,
    )
    assert d.max() <= sampler.chord
    assert (np.linalg.norm(ring[:, :2] - foot[:2], axis=1) < 1e-3).sum() == 1
    assert (np.linalg.norm(piled[:, :2] - foot[:2], axis=1) < 1e-3).sum() >= 10


@pytest.fixture(scope="module")
def half_cone_sampler(tmp_path_factory):
    """The conftest cone cut to its half y >= 0: the cone face's trim ends at the plane y = 0."""
    import build123d as bd

    from tests.conftest import build_part, write_step

    half = build_part("cone", radius=RADIUS, height=HEIGHT) & bd.Box(
        30, 30, 30, align=(bd.Align.CENTER, bd.Align.MIN, bd.Align.MIN)
    )
    path = write_step(half, tmp_path_factory.mktemp("hc") / "half_cone.step", nurbs=False)
    mesh = _topomesh_of(path)
    topo = cut_topology(mesh, np.array([Z]), on_plane_tol=C.ON_PLANE_TOL_MM, noise_tol=np.zeros(1))
    return mesh, topo, [f.ad.GetType() for f in mesh.faces].index(GeomAbs_Cone)


@pytest.mark.parametrize("reference", [False, True])
def test_a_corner_whose_faces_curve_runs_on_past_the_trim_joins_it_where_it_enters_the_trim(
    half_cone_sampler, reference
):
    """A corner next to which its face's section curve runs on past the face's trim (the face's
    surface and its boundary edge apart within a file's tolerance): the half cone's circle of radius
    7.5 at z = 5 leaves the face at y = 0. The build's ring (a corner 0.02 mm off the circle, 0.005
    rad past its end, at a 0.025 mm budget: the curve's nearest point lies beyond the trim) and the report's reference (a
    corner on the circle's extension 0.05 rad past its end: its samples there lie beyond the trim and
    are dropped) both join the corner to the circle where it enters the trim, (7.5, 0, 5): a point
    of the B-rep (``stats.trim_entry_points``), not their first sample inside the face."""
    from worker.dst.runs import Run

    mesh, topo, cone = half_cone_sampler
    if reference:
        s = RingSampler(
            mesh, topo, VertexPool(), segment_length=1.0, chord_error=0.001, gap_ends=False, exact_trim=True
        )
        a0, off = -0.05, 0.0
    else:
        s = RingSampler(mesh, topo, VertexPool(), segment_length=1.0, chord_error=0.025)
        a0, off = -0.005, 0.02
    a1 = 0.6
    ev = mesh.faces[cone]
    start = _on_circle(a0) * np.array([1.0 + off / R_Z, 1.0 + off / R_Z, 1.0])
    uv = np.array([ev.uv_near(tuple(_on_circle(a)), (0.0, 0.0)) for a in np.linspace(a0, a1, 5)])
    vids = [s.pool.add(tuple(start), 0), s.pool.add(tuple(_on_circle(a1)), 0)]
    s.corner_vids.add(vids[0])
    run = Run(cone, R_Z * (np.linspace(a0, a1, 5) - a0), uv, 0.5, *vids, 4, Z, 0, gap_ends=not reference)
    (ids,) = s._sample_runs([run])
    ring = s.pool.xyz[ids]
    assert ids[0] == vids[0] and ids[-1] == vids[1]
    np.testing.assert_allclose(ring[1], [R_Z, 0.0, Z], atol=1e-5)
    assert s.stats.trim_entry_points == 1
    assert (ring[1:, 1] >= -1e-6).all()  # nothing beyond the trim but the corner
    # the arc from the entry point on is within the budget of the ring
    arc = np.array([_on_circle(a) for a in np.linspace(0.0, a1, 4001)])
    d = np.min(
        [
            point_segment_distance(arc, np.broadcast_to(p, arc.shape), np.broadcast_to(q, arc.shape))
            for p, q in zip(ring[1:-1], ring[2:], strict=True)
        ],
        axis=0,
    )
    assert d.max() <= s.chord + 1e-9


def test_where_a_runs_curve_leaves_its_face_for_good_before_its_corner_the_ring_bridges_from_there(
    half_cone_sampler,
):
    """A run whose corner lies beyond its face's trim (the half cone's circle of radius 7.5 at
    z = 5, the corner on it 0.05 rad past the trim at y = 0, as where the B-rep's faces disagree and
    the section runs on the corner's other face there): its samples beyond the trim are dropped, and
    the ring bridges from the circle's entry into the trim, (7.5, 0, 5), to the corner. That entry,
    and no other vertex of the run, is marked as such a bridge's end (``bridge_vids``): a pinned
    loop samples the bridge on the corner's other face (``RingSampler._corner_handovers``)."""
    from worker.dst.runs import Run

    mesh, topo, cone = half_cone_sampler
    # every sample checked against the trim (as the report's reference is): the build checks those
    # near moved ends and corners, which trj7's were
    s = RingSampler(mesh, topo, VertexPool(), segment_length=1.0, chord_error=0.001, exact_trim=True)
    a0, a1 = -0.05, 0.6
    ev = mesh.faces[cone]
    uv = np.array([ev.uv_near(tuple(_on_circle(a)), (0.0, 0.0)) for a in np.linspace(a0, a1, 5)])
    vids = [s.pool.add(tuple(_on_circle(a1)), 0), s.pool.add(tuple(_on_circle(a0)), 0)]
    s.corner_vids.add(vids[1])
    run = Run(cone, R_Z * (a1 - np.linspace(a1, a0, 5)), uv[::-1], 0.5, *vids, 4, Z, 0)
    (ids,) = s._sample_runs([run])
    ring = s.pool.xyz[ids]
    assert ids[0] == vids[0] and ids[-1] == vids[1]
    np.testing.assert_allclose(ring[-2], [R_Z, 0.0, Z], atol=1e-5)
    assert (ring[:-1, 1] >= -1e-6).all()  # nothing beyond the trim but the corner
    assert s.bridge_vids & set(ids) == {ids[-2]}


def test_a_runs_samples_at_one_point_are_dropped_against_the_point_kept_before_and_the_runs_end():
    """``RunRefiner._without_repeats``: an inner sample within 1 nm (in x, y and z) of the sample
    kept before it, or of the run's end, is dropped (and counted), whatever the ids; the run's two
    ends stay; a run without repeats is returned as it is."""
    from types import SimpleNamespace

    from worker.dst.refine import RunRefiner
    from worker.dst.sampler_records import SamplingStats

    pool = VertexPool()
    x = [
        0.0,
        1.0,
        1.0 + 4e-10,
        1.0 + 8e-10,
        2.0,
        3.0 - 3e-10,
        3.0,
    ]  # (a chain of repeats: each near the last kept)
    ids = [pool.add((xi, 0.5, 7.0), 0) for xi in x]
    far = [pool.add((xi, 0.5, 7.0), 0) for xi in (10.0, 11.0, 12.0)]
    host = SimpleNamespace(pool=pool, stats=SamplingStats())
    out = RunRefiner._without_repeats(host, [ids, far])
    assert out == [[ids[0], ids[1], ids[4], ids[6]], far]
    assert host.stats.repeat_samples == 3
    # 2 nm apart in x and 0 in y, z: not a repeat (the test is per coordinate)
    apart = [pool.add((xi, 0.5, 7.0), 0) for xi in (20.0, 20.0 + 2e-9, 21.0)]
    assert RunRefiner._without_repeats(host, [apart]) == [apart]
    assert RunRefiner._without_repeats(host, [[]]) == [[]]
    # runs that share their end vertex (a loop's runs, end to start) hold no repeat for that
    chained = [[far[0], far[1]], [far[1], far[2]], [far[2], far[0]]]
    assert RunRefiner._without_repeats(host, chained) is chained
    assert host.stats.repeat_samples == 3


def _loop_passes(crossings: list[tuple[int, list[int]]]) -> tuple[dict[int, tuple[int, int]], set[int]]:
    """``ring_passes`` of a simple loop given as (crossing vertex, inner points) in order, the
    crossings numbered 10, 11, ..."""
    cl = [10 + i for i in range(len(crossings))]
    subdiv = {c: inner for c, (_, inner) in zip(cl, crossings, strict=True)}
    nxt_pos = (np.arange(len(cl)) + 1) % len(cl)
    return ring_passes(cl, [v for v, _ in crossings], subdiv, nxt_pos)


def test_crossings_without_segments_at_a_node_are_one_pass_started_by_the_segment_leaving_it():
    # node 100 holds five crossings in a row (the last two wrapping round the list's end), four
    # with no segment; the fourth leaves it through 200, 201 to crossing 101
    starts, twice = _loop_passes(
        [(100, []), (100, []), (100, []), (100, [200, 201]), (101, [202]), (100, [])]
    )
    assert twice == set()
    assert starts == {100: (13, 0), 200: (13, 1), 201: (13, 2), 101: (14, 0), 202: (14, 1)}


def test_a_vertex_the_loop_comes_back_to_has_no_one_place():
    starts, twice = _loop_passes([(100, [200]), (101, [201]), (100, [202]), (102, [])])
    assert twice == {100}
    assert starts[101] == (11, 0) and starts[102] == (13, 0)
    # a segment with no inner points between two different crossings is a pass of its own
    starts, twice = _loop_passes([(100, []), (101, []), (102, [])])
    assert twice == set() and starts == {100: (10, 0), 101: (11, 0), 102: (12, 0)}


def test_a_loop_all_at_one_vertex_keeps_every_crossing():
    starts, twice = _loop_passes([(100, []), (100, [])])
    assert starts == {100: (10, 0)} and twice == {100}


def test_surface_points_are_the_same_whether_a_batch_or_occt_evaluates_them(tmp_path):
    """``BatchedSolves._d1`` evaluates a face's points with its vectorised evaluator in batches of at
    least ``BATCH_MIN_D1`` (``BATCH_MIN_P`` without derivatives) and one by one with OCCT's D1 below
    that (a call of the evaluator costs as much as several points of OCCT's). Either way the rows
    are OCCT's point and derivatives, on a B-spline hemisphere and its flat bottom, mixed in one
    call; only the large batches reach the evaluator."""
    from OCP.gp import gp_Pnt, gp_Vec

    from tests.conftest import build_part, write_step
    from worker.dst.solves import BATCH_MIN_D1, BATCH_MIN_P

    mesh = _topomesh_of(write_step(build_part("hemisphere", radius=20.0), tmp_path / "h.step"))
    topo = cut_topology(mesh, np.array([5.0]), on_plane_tol=C.ON_PLANE_TOL_MM, noise_tol=np.zeros(1))
    s = RingSampler(mesh, topo, VertexPool(), segment_length=1.0, chord_error=0.01)
    assert s._analytic.all()
    calls = []
    evals = list(s._evals)
    s._evals = [
        (lambda u, v, d, f=f, ev=ev: calls.append((f, len(u))) or ev(u, v, d)) for f, ev in enumerate(evals)
    ]
    rng = np.random.default_rng(5)
    p, du, dv = gp_Pnt(), gp_Vec(), gp_Vec()
    for derivatives, least in ((True, BATCH_MIN_D1), (False, BATCH_MIN_P)):
        for sizes in ((1, least + 3), (least - 1, 1), (least, least + 20)):
            fa = np.repeat(np.arange(2), sizes)
            rng.shuffle(fa)
            ua = np.array([rng.uniform(mesh.faces[f].u0, mesh.faces[f].u1) for f in fa])
            lo, hi = (np.array([getattr(mesh.faces[f], k) for f in fa]) for k in ("v0", "v1"))
            va = rng.uniform(lo + 0.1 * (hi - lo), hi - 0.1 * (hi - lo))
            calls.clear()
            got = s._d1(fa, ua, va, s._ads, p, du, dv, derivatives=derivatives)
            assert sorted(calls) == [(f, n) for f, n in enumerate(sizes) if n >= least]
            for row, f, u, v in zip(got, fa.tolist(), ua.tolist(), va.tolist(), strict=True):
                s._ads[f].D1(u, v, p, du, dv)
                want = np.array(p.Coord() + du.Coord() + dv.Coord())
                cols = 9 if derivatives else 3
                np.testing.assert_allclose(row[:cols], want[:cols], rtol=0, atol=1e-9)


def test_a_vertex_solved_on_a_face_keeps_its_parameters_there_and_is_projected_from_them(
    cone_sampler, monkeypatch
):
    """The vertex pool keeps the face and (u, v) each sampled vertex was solved at, and the trim and
    excursion checks start from them (``Traces._uv_at``) instead of a projection seeded at (0, 0),
    which mostly fell to OCCT's global projection (~0.3 ms a point: 28 s of trj3_s1-al's 70 s
    reference). So does a topology crossing whose root was found on the face; a vertex added without
    them (a topology node, a root on a B-rep edge) has none, and is projected as before."""
    import worker.dst.traces as traces_mod

    base, cone, plane = cone_sampler
    sampler = RingSampler(base.mesh, base.topo, VertexPool(), segment_length=1.0, chord_error=0.01)
    (ring,) = sampler.free_loops([0]).values()
    pool = sampler.pool
    solved = [v for v in ring if pool.uv_on(cone, v) is not None]
    assert len(solved) > 0.8 * len(ring)
    surface = sampler.mesh.faces[cone]
    for v in solved:
        assert pool.uv_on(plane, v) is None  # only on the face it was solved on
        # where the cone's surface passes through the vertex (Newton's |z - plane| tolerance)
        assert (
            np.linalg.norm(np.array(surface.point(*pool.uv_on(cone, v))) - pool.xyz[v]) < 2 * C.LEVEL_TOL_MM
        )

    def global_projection(*args):
        raise AssertionError("a vertex solved on the face was projected from (0, 0)")

    monkeypatch.setattr(traces_mod, "uv_of", global_projection)
    for v in solved:
        u, w = sampler._uv_at(cone, v)
        assert np.linalg.norm(np.array(surface.point(u, w)) - pool.xyz[v]) < 2 * C.LEVEL_TOL_MM


def test_the_vertex_pool_keeps_faces_and_parameters_as_it_grows():
    pool = VertexPool(capacity=2)
    a = pool.add((0.0, 0.0, 1.0), 0)
    ids = pool.extend(
        np.array([[1.0, 0.0], [2.0, 0.0], [3.0, 0.0]]),
        np.full(3, 1.0),
        np.zeros(3, dtype=np.int64),
        np.array([4, 5, 4]),
        np.array([[0.1, 0.2], [np.nan, np.nan], [0.5, 0.6]]),
    )
    b = pool.extend(np.array([[4.0, 0.0]]), np.ones(1), np.zeros(1, dtype=np.int64))[0]
    assert len(pool) == 5 and ids.tolist() == [1, 2, 3]
    assert pool.uv_on(4, 1) == (0.1, 0.2) and pool.uv_on(4, 3) == (0.5, 0.6)
    assert pool.uv_on(5, 1) is None  # another face
    assert pool.uv_on(5, 2) is None  # (u, v) not known
    assert pool.uv_on(4, a) is None and pool.uv_on(4, b) is None  # added without them
    assert pool.uv_on(4, 7) is None  # no such vertex
    assert np.array_equal(pool.xyz[:, 0], [0, 1, 2, 3, 4])


@pytest.mark.parametrize(
    "kind, nurbs", [("hemisphere", True), ("hemisphere", False), ("torus", False), ("tube", False)]
)
def test_many_points_placed_on_their_faces_at_once_land_where_each_alone_does(
    tmp_path, monkeypatch, kind, nurbs
):
    """``BatchedSolves._uv_near`` batches ``FaceEval.uv_near``'s Gauss-Newton over many points of mixed
    faces (a B-spline hemisphere and its flat bottom, an analytic sphere with its pole, a torus
    periodic both ways, a tilted tube's cylinders and planar ends): each point lands where
    ``uv_near`` puts it alone, on the seed's branch of a periodic surface: points on the surface,
    feet of points off it (``foot``), and where Newton gets nowhere (the seed far off, a point past
    the face's box) OCCT's projection as before. A foot past a bounded side of the surface (on its
    extension) gets the surface's nearest point within its bounds, as OCCT's projection gives it,
    without that projection (~0.2 ms a point)."""
    from tests.conftest import build_part, write_step
    from worker.dst.exact import FaceEval

    mesh = _topomesh_of(write_step(build_part(kind), tmp_path / "p.step", nurbs=nurbs))
    topo = cut_topology(mesh, np.array([1.0]), on_plane_tol=C.ON_PLANE_TOL_MM, noise_tol=np.zeros(1))
    s = RingSampler(mesh, topo, VertexPool(), segment_length=1.0, chord_error=0.01)
    rng = np.random.default_rng(11)
    rows = []  # face, xyz, seed, how far off the surface
    for f, fe in enumerate(mesh.faces):
        box = np.array([[fe.u0, fe.u1], [fe.v0, fe.v1]])
        span = box[:, 1] - box[:, 0]
        for _ in range(40):
            uv = box[:, 0] + span * rng.uniform(0.05, 0.95, 2)
            p, du, dv = np.array(fe.point(*uv)), *(np.zeros(3) for _ in range(2))
            eps = 1e-6 * span
            du = (np.array(fe.point(uv[0] + eps[0], uv[1])) - p) / eps[0]
            dv = (np.array(fe.point(uv[0], uv[1] + eps[1])) - p) / eps[1]
            normal = np.cross(du, dv)
            normal /= np.linalg.norm(normal)
            off = float(rng.choice([0.0, 0.0, 1e-5, 0.003, 0.03, 2.0]))
            near = rng.uniform(-0.03, 0.03, 2) * span  # a seed near the point, or far off
            seed = uv + (near if rng.uniform() < 0.8 else rng.uniform(-0.5, 0.5, 2) * span)
            for axis in (0, 1):  # on another period than the point's
                if fe.period(axis) and rng.uniform() < 0.3:
                    seed[axis] += fe.period(axis) * rng.choice([-1, 1])
            rows.append((f, p + off * normal, seed, off))
        # beyond a side of the surface's own bounds (not wrapping, no pole there): the foot is on
        # the surface's extension, and the nearest point within the bounds is on that side
        u_lo, u_hi, v_lo, v_hi = fe.surface_bounds()
        for axis, bound, inward in ((0, u_lo, 1.0), (0, u_hi, -1.0), (1, v_lo, 1.0), (1, v_hi, -1.0)):
            if not fe.bounded[axis] or abs(bound) > 1e99 or not box[axis, 0] <= bound <= box[axis, 1]:
                continue
            if fe.is_pole(axis, bound):
                continue
            for _ in range(10):
                uv = box[:, 0] + span * rng.uniform(0.1, 0.9, 2)
                uv[axis] = bound
                p = np.array(fe.point(*uv))
                eps = np.zeros(2)
                eps[axis] = 1e-6 * span[axis] * inward
                along = (np.array(fe.point(*(uv + eps))) - p) / np.linalg.norm(
                    np.array(fe.point(*(uv + eps))) - p
                )
                seed = uv.copy()
                seed[axis] += 0.01 * span[axis] * inward
                rows.append((f, p - 0.05 * along, seed, -1.0))  # 0.05 mm past the side, along it
    order = rng.permutation(len(rows))
    face = np.array([rows[k][0] for k in order])
    xyz = np.array([rows[k][1] for k in order])
    seed = np.array([rows[k][2] for k in order])
    off = np.array([rows[k][3] for k in order])
    projected = []
    project = FaceEval.project
    past = off < 0  # the points past a side
    assert past.any() == (kind == "hemisphere" and nurbs)  # its B-spline's rim, its bottom's sides
    for foot in (False, True):
        projected.clear()
        monkeypatch.setattr(FaceEval, "project", lambda fe, p, w: projected.append(p) or project(fe, p, w))
        got = s._uv_near(face, xyz, seed, foot=foot)
        if foot:  # the nearest points within the bounds are found without OCCT's projection
            assert not {tuple(p) for p in xyz[past].tolist()} & set(projected)
        monkeypatch.setattr(FaceEval, "project", project)
        for k, f in enumerate(face.tolist()):
            fe = mesh.faces[f]
            want = fe.uv_near(tuple(xyz[k]), tuple(seed[k]), foot=foot)
            gap = np.linalg.norm(np.array(fe.point(*got[k])) - fe.point(*want))
            # a foot settles once a step moves less than SETTLED_STEP_REL of the gap: a step's
            # difference apart at most
            far = np.linalg.norm(xyz[k] - fe.point(*want))
            assert gap <= (2e-3 * far if foot else 0.0) + 1e-8, (f, xyz[k], seed[k], got[k], want)
            for axis in (0, 1):  # on the seed's branch, as uv_near's
                if fe.period(axis):
                    assert abs(got[k, axis] - want[axis]) < 0.25 * fe.period(axis), (got[k], want)


def test_a_resampled_piece_is_lost_only_where_a_dropped_vertex_on_its_face_lies_beyond_the_budget(
    cone_sampler, monkeypatch
):
    """``Traces._lost_pieces``: a re-sampled piece is refused where one of the vertices it drops
    lies on its face's trim and farther than the chord budget from the new ring (the trace stopped
    short of a narrow excursion). Vertices the new ring passes within the budget are not asked
    about the trim at all (a check costs ~40 us: 74,000 of them in trj3_s1-al's reference)."""
    base, cone, _ = cone_sampler
    s = RingSampler(base.mesh, base.topo, VertexPool(), segment_length=1.0, chord_error=0.01)
    # a square ring of side 10 at the plane; the piece from vertex 0 to vertex 2 drops vertex 1
    corners = [(0.0, 0.0), (5.0, 0.0), (10.0, 0.0), (10.0, 10.0), (0.0, 10.0)]
    ring = [s.pool.add(np.array([x, y, Z]), 0) for x, y in corners]
    new_near = [ring[0], s.pool.add(np.array([5.0, 0.004, Z]), 0), *ring[2:]]  # within 0.01 of vertex 1
    new_far = [ring[0], s.pool.add(np.array([5.0, 0.05, Z]), 0), *ring[2:]]  # 0.05 from it
    face_of = {v: cone for v in ring}
    asked = []
    inside = {ring[1]: True}
    monkeypatch.setattr(s, "_in_trim", lambda face, v: asked.append(v) or inside[v])
    piece = (0, 2, [])
    assert s._lost_pieces(ring, [piece], new_near, face_of) == []
    assert asked == []  # within the budget: no trim check
    assert s._lost_pieces(ring, [piece], new_far, face_of) == [piece]
    assert asked == [ring[1]]
    inside[ring[1]] = False  # beyond the budget but off the face's trim: not the curve's
    assert s._lost_pieces(ring, [piece], new_far, face_of) == []
    # a vertex with no face (a corner of the B-rep's edges) is never the curve's to lose
    assert s._lost_pieces(ring, [piece], new_far, {v: cone for v in ring if v != ring[1]}) == []


@pytest.mark.parametrize("kind", ["hemisphere", "torus"])
def test_a_vertex_without_a_face_is_projected_from_the_faces_nearest_topology_node(
    tmp_path, monkeypatch, kind
):
    """A pool vertex added without a face and (u, v) (a root on a B-rep edge, a topology node: off
    the face's surface by the file's tolerance) gets its (u, v) on a face by one OCCT projection
    from the (u, v) of that face's nearest topology node (``Traces._node_uv``), where ``uv_of``
    projected from (0, 0) first: the same point, on the same parameter branch (nearest (0, 0))."""
    from tests.conftest import build_part, write_step
    from worker.dst.exact import FaceEval
    from worker.dst.face_limits import uv_of

    mesh = _topomesh_of(write_step(build_part(kind), tmp_path / "p.step", nurbs=kind == "hemisphere"))
    topo = cut_topology(mesh, np.array([1.0]), on_plane_tol=C.ON_PLANE_TOL_MM, noise_tol=np.zeros(1))
    s = RingSampler(mesh, topo, VertexPool(), segment_length=1.0, chord_error=0.01)
    rng = np.random.default_rng(3)
    calls = []
    project = FaceEval.project
    for f, fe in enumerate(mesh.faces):
        for _ in range(15):
            lo, hi = np.array([fe.u0, fe.v0]), np.array([fe.u1, fe.v1])
            uv = lo + (hi - lo) * rng.uniform(0.05, 0.95, 2)
            p = np.array(fe.point(*uv))
            q = np.array(fe.point(uv[0] + 1e-6, uv[1])) - p
            r = np.array(fe.point(uv[0], uv[1] + 1e-6)) - p
            normal = np.cross(q, r) / np.linalg.norm(np.cross(q, r))
            v = s.pool.add(p + rng.choice([0.0, 1e-4, 0.01]) * normal, 0)  # no face, no (u, v)
            monkeypatch.setattr(FaceEval, "project", lambda fe_, x, w: calls.append(x) or project(fe_, x, w))
            calls.clear()
            got = s._uv_at(f, v)
            assert len(calls) <= 1
            monkeypatch.setattr(FaceEval, "project", project)
            want = uv_of(fe, s.pool.xyz[v])
            assert np.linalg.norm(np.array(fe.point(*got)) - fe.point(*want)) < 1e-9
            for axis in (0, 1):
                if fe.period(axis):
                    assert abs(got[axis] - want[axis]) < 0.25 * fe.period(axis)
