"""The report's metrics pinned on hand-built meshes and polylines with known deviations (no OCCT)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from worker.dst.cuts import (
    _slit_segments,
    cut_mesh,
    loop_self_crossings,
    loops_cut,
    loops_to_segments,
    self_crossings,
)
from worker.dst.deviation import (
    _FIRST_RADIUS_MM,
    _K_NEIGHBOURS,
    SegmentSet,
    arc_midpoints,
    compare,
    loop_successors,
    max_per_plane,
    midpoints,
    segment_neighbours,
    span_curvatures,
    span_max,
)


def circle(r: float, n: int, cx: float = 0.0, cy: float = 0.0, phase: float = 0.0) -> np.ndarray:
    t = phase + 2 * np.pi * np.arange(n) / n
    return np.column_stack([cx + r * np.cos(t), cy + r * np.sin(t)])


def stacked(rings: list[np.ndarray], z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A closed mesh through rings of equal vertex count (CCW) at heights ``z``, capped at both ends."""
    n = len(rings[0])
    v = np.vstack([np.column_stack([r, np.full(n, zk)]) for r, zk in zip(rings, z, strict=True)])
    tris = []
    for k in range(len(z) - 1):
        for i in range(n):
            a, b = k * n + i, k * n + (i + 1) % n
            tris += [(a, b, b + n), (a, b + n, a + n)]
    top = (len(z) - 1) * n
    for i in range(1, n - 1):
        tris += [(0, i + 1, i), (top, top + i, top + i + 1)]
    return v, np.array(tris, dtype=np.int64)


def prism(polygon: np.ndarray, z: tuple[float, ...]) -> tuple[np.ndarray, np.ndarray]:
    """A closed prism over a CCW polygon with vertex rings at the heights ``z`` (ascending)."""
    return stacked([polygon] * len(z), np.asarray(z, dtype=np.float64))


def reference(loops_per_plane: list[list[np.ndarray]]) -> tuple[SegmentSet, np.ndarray]:
    seg, plane = loops_to_segments(loops_per_plane)
    per = np.array(
        [
            sum(float(np.linalg.norm(np.roll(p, -1, 0) - p, axis=1).sum()) for p in ls)
            for ls in loops_per_plane
        ]
    )
    return SegmentSet(seg, plane, curv=span_curvatures(loops_per_plane)), per


def test_square_cut_from_a_circle():
    """A square prism whose corners lie on the circle, with its vertex ring on the plane: the cut's
    vertices are the corners (vertex_dev 0), the deepest point is the side's midpoint
    (chord_dev = R (1 - 1/sqrt 2)), and the perimeter is 4 sqrt(2) R against 2 pi R."""
    r = 10.0
    v, t = prism(circle(r, 4), (-1.0, 0.0, 1.0))
    ref, per = reference([[circle(r, 4000)]])
    cut = cut_mesh(v, t, np.array([0.0]))
    assert cut.loops.tolist() == [1] and cut.open_chains.tolist() == [0]
    assert len(cut.vertices) == 4
    m = compare(cut, ref, np.array([2 * np.pi * r]), 1)
    assert m.vertex_dev[0] == pytest.approx(0.0, abs=1e-9)
    # (distances to the reference arcs are exact to second order in the arcs' slope: 1e-6 relative here)
    assert m.chord_dev[0] == pytest.approx(r * (1 - 1 / math.sqrt(2)), rel=1e-6)
    assert m.perimeter_err[0] == pytest.approx(
        abs(2 * np.pi * r - 4 * math.sqrt(2) * r) / (2 * np.pi * r), rel=1e-12
    )
    # the reference's own perimeter (its polyline) is within 1e-6 relative of the circle's
    assert per[0] == pytest.approx(2 * np.pi * r, rel=1e-6)


