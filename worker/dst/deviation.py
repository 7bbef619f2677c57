"""Measure a mesh's cuts (``cuts``) against the exact sections: distances to the nearest segment or
curve of a set, exact, and the per-plane metrics of the deviation report.

Pure numpy / scipy: no OCCT here, so the metrics can be pinned with hand-built meshes and polylines.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from worker.dst.cuts import _PLANE_SEPARATION_MM, MeshCut

# Points along every target segment at most this far apart (mm) index the nearest-segment search.
# Any spacing gives exact distances (the search widens until it is sure); this one keeps it fast.
DENSE_SPACING_MM = 0.2
_K_NEIGHBOURS = 4
_QUERY_CHUNK = 8192  # queries per nearest-segment search step
_FIRST_RADIUS_MM = 0.5  # see SegmentSet._nearest
# A set whose k-d tree is not built yet answers a search by trying every segment of each point's
# plane while that takes at most this many point-segment distances per segment of the set (or the
# minimum): the tree costs about as much to build as ~5 such distances per segment.
_BRUTE_PAIRS_PER_SEGMENT = 4
_BRUTE_PAIRS_MIN = 20_000
# see _covering_pairs
_MAX_COVER = 256
CORNER_RAD = 1.0  # a reference polyline turning more than this (rad) at a vertex has a corner there


def span_curvatures(
    loops: list[list[np.ndarray]],
    *,
    chord: float | None = None,
    corners: list[list[np.ndarray]] | None = None,
    corner_rad: float = CORNER_RAD,
) -> np.ndarray:
    """Signed curvature (1/mm, > 0 turning left) of the curve at the start and the end of every span,
    (n, 2) in ``loops_to_segments`` order, for closed polylines whose vertices lie on smooth curves
    with every span's midpoint within ``chord`` of the span.

    The curvature at a vertex is that of the circle through it and its two neighbours. A vertex is a
    corner of the section (no curvature to carry across it) where the polyline turns by more than
    ``corner_rad``, or where that circle would put an adjacent span's midpoint farther than 4 ``chord``
    from the span (impossible on the sampled curve). A span with one corner end takes the other end's
    curvature at both; a span between two corners is straight. So is a span whose modelled curve
    would put its midpoint farther than ``chord`` from it: the sampled curve's is not, so its
    curvature is not what its ends' circles say (it turns the other way between them: a torus's
    section at an odd angle had 1.8 mm spans bowed 0.003 mm off the curve, 0.001 mm from the chord).
    """
    pts = [p for ls in loops for p in ls]
    if not pts:
        return np.zeros((0, 2))
    p = np.concatenate(pts)  # every loop at once: each vertex's successor and predecessor in its loop
    nxt = loop_successors(loops)
    prv = np.empty_like(nxt)
    prv[nxt] = np.arange(len(nxt))
    a = p - p[prv]  # into each vertex
    b = p[nxt] - p  # out of each vertex
    cross = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
    dot = np.einsum("ij,ij->i", a, b)
    la, lb = np.linalg.norm(a, axis=1), np.linalg.norm(b, axis=1)
    lc = np.linalg.norm(a + b, axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        kappa = np.where(la * lb * lc > 0, 2.0 * cross / (la * lb * lc), 0.0)
    smooth = np.abs(np.arctan2(cross, dot)) < corner_rad
    if chord is not None:
        smooth &= np.abs(kappa) * np.maximum(la, lb) ** 2 / 8.0 <= 4.0 * chord
    if corners is not None:
        smooth &= ~np.concatenate([c for cs in corners for c in cs]).astype(bool)
    k0, k1 = kappa, kappa[nxt]
    s0, s1 = smooth, smooth[nxt]
    start = np.where(s0, k0, np.where(s1, k1, 0.0))
    end = np.where(s1, k1, np.where(s0, k0, 0.0))
    if chord is not None:
        bowed = np.abs(_offset(np.full(len(p), 0.5), start, end, lb * lb)) > chord
        start, end = np.where(bowed, 0.0, start), np.where(bowed, 0.0, end)
    return np.column_stack([start, end])


def _offset(t: np.ndarray, k0: np.ndarray, k1: np.ndarray, length2: np.ndarray | float) -> np.ndarray:
    """Offset along the span's left normal, at chord parameter t, of the curve whose curvature goes
    linearly from k0 to k1 along the span (y'' = -kappa L^2, y(0) = y(1) = 0)."""
    return length2 * t * (k0 * (t * (0.5 - t / 6.0) - 1.0 / 3.0) + k1 * (t * t - 1.0) / 6.0)


def _slope(t: np.ndarray, k0: np.ndarray, k1: np.ndarray, length2: np.ndarray | float) -> np.ndarray:
    return length2 * (k0 * (t - t * t / 2.0 - 1.0 / 3.0) + k1 * (t * t / 2.0 - 1.0 / 6.0))


def curve_lengths(seg: np.ndarray, curv: np.ndarray) -> np.ndarray:
    """Length of each span's modelled curve (chord length plus the arc's excess, Gauss quadrature)."""
    length = np.linalg.norm(seg[:, 1] - seg[:, 0], axis=1)
    if not len(seg):
        return length
    x, w = np.polynomial.legendre.leggauss(6)
    t = 0.5 * (x + 1.0)
    dy = _slope(t[None, :], curv[:, :1], curv[:, 1:], (length**2)[:, None])  # dy/dt; dy/dx = dy/dt / L
    with np.errstate(divide="ignore", invalid="ignore"):
        slope = np.where(length[:, None] > 0, dy / length[:, None], 0.0)
    return length * (0.5 * w[None, :] * np.sqrt(1.0 + slope**2)).sum(axis=1)


def loop_successors(loops: list[list[np.ndarray]]) -> np.ndarray:
    """Index of the next span of the same loop, for every span in ``loops_to_segments`` order."""
    out, off = [], 0
    for ls in loops:
        for p in ls:
            out.append(off + (np.arange(len(p)) + 1) % len(p))
            off += len(p)
    return np.concatenate(out) if out else np.zeros(0, dtype=np.int64)


def span_max(f0: np.ndarray, fm: np.ndarray, f1: np.ndarray, cap: float) -> np.ndarray:
    """Max over each span of the parabola through its values at t = 0, 1/2, 1 (a smooth distance
    function peaks between samples), at most ``cap`` above the largest sample."""
    sampled = np.maximum(np.maximum(f0, f1), fm)
    with np.errstate(divide="ignore", invalid="ignore"):  # inf where a plane has no cut: stays inf
        a = 2.0 * (f0 + f1 - 2.0 * fm)
        b = f1 - f0 - a
        t = np.where(a < 0, -b / (2.0 * a), -1.0)
        peak = np.where((t > 0) & (t < 1), f0 - b * b / (4.0 * a), sampled)
        out = np.minimum(np.maximum(sampled, peak), sampled + cap)
    return np.where(np.isfinite(sampled), out, sampled)


def segment_lengths_per_plane(seg: np.ndarray, seg_plane: np.ndarray, n_planes: int) -> np.ndarray:
    lengths = np.linalg.norm(seg[:, 1] - seg[:, 0], axis=1)
    return np.bincount(seg_plane, weights=lengths, minlength=n_planes)


def densify(
    seg: np.ndarray, seg_plane: np.ndarray, spacing: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points along every segment at most ``spacing`` apart (ends included).

    Returns (points (k, 2), plane of each point, segment of each point).
    """
    if len(seg) == 0:
        return np.zeros((0, 2)), np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    length = np.linalg.norm(seg[:, 1] - seg[:, 0], axis=1)
    n = np.maximum(1, np.ceil(length / spacing).astype(np.int64))  # sub-spans per segment
    owner = np.repeat(np.arange(len(seg)), n + 1)
    start = np.repeat(np.cumsum(n + 1) - (n + 1), n + 1)
    frac = (np.arange(len(owner)) - start) / n[owner]
    pts = seg[owner, 0] + frac[:, None] * (seg[owner, 1] - seg[owner, 0])
    return pts, seg_plane[owner], owner


