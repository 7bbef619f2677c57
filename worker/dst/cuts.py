"""Cut triangle meshes with the slicing planes, and find where a cut (or any closed polyline) crosses
itself.

The cut is the slicer's: a vertex exactly on a plane counts as below it (the cut is the limit from
just above the plane), so a DST mesh, whose ring vertices lie exactly on the planes, is cut exactly
along its rings, and a flat face lying on a plane gives the outline above it. Pure numpy / scipy.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from worker.dst.chords import distances_to_segments
from worker.dst.meshops import unique_ints

_PLANE_SEPARATION_MM = 1e7  # farther than any two points of a part in one plane
_PAIR_PIECES = 2.0  # see segment_pairs_near
# A closed polyline turning back by more than this (cosine of the turn) at a vertex may have a needle
# there (``loop_needles``): a spike out and back turns by nearly 180 degrees at its tip
NEEDLE_TURN_COS = -0.9
# ... whose legs are followed at most this many vertices each way from the tip
NEEDLE_WINDOW = 256


@dataclass
class MeshCut:
    """The sections of one mesh at every plane.

    seg : (n, 2, 2) float64   segments (x, y), mm
    seg_plane : (n,) int64    plane index of each segment
    loops : (P,) int64        closed loops per plane
    open_chains : (P,) int64  chains that do not close (a mesh with holes or non-manifold edges)
    vertices : (m, 2) float64 the distinct cut vertices; vertex_plane (m,) their planes
    seg_node : (n, 2) int64   the vertices each segment joins
    """

    seg: np.ndarray
    seg_plane: np.ndarray
    loops: np.ndarray
    open_chains: np.ndarray
    vertices: np.ndarray
    vertex_plane: np.ndarray
    seg_node: np.ndarray


def cut_mesh(
    vertices: np.ndarray,
    triangles: np.ndarray,
    heights: np.ndarray,
    crossed: tuple[np.ndarray, np.ndarray] | None = None,
) -> MeshCut:
    """Sections of a triangle mesh at ``heights`` (ascending), vertices on a plane counting as below.
    ``crossed``: the triangles' ``crossed_planes`` at these heights, where the caller has them."""
    v = np.asarray(vertices, dtype=np.float64)
    t = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    h = np.asarray(heights, dtype=np.float64)
    n_planes = len(h)
    nv = len(v)
    if len(t) == 0 or n_planes == 0:
        return _empty_cut(n_planes)
    vz = v[:, 2]
    tz = vz[t]
    first, stop = crossed_planes(tz, h) if crossed is None else crossed
    count = np.maximum(stop - first, 0)
    tri = np.repeat(np.arange(len(t)), count)
    if len(tri) == 0:
        return _empty_cut(n_planes)
    start = np.repeat(np.cumsum(count) - count, count)
    plane = np.repeat(first, count) + (np.arange(len(tri)) - start)
    hz = h[plane]
    corners = t[tri]  # (k, 3)
    above = tz[tri] > hz[:, None]
    # The plane leaves the lowest corner below (or on it) and the highest above: exactly two of the
    # corner edges k -> k + 1 (edge 0: corners 0 -> 1, 1: 1 -> 2, 2: 2 -> 0) have ends on different
    # sides, in order (0, 1), (0, 2) or (1, 2).
    cross0 = above[:, 0] != above[:, 1]
    edge_k = np.column_stack([np.where(cross0, 0, 1), np.where(cross0 & (above[:, 1] != above[:, 2]), 1, 2)])
    a = np.take_along_axis(corners, edge_k, axis=1)
    b = np.take_along_axis(corners, (edge_k + 1) % 3, axis=1)
    a_above = np.take_along_axis(above, edge_k, axis=1)
    lo = np.where(a_above, b, a)  # the end below or on the plane
    hi = np.where(a_above, a, b)
    z_lo = vz[lo]
    frac = (hz[:, None] - z_lo) / (vz[hi] - z_lo)
    on = z_lo == hz[:, None]
    frac[on] = 0.0
    vx, vy = v[:, 0], v[:, 1]
    x_lo, y_lo = vx[lo], vy[lo]
    pts = np.stack([x_lo + frac * (vx[hi] - x_lo), y_lo + frac * (vy[hi] - y_lo)], axis=-1)
    key = np.where(on, lo, nv + np.minimum(lo, hi) * nv + np.maximum(lo, hi))
    key = key * n_planes + plane[:, None]
    # the cut's nodes (numbered in key order), then the segments kept: not from a node to itself,
    # not a slit
    uniq, inv = np.unique(key.ravel(), return_inverse=True)
    inv = inv.reshape(-1, 2)
    keep = (inv[:, 0] != inv[:, 1]) & ~_slit_segments(inv)
    pts, inv, plane = pts[keep], inv[keep], plane[keep]
    used = np.zeros(len(uniq), dtype=bool)
    used[inv.ravel()] = True
    if not used.all():  # nodes only dropped segments had
        inv = (np.cumsum(used) - 1)[inv]
        uniq = uniq[used]
    # loops: connected components of the segment graph, per plane (keys include the plane)
    n_nodes = len(uniq)
    graph = coo_matrix((np.ones(len(inv)), (inv[:, 0], inv[:, 1])), shape=(n_nodes, n_nodes))
    n_comp, label = connected_components(graph, directed=False)
    label = label.astype(np.int64)
    node_plane = (uniq % n_planes).astype(np.int64)
    degree = np.bincount(inv.ravel(), minlength=n_nodes)
    comp_open = np.zeros(n_comp, dtype=bool)
    comp_open[label[degree != 2]] = True
    comp_plane = np.zeros(n_comp, dtype=np.int64)
    comp_plane[label] = node_plane
    loops = np.bincount(comp_plane[~comp_open], minlength=n_planes)
    open_chains = np.bincount(comp_plane[comp_open], minlength=n_planes)
    node_xy = np.empty((n_nodes, 2))
    node_xy[inv.ravel()] = pts.reshape(-1, 2)
    return MeshCut(
        seg=pts,
        seg_plane=plane,
        loops=loops.astype(np.int64),
        open_chains=open_chains.astype(np.int64),
        vertices=node_xy,
        vertex_plane=node_plane,
        seg_node=inv.astype(np.int64),
    )