def test_mesh_shifted_by_a_known_offset():
    """A fine polygonal prism moved by (dx, 0): every metric follows the offset."""
    r, dx = 5.0, 0.3
    poly = circle(r, 3000) + [dx, 0.0]
    v, t = prism(poly, (0.0, 2.0))
    heights = np.array([0.5, 1.0, 1.5])
    ref, per = reference([[circle(r, 3000)] for _ in heights])
    m = compare(cut_mesh(v, t, heights), ref, np.full(3, 2 * np.pi * r), 3)
    # distance of the shifted circle's points from the circle: max |sqrt((x+dx)^2 + y^2) - r| = dx
    assert np.allclose(m.vertex_dev, dx, atol=1e-6)
    assert np.allclose(m.chord_dev, dx, atol=1e-6)
    assert np.allclose(m.perimeter_err, 0.0, atol=1e-6)  # moved, not resized
    assert m.loops.tolist() == [1, 1, 1]


def test_vertices_on_a_plane_count_as_below():
    """A slicer's convention: a plane through a flat top face cuts nothing, one through the bottom
    face cuts the outline, and a ring on a plane is the cut itself."""
    sq = np.array([[0.0, 0.0], [2.0, 0.0], [2.0, 2.0], [0.0, 2.0]])
    v, t = prism(sq, (0.0, 1.0, 2.0))
    cut = cut_mesh(v, t, np.array([0.0, 1.0, 2.0]))
    assert cut.loops.tolist() == [1, 1, 0]
    lengths = np.bincount(
        cut.seg_plane, weights=np.linalg.norm(cut.seg[:, 1] - cut.seg[:, 0], axis=1), minlength=3
    )
    assert lengths.tolist() == [8.0, 8.0, 0.0]
    assert sorted(map(tuple, cut.vertices[cut.vertex_plane == 1].tolist())) == sorted(map(tuple, sq.tolist()))


def _v_block():
    """A 10 x 4 block whose top is a V: 2 high at x = 0 and 10, its valley line at x = 5, z = 1."""
    import trimesh

    v = np.array(
        [[0, 0, 0], [10, 0, 0], [10, 4, 0], [0, 4, 0]]  # bottom
        + [[0, y, 2] for y in (0, 4)]  # 4, 5
        + [[5, y, 1] for y in (0, 4)]  # 6, 7: the valley
        + [[10, y, 2] for y in (0, 4)],  # 8, 9
        dtype=float,
    )
    # fmt: off
    t = [
        (0, 2, 1), (0, 3, 2),  # bottom
        (0, 4, 5), (0, 5, 3), (1, 2, 9), (1, 9, 8),  # ends x = 0 and x = 10
        (0, 1, 8), (0, 8, 6), (0, 6, 4), (3, 9, 2), (3, 7, 9), (3, 5, 7),  # sides y = 0 and y = 4
        (4, 6, 7), (4, 7, 5), (6, 8, 9), (6, 9, 7),  # the two slopes of the V
    ]
    # fmt: on
    mesh = trimesh.Trimesh(v, t, process=False)
    trimesh.repair.fix_normals(mesh)
    assert mesh.is_watertight and mesh.volume == pytest.approx(60.0)
    return mesh.vertices, mesh.faces


def test_a_valley_edge_on_a_plane_leaves_no_slit_in_the_cut():
    """At z = 1 the block's section is the whole 10 x 4 rectangle; the valley line lying on the plane
    is cut by the triangles on both its sides (corners on the plane count as below): a zero-width
    slit that must not join or open the loop, nor count as contour."""
    v, t = _v_block()
    cut = cut_mesh(v, t, np.array([1.0]))
    assert cut.loops.tolist() == [1] and cut.open_chains.tolist() == [0]
    length = np.linalg.norm(cut.seg[:, 1] - cut.seg[:, 0], axis=1).sum()
    assert length == pytest.approx(28.0, abs=1e-12)