def midpoints(seg: np.ndarray) -> np.ndarray:
    return 0.5 * (seg[:, 0] + seg[:, 1])


def arc_midpoints(seg: np.ndarray, curv: np.ndarray) -> np.ndarray:
    """The modelled curve's point over each span's midpoint."""
    ab = seg[:, 1] - seg[:, 0]
    length = np.linalg.norm(ab, axis=1)
    normal = np.column_stack([-ab[:, 1], ab[:, 0]]) / np.where(length > 0, length, 1.0)[:, None]
    off = _offset(np.full(len(seg), 0.5), curv[:, 0], curv[:, 1], length**2)
    return midpoints(seg) + off[:, None] * normal


def _group_nearest(
    dist: np.ndarray, group: np.ndarray, first: np.ndarray, candidate: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Per group of consecutive rows (``group``: each row's group, ``first``: each group's first
    row), the least distance and the candidate at it (of equal ones, the first)."""
    best = np.minimum.reduceat(dist, first)
    at = np.flatnonzero(dist == best[group])[::-1]
    which = np.empty(len(first), dtype=np.int64)
    which[group[at]] = candidate[at]
    return best, which


def _loop_runs(nxt: np.ndarray) -> tuple[np.ndarray | None, np.ndarray | None]:
    """For successors ``nxt`` of closed loops each of consecutive spans (each span's successor the
    next one, the last's the loop's first), each span's loop's first span and its size; (None,
    None) for any other order."""
    n = len(nxt)
    last = np.flatnonzero(nxt != np.arange(1, n + 1))
    starts = np.concatenate([[0], last[:-1] + 1]) if len(last) else np.zeros(0, dtype=np.int64)
    if n == 0 or last[-1] != n - 1 or not np.array_equal(nxt[last], starts):
        return None, None
    size = last - starts + 1
    return np.repeat(starts, size), np.repeat(size, size)


class SegmentSet:
    """Distance from points to the nearest of a set of segments (or shallow curves) in the same plane.

    With ``curv`` (see :func:`span_curvatures`) each segment stands for the curve through its ends
    whose curvature goes linearly between the given end values: dense exact points of a smooth curve
    then give distances to the curve itself, not to its polyline.
    """

    def __init__(
        self,
        seg: np.ndarray,
        seg_plane: np.ndarray,
        *,
        spacing: float = DENSE_SPACING_MM,
        curv: np.ndarray | None = None,
        nxt: np.ndarray | None = None,
        chord: float = 0.0,
        neighbours: np.ndarray | None = None,
        lazy: bool = False,
    ):
        self.seg, self.seg_plane, self.spacing = seg, seg_plane, spacing
        self.nxt, self.chord = nxt, chord  # closed loops: next span; the curves' sampling tolerance
        # with loops of consecutive spans (``loop_successors``): each span's loop's first span and size
        self.loop_first, self.loop_size = _loop_runs(nxt) if nxt is not None else (None, None)
        # (n, 2): the segments joined to each one's two ends (itself where none): the nearest segment
        # of a point is most often the nearest of a point close by or one of its neighbours
        if neighbours is None and nxt is not None:
            prev = np.empty_like(nxt)
            prev[nxt] = np.arange(len(nxt))
            neighbours = np.column_stack([prev, nxt])
        self.neighbours = (
            np.repeat(np.arange(len(seg))[:, None], 2, axis=1) if neighbours is None else neighbours
        )
        self.curv = np.zeros((len(seg), 2)) if curv is None else np.asarray(curv, dtype=np.float64)
        self.curved = bool(np.any(self.curv != 0.0))
        ab = seg[:, 1] - seg[:, 0]
        self.len2 = (ab**2).sum(axis=1)
        # one row per segment, gathered at once per candidate: a, b - a, 1 / |b - a|^2 and, for
        # curves, the end curvatures times |b - a|
        inv = np.where(self.len2 > 0, 1.0 / np.where(self.len2 > 0, self.len2, 1.0), 0.0)
        cols = [seg[:, 0], ab, inv[:, None]]
        if self.curved:
            cols.append(self.curv * np.sqrt(self.len2)[:, None])
        self._rows = np.column_stack(cols) if len(seg) else np.zeros((0, 7 if self.curved else 5))
        # largest offset of a curve from its span: |phi0|, |phi1| <= 1/8
        self.max_offset = float((self.len2 * np.abs(self.curv).sum(axis=1)).max() / 8.0) if len(seg) else 0.0
        self._count = np.bincount(seg_plane) if len(seg) else np.zeros(0, dtype=np.int64)  # per plane
        self._present = self._count > 0
        self._tree: cKDTree | None = None
        self._by_plane: np.ndarray | None = None  # the segments in plane order (``_brute``)
        self._arc_mid: np.ndarray | None = None  # see ``arc_mid``
        if not lazy and len(seg):  # both made now (a reference's: before measuring helpers fork)
            self._index()
            self._arc_mid = arc_midpoints(seg, self.curv)

    @property
    def tree(self) -> cKDTree:
        return self._index()

    @property
    def arc_mid(self) -> np.ndarray:
        """The modelled curve's point over each segment's midpoint (``arc_midpoints``), made once (a
        set that is not ``lazy``: when it is made): a reference's serves every mesh measured against it."""
        if self._arc_mid is None:
            self._arc_mid = arc_midpoints(self.seg, self.curv)
        return self._arc_mid

    def _index(self) -> cKDTree:
        """The k-d tree of points along the segments (built on first use)."""
        if self._tree is None:
            pts, plane, self.owner = densify(self.seg, self.seg_plane, self.spacing)
            # Segments mostly shorter than the spacing give two points each, both shared with the
            # neighbours: the k nearest points then cover half as many places, and a search for k of
            # them would need widening for a third of the points (a fine mesh's cut, ~2.4 points per
            # segment): ask for twice k. (At ~3 points per segment, the hemisphere's reference, k is
            # ~20% faster than twice k; at 2.4, ~15% slower.)
            self.k = _K_NEIGHBOURS if len(pts) >= 2.5 * len(self.seg) else 2 * _K_NEIGHBOURS
            # unbalanced, non-compact: builds ~3x faster and queries no slower on these point sets
            self._tree = cKDTree(self._lift(pts, plane), balanced_tree=False, compact_nodes=False)
        return self._tree

    def _lift(self, pts: np.ndarray, plane: np.ndarray) -> np.ndarray:
        # each plane's points lifted far from every other plane's: one tree serves all planes
        return np.column_stack([pts, plane * _PLANE_SEPARATION_MM])

    def distance(self, pts: np.ndarray, plane: np.ndarray, *, workers: int = -1) -> np.ndarray:
        """Distance of each point to the nearest segment of its own plane (inf if the plane has none).
        ``workers``: threads of the k-d tree search (-1: all CPUs)."""
        return self.nearest(pts, plane, workers=workers)[0]

    def nearest(
        self, pts: np.ndarray, plane: np.ndarray, *, workers: int = -1
    ) -> tuple[np.ndarray, np.ndarray]:
        """Distance of each point to the nearest segment of its own plane and that segment's index
        (inf and -1 if the plane has none)."""
        out = np.full(len(pts), np.inf)
        idx = np.full(len(pts), -1, dtype=np.int64)
        if not len(self.seg) or not len(pts):
            return out, idx
        plane = np.asarray(plane)
        has = np.zeros(len(plane), dtype=bool)
        inside = (plane >= 0) & (plane < len(self._present))
        has[inside] = self._present[plane[inside]]
        if not has.any():
            return out, idx
        if self._tree is None:
            pairs = int(self._count[plane[has]].sum())
            if pairs <= max(_BRUTE_PAIRS_PER_SEGMENT * len(self.seg), _BRUTE_PAIRS_MIN):
                out[has], idx[has] = self._brute(pts[has], plane[has])
                return out, idx
        self._index()
        p2, q = pts[has], self._lift(pts[has], plane[has])
        # in chunks whose (chunk, k, columns) temporaries stay in the CPU's cache: ~10% faster
        found = [
            self._nearest(p2[i : i + _QUERY_CHUNK], q[i : i + _QUERY_CHUNK], workers)
            for i in range(0, len(q), _QUERY_CHUNK)
        ]
        out[has] = np.concatenate([d for d, _ in found])
        idx[has] = np.concatenate([i for _, i in found])
        return out, idx

    def _nearest(self, p2: np.ndarray, q: np.ndarray, workers: int) -> tuple[np.ndarray, np.ndarray]:
        d = np.full(len(q), np.inf)
        idx = np.full(len(q), -1, dtype=np.int64)
        todo = np.arange(len(q))
        k = self.k
        reach = 0.5 * self.spacing + self.max_offset
        # the first search bounded: it visits fewer tree nodes (~8% less measuring time), and its
        # answer is sure for every point within _FIRST_RADIUS_MM of the segments
        bound = _FIRST_RADIUS_MM + reach
        tree = self._index()  # built already: ``nearest`` indexed the segments first
        n = tree.n
        while len(todo):
            k = min(k, n)
            dk, ik = tree.query(q[todo], k=k, workers=workers, distance_upper_bound=bound)
            dk, ik = dk.reshape(len(todo), k), ik.reshape(len(todo), k)
            found = ik < n  # fewer than k points within the bound: the others come back as index n
            owner = self.owner[np.where(found, ik, 0)]
            dist = np.where(found, _point_curve(p2[todo][:, None, :], self._rows[owner]), np.inf)
            best = dist.argmin(axis=1)
            rows = np.arange(len(todo))
            d[todo] = dist[rows, best]
            idx[todo] = np.where(found[rows, best], owner[rows, best], -1)
            if k == n and bound == np.inf:
                break
            # The nearest segment has a dense point within d + spacing/2 (+ a curve's offset) of
            # the query: when the points found do not cover that ball (fewer than k found: when it
            # leaves the bound), look again, with more and unbounded.
            ball = d[todo] + reach
            last = dk[:, -1]
            todo = todo[(last <= ball) | (np.isinf(last) & (ball >= bound))]
            k *= 4
            bound = np.inf
        return d, idx

    def _brute(self, pts: np.ndarray, plane: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Nearest segment of each point (whose plane has segments) by trying every segment of its
        plane: for a few points, cheaper than building the k-d tree."""
        if self._by_plane is None:
            self._by_plane = np.argsort(self.seg_plane, kind="stable")
        start = np.cumsum(self._count) - self._count  # each plane's first position in that order
        c = self._count[plane]
        first = np.cumsum(c) - c
        q = np.repeat(np.arange(len(pts)), c)
        s = self._by_plane[np.repeat(start[plane] - first, c) + np.arange(len(q))]
        return _group_nearest(_point_curve(pts[q], self._rows[s]), q, first, s)

    def distance_to(self, pts: np.ndarray, candidates: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Distance of each point to the nearest of its candidate segments ((n, c) indices, -1 for
        none) and that segment: an upper bound of its distance to the set (inf without candidates)."""
        d = np.full(len(pts), np.inf)
        idx = np.full(len(pts), -1, dtype=np.int64)
        if not len(self.seg):
            return d, idx
        for i in range(0, len(pts), _QUERY_CHUNK):
            c = candidates[i : i + _QUERY_CHUNK]
            ok = c >= 0
            dist = np.where(
                ok, _point_curve(pts[i : i + _QUERY_CHUNK, None, :], self._rows[np.where(ok, c, 0)]), np.inf
            )
            best = dist.argmin(axis=1)
            rows = np.arange(len(c))
            d[i : i + len(c)] = dist[rows, best]
            idx[i : i + len(c)] = np.where(ok[rows, best], c[rows, best], -1)
        return d, idx

    def around(self, seg_idx: np.ndarray) -> np.ndarray:
        """Candidate segments for points near points whose nearest segments are ``seg_idx`` ((n, m),
        -1 for none): those segments and their neighbours, (n, 3 m)."""
        ok = seg_idx >= 0
        nb = self.neighbours[np.where(ok, seg_idx, 0)]  # (n, m, 2)
        nb = np.where(ok[..., None], nb, -1)
        return np.concatenate([seg_idx, nb.reshape(len(seg_idx), 2 * seg_idx.shape[1])], axis=1)


def _point_curve(p: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """Distance from points ``p`` (..., 2) to segments or curves given as ``SegmentSet`` rows
    (..., 5 or 7: a, b - a, 1 / |b - a|^2 [, curvatures at a and b times |b - a|]), broadcast.

    The nearest point of a straight segment is its clamped projection. On a curve it is found from
    the projection on the chord by one Gauss-Newton step in the chord parameter (clamped to the
    span): the curves are shallow (slopes of the order of 4 chord / length), so the step leaves an
    error of the order of the distance times the slope to the fourth power.
    """
    apx, apy = p[..., 0] - rows[..., 0], p[..., 1] - rows[..., 1]
    abx, aby, inv = rows[..., 2], rows[..., 3], rows[..., 4]
    t = np.clip((apx * abx + apy * aby) * inv, 0.0, 1.0)
    if rows.shape[-1] == 5:
        rx, ry = t * abx - apx, t * aby - apy
        return np.sqrt(rx * rx + ry * ry)
    k0, k1 = rows[..., 5], rows[..., 6]
    # C(t) = a + t ab + off(t) (-aby, abx): _offset and _slope per unit of |ab| (length2 = 1 with
    # the curvatures already scaled by |ab|)
    off, slope = _offset(t, k0, k1, 1.0), _slope(t, k0, k1, 1.0)
    rx, ry = t * abx - off * aby - apx, t * aby + off * abx - apy  # C(t) - p
    dx, dy = abx - slope * aby, aby + slope * abx  # C'(t)
    t = np.clip(t - (rx * dx + ry * dy) / np.maximum(dx * dx + dy * dy, 1e-300), 0.0, 1.0)
    off = _offset(t, k0, k1, 1.0)
    rx, ry = t * abx - off * aby - apx, t * aby + off * abx - apy
    return np.sqrt(rx * rx + ry * ry)


@dataclass
class LayerMetrics:
    """Per-plane metrics of one mesh (NaN where undefined: see ``compare``)."""

    vertex_dev: np.ndarray
    chord_dev: np.ndarray
    perimeter_err: np.ndarray
    loops: np.ndarray
    open_chains: np.ndarray
    vertices: np.ndarray
    perimeter: np.ndarray


def max_per_plane(values: np.ndarray, plane: np.ndarray, n_planes: int) -> np.ndarray:
    out = np.full(n_planes, -np.inf)
    np.maximum.at(out, plane, values)
    return out


def segment_neighbours(seg_node: np.ndarray) -> np.ndarray:
    """(n, 2): for each segment, the other segment at each of its ends where exactly two meet there
    (along a chain), else the segment itself."""
    n = len(seg_node)
    flat = seg_node.ravel()
    own = np.repeat(np.arange(n), 2)
    order = np.argsort(flat, kind="stable")
    f = flat[order]
    start = np.flatnonzero(np.concatenate([[True], f[1:] != f[:-1]]))
    pair = start[np.diff(np.append(start, len(f))) == 2]
    other = own.copy()
    other[order[pair]] = own[order[pair + 1]]
    other[order[pair + 1]] = own[order[pair]]
    return other.reshape(n, 2)


def _bounded_distances(
    target: SegmentSet,
    pts: np.ndarray,
    plane: np.ndarray,
    candidates: np.ndarray,
    value: Callable[[np.ndarray], np.ndarray],
    lower: np.ndarray,
    n_planes: int,
    workers: int,
) -> np.ndarray:
    """Distances of ``pts`` to ``target``, as far as the per-plane maximum of ``value(distances)``
    needs them. ``value`` maps the distances to each point's contribution, non-decreasing in its own
    distance; ``lower`` (per plane) is at most that maximum. The result is exact wherever the
    contribution could exceed the maximum, elsewhere the distance to the nearest candidate segment
    (an upper bound whose contribution does not): the maximum is exact, with a k-d tree search only
    for those points. First the point of each plane with the largest bound is measured: where the
    candidates hold the nearest segment (mostly), its value is the maximum, and every other point is
    settled by its bound."""
    d, _ = target.distance_to(pts, candidates)
    if not len(d):
        return d
    top = _first_per_plane(value(d), plane)
    d[top] = target.distance(pts[top], plane[top], workers=workers)
    lower = np.maximum(lower, max_per_plane(value(d)[top], plane[top], n_planes))
    need = value(d) > lower[plane]
    need[top] = False
    d[need] = target.distance(pts[need], plane[need], workers=workers)
    return d


def _first_per_plane(values: np.ndarray, plane: np.ndarray) -> np.ndarray:
    """Index of a largest value of each plane present."""
    top = max_per_plane(values, plane, int(plane.max()) + 1)
    at = np.flatnonzero(values == top[plane])
    first = np.full(len(top), -1, dtype=np.int64)
    first[plane[at][::-1]] = at[::-1]  # of equal ones, the first
    return first[first >= 0]


def _reference_to_cut(
    ref: SegmentSet,
    cut_set: SegmentSet,
    ends_near: np.ndarray,
    cut_has: np.ndarray,
    n_planes: int,
    workers: int,
) -> np.ndarray:
    """Per plane, the largest distance from the reference's closed loops (each span's peak from its
    ends and its arc midpoint, ``span_max``) to the cut, at the planes the cut reaches (-inf at the
    others). ``ends_near``: (m, 2) the reference span nearest to each end of every cut segment.

    Exact, as a search for every point would give it, with few searches: each reference vertex is
    first measured against the cut segments whose ends lie nearest to the spans round it (an upper
    bound of its distance, ``_covering_pairs``), each arc midpoint against the neighbours of its
    ends' segments; the vertices none covers and the one with the largest bound of each plane are
    then searched, which gives a lower bound of the plane's largest distance; a span whose bounds (plus ``span_max``'s cap) stay
    below it cannot reach it, and only the others are searched: their ends, then their midpoints
    where the peak could still be the plane's largest."""
    assert ref.nxt is not None and ref.loop_first is not None  # closed loops of consecutive spans
    n_ref = len(ref.seg)
    sel = cut_has[ref.seg_plane]  # elsewhere the distances are undefined (NaN in ``compare``)
    d0 = np.full(n_ref, np.inf)
    near0 = np.full(n_ref, -1, dtype=np.int64)
    vertex, segment = _covering_pairs(ref, ends_near)
    if len(vertex):
        dist = _point_curve(ref.seg[vertex, 0], cut_set._rows[segment])
        order = np.argsort(vertex, kind="stable")
        vertex, segment, dist = vertex[order], segment[order], dist[order]
        first = np.flatnonzero(np.concatenate([[True], vertex[1:] != vertex[:-1]]))
        group = np.repeat(np.arange(len(first)), np.diff(np.append(first, len(vertex))))
        d0[vertex[first]], near0[vertex[first]] = _group_nearest(dist, group, first, segment)
    exact = np.zeros(n_ref, dtype=bool)
    d0[~sel] = -np.inf  # not measured

    def search(vertices: np.ndarray) -> None:
        v = vertices[~exact[vertices]]
        d0[v], near0[v] = cut_set.nearest(ref.seg[v, 0], ref.seg_plane[v], workers=workers)
        exact[v] = True

    ids = np.flatnonzero(sel)
    if not len(ids):
        return np.full(n_planes, -np.inf)
    plane = ref.seg_plane[ids]
    # those no cut segment covers (they need a search whatever the plane's largest) and each plane's
    # largest bound
    uncovered = ids[np.isinf(d0[ids])]
    search(np.concatenate([uncovered, ids[_first_per_plane(d0[ids], plane)]]))
    lower = max_per_plane(d0[ids][exact[ids]], plane[exact[ids]], n_planes)
    nxt = ref.nxt[ids]
    mid = ref.arc_mid[ids]

    def mid_bound(spans: np.ndarray) -> np.ndarray:
        """The arc midpoints' distances to the nearest segments of their ends and neighbours."""
        near = cut_set.around(np.column_stack([near0[ids[spans]], near0[nxt[spans]]]))
        return cut_set.distance_to(mid[spans], near)[0]

    d_mid = mid_bound(np.arange(len(ids)))
    bound = np.maximum(np.maximum(d0[ids], d0[nxt]), d_mid) + ref.chord
    need = np.flatnonzero(bound > lower[plane])  # spans that could reach their plane's largest
    ends = np.zeros(n_ref, dtype=bool)
    ends[ids[need]] = ends[nxt[need]] = True
    before = near0.copy()
    search(np.flatnonzero(ends))
    f0, f1 = d0[ids[need]], d0[nxt[need]]
    lower = np.maximum(lower, max_per_plane(np.maximum(f0, f1), plane[need], n_planes))
    # a midpoint's distance raises its span's peak: searched where the bound (also from its ends'
    # nearest segments as searched, where the search found others) could be the largest
    fm = d_mid[need]
    moved = (near0[ids[need]] != before[ids[need]]) | (near0[nxt[need]] != before[nxt[need]])
    if moved.any():
        fm[moved] = np.minimum(fm[moved], mid_bound(need[moved]))
    again = span_max(f0, fm, f1, ref.chord) > lower[plane[need]]
    fm[again] = cut_set.distance(mid[need][again], plane[need][again], workers=workers)
    peak = max_per_plane(span_max(f0, fm, f1, ref.chord), plane[need], n_planes)
    return np.maximum(lower, peak)


def _covering_pairs(ref: SegmentSet, ends_near: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(reference vertex, cut segment) pairs: every cut segment with the reference vertices between
    the spans nearest to its two ends ``ends_near`` ((m, 2), -1 for none), along their loop the
    shorter way and one more at either end; a segment whose ends are nearest to different loops,
    or to spans more than ``_MAX_COVER`` vertices apart, with the vertices of those two spans."""
    assert ref.nxt is not None and ref.loop_first is not None and ref.loop_size is not None
    ra, rb = ends_near[:, 0], ends_near[:, 1]
    ok = (ra >= 0) & (rb >= 0)
    ra, rb, seg = ra[ok], rb[ok], np.flatnonzero(ok)
    first, size = ref.loop_first[ra], ref.loop_size[ra]
    pa, pb = ra - first, rb - ref.loop_first[rb]
    fwd = (pb - pa) % size
    forward = fwd <= size // 2
    start = np.where(forward, pa, pb)
    count = np.minimum(np.where(forward, fwd, size - fwd) + 2, size)
    along = (ref.loop_first[rb] == first) & (count <= _MAX_COVER)
    # along the loop: count vertices from start; otherwise both spans' two vertices
    n = np.where(along, count, 4)
    owner = np.repeat(np.arange(len(seg)), n)
    k = np.arange(len(owner)) - np.repeat(np.cumsum(n) - n, n)
    o_along = along[owner]
    vertex = np.where(
        o_along,
        first[owner] + (start[owner] + k) % size[owner],
        np.where(k < 2, ra[owner], rb[owner]),
    )
    nxt_of = ~o_along & (k % 2 == 1)  # the span's second vertex
    vertex[nxt_of] = ref.nxt[vertex[nxt_of]]
    return vertex, seg[owner]


def compare(
    cut: MeshCut, ref: SegmentSet, ref_perimeter: np.ndarray, n_planes: int, *, workers: int = -1
) -> LayerMetrics:
    """Metrics of ``cut`` against the reference segments, per plane.

    vertex_dev : max distance of the cut's vertices from the reference
    chord_dev : two-sided distance between the cut polyline and the reference: the larger of the
                max distance of the reference's vertices and arc midpoints from the cut and the max
                distance of the cut's vertices and segment midpoints from the reference. The
                reference's vertices are as dense as its chord tolerance needs (spacing ~ sqrt(8 R c)),
                so a maximum between two of them is missed by at most about that tolerance.
    perimeter_err : |L_ref - L_cut| / L_ref
    workers : threads of the nearest-segment searches (-1: all CPUs)
    Only the per-plane maxima are kept, so a midpoint (of a cut segment, or a reference span's arc
    midpoint) is searched only where it could raise its plane's maximum (``_bounded_distances``):
    the maxima are exactly those of a search for every point.
    A plane where one side is empty and the other is not has NaN distances (and perimeter_err 1 when
    the cut is empty, NaN when the reference is); a plane where both are empty has zeros.
    """
    cut_has = np.bincount(cut.seg_plane, minlength=n_planes) > 0
    ref_has = np.bincount(ref.seg_plane, minlength=n_planes) > 0
    # the cut's vertices against the reference; its segment midpoints exactly where they could be
    # their plane's farthest, from the vertices' nearest spans
    d_vert, near_vert = ref.nearest(cut.vertices, cut.vertex_plane, workers=workers)
    vertex_dev = max_per_plane(d_vert, cut.vertex_plane, n_planes)
    d_mid = _bounded_distances(
        ref,
        midpoints(cut.seg),
        cut.seg_plane,
        ref.around(near_vert[cut.seg_node]),
        lambda d: d,
        vertex_dev,
        n_planes,
        workers,
    )
    d_cut_to_ref = np.maximum(vertex_dev, max_per_plane(d_mid, cut.seg_plane, n_planes))

    # the cut's own k-d tree only if a search needs it: most reference points get their distance
    # from the cut segments round them (below)
    cut_set = SegmentSet(
        cut.seg,
        cut.seg_plane,
        spacing=ref.spacing,
        neighbours=segment_neighbours(cut.seg_node),
        lazy=True,
    )
    # every vertex of the closed reference loops and the curve's point over every span's midpoint;
    # with loops known, each span's peak is interpolated from its three values, exactly where that
    # peak could be its plane's largest
    n_ref = len(ref.seg)
    if ref.loop_first is not None and n_ref:
        d_ref_to_cut = _reference_to_cut(ref, cut_set, near_vert[cut.seg_node], cut_has, n_planes, workers)
    else:
        ref_pts = np.concatenate([ref.seg[:, 0], ref.arc_mid])
        ref_pl = np.concatenate([ref.seg_plane, ref.seg_plane])
        d_ref_to_cut = max_per_plane(cut_set.distance(ref_pts, ref_pl, workers=workers), ref_pl, n_planes)
    chord_dev = np.maximum(d_ref_to_cut, d_cut_to_ref)

    cut_perimeter = segment_lengths_per_plane(cut.seg, cut.seg_plane, n_planes)
    with np.errstate(divide="ignore", invalid="ignore"):
        perimeter_err = np.abs(ref_perimeter - cut_perimeter) / ref_perimeter
    both_empty = ~cut_has & ~ref_has
    one_empty = cut_has ^ ref_has
    for arr in (vertex_dev, chord_dev):
        arr[both_empty] = 0.0
        arr[one_empty] = np.nan
    perimeter_err[both_empty] = 0.0
    perimeter_err[cut_has & ~ref_has] = np.nan
    perimeter_err[~cut_has & ref_has] = 1.0
    return LayerMetrics(
        vertex_dev=vertex_dev,
        chord_dev=chord_dev,
        perimeter_err=perimeter_err,
        loops=cut.loops,
        open_chains=cut.open_chains,
        vertices=np.bincount(cut.vertex_plane, minlength=n_planes),
        perimeter=cut_perimeter,
    )