def _slit_segments(node: np.ndarray) -> np.ndarray:
    """Mask of cut segments (their two nodes, ``node`` (n, 2), numbered below 2**31) that come in
    pairs between the same two nodes. A valley edge lying exactly on a plane (both faces rising from
    it) is cut by the triangles on both sides, a corner on the plane counting as below: a slit of
    zero width through the contour, which slicers drop when they clean their polygons. Left in, it
    would join loops and count as contour. (The cut's segment directions follow the triangles'
    corner order, not the surface's orientation, so the pair is found without them.)"""
    both = np.minimum(node[:, 0], node[:, 1]) << 32 | np.maximum(node[:, 0], node[:, 1])
    slit = np.zeros(len(node), dtype=bool)
    ordered = np.sort(both)
    if not len(both) or not (ordered[1:] == ordered[:-1]).any():  # no two alike: mostly
        return slit
    order = np.argsort(both, kind="stable")  # equal segments keep their order
    both = both[order]
    start = np.concatenate([[True], both[1:] != both[:-1]])
    first = np.flatnonzero(start)  # where each run of equal segments begins
    run = np.cumsum(start) - 1
    run_len = np.diff(np.append(first, len(node)))
    slit[order] = np.arange(len(node)) - first[run] < 2 * (run_len[run] // 2)  # whole pairs of each run
    return slit


def self_crossings(cut: MeshCut, points: bool = False) -> list[tuple]:
    """Where a loop of ``cut`` crosses itself: (plane, area mm^2, length mm) of the pocket between
    each two crossing segments of one loop, the shorter way round it (inf where neither way closes:
    an open chain, or a vertex where the loop's direction turns over, a folded strip of triangles),
    and with ``points`` the crossing's (x, y) too. Loops that cross other loops are not looked at
    (an assembly's solids may overlap). A loop whose points came out of order by micrometres makes a
    bow tie with no pocket to speak of; one that goes round a hole three times, a pocket of the
    hole's area."""
    i, k = _crossing_segments(cut)
    if not len(i):
        return []
    node = cut.seg_node
    n = len(cut.vertices)
    graph = coo_matrix((np.ones(len(node)), (node[:, 0], node[:, 1])), shape=(n, n))
    _, loop_of = connected_components(graph, directed=False)
    same = loop_of[node[i, 0]] == loop_of[node[k, 0]]
    nxt: dict[int, int] = {}
    for u, w in node.tolist():
        nxt[u] = w if u not in nxt else -1  # -1: the loop's direction turns over here
    out = []
    for s, t in zip(i[same].tolist(), k[same].tolist(), strict=True):
        best = (np.inf, np.inf)
        for first, second in ((s, t), (t, s)):  # from the end of one to the start of the other
            path: list[int] = []
            v, end = int(node[first, 1]), int(node[second, 0])
            while v != end and v >= 0 and len(path) <= n:
                path.append(v)
                v = nxt.get(v, -1)
            if v != end:
                continue
            pts = cut.vertices[[*path, v]]
            length = float(np.linalg.norm(np.diff(pts, axis=0), axis=1).sum())
            area = 0.5 * abs(
                float(np.dot(pts[:, 0], np.roll(pts[:, 1], -1)) - np.dot(pts[:, 1], np.roll(pts[:, 0], -1)))
            )
            best = min(best, (length, area))
        found = (int(cut.seg_plane[s]), best[1], best[0])
        out.append((*found, *_crossing_point(cut.seg[s], cut.seg[t])) if points else found)
    return out


def _crossing_point(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """Where segments ``a`` and ``b`` ((2, 2) each) that cross meet; where they run (nearly) parallel,
    the mean of their ends."""
    da, db = a[1] - a[0], b[1] - b[0]
    denom = float(da[0] * db[1] - da[1] * db[0])
    if abs(denom) > 1e-12 * float(np.linalg.norm(da) * np.linalg.norm(db)):
        w = b[0] - a[0]
        u = float(np.clip((w[0] * db[1] - w[1] * db[0]) / denom, 0.0, 1.0))
        x, y = a[0] + u * da
    else:
        x, y = 0.25 * (a[0] + a[1] + b[0] + b[1])
    return float(x), float(y)


def loop_self_crossings(
    loops: list[list[np.ndarray]], nearest: int | None = None, tol: float = 0.0
) -> list[tuple[int, float, float]]:
    """``self_crossings`` of closed polylines per plane (first point not repeated), each loop's
    points in order: its pockets from prefix sums along the loop (the shoelace terms and the
    segment lengths), at once for every crossing (a walk per crossing took minutes on a reference
    tangled into thousands of crossings at one plane). ``nearest``: a bounded pair search (see
    ``segment_pairs_near``); ``tol``: only crossings whose segments' ends lie farther than that from
    the other segment's line (see ``_crossing_segments``)."""
    cut = loops_cut(loops)
    i, k = _crossing_segments(cut, nearest, tol)
    if not len(i):
        return []
    sizes = np.array([len(p) for ls in loops for p in ls], dtype=np.int64)
    start = np.cumsum(sizes) - sizes  # each loop's first vertex (= first segment)
    loop_of = np.repeat(np.arange(len(sizes)), sizes)
    same = loop_of[i] == loop_of[k]
    i, k = i[same], k[same]
    if not len(i):
        return []
    # per loop, centred (small shoelace terms), prefix sums of x_i y_i+1 - y_i x_i+1 and of lengths
    p = cut.vertices - np.repeat(np.array([q.mean(axis=0) for ls in loops for q in ls]), sizes, axis=0)
    q = p[cut.seg_node[:, 1]]
    term = p[:, 0] * q[:, 1] - p[:, 1] * q[:, 0]
    length = np.linalg.norm(q - p, axis=1)
    offset = start + np.arange(len(sizes))  # each loop's prefix sums: sizes + 1 values
    first = np.zeros(len(p) + len(sizes), dtype=bool)
    first[offset] = True
    at = np.flatnonzero(~first)

    def prefix(values: np.ndarray) -> np.ndarray:
        out = np.zeros(len(first))
        out[at] = values
        out = np.cumsum(out)
        return out - np.repeat(out[offset], sizes + 1)

    term_sum, length_sum = prefix(term), prefix(length)
    lp, m = loop_of[i], sizes[loop_of[i]]

    def along(u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(length, area) of the path from local vertex u forward to v, closed by the chord v-u."""
        o = offset[lp]
        whole = np.where(v >= u, 0.0, 1.0)

        def span(total: np.ndarray) -> np.ndarray:
            return total[o + v] - total[o + u] + whole * total[o + m]

        pu, pv = p[start[lp] + u], p[start[lp] + v]
        close = pv[:, 0] * pu[:, 1] - pv[:, 1] * pu[:, 0]
        return span(length_sum), 0.5 * np.abs(span(term_sum) + close)

    li, lk = i - start[lp], k - start[lp]  # local segment (= start vertex) indices
    one = along((li + 1) % m, lk)  # from the end of segment i to the start of segment k
    other = along((lk + 1) % m, li)
    shorter = (one[0] < other[0]) | ((one[0] == other[0]) & (one[1] <= other[1]))
    plane = cut.seg_plane[i]
    return [
        (int(j), float(area), float(size))
        for j, area, size in zip(
            plane, np.where(shorter, one[1], other[1]), np.where(shorter, one[0], other[0]), strict=True
        )
    ]


def _crossing_segments(
    cut: MeshCut, nearest: int | None = None, tol: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    """Pairs (i, k) of segments of one plane of ``cut`` with no end in common that cross (``nearest``:
    see ``segment_pairs_near``). With ``tol``, each segment's ends must lie on either side of the
    other's line and farther than ``tol`` from it: two segments running along each other within it
    (a section doubled along a line where two faces touch: trj7_b1-ec-214 at z = 56.9, x = 155.6143,
    1e-9 mm apart) or one ending on the other (a branch of such a section) do not count."""
    a, b = cut.seg[:, 0], cut.seg[:, 1]
    if len(a) < 4:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    i, k = segment_pairs_near(a, b, cut.seg_plane, nearest)
    node = cut.seg_node
    apart = ~(node[i][:, :, None] == node[k][:, None, :]).any(axis=(1, 2))  # no end in common
    i, k = i[apart], k[apart]

    def apart_by_line(p: np.ndarray, q: np.ndarray, r: np.ndarray, t: np.ndarray) -> np.ndarray:
        """r and t on either side of line p -> q (and farther than ``tol`` from it)."""
        u, v = _turn(p, q, r), _turn(p, q, t)
        out = np.sign(u) * np.sign(v) < 0
        if tol > 0.0:
            reach = tol * np.linalg.norm(q - p, axis=1)  # |turn| is the distance times |q - p|
            out &= (np.abs(u) > reach) & (np.abs(v) > reach)
        return out

    cross = apart_by_line(a[i], b[i], a[k], b[k]) & apart_by_line(a[k], b[k], a[i], b[i])
    return i[cross], k[cross]


def side(p: np.ndarray, q: np.ndarray, r: np.ndarray) -> np.ndarray:
    """Per row, the side of line p -> q that point r lies on: +1 left, -1 right, 0 on it."""
    return np.sign(_turn(p, q, r))


def _turn(p: np.ndarray, q: np.ndarray, r: np.ndarray) -> np.ndarray:
    """Per row, the cross product (q - p) x (r - p): > 0 where r lies left of line p -> q."""
    return (q[:, 0] - p[:, 0]) * (r[:, 1] - p[:, 1]) - (q[:, 1] - p[:, 1]) * (r[:, 0] - p[:, 0])


def segment_pairs_near(
    a: np.ndarray, b: np.ndarray, plane: np.ndarray, nearest: int | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Pairs (i, k), i < k, of segments a-b of one plane that may cross: each segment split into pieces
    no longer than ``_PAIR_PIECES`` times the median segment (two crossing pieces have midpoints within
    that length), so that a few long segments (a dense reference's 2 mm spans along straight edges)
    do not widen the search for all the short ones. ``nearest``: only each piece's that many nearest
    pieces (a bounded search: in a tangle of thousands of points within that length some pairs are
    then left out)."""
    length = np.linalg.norm(b - a, axis=1)
    reach = max(_PAIR_PIECES * float(np.median(length)), 1e-9)
    m = np.maximum(1, np.ceil(length / reach).astype(np.int64))
    owner = np.repeat(np.arange(len(a)), m)
    t = (np.arange(len(owner)) - np.repeat(np.cumsum(m) - m, m) + 0.5) / m[owner]
    mid = a[owner] + t[:, None] * (b - a)[owner]
    lift = plane[owner] * _PLANE_SEPARATION_MM  # each plane's segments far from every other's
    tree = cKDTree(np.column_stack([mid, lift]))
    if nearest is None:
        pairs = tree.query_pairs(reach * (1.0 + 1e-9), output_type="ndarray")
        i, k = owner[pairs[:, 0]], owner[pairs[:, 1]]
    else:
        _, idx = tree.query(
            tree.data, k=min(nearest + 1, len(owner)), distance_upper_bound=reach * (1.0 + 1e-9)
        )
        idx = idx.reshape(len(owner), -1)
        found = idx < len(owner)
        i, k = owner[np.nonzero(found)[0]], owner[idx[found]]
    key = unique_ints((np.minimum(i, k) * len(a) + np.maximum(i, k))[i != k])
    return key // len(a), key % len(a)


def crossed_planes(tri_z: np.ndarray, heights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per triangle (corner heights (m, 3)), the planes ``first .. stop - 1`` that cut it, a corner
    on a plane counting as below it: the first plane at or above the lowest corner, and the first
    at or above the highest."""
    return (
        np.searchsorted(heights, tri_z.min(axis=1), side="left"),
        np.searchsorted(heights, tri_z.max(axis=1), side="left"),
    )


def offset_cut(cut: MeshCut, first: int, n_planes: int) -> MeshCut:
    """A cut made at planes ``first``, ``first + 1``, ... renumbered as part of ``n_planes`` planes."""
    loops = np.zeros(n_planes, dtype=np.int64)
    chains = np.zeros(n_planes, dtype=np.int64)
    loops[first : first + len(cut.loops)] = cut.loops
    chains[first : first + len(cut.loops)] = cut.open_chains
    return MeshCut(
        seg=cut.seg,
        seg_plane=cut.seg_plane + first,
        loops=loops,
        open_chains=chains,
        vertices=cut.vertices,
        vertex_plane=cut.vertex_plane + first,
        seg_node=cut.seg_node,
    )


def select_planes(cut: MeshCut, mask: np.ndarray) -> MeshCut:
    """The part of ``cut`` at the planes where ``mask`` is true (the others empty)."""
    keep_seg, keep_vert = mask[cut.seg_plane], mask[cut.vertex_plane]
    new_id = np.cumsum(keep_vert) - 1  # a kept segment's ends lie on its plane: kept too
    return MeshCut(
        seg=cut.seg[keep_seg],
        seg_plane=cut.seg_plane[keep_seg],
        loops=np.where(mask, cut.loops, 0),
        open_chains=np.where(mask, cut.open_chains, 0),
        vertices=cut.vertices[keep_vert],
        vertex_plane=cut.vertex_plane[keep_vert],
        seg_node=new_id[cut.seg_node[keep_seg]],
    )


def _empty_cut(n_planes: int) -> MeshCut:
    z = np.zeros(n_planes, dtype=np.int64)
    return MeshCut(
        np.zeros((0, 2, 2)),
        np.zeros(0, dtype=np.int64),
        z,
        z.copy(),
        np.zeros((0, 2)),
        np.zeros(0, np.int64),
        np.zeros((0, 2), np.int64),
    )


def loops_to_segments(loops: list[list[np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    """Closed polylines per plane -> (segments (n, 2, 2), plane of each segment)."""
    segs, planes = [], []
    for j, ls in enumerate(loops):
        for p in ls:
            segs.append(np.stack([p, np.roll(p, -1, axis=0)], axis=1))
            planes.append(np.full(len(p), j, dtype=np.int64))
    if not segs:
        return np.zeros((0, 2, 2)), np.zeros(0, dtype=np.int64)
    return np.concatenate(segs), np.concatenate(planes)


def loops_cut(loops: list[list[np.ndarray]]) -> MeshCut:
    """Closed polylines per plane (first point not repeated) as a ``MeshCut``: each loop's points its
    own vertices, joined in order."""
    pts = [p for ls in loops for p in ls]
    sizes = np.array([len(p) for p in pts], dtype=np.int64)
    vertices = np.concatenate(pts) if pts else np.zeros((0, 2))
    start = np.repeat(np.cumsum(sizes) - sizes, sizes)
    k = np.arange(len(vertices)) - start
    seg_node = np.column_stack([start + k, start + (k + 1) % np.repeat(sizes, sizes)]).reshape(-1, 2)
    seg_plane = np.repeat(np.array([j for j, ls in enumerate(loops) for _ in ls], dtype=np.int64), sizes)
    return MeshCut(
        seg=vertices[seg_node].reshape(-1, 2, 2),
        seg_plane=seg_plane,
        loops=np.array([len(ls) for ls in loops], dtype=np.int64),
        open_chains=np.zeros(len(loops), dtype=np.int64),
        vertices=vertices,
        vertex_plane=seg_plane.copy(),
        seg_node=seg_node,
    )


def loop_needles(loop: np.ndarray, width: float, min_length: float) -> list[tuple[float, np.ndarray]]:
    """The needles of the closed polyline ``loop`` (k, 2) longer than ``min_length``: where it turns
    back at a vertex (by more than ``NEEDLE_TURN_COS``) and its two legs from there run within
    ``width`` of each other, so that the loop encloses nothing there: a spike out and back along
    itself, or the thin end of a cusp. A needle's length is how far from its tip (by arc length along
    one leg, the longer such stretch of the two) the leg's points all stay within ``width`` of the
    other leg, followed up to ``NEEDLE_WINDOW`` vertices each way (a leg may fold back on itself: the
    bug27453 reference's spike returns past its root and out again by 7 um). Returns (length, tip
    (2,)) of each, one per turning vertex."""
    n = len(loop)
    if n < 4:
        return []
    d_in = loop - np.roll(loop, 1, axis=0)  # (p[i] - p[i - 1])
    d_out = np.roll(loop, -1, axis=0) - loop
    size = np.linalg.norm(d_in, axis=1) * np.linalg.norm(d_out, axis=1)
    cos = (d_in * d_out).sum(axis=1) / np.where(size > 0, size, 1.0)
    out = []
    m = min(NEEDLE_WINDOW, (n - 1) // 2)
    steps = np.arange(m + 1)
    for i in np.flatnonzero((cos < NEEDLE_TURN_COS) & (size > 0)).tolist():
        a, b = loop[(i - steps) % n], loop[(i + steps) % n]  # the two legs, from the tip
        length = max(_close_extent(a, b, width), _close_extent(b, a, width))
        if length > min_length:
            out.append((length, loop[i].copy()))
    return out


def _close_extent(leg: np.ndarray, other: np.ndarray, width: float) -> float:
    """Arc length along ``leg`` (from ``leg[0]``) of its points before the first farther than
    ``width`` from the polyline ``other``."""
    d = distances_to_segments(leg[1:], np.stack([other[:-1], other[1:]], axis=1))
    far = np.flatnonzero(d > width)
    last = len(leg) - 1 if not len(far) else int(far[0])  # leg[last] is the last point within width
    return float(np.linalg.norm(np.diff(leg[: last + 1], axis=0), axis=1).sum())