def test_empty_cut_and_missing_loop_are_reported():
    """Plane 0: the mesh has one of the two exact loops; plane 1: the mesh ends below it; plane 2:
    neither has a section."""
    r = 2.0
    v, t = prism(circle(r, 512), (0.0, 1.0))
    loops = [[circle(r, 2000), circle(r, 2000, cx=10.0)], [circle(r, 2000)], []]
    ref, per = reference(loops)
    exact_per = np.array([4 * np.pi * r, 2 * np.pi * r, 0.0])
    cut = cut_mesh(v, t, np.array([0.5, 1.5, 2.5]))
    m = compare(cut, ref, exact_per, 3)
    assert m.loops.tolist() == [1, 0, 0]
    # the missing circle's far side is 10 + r from the mesh's circle: distance 10 + r - r = 10 ... its
    # farthest point (12, 0) is 12 - 2 = 10 from the cut
    assert m.chord_dev[0] == pytest.approx(10.0, abs=1e-3)
    assert m.vertex_dev[0] < 1e-3  # what is there is right
    assert m.perimeter_err[0] == pytest.approx(0.5, abs=1e-3)
    assert math.isnan(m.vertex_dev[1]) and math.isnan(m.chord_dev[1]) and m.perimeter_err[1] == 1.0
    assert m.vertex_dev[2] == 0.0 and m.chord_dev[2] == 0.0 and m.perimeter_err[2] == 0.0
    # a cut with no segments at all (a plane range above a user's mesh, measured in one piece:
    # trj7_b1-ec-214 against a mesh placed elsewhere once failed there)
    m = compare(cut_mesh(v, t, np.array([1.5, 2.5, 3.5])), ref, exact_per, 3)
    assert np.isnan(m.vertex_dev[:2]).all() and np.isnan(m.chord_dev[:2]).all()
    assert m.perimeter_err.tolist() == [1.0, 1.0, 0.0] and m.loops.tolist() == [0, 0, 0]
    assert m.vertex_dev[2] == 0.0 and m.chord_dev[2] == 0.0


def brute_force_distances(seg, plane, pts, pts_plane) -> np.ndarray:
    """Each point's distance to the nearest segment of its plane, over every segment."""
    ab = seg[:, 1] - seg[:, 0]  # (s, 2)
    ap = pts[:, None, :] - seg[None, :, 0]  # (p, s, 2)
    tt = np.clip(np.einsum("psi,si->ps", ap, ab) / np.einsum("si,si->s", ab, ab), 0, 1)
    dist = np.linalg.norm(ap - tt[..., None] * ab, axis=2)
    return np.where(plane[None, :] == pts_plane[:, None], dist, np.inf).min(axis=1)


def test_segment_distances_are_exact_against_brute_force():
    """Every point's distance, near the segments (found by the first, bounded search) and far from
    them (beyond its bound: searched again)."""
    rng = np.random.default_rng(7)
    a = rng.uniform(-5, 5, (400, 2))
    seg = np.stack([a, a + rng.normal(0, 1.5, (400, 2))], axis=1)
    plane = rng.integers(0, 3, 400)
    pts = rng.uniform(-8, 8, (2000, 2))
    pts_plane = rng.integers(0, 3, 2000)
    d = SegmentSet(seg, plane, spacing=0.7).distance(pts, pts_plane)
    brute = brute_force_distances(seg, plane, pts, pts_plane)
    np.testing.assert_allclose(d, brute, rtol=0, atol=1e-12)
    assert (brute < 0.2).sum() > 200 and (brute > 1.5).sum() > 200  # both searches were needed


def test_fine_polylines_are_measured_exactly_too():
    """Closed wavy loops of segments much shorter than the spacing (every dense point shared by two
    segments: the search asks for twice as many neighbours) against brute force."""
    rng = np.random.default_rng(11)
    loops = []
    for j in range(3):
        t = np.linspace(0, 2 * np.pi, 900, endpoint=False)
        r = 6 + 0.8 * np.sin(7 * t + j) + 0.05 * rng.normal(size=len(t))
        loops.append([np.column_stack([r * np.cos(t), r * np.sin(t)])])
    seg, plane = loops_to_segments(loops)
    s = SegmentSet(seg, plane, spacing=0.2)
    assert s.k > _K_NEIGHBOURS  # the shared-ends case
    pts = rng.uniform(-8, 8, (3000, 2))
    pts_plane = rng.integers(0, 3, 3000)
    d = s.distance(pts, pts_plane)
    brute = brute_force_distances(seg, plane, pts, pts_plane)
    np.testing.assert_allclose(d, brute, rtol=0, atol=1e-12)
    assert (brute < 0.05).sum() > 20 and (brute > 1.0).sum() > 1000


def test_a_nearer_segment_whose_dense_points_lie_beyond_the_first_search_is_found():
    """The first search only looks within a bound: a point 0.9 mm from a long segment whose dense
    points are all farther than that bound, and 0.95 mm from a short one with a point inside it,
    must be searched again (not take the short one's 0.95)."""
    spacing = 1.0
    seg = np.array([[[0.0, 0.0], [10.0, 0.0]], [[0.45, 1.85], [0.55, 1.85]]])
    q = np.array([[0.5, 0.9]])
    s = SegmentSet(seg, np.zeros(2, dtype=np.int64), spacing=spacing)
    bound = _FIRST_RADIUS_MM + 0.5 * spacing
    near = np.linalg.norm(s.tree.data[:, :2] - q, axis=1) <= bound
    assert near.any() and (s.owner[near] == 1).all()  # only the short one's points are within it
    assert s.distance(q, np.zeros(1, dtype=np.int64))[0] == pytest.approx(0.9, abs=1e-12)


def test_arc_correction_measures_the_curve_not_its_polyline():
    """A circle sampled at chord error ~1e-3: distances from exact circle points are ~0 with the arc
    correction (to the polyline they would reach the chord error)."""
    r = 3.0
    p = circle(r, 140)
    sag = r * (1 - math.cos(math.pi / 140))
    seg, plane = loops_to_segments([[p]])
    q = circle(r, 5000, phase=0.0123)
    plain = SegmentSet(seg, plane).distance(q, np.zeros(len(q), dtype=np.int64))
    arced = SegmentSet(seg, plane, curv=span_curvatures([[p]])).distance(q, np.zeros(len(q), dtype=np.int64))
    assert plain.max() == pytest.approx(sag, rel=1e-3)
    assert arced.max() < 1e-3 * sag


def test_corner_is_not_rounded_by_the_arc_correction():
    """A square's corners turn by 90 degrees: its sides stay straight."""
    sq = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    dense = np.vstack([np.linspace(sq[i], sq[(i + 1) % 4], 50, endpoint=False) for i in range(4)])
    assert np.abs(span_curvatures([[dense]], chord=1e-3)).max() == 0.0


def test_a_span_the_curvature_model_would_bow_beyond_the_chord_stays_straight():
    """A stadium: straight sides 2 mm long between half circles of radius 100 mm, sampled at a
    0.001 mm chord (spans of 0.894 mm on the arcs, one span per side). The circles through a side's
    ends and their arc neighbours curve it (0.0031 /mm, within the vertex test's 4-chord margin), which
    would bow the side 0.0015 mm: more than the sampling allows, so the side stays straight; the arcs
    keep their correction."""
    r, half, chord = 100.0, 1.0, 1e-3
    step = math.sqrt(8.0 * r * chord)
    k = int(math.ceil(math.pi * r / step))
    t = np.linspace(-math.pi / 2, math.pi / 2, k + 1)
    right = np.column_stack([half + r * np.cos(t), r + r * np.sin(t)])  # from (1, 0) to (1, 200)
    left = np.column_stack([-half - r * np.cos(t), r - r * np.sin(t)])  # from (-1, 200) to (-1, 0)
    p = np.vstack([right, left])
    curv = span_curvatures([[p]], chord=chord)
    seg, plane = loops_to_segments([[p]])
    on_side = np.array([[0.0, 0.0], [0.0, 2.0 * r]])
    mid = 0.5 * (t[1:] + t[:-1])
    on_arc = np.column_stack([half + r * np.cos(mid), r + r * np.sin(mid)])
    zeros = np.zeros(len(on_side), dtype=np.int64)
    assert np.abs(SegmentSet(seg, plane, curv=curv).distance(on_side, zeros)).max() < 1e-9
    arced = SegmentSet(seg, plane, curv=curv).distance(on_arc, np.zeros(len(on_arc), dtype=np.int64))
    assert arced[1:-1].max() < 1e-3 * chord  # the end spans run into the sides' curvature jump
    assert arced.max() < chord
    # what the ends' circles alone would give the sides (the check's reason to be)
    unchecked = span_curvatures([[p]], chord=4.0 * chord)
    assert SegmentSet(seg, plane, curv=unchecked).distance(on_side, zeros).max() > chord


def test_nearest_names_a_segment_at_that_distance():
    rng = np.random.default_rng(3)
    a = rng.uniform(-5, 5, (300, 2))
    seg = np.stack([a, a + rng.normal(0, 1.0, (300, 2))], axis=1)
    plane = rng.integers(0, 3, 300)
    pts = rng.uniform(-8, 8, (1500, 2))
    pts_plane = rng.integers(0, 4, 1500)  # plane 3 has no segments
    s = SegmentSet(seg, plane, spacing=0.5)
    d, idx = s.nearest(pts, pts_plane)
    none = pts_plane == 3
    assert np.isinf(d[none]).all() and (idx[none] == -1).all()
    assert (plane[idx[~none]] == pts_plane[~none]).all()
    # the named segment is at the distance found (its own candidate distance, exactly)
    own, own_idx = s.distance_to(pts[~none], idx[~none, None])
    np.testing.assert_array_equal(own, d[~none])
    np.testing.assert_array_equal(own_idx, idx[~none])


def test_segment_neighbours_along_chains():
    # a closed triangle 0-1-2 (segments in any direction) and an open chain 3-4-5
    seg_node = np.array([[0, 1], [2, 1], [2, 0], [3, 4], [4, 5]])
    nb = segment_neighbours(seg_node)
    assert nb.tolist() == [[2, 1], [2, 0], [1, 0], [3, 4], [3, 4]]


def every_point_searched(cut, ref: SegmentSet, n_planes: int) -> tuple[np.ndarray, np.ndarray]:
    """vertex_dev and chord_dev from a k-d tree search for every point (no bounds, no pruning)."""
    d_vert = ref.distance(cut.vertices, cut.vertex_plane)
    vertex_dev = max_per_plane(d_vert, cut.vertex_plane, n_planes)
    d_mid = ref.distance(midpoints(cut.seg), cut.seg_plane)
    cut_to_ref = np.maximum(vertex_dev, max_per_plane(d_mid, cut.seg_plane, n_planes))
    cut_set = SegmentSet(cut.seg, cut.seg_plane, spacing=ref.spacing)
    d0 = cut_set.distance(ref.seg[:, 0], ref.seg_plane)
    dm = cut_set.distance(arc_midpoints(ref.seg, ref.curv), ref.seg_plane)
    spans = span_max(d0, dm, d0[ref.nxt], ref.chord)
    return vertex_dev, np.maximum(cut_to_ref, max_per_plane(spans, ref.seg_plane, n_planes))


def jittered_rings(rng, n_ring: int, z: np.ndarray, r0: float, amp: float, waves: int, noise: float):
    """Wavy rings of ``n_ring`` vertices at heights ``z``, jittered in angle and radius."""
    rings = []
    for zk in z:
        t = np.linspace(0, 2 * np.pi, n_ring, endpoint=False) + rng.uniform(0, 0.01)
        r = r0 + amp * np.sin(waves * t + zk) + rng.normal(0, noise, n_ring)
        rings.append(np.column_stack([r * np.cos(t), r * np.sin(t)]))
    return rings


def dense_reference(loops: list[list[np.ndarray]]) -> SegmentSet:
    seg, plane = loops_to_segments(loops)
    return SegmentSet(
        seg, plane, curv=span_curvatures(loops, chord=1e-3), nxt=loop_successors(loops), chord=1e-3
    )


def compared_and_searched(cut, ref: SegmentSet, n_planes: int, monkeypatch, *, cut_only: bool = False):
    """``compare``'s metrics and how many points it searched (in the cut's own set only, with
    ``cut_only``)."""
    searched = []
    nearest = SegmentSet.nearest

    def counting(self, pts, pl, **kw):
        if not cut_only or self is not ref:
            searched.append(len(pts))
        return nearest(self, pts, pl, **kw)

    monkeypatch.setattr(SegmentSet, "nearest", counting)
    m = compare(cut, ref, np.ones(n_planes), n_planes)
    monkeypatch.setattr(SegmentSet, "nearest", nearest)
    return m, sum(searched)


@pytest.mark.parametrize("n_ring", [24, 150, 900])  # coarse to finer than the reference's spans
def test_measuring_only_the_points_that_can_matter_gives_the_same_maxima(n_ring, monkeypatch):
    """compare searches the k-d trees for the vertices, and for a midpoint only where its bound (the
    distance to its neighbours' nearest segments) could be its plane's maximum. On jittered meshes
    against wavy reference loops, plus a small reference loop beside the middle of one cut segment
    (nearest to that midpoint, far from its ends: a bound that misleads), every metric equals the
    one from a search for every point, while far fewer points are searched."""
    rng = np.random.default_rng(n_ring)
    heights = np.array([0.5, 1.5, 2.5, 3.5])
    v, tri = stacked(jittered_rings(rng, n_ring, np.arange(5.0), 8.0, 0.4, 5, 0.02), np.arange(5.0))
    cut = cut_mesh(v, tri, heights)
    loops = []
    for j, h in enumerate(heights):
        t = np.linspace(0, 2 * np.pi, 2000, endpoint=False)
        r = 8 + 0.4 * np.sin(5 * t + h)
        plane_loops = [np.column_stack([r * np.cos(t), r * np.sin(t)])]
        if j == 1:  # a small loop 0.05 mm inside the middle of the plane's first cut segment
            k = np.flatnonzero(cut.seg_plane == j)[0]
            a, b = cut.seg[k]
            mid = 0.5 * (a + b)
            inward = -mid / np.linalg.norm(mid)
            plane_loops.append(circle(0.02, 40, *(mid + 0.07 * inward)))
        loops.append(plane_loops)
    ref = dense_reference(loops)
    m, pruned = compared_and_searched(cut, ref, len(heights), monkeypatch)
    vertex_dev, chord_dev = every_point_searched(cut, ref, len(heights))
    np.testing.assert_array_equal(m.vertex_dev, vertex_dev)
    np.testing.assert_array_equal(m.chord_dev, chord_dev)
    every = len(cut.vertices) + len(cut.seg) + 2 * len(ref.seg)  # what every_point_searched searches
    assert pruned < 0.7 * every


@pytest.mark.parametrize("n_ring", [6, 40, 300])  # cut segments covering ~330 (> _MAX_COVER) to ~7 spans
def test_reference_points_take_their_distances_from_the_cut_segments_round_them(n_ring, monkeypatch):
    """compare measures each reference vertex first against the cut segments whose ends lie nearest
    to the spans round it, and searches only where that could change a plane's maximum. Cases
    where those segments are not the nearest: two reference loops 0.06 mm apart (a thin wall) with
    the cut between them, its ends nearest to either loop; a reference loop no cut segment comes
    near (plane 1); a cut loop far from any reference loop (plane 2); a loop's seam inside a cut
    segment. Every metric equals the one from a search for every point, and on the finer cuts the
    cut's own k-d tree is searched for few of the reference's points."""
    rng = np.random.default_rng(n_ring)
    heights = np.array([0.5, 1.5, 2.5])
    v, tri = stacked(jittered_rings(rng, n_ring, np.arange(4.0), 8.03, 0.3, 3, 0.01), np.arange(4.0))
    far_v, far_tri = prism(circle(1.0, 12, 30.0, 0.0), (2.2, 2.8))  # cut at plane 2 only
    cut = cut_mesh(np.vstack([v, far_v]), np.vstack([tri, far_tri + len(v)]), heights)
    loops = []
    for j, h in enumerate(heights):
        t = np.linspace(0, 2 * np.pi, 2000, endpoint=False) + 0.3 * j  # seams at different places
        r = 8 + 0.3 * np.sin(3 * t + h + 0.5)
        walls = (1.0, 1.0075) if j == 0 else (1.0,)
        plane_loops = [np.column_stack([r * np.cos(t), r * np.sin(t)]) * s for s in walls]
        if j == 1:
            plane_loops.append(circle(0.5, 300, -20.0, 0.0))
        loops.append(plane_loops)
    ref = dense_reference(loops)
    m, pruned = compared_and_searched(cut, ref, len(heights), monkeypatch, cut_only=True)
    vertex_dev, chord_dev = every_point_searched(cut, ref, len(heights))
    np.testing.assert_array_equal(m.vertex_dev, vertex_dev)
    np.testing.assert_array_equal(m.chord_dev, chord_dev)
    assert chord_dev[1] > 10 and chord_dev[2] > 20  # the unmatched loops count
    if n_ring >= 40:  # (the wall's loop nearest to none of the cut's vertices is searched)
        assert pruned < 0.4 * len(ref.seg)


def test_self_crossings_find_the_pockets_a_loop_winds_round():
    """A loop through points of a circle crosses itself nowhere in order; with two neighbours
    swapped it makes a bow tie (a pocket of no area); going round three times (each step 3/25 of a
    turn) it crosses itself everywhere, round pockets of the circle's own size."""
    r, n = 5.0, 25
    z = np.array([0.0, 1.0, 2.0])
    in_order = circle(r, n)
    swapped = in_order.copy()
    swapped[[7, 8]] = swapped[[8, 7]]
    thrice = circle(r, n)[(3 * np.arange(n)) % n]
    found = {}
    for name, ring in (("in order", in_order), ("swapped", swapped), ("thrice", thrice)):
        v, t = stacked([in_order, ring, in_order], z)
        found[name] = self_crossings(cut_mesh(v, t, np.array([1.0])))
    assert found["in order"] == []
    assert len(found["swapped"]) == 1
    (plane, area, length) = found["swapped"][0]
    assert plane == 0 and area == pytest.approx(0.0, abs=1e-12)
    assert length == pytest.approx(np.linalg.norm(in_order[8] - in_order[7]))
    assert len(found["thrice"]) >= n and all(p == 0 for p, _, _ in found["thrice"])
    assert max(a for _, a, _ in found["thrice"]) > 1.0  # against a 0.025 mm budget's 6e-4 mm^2


def test_self_crossings_find_a_long_segment_crossed_far_from_its_middle():
    """Closed loops (``loops_cut``): a 10 mm edge crossed twice near its end by a notch of short
    segments, with a circle beside it that crosses nothing. The crossing pairs are searched among
    pieces of twice the median segment (not within the longest segment's reach of every midpoint):
    the long edge's crossings 4 mm beyond that reach from its middle are still found, with the
    pockets between them (the notch's 0.4 mm^2 below the edge, and 0.9 mm^2 the other way round)."""
    notch = np.array([(0, 0), (10, 0), (10, 1), (9.2, 1), (9.2, -0.5), (8.8, -0.5), (8.8, 1), (0, 1)], float)
    loops = [[circle(1.0, 50)], [notch, circle(1.0, 50) + 20.0]]
    found = self_crossings(loops_cut(loops))
    assert sorted((p, round(a, 9), round(s, 9)) for p, a, s in found) == [(1, 0.4, 1.8), (1, 0.9, 3.7)]
    assert self_crossings(loops_cut([[], [circle(1.0, 50)]])) == []
    assert loop_self_crossings([[], [circle(1.0, 50)]]) == []
    np.testing.assert_allclose(loop_self_crossings(loops), found, rtol=1e-12, atol=1e-12)


def test_loop_self_crossings_are_the_walked_pockets_of_a_tangled_loop():
    """Prefix sums along ordered loops give every pocket the walk along a cut gives: a loop of 40
    points of a circle in a random order (216 crossings), beside a circle that crosses nothing,
    and a loop going round three times."""
    rng = np.random.default_rng(1)
    loops = [
        [circle(3.0, 40)[rng.permutation(40)], circle(1.0, 30, cx=10.0)],
        [circle(5.0, 25)[(3 * np.arange(25)) % 25]],
    ]
    walked = self_crossings(loops_cut(loops))
    assert len(walked) > 200 and {p for p, _, _ in walked} == {0, 1}
    np.testing.assert_allclose(loop_self_crossings(loops), walked, rtol=1e-9, atol=1e-9)


def test_slits_are_dropped_in_whole_pairs():
    # three cuts of one edge between nodes 4 and 7 (either direction) and two ordinary segments: the
    # first two of the three make a pair, the third stays
    node = np.array([[4, 7], [1, 4], [7, 4], [7, 2], [4, 7]])
    assert _slit_segments(node).tolist() == [True, False, True, False, False]
    assert not _slit_segments(np.array([[0, 1], [1, 2], [2, 0]])).any()
