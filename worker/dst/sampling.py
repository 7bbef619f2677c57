"""Exact ring vertices: every section loop sampled under the segment-length and chord-error budget.

Two kinds of loops (see ``sections``):

- *free* loops (an annulus component on both sides) are re-sampled from scratch. Corners of the
  section (where it crosses a B-rep edge, or meets a mesh node lying on the plane) are kept, each
  solved exactly on its edge. Between two corners the section runs inside one face: points are
  seeded at equal arc length along the topology-mesh path and moved onto the exact level set
  ``z(u, v) = plane`` by Newton in that face's parameter space.
- *pinned* loops (a cap or branching component on one side) keep every crossing of a topology-mesh
  edge, each solved exactly (Brent along the edge), because the kept pieces are built on them.

Then every segment is checked against the exact curve: the curve point halfway along it (Newton
again) must lie within ``chord_error`` of the chord, and the chord must be no longer than
``segment_length``; a failing segment is split and its parts checked again. The midpoint test is
exact for circles and measures the sagitta to second order in the segment length for other smooth
curves; a segment whose midpoint may not show its largest distance (see ``_quarter_sags``) is also
checked at its quarter points.

Last, where a ring turns sharply at a vertex inside a face and a segment there runs against the
section curve's own direction (from the surface normal: the loops keep the material on their left),
the curve makes an excursion the seeds did not follow: the tongue a plane cuts where it grazes a
crest that is not level, whose tip lies beyond the topology mesh's. That piece is traced along the
exact curve from one end to the other and sampled again with the trace as seeds
(``_excursion_runs``).

All Newton solves of one loop run as one batch (numpy bookkeeping, one OCCT ``D1`` per point and
iteration), which keeps the Python overhead per ring vertex to a few microseconds.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, fields

import numpy as np
from OCP.collections import Array1_double
from OCP.GeomAbs import GeomAbs_C1
from OCP.gp import gp_Pnt, gp_Vec

from worker.dst.constants import (
    LEVEL_TOL_MM,
    MAX_SUBDIVISION,
    MIN_LOOP_VERTICES,
    NEWTON_MAX_ITER,
    SEGMENT_FILL,
)
from worker.dst.errors import TessellationError
from worker.dst.exact import ExactFailure, FaceEval, WalkPassed
from worker.dst.sections import SectionTopology
from worker.dst.topomesh import TopoMesh

# Segments are accepted with their sampled largest distance from the curve at most this share of the
# chord budget: the samples (midpoint, quarter points, the parabola through them) can miss the true
# largest distance by a few per cent where the bend is off-centre.
CHORD_FILL = 0.97
# A sampler that is ``halving`` checks its segments at this many times the chord; one within that
# but not within the chord is kept as its two halves, each within the chord where the curve is a
# parabola (a quarter of the distance), and checked so
HALVING_FACTOR = 4.0
# ... where each half's distance is within this share of a quarter of the segment's: a bend whose
# curvature changes linearly by up to ~2.3x along the segment (its one-sample peaks < 0.2% low)
HALF_SAG_SPREAD = 0.2
# A segment whose curve lies more than this share of its length from its chord turns through more
# than ~67 degrees (a circular arc: 4 atan(2 sag / length)): no shallow arc, whose largest distance the
# samples show. Such a segment is split while its sampled distance is above a quarter of the budget
# (Ventilator turned (-135.2, -164.2, -177.2) at z = 0.1: a 0.117 mm segment round a 0.035 mm bend,
# sampled at 0.022 at its midpoint, one quarter point on the curve past its end, was 0.032 from it).
DEEP_BEND_REL = 0.15
GAP_SPAN_REL = 1e-6  # a seed interval this small (relative to its run) cannot hold another exact point
# A segment's midpoint (placed by arc length along the seed path) this close to either end, relative
# to the segment, is off the path: solved again from the chord's middle (``_midpoints_off_the_path``)
MID_OFF_PATH = 0.1
# A run whose exact end lies more than this many topology deflections from its topology crossing has
# its points checked against the face's trim (the ordinary gap is within one deflection)
SUSPECT_DEFLECTIONS = 5.0
# steps (in topology deflections) of a walk along a section curve: short enough that the pull back
# onto the plane cannot reach another branch of the section
WALK_STEP_DEFLECTIONS = 5.0
TRIM_TOL_MM = 1e-6
# C0 lines of a face this close to its (u, v) box's sides are its edges' business (relative to the box)
KINK_MARGIN_REL = 1e-9
KINK_MIN_SPACING_REL = 1e-9  # a kink this close to a run's end (relative to its length) is that end
# rounds of the check of segments with an inflection inside (each: those the last round split)
MAX_INFLECTION_ROUNDS = 4
# A shallow arc within the chord budget e leaves its chord at ~4 e / L (L: the chord's length). A run's
# end segment whose curve leaves the corner at more than this many times that (by its own face's
# tangent there) hides a bend next to the corner that its midpoint does not show: checked at its
# quarter points and split where it fails, round after round on the new end segments
END_BEND_FACTOR = 1.5
MAX_END_BEND_ROUNDS = 6
END_TANGENT_ITER = 6  # Gauss-Newton steps placing a run's end vertex on its face (from its seed path)
# ... where it lies within this of the face (a file's tolerance): the face's tangent
END_TANGENT_TOL_MM = 0.01
END_TANGENT_MIN_SLOPE = 1e-3  # a face steeper than this (normal's horizontal share) has a section tangent
MAX_REFINE_ROUNDS = 40  # halving a segment 24 times takes 1 m down to 60 nm: still failing means broken
# A sampled ring turning by more than this (cosine) at a vertex inside a face is checked for an
# excursion of the curve its segments skip (``_excursion_runs``); a correct sampling turns that much
# only round a bend of radius under ~7 chord budgets
EXCURSION_TURN_COS = 0.5
# ... and a segment leaving (or reaching) such a vertex at more than this angle (cosine) from the
# curve's own direction there is followed along the exact curve
EXCURSION_TANGENT_COS = 0.5
# a trace from one end of a segment to the other gives up after this many mm (or 100 segment lengths)
EXCURSION_MAX_TRACE_MM = 50.0
# a ring turning back this sharply at a vertex outside its face's trim has a spur there
SPUR_TURN_COS = -0.9
# segments against the curve's direction this few ring positions apart are one stretch to re-trace
EXCURSION_CLUSTER_GAP = 32


class VertexPool:
    """Output vertices in world millimetres; ``plane`` is the plane index of ring vertices, else -1.

    A growable numpy buffer: ``xyz`` and ``plane`` are views of the vertices added so far.
    """

    def __init__(self, capacity: int = 4096):
        self._xyz = np.empty((capacity, 3), dtype=np.float64)
        self._plane = np.empty(capacity, dtype=np.int64)
        self.n = 0

    @property
    def xyz(self) -> np.ndarray:
        return self._xyz[: self.n]

    @property
    def plane(self) -> np.ndarray:
        return self._plane[: self.n]

    def __len__(self) -> int:
        return self.n

    def _reserve(self, extra: int) -> None:
        need = self.n + extra
        if need > len(self._plane):
            cap = max(need, 2 * len(self._plane))
            self._xyz = np.concatenate([self._xyz[: self.n], np.empty((cap - self.n, 3))])
            self._plane = np.concatenate([self._plane[: self.n], np.empty(cap - self.n, dtype=np.int64)])

    def add(self, p: tuple[float, float, float], plane: int) -> int:
        self._reserve(1)
        self._xyz[self.n] = p
        self._plane[self.n] = plane
        self.n += 1
        return self.n - 1

    def extend(self, xy: np.ndarray, z: np.ndarray, plane: np.ndarray) -> np.ndarray:
        """Add ring vertices (x, y) at heights ``z`` on planes ``plane``; returns their ids."""
        k = len(xy)
        self._reserve(k)
        n0 = self.n
        self._xyz[n0 : n0 + k, :2] = xy
        self._xyz[n0 : n0 + k, 2] = z
        self._plane[n0 : n0 + k] = plane
        self.n += k
        return np.arange(n0, self.n, dtype=np.int64)


@dataclass
class SamplingStats:
    newton_solves: int = 0
    edge_roots: int = 0
    fallbacks: int = 0  # corner points solved on a face because the curve root failed
    tolerance_gaps: int = 0  # segments kept over budget because the B-rep is inconsistent there
    tangent_segments: int = 0  # segments kept over budget where the plane is tangent to the surface
    newton_failures: int = 0  # seeds with no exact point (dropped; see tangent_segments)
    outside_face_points: int = 0  # points beyond a face's trim (a nearly tangent edge), dropped
    excursions: int = 0  # segments re-sampled along an excursion of the curve they skipped
    excursion_failures: int = 0  # segments suspected of skipping one that could not be traced
    spur_vertices: int = 0  # ring vertices dropped as tips of spurs onto a face's extension
    reordered_crossings: int = 0  # crossings put at the section point nearest them (see _solve_crossing)
    kink_corners: int = 0  # corners placed where a section crosses a C0 line inside a face
    deep_bends: int = 0  # segments split for turning through more than ~67 degrees (DEEP_BEND_REL)
    quarter_checks: int = 0  # segments also checked at their quarter points (see _quarter_sags)
    halved_segments: int = 0  # segments kept as their two halves (see RingSampler._halves)
    inflection_checks: int = 0  # segments checked again for an inflection inside (_inflected_segments)
    end_bend_checks: int = 0  # run end segments checked again for a bend at their corner (END_BEND_FACTOR)
    unchecked_segments: int = 0  # segments whose midpoint could not be placed (see _midpoints_off_the_path)
    off_trim_crossings: int = 0  # crossings whose root lay beyond their face's trim (see _drop_off_trim)
    max_gap_mm: float = 0.0
    max_gap_at: str = ""

    def add(self, other: SamplingStats) -> None:
        """Accumulate another sampler's counts (the largest gap, with its place, is kept)."""
        for f in fields(self):
            if f.name == "max_gap_mm":
                if other.max_gap_mm > self.max_gap_mm:
                    self.max_gap_mm, self.max_gap_at = other.max_gap_mm, other.max_gap_at
            elif f.name != "max_gap_at":
                setattr(self, f.name, getattr(self, f.name) + getattr(other, f.name))


@dataclass
class _Run:
    """A piece of a section curve inside one face, parametrised by arc length along a seed path."""

    face: int
    s: np.ndarray  # (k,) arc length of the seed path, 0 .. length
    uv: np.ndarray  # (k, 2) seed path in the face's (u, v)
    max_step: float  # Newton trust region in (u, v)
    start: int  # vertex id of the exact start point
    end: int  # vertex id of the exact end point
    n_seg: int  # initial number of segments
    zc: float  # world height of the plane, mm
    plane: int  # plane index
    # exact ends far from their topology crossings, with the distance they moved: points near them are
    # checked against the face's trim
    moved: tuple[tuple[np.ndarray, float], ...] = ()
    # the seed path is a trace along the exact curve (``_excursion_runs``): a point placed by arc length
    # along it is on the right piece of the curve even where it projects beyond its segment's chord
    traced: bool = False


class RingSampler:
    """Computes and caches the exact ring vertices of one solid."""

    def __init__(
        self,
        mesh: TopoMesh,
        topo: SectionTopology,
        pool: VertexPool,
        *,
        segment_length: float,
        chord_error: float,
        keep_crossings: bool = True,
        halving: bool = False,
    ):
        self.mesh, self.topo, self.pool = mesh, topo, pool
        self.seg_len = segment_length
        self.chord = chord_error
        # ``halving``: segments checked at HALVING_FACTOR times the chord first, and one over the
        # chord but within that kept as its two halves, each checked at its own midpoint (the
        # segment's quarter point, solved already; see ``_halves``) instead of split and solved
        # again: the report's dense reference at 1 um, 129.9k -> 72.0k Newton solves on the hemisphere
        self.halving = halving
        self.trace_reach = max(EXCURSION_MAX_TRACE_MM, 100.0 * segment_length)  # a trace's longest
        # a pinned loop's crossings are kept (the kept triangles use them): False where only the
        # loops are wanted (the deviation report's reference), so that a stretch of them in the
        # wrong order can be traced again
        self.keep_crossings = keep_crossings
        self.stats = SamplingStats()
        self.node_vid: dict[int, int] = {}
        self.cross_vid: dict[int, int] = {}
        # crossings whose root on their face lies beyond the face's trim (on the surface's extension,
        # not on the B-rep): see pinned_loop
        self.off_trim: set[int] = set()
        self._on_brep_edge = np.zeros(mesh.n_nodes, dtype=bool)  # nodes on a B-rep edge
        if mesh.edge_of:
            self._on_brep_edge[np.fromiter((n for key in mesh.edge_of for n in key), dtype=np.int64)] = True
        self.subdiv: dict[int, list[int]] = {}  # start crossing of a pinned segment -> inner vertex ids
        # topology edges lying in a plane (both ends are nodes on it) whose ring segment was
        # subdivided: (a, b) with a < b -> inner vertex ids from a to b
        self.edge_subdiv: dict[tuple[int, int], list[int]] = {}
        self._edge_param: dict[tuple[int, int], float] = {}
        self._pred: np.ndarray | None = None  # previous crossing along its loop (``topo.succ`` inverted)
        self._solving: set[int] = set()  # crossings whose neighbours are being solved
        self._gaps: list[tuple] = []  # (length, z, face, one end, the other): see settle_gaps
        # vertex ids where the section changes face or meets a B-rep edge: its curvature may jump there
        self.corner_vids: set[int] = set()
        self._kinks: dict[int, tuple[np.ndarray, np.ndarray]] = {}  # face -> interior C0 u and v lines
        self._ads = [f.ad for f in mesh.faces]
        self._evals = [f.batch for f in mesh.faces]
        self._analytic = np.array([e is not None for e in self._evals], dtype=bool)
        # each face's (u, v) box, and whether a point beyond it in u or v is certainly off the face
        # (``FaceEval.bounded``)
        fs = mesh.faces
        self._uv_box = np.array([(f.u0, f.u1, f.v0, f.v1) for f in fs], dtype=np.float64).reshape(-1, 4)
        self._box_checked = np.array([f.bounded for f in fs], dtype=bool).reshape(-1, 2)
        uv = mesh.tri_uv
        # (u, v) size of each topology triangle: the scale of a Newton step from a seed
        self.tri_uv_scale = np.max(np.linalg.norm(uv - np.roll(uv, 1, axis=1), axis=2), axis=1) + 1e-12

    # --- single exact vertices ---------------------------------------------------------------------
    def node(self, n: int) -> int:
        vid = self.node_vid.get(n)
        if vid is None:
            p = self.mesh.xyz[n]
            vid = self.pool.add(
                (float(p[0]), float(p[1]), float(self.topo.z[n])), int(self.topo.node_plane[n])
            )
            self.node_vid[n] = vid
        return vid

    def crossing(self, c: int) -> int:
        """Vertex id of crossing ``c``, solved exactly on first use."""
        vid = self.cross_vid.get(c)
        if vid is not None:
            return vid
        topo = self.topo
        node = int(topo.cross_node[c])
        if node >= 0:
            vid = self.node(node)
        else:
            j = int(topo.cross_plane[c])
            vid = self.pool.add(self._solve_crossing(c, float(topo.planes[j])), j)
        self.cross_vid[c] = vid
        return vid

    def _solve_crossing(self, c: int, zc: float) -> tuple[float, float, float]:
        topo, mesh = self.topo, self.mesh
        e = int(topo.cross_edge[c])
        a, b = (int(x) for x in topo.edges[e])
        brep_edge = mesh.edge_of.get((a, b))
        if brep_edge is not None:
            try:
                self.stats.edge_roots += 1
                return self._root_on_brep_edge(brep_edge, a, b, zc)
            except ExactFailure:
                self.stats.fallbacks += 1
        t = int(topo.edge_tris[e, 0])
        row = mesh.tris[t].tolist()
        ua, va = mesh.tri_uv[t, row.index(a)]
        ub, vb = mesh.tri_uv[t, row.index(b)]
        face = int(mesh.tri_face[t])
        try:
            x, y, _, ur, vr = self._root_on_face(face, a, b, (ua, va), (ub, vb), zc)
            # Between nodes on the face's boundary, the root can lie beyond the trim, where the
            # face is narrower than its topology triangle (a sliver's tip): not on the B-rep.
            if (self._on_brep_edge[a] or self._on_brep_edge[b]) and not mesh.faces[face].contains(
                ur, vr, tol=TRIM_TOL_MM
            ):
                self.off_trim.add(c)
            near = topo.cross_xyz[c]
            d_root = math.hypot(x - near[0], y - near[1])
            if d_root > SUSPECT_DEFLECTIONS * mesh.deflection:
                # Along an edge that runs nearly level over the surface (a long triangle across a
                # ridge or a valley just off the plane), the surface's root can lie far from the
                # edge's crossing, out of order with its neighbours along the section (a ring that
                # doubles back). The point of the root's own section curve nearest the crossing keeps
                # the order: walked to along that curve, since Newton from the crossing can land on
                # the other side of a ridge a few micrometres above the plane (a gap narrower than
                # the crossing's distance from either side).
                walked = self._reordered(c, face, ur, vr, zc, near, d_root)
                if walked is not None:
                    x, y = walked
                    self.off_trim.discard(c)
                    self.stats.reordered_crossings += 1
        except ExactFailure:
            # The surface at a node's (u, v) can differ from the node (an edge point) by the file's
            # tolerance, so a plane that close to a node is not bracketed: Newton from the seed.
            self.stats.fallbacks += 1
            p = self._newton_from_crossing(t, a, b, (ua, va), (ub, vb), zc)
            if p is None:
                raise TessellationError(
                    f"no exact point of face {face + 1} at z={zc:.4f} mm near a topology edge"
                ) from None
            x, y, _ = p
        return x, y, zc

    def _reordered(
        self, c: int, face: int, ur: float, vr: float, zc: float, near: np.ndarray, d_root: float
    ) -> tuple[float, float] | None:
        """Where crossing ``c`` goes instead of its root at (``ur``, ``vr``) on ``face``, far from the
        crossing's own point ``near``: the point of the root's section curve nearest ``near``
        (walked to), or None to keep the root (no such point inside the face's trim, or none
        nearer). A walk that passes a neighbouring crossing's point along the loop is taken only if
        the root does not lie on the curve between those neighbours (``_between_neighbours``): the
        root can be in order and ``near`` not (r103ec turned (35.3, -158.7, -40.5) at z = 52.5: the
        root at a tongue's tip, between its neighbours on either side of the tongue; the crossing
        inside the tongue, whose nearest point down one side lies past the next crossing: the ring
        crossed the tongue four times), or the root out of order beyond a neighbour (a long edge
        along a level ridge line: ec_soapbox-A turned (0, 35, 0), where the walk back passes it)."""
        ev = self.mesh.faces[face]
        step = WALK_STEP_DEFLECTIONS * self.mesh.deflection
        target = (float(near[0]), float(near[1]))
        max_steps = int(d_root / step) + 100
        pred, succ = self._neighbour_points(c)
        try:
            try:
                px, py, pu, pv = ev.walk_level(
                    ur, vr, zc, target, step=step, max_steps=max_steps, avoid=[q for q in (pred, succ) if q]
                )
            except WalkPassed:
                # (with a neighbour unknown, the order cannot be told: walked as before)
                if pred and succ and self._between_neighbours(ev, ur, vr, zc, pred, succ, step, d_root):
                    return None
                px, py, pu, pv = ev.walk_level(ur, vr, zc, target, step=step, max_steps=max_steps)
        except ExactFailure:
            return None
        if math.hypot(px - target[0], py - target[1]) < d_root and ev.contains(pu, pv, tol=TRIM_TOL_MM):
            return px, py
        return None

    def _between_neighbours(
        self,
        ev: FaceEval,
        ur: float,
        vr: float,
        zc: float,
        pred: tuple[float, float],
        succ: tuple[float, float],
        step: float,
        reach: float = 0.0,
    ) -> bool:
        """Whether the section point at (``ur``, ``vr``) of face ``ev`` lies on the section curve
        from ``pred`` to ``succ`` (x, y): a trace along it from one (in the loops' direction) to
        the other passes within a tenth of a step of it. False where the trace fails, or runs
        farther than 4 times the neighbours' distance and ``reach`` (the point's distance from its
        crossing) without arriving."""
        x, y = ev.point(ur, vr)[:2]
        try:
            u0, v0 = ev.uv_near((*pred, zc), (ur, vr))
            direction = ev.section_direction(*ev.uv_near((*succ, zc), (ur, vr)))
            if direction is None:
                return False
            longest = 4.0 * (math.hypot(succ[0] - pred[0], succ[1] - pred[1]) + reach) + step
            trace = ev.trace_level(u0, v0, zc, succ, direction, step=step, max_length=longest)
        except ExactFailure:
            return False
        path = np.array([pred, *(t[:2] for t in trace), succ], dtype=np.float64)
        seg = np.stack([path[:-1], path[1:]], axis=1)
        return bool(distances_to_segments(np.array([[x, y]]), seg).min() <= 0.1 * step)

    def _neighbour_points(self, c: int) -> tuple[tuple[float, float] | None, tuple[float, float] | None]:
        """The exact (x, y) of crossing ``c``'s neighbours along its loop (before it, after it), solved
        here if they are not yet (not while another crossing's neighbours are being solved: no
        chains along the loop); None for one without an exact point."""
        if self._pred is None:
            self._pred = np.empty_like(self.topo.succ)
            self._pred[self.topo.succ] = np.arange(len(self.topo.succ))
        nested = bool(self._solving)
        self._solving.add(c)
        try:
            out: list[tuple[float, float] | None] = []
            for q in (int(self._pred[c]), int(self.topo.succ[c])):
                vid = self.cross_vid.get(q)
                if vid is None and not nested and q != c:
                    try:
                        vid = self.crossing(q)
                    except TessellationError:
                        vid = None
                out.append(
                    None if vid is None else (float(self.pool.xyz[vid, 0]), float(self.pool.xyz[vid, 1]))
                )
            return out[0], out[1]
        finally:
            self._solving.discard(c)

    def _root_on_face(self, face: int, a: int, b: int, uva, uvb, zc: float) -> tuple[float, ...]:
        """``FaceEval.root_on_uv_segment`` of face ``face`` between nodes ``a`` and ``b`` at (u, v)
        ``uva`` and ``uvb``, or where those do not bracket the plane, between the (u, v) of the
        nodes' own positions: a node on a B-rep edge has the (u, v) of the edge's curve on the face,
        which can lie farther from the node (the edge's 3D curve) than the file's tolerance admits
        (``trj3_s1-al-214`` turned (78.4, 32.6, -18.9): 0.37 mm at an edge of tolerance 0.003 mm,
        the node 0.17 mm above the plane and the surface at its (u, v) 0.16 mm below it).
        Raises ExactFailure if neither brackets it."""
        fe = self.mesh.faces[face]
        try:
            return fe.root_on_uv_segment(*uva, *uvb, zc)
        except ExactFailure:
            if not (self._on_brep_edge[a] or self._on_brep_edge[b]):
                raise
        own = [
            fe.uv_near(tuple(self.mesh.xyz[n]), tuple(uv)) if self._on_brep_edge[n] else tuple(uv)
            for n, uv in ((a, uva), (b, uvb))
        ]
        return fe.root_on_uv_segment(*own[0], *own[1], zc)

    def _newton_from_crossing(self, t: int, a: int, b: int, uva, uvb, zc: float) -> np.ndarray | None:
        """Newton (the smallest 3D move onto ``z = zc``) from where edge a-b of triangle ``t``
        crosses the plane, interpolated in (u, v): the point, or None if it fails."""
        mesh = self.mesh
        za, zb = mesh.xyz[a, 2], mesh.xyz[b, 2]
        frac = min(1.0, max(0.0, (zc - za) / (zb - za))) if zb != za else 0.5
        seed = np.asarray(uva, dtype=np.float64) + frac * np.subtract(uvb, uva)
        pts, ok, _ = self._newton(
            np.array([int(mesh.tri_face[t])]),
            seed[:1],
            seed[1:],
            zc,
            np.array([2.0 * self.tri_uv_scale[t]]),
        )
        return pts[0] if ok[0] else None

    def _root_on_brep_edge(self, ei: int, a: int, b: int, zc: float) -> tuple[float, float, float]:
        ev = self.mesh.edges[ei]
        sa, sb = self._param(ei, a), self._param(ei, b)
        if ev.closed and abs(sa - sb) > 0.5 * (ev.s1 - ev.s0):
            # A node at the closing vertex of a closed curve projects to either end: use the end on
            # the other node's side.
            mid = 0.5 * (ev.s0 + ev.s1)
            if min(abs(sa - ev.s0), abs(sa - ev.s1)) < min(abs(sb - ev.s0), abs(sb - ev.s1)):
                sa = ev.s1 if sb > mid else ev.s0
            else:
                sb = ev.s1 if sa > mid else ev.s0
        x, y, _ = ev.root(min(sa, sb), max(sa, sb), zc)
        return x, y, zc

    def _param(self, ei: int, node: int) -> float:
        key = (ei, node)
        s = self._edge_param.get(key)
        if s is None:
            s = self.mesh.edges[ei].parameter_of(tuple(self.mesh.xyz[node]))
            self._edge_param[key] = s
        return s

    # --- loops -------------------------------------------------------------------------------------
    def free_loops(self, loop_ids: list[int]) -> dict[int, list[int]]:
        """Re-sampled rings of free loops (corners kept, budget-driven points between them), all in one batch."""
        out: dict[int, list[int]] = {}
        runs: list[_Run] = []
        owner: list[int] = []
        for li in loop_ids:
            loop_runs = self._loop_runs(li, min_seg=1)
            runs.extend(loop_runs)
            owner.extend([li] * len(loop_runs))
        pieces: dict[int, list[int]] = {li: [] for li in loop_ids}
        face_of: dict[int, int] = {}  # vertex id -> face of the ring segment that starts there
        for li, run, run_pts in zip(owner, runs, self._sample_runs(runs), strict=True):
            pieces[li].extend(run_pts[:-1])
            face_of.update(dict.fromkeys(run_pts[:-1], run.face))
        for li in loop_ids:
            ring = _dedupe_cyclic(pieces[li], self.pool)
            if len(ring) < MIN_LOOP_VERTICES:
                # a tiny loop (a dome just below its top): sample it with at least three segments
                tiny = self._loop_runs(li, min_seg=MIN_LOOP_VERTICES)
                ring = []
                for run, run_pts in zip(tiny, self._sample_runs(tiny), strict=True):
                    ring.extend(run_pts[:-1])
                    face_of.update(dict.fromkeys(run_pts[:-1], run.face))
                ring = _dedupe_cyclic(ring, self.pool)
                if len(ring) < MIN_LOOP_VERTICES:
                    zc = float(self.topo.planes[self.topo.loops[li][0]])
                    raise TessellationError(
                        f"a section loop at z={zc:.4f} mm collapses to fewer than 3 points"
                    )
            out[li] = ring
        # excursions the seeds skipped, re-sampled in one batch and spliced in (last first per ring,
        # so that the segment indices of the others stay valid)
        self._replace_excursions(out, face_of)
        return out

    def _replace_excursions(self, rings: dict[int, list[int]], face_of: dict[int, int]) -> None:
        """Re-sample (in place, all in one batch) the stretches of these rings that skip the exact
        curve's excursions (``_excursion_runs``); their vertices may be dropped. Spurs onto a face's
        extension are dropped first (``_without_spurs``)."""
        for li, ring in rings.items():
            rings[li] = self._without_spurs(ring, face_of)
        found = [
            (li, i, j, run)
            for li, ring in rings.items()
            for i, j, run in self._excursion_runs(ring, face_of, li, stretches=True)
        ]
        if not found:
            return
        by_loop: dict[int, list[tuple[int, int, list[int]]]] = {}
        for (li, i, j, _), run_pts in zip(found, self._sample_traced([f[3] for f in found]), strict=True):
            if run_pts is not None:
                by_loop.setdefault(li, []).append((i, j, run_pts[1:-1]))
        for li, pieces in by_loop.items():
            ring = rings[li]
            widened = False
            while pieces:  # each piece must keep the curve its dropped vertices lie on
                new = _splice(ring, pieces)
                lost = self._lost_pieces(ring, pieces, new, face_of)
                if not lost:
                    break
                if not widened:
                    # Once: a lost piece's whole run, traced from the corner before it to the corner
                    # after it, in its place (then checked like the others)
                    widened = True
                    kept = [pc for pc in pieces if pc not in lost]
                    n_kept = len(kept)
                    for pc in lost:  # (each kept: the next must not overlap it)
                        if wide := self._whole_run(li, ring, face_of, pc, kept):
                            kept.append(wide)
                    if len(kept) > n_kept:
                        pieces = kept
                        continue
                self.stats.excursion_failures += len(lost)
                pieces = [pc for pc in pieces if pc not in lost]
            if pieces:
                rings[li] = new
                self.stats.excursions += len(pieces)

    def _whole_run(
        self,
        li: int,
        ring: list[int],
        face_of: dict[int, int],
        piece: tuple[int, int, list[int]],
        others: list[tuple[int, int, list[int]]],
    ) -> tuple[int, int, list[int]] | None:
        """The run of ``ring`` (loop ``li``) round a re-sampled piece that lost vertices of the curve
        (``_lost_pieces``), traced along the exact curve from the corner before it to the corner after
        it and sampled: (i, j, inner) to splice in instead, or None (no such run of one face, one that
        overlaps ``others``, or a trace that fails).

        Out of order over a tongue's tip (boxed_sphere turned (-11.5, -70.9, -79.8) at z = 0.3,
        sampled to the reference's 1 um: 116 vertices passing the tip five times), the stretch the
        suspect segments bound holds vertices of the curve beyond its own ends, which a trace between
        those ends cannot keep; between the run's corners the curve is one piece on one face, and
        its trace keeps them all."""
        i, j, _ = piece
        n = len(ring)
        face = face_of.get(ring[i % n])
        if face is None:
            return None
        corner = np.array([v in self.corner_vids for v in ring], dtype=bool)
        wide = self._run_ends(ring, face_of, face, corner, i, j)
        if wide is None or wide == (i, j):  # (the same ends: the same trace)
            return None
        whole = {k % n for k in range(wide[0], wide[1] + 1)}
        if any({k % n for k in range(a + 1, b)} & whole for a, b, _ in others):
            return None
        run = self._stretch_run(li, ring, self.pool.xyz[ring, :2], face, *wide)
        pts = None if run is None else self._sample_traced([run])[0]
        return None if pts is None else (wide[0], wide[1], pts[1:-1])

    def _lost_pieces(
        self,
        ring: list[int],
        pieces: list[tuple[int, int, list[int]]],
        new: list[int],
        face_of: dict[int, int],
    ) -> list[tuple[int, int, list[int]]]:
        """The pieces from whose dropped vertices lying on their faces (exact points of the curve)
        ``new`` (``ring`` with the pieces re-sampled) passes farther than the budget: a trace that
        stopped short of a narrow excursion the ring had reached (boxed_sphere turned: 6 um)."""
        n = len(ring)
        kept = set(new)
        p = self.pool.xyz[new, :2]
        seg = np.stack([p, np.roll(p, -1, axis=0)], axis=1)
        lost = []
        for piece in pieces:
            i, j, _ = piece
            dropped = [
                v
                for v in (ring[k % n] for k in range(i + 1, j))
                if v not in kept and (face := face_of.get(v)) is not None and self._in_trim(face, v)
            ]
            if dropped and distances_to_segments(self.pool.xyz[dropped, :2], seg).max() > self.chord:
                lost.append(piece)
        return lost

    def _in_trim(self, face: int, v: int) -> bool:
        """Whether vertex ``v`` lies on ``face`` within its trim (not on its surface's extension)."""
        ev = self.mesh.faces[face]
        return ev.contains(*_uv_of(ev, self.pool.xyz[v]), tol=TRIM_TOL_MM)

    def _without_spurs(self, ring: list[int], face_of: dict[int, int]) -> list[int]:
        """``ring`` without the tips of its spurs onto a face's extension, tip after tip: vertices
        where it turns back (``SPUR_TURN_COS``) that lie outside their face's trim. Out of order, a
        finer topology mesh's crossings past a face's edge have Newton put points on the face's
        surface beyond it (M6-1x12-countersunk-screw turned: 0.3 mm out and back, 0.05 mm off the
        B-rep); no section of the B-rep turns back there."""
        xyz = self.pool.xyz
        while len(ring) > MIN_LOOP_VERTICES:
            p = xyz[ring, :2]
            d = np.roll(p, -1, axis=0) - p
            length = np.hypot(d[:, 0], d[:, 1])
            unit = d / np.where(length > 0, length, 1.0)[:, None]
            back = np.einsum("ij,ij->i", np.roll(unit, 1, axis=0), unit) < SPUR_TURN_COS
            tips = []
            for i in np.flatnonzero(back).tolist():
                v = ring[i]
                face = face_of.get(v, face_of.get(ring[i - 1]))
                if face is not None and v not in self.corner_vids and not self._in_trim(face, v):
                    tips.append(i)
            if not tips or len(ring) - len(tips) < MIN_LOOP_VERTICES:
                break
            drop = set(tips)
            ring = [v for i, v in enumerate(ring) if i not in drop]
            self.stats.spur_vertices += len(tips)
        return ring

    def _sample_traced(self, runs: list[_Run]) -> list[list[int] | None]:
        """``_sample_runs`` of traced runs, None for one that cannot meet the budget (counted in
        ``excursion_failures``; its ring keeps the points it had): the excursion check may improve a
        ring, never fail a build that would otherwise succeed."""
        try:
            return self._sample_runs(runs)
        except TessellationError:
            out: list[list[int] | None] = []
            for run in runs:
                try:
                    out.append(self._sample_runs([run])[0])
                except TessellationError:
                    self.stats.excursion_failures += 1
                    out.append(None)
            return out

    def _loop_runs(self, li: int, *, min_seg: int) -> list[_Run]:
        """The runs of a free loop: the pieces of its section between consecutive corners."""
        topo = self.topo
        j, cross = topo.loops[li]
        zc = float(topo.planes[j])
        n = len(cross)
        seg_tri = topo.seg_tri[cross]
        faces = self.mesh.tri_face[seg_tri]
        corner = topo.cross_is_corner[cross] | (faces != np.roll(faces, 1))
        starts = np.flatnonzero(corner).tolist() or [0]
        vids = [self.crossing(int(cross[i])) for i in starts]
        if corner.any():
            self.corner_vids.update(vids)
        # the loop's crossings twice over, so that every run (which may wrap) is one slice; corners
        # at their exact positions
        exact = self.pool.xyz[vids]
        topo_xyz = topo.cross_xyz[cross]
        pts = topo_xyz.copy()
        pts[starts] = exact
        pts = np.concatenate([pts, pts[:1]])
        cum = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))])
        cum = np.concatenate([cum[:-1], cum[-1] + cum])
        uv_start = np.concatenate([topo.cross_uv_start[cross]] * 2)
        uv_end = np.concatenate([topo.cross_uv_end[cross]] * 2)
        scale = np.concatenate([self.tri_uv_scale[seg_tri]] * 2)
        gap = np.linalg.norm(exact - topo_xyz[starts], axis=1)
        far = gap > SUSPECT_DEFLECTIONS * self.mesh.deflection
        single = len(starts) == 1
        runs = []
        for r, i0 in enumerate(starts):
            r1 = (r + 1) % len(starts)
            count = (starts[r1] - i0) % n or n
            s = cum[i0 : i0 + count + 1] - cum[i0]
            uv = np.concatenate([uv_start[i0 : i0 + count], uv_end[i0 + count - 1 : i0 + count]])
            n_seg = max(min_seg if single else 1, math.ceil(s[-1] / (self.seg_len * SEGMENT_FILL)))
            step = 2.0 * float(scale[i0 : i0 + count].max())
            moved = tuple((exact[k].copy(), float(gap[k]) + self.seg_len) for k in (r, r1) if far[k])
            if moved:
                uv = self._seeds_toward_exact_ends(
                    int(faces[i0]), uv, s, exact[r] if far[r] else None, exact[r1] if far[r1] else None
                )
            runs.append(_Run(int(faces[i0]), s, uv, step, vids[r], vids[r1], n_seg, zc, j, moved))
        return runs

    def _suspect_segments(self, ring: list[int], face_of: dict[int, int]) -> list[int]:
        """The segments of ``ring`` (by their start's position) that leave or reach a vertex inside a
        face against the exact curve's own direction there, where the ring turns sharply (see
        ``_excursion_runs``); only segments in ``face_of`` (vertex id -> face of the segment it
        starts) are looked at."""
        n = len(ring)
        if n < 3:
            return []
        xyz = self.pool.xyz
        p = xyz[ring, :2]
        d = np.roll(p, -1, axis=0) - p
        length = np.hypot(d[:, 0], d[:, 1])
        unit = d / np.where(length > 0, length, 1.0)[:, None]
        turn = np.einsum("ij,ij->i", np.roll(unit, 1, axis=0), unit)
        sharp = (turn < EXCURSION_TURN_COS) & (length > 1e-9) & (np.roll(length, 1) > 1e-9)
        if not sharp.any():
            return []
        faces = self.mesh.faces
        suspects: set[int] = set()  # segments against the curve's direction at an end
        for i in np.flatnonzero(sharp).tolist():
            v = ring[i]
            if v in self.corner_vids:  # at a corner the turn is the B-rep's
                continue
            for k in (i, (i - 1) % n):  # the segment leaving v, the one reaching it
                face = face_of.get(ring[k])
                if face is None or k in suspects:
                    continue
                direction = faces[face].section_direction(*_uv_of(faces[face], xyz[v]))
                if direction is not None and np.dot(direction, unit[k]) < EXCURSION_TANGENT_COS:
                    suspects.add(k)
        return sorted(suspects)

    def _excursion_runs(
        self, ring: list[int], face_of: dict[int, int], li: int, *, stretches: bool
    ) -> list[tuple[int, int, _Run]]:
        """Runs that re-sample the pieces of loop ``li``'s sampled ``ring`` along which the exact
        curve goes where the ring does not: (i, j, run) for the piece ring[i] -> ring[j] (j > i;
        indices modulo the ring's length), the vertices between to be replaced by the run's.
        ``face_of``: the face of the segment that starts at each vertex id (segments not in it are
        left alone).

        Where a plane grazes a crest that is not a level ridge line (ec_soapbox-A's rounded rim turned
        35 degrees), the section has a narrow tongue (0.07 mm wide, 1 mm long) whose tip the topology
        mesh's cut stops short of (by 0.73 mm): the seeds turn back early, and the segment across the
        tongue passes its midpoint test on whichever side Newton lands. Finer topology meshes cut such
        a tongue many times over, and their exact crossings come in the wrong order: the ring
        zigzags between its sides. Either way a segment leaves (or reaches) a vertex against the
        curve's own direction there (the loops' direction, from the surface normal). Looked for where
        the ring turns sharply at a vertex inside a face, such segments are followed along the exact
        curve (``FaceEval.trace_level``) and sampled again with the trace as seeds, where the trace
        departs from them by more than the budget: each alone (``stretches`` False: the ring's
        vertices are kept, as a pinned loop's crossings must be), or the whole stretch from the
        vertex before the first such segment to the vertex after the last one of a cluster, the
        vertices between dropped.
        """
        n = len(ring)
        ks = self._suspect_segments(ring, face_of)
        if not ks:
            return []
        xyz = self.pool.xyz
        p = xyz[ring, :2]
        corner = np.array([v in self.corner_vids for v in ring], dtype=bool)
        if stretches:
            # clusters never across a corner: a stretch is traced on one face (M6-1x12-countersunk-screw
            # turned had suspects either side of the ring's end, a corner between them)
            pieces = []
            cidx = np.flatnonzero(corner)
            run = np.searchsorted(cidx, ks, side="right") % max(1, len(cidx))
            for r in sorted(set(run.tolist())):
                pieces += _clusters(
                    [k for k, q in zip(ks, run.tolist(), strict=True) if q == r], n, EXCURSION_CLUSTER_GAP
                )
            pieces.sort()
        else:
            pieces = [(k, k + 1) for k in ks]
        out = []
        taken: set[int] = set()  # vertices of the stretches so far (widened ones must not overlap)

        def span(a: int, b: int) -> set[int]:  # the ring positions of stretch a -> b, ends included
            return {k % n for k in range(a, b + 1)}

        for i, j in pieces:
            face = face_of.get(ring[i])
            if stretches and face is not None:
                i, j = self._inside_ends(ring, face_of, face, corner, i, j)
                here = span(i, j)
                if here & taken:
                    if not here <= taken:  # (inside a stretch already re-sampled: nothing to do)
                        self.stats.excursion_failures += 1
                    continue
            inner = [k % n for k in range(i + 1, j)]
            if face is None or corner[inner].any() or any(face_of.get(ring[k]) != face for k in inner):
                self.stats.excursion_failures += 1  # crosses a face boundary: not traced
                continue
            run = self._stretch_run(li, ring, p, face, i, j)
            if run is None and stretches:
                # Out of order over a bend the trace from ring[i] cannot reach ring[j] from (the
                # ring passes M6-1x12-countersunk-screw's U-shaped section four times, the trace
                # runs up its other branch and off the face): the whole run between the corners
                # either side, traced from one to the other.
                # (Stretches of the run re-sampled already are replaced with the rest of it.)
                wide = self._run_ends(ring, face_of, face, corner, i, j)
                if wide is not None:
                    whole = span(*wide)
                    inside = [o for o in out if span(o[0], o[1]) <= whole]
                    freed = set().union(*(span(o[0], o[1]) for o in inside))
                    if (taken - freed) & whole:
                        wide = None  # it would overlap a stretch beyond the run
                if wide is not None:
                    wide_run = self._stretch_run(li, ring, p, face, *wide)
                    if wide_run is not None:
                        out = [o for o in out if o not in inside]
                        taken -= freed
                        (i, j), run = wide, wide_run
            if run is not None:
                out.append((i, j, run))
                if stretches:
                    taken |= span(i, j)
        return out

    def _stretch_run(self, li: int, ring: list[int], p: np.ndarray, face: int, i: int, j: int) -> _Run | None:
        """``_traced_run`` of loop ``li``'s ring (its x/y ``p``) from ring[i] to ring[j] on ``face``
        (indices modulo its length, j > i): the ring's vertices between them as ``between``, its
        segments beside the stretch as ``elsewhere``."""
        n = len(ring)
        plane = int(self.topo.loops[li][0])
        return self._traced_run(
            face,
            ring[i % n],
            ring[j % n],
            float(self.topo.planes[plane]),
            plane,
            between=[ring[k % n] for k in range(i + 1, j)],
            elsewhere=_segments_beside(p, i, j),
        )

    def _run_ends(
        self, ring: list[int], face_of: dict[int, int], face: int, corner: np.ndarray, i: int, j: int
    ) -> tuple[int, int] | None:
        """The stretch ring[i] -> ring[j] widened to the corners either side of it, if those bound a
        run of ``face`` alone, short of the whole ring (else None)."""
        n = len(ring)
        while not corner[i % n]:
            i -= 1
            if j - i >= n - 1 or face_of.get(ring[i % n]) != face:
                return None
        while not corner[j % n]:
            if face_of.get(ring[j % n]) != face:
                return None
            j += 1
            if j - i >= n - 1:
                return None
        return i, j

    def _inside_ends(
        self, ring: list[int], face_of: dict[int, int], face: int, corner: np.ndarray, i: int, j: int
    ) -> tuple[int, int]:
        """The stretch ring[i] -> ring[j] of ``face`` widened to ends inside the face's trim (or at a
        corner): out of order, a finer topology mesh's crossings near a face's edge can have Newton
        put points on the surface's extension beyond it (boxed_sphere turned: a spur 0.08 mm past
        the edge and back), where no trace along the face can reach them. At most a stretch short
        of the whole ring."""
        n = len(ring)

        def outside(k: int) -> bool:
            v = ring[k % n]
            return not corner[k % n] and face_of.get(v) == face and not self._in_trim(face, v)

        while j - i < n - 2 and outside(j):
            j += 1
        while j - i < n - 2 and outside(i):
            i -= 1
        return i, j

    def _traced_run(
        self,
        face: int,
        a: int,
        b: int,
        zc: float,
        plane: int,
        *,
        between: Sequence[int] = (),
        elsewhere: np.ndarray | None = None,
    ) -> _Run | None:
        """The run from vertex ``a`` to vertex ``b`` of face ``face`` along the exact curve through
        them (seeded by a trace from a), or None if the trace fails (counted) or, where the ring has
        no vertices ``between`` a and b, if the chord a-b is within budget of that curve. (With
        vertices between, out of order, the run replaces them even where the curve keeps to the
        chord: boxed_sphere turned, 340 vertices fanning back and forth over a 0.2 mm bend.)
        A trace that runs along the ring's other segments (``elsewhere``, (m, 2, 2) x/y) went round
        a piece of the section the ring has already (bug24595_281390 turned: 11.8 mm to join points
        4.6 mm apart): a failure too."""
        xyz = self.pool.xyz
        ev = self.mesh.faces[face]
        uv_a = _uv_of(ev, xyz[a])
        b_direction = ev.section_direction(*_uv_of(ev, xyz[b]))
        if b_direction is None:
            self.stats.excursion_failures += 1
            return None
        try:
            trace = ev.trace_level(
                *uv_a,
                zc,
                (float(xyz[b, 0]), float(xyz[b, 1])),
                b_direction,
                step=self.seg_len,
                max_length=self.trace_reach,
            )
        except ExactFailure:
            self.stats.excursion_failures += 1
            return None
        tr = np.array(trace).reshape(-1, 4)
        path = np.vstack([xyz[a, :2], tr[:, :2], xyz[b, :2]])
        s = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(path, axis=0).T))])
        if elsewhere is not None and len(tr) and len(elsewhere):
            # near its ends the trace runs beside the ring's segments next to a and b: only points
            # beyond a segment budget of both are looked at
            look = (np.hypot(*(tr[:, :2] - xyz[a, :2]).T) > self.seg_len) & (
                np.hypot(*(tr[:, :2] - xyz[b, :2]).T) > self.seg_len
            )
            # Round a loop smaller than the budget (trj4_k1_top-pe-214 at z = 1.3: a trace from a
            # crossing to the one just behind it lapped a 2.3 mm hole, every point within 0.8 mm
            # of the ends; three laps were spliced into one ring) that leaves nothing: a trace as
            # long as half the rest of the ring is also looked at along its middle half.
            rest = float(np.linalg.norm(elsewhere[:, 1] - elsewhere[:, 0], axis=1).sum())
            if s[-1] >= 0.5 * rest:
                look |= (s[1:-1] > 0.25 * s[-1]) & (s[1:-1] < 0.75 * s[-1])
            away = tr[look, :2]
            if len(away) and distances_to_segments(away, elsewhere).min() <= CHORD_FILL * self.chord:
                self.stats.excursion_failures += 1
                return None
        on_plane = np.column_stack([tr[:, :2], np.full(len(tr), xyz[a, 2])])
        ends = np.broadcast_to(xyz[a], on_plane.shape), np.broadcast_to(xyz[b], on_plane.shape)
        if not len(tr) or point_segment_distance(on_plane, *ends).max() <= CHORD_FILL * self.chord:
            if not between:
                return None  # the curve stays by the chord: the segment was right
            # the ring's vertices between, on the face, must be within reach of it: else the trace
            # arrived before an excursion they reach (boxed_sphere turned: ends 0.6 um apart, a
            # vertex between 0.047 mm out)
            on_face = [v for v in between if self._in_trim(face, v)]
            if on_face:
                pts = xyz[on_face]
                far = point_segment_distance(pts, *(np.broadcast_to(xyz[q], pts.shape) for q in (a, b)))
                # farther than half the chord: beyond any arc of a half turn from a to b, which the
                # run (sampled from its seed path to the budget) would follow; the points the rest
                # of the ring passes are not lost
                reach = max(self.chord, 0.5 * float(np.linalg.norm(xyz[b, :2] - xyz[a, :2])))
                away = pts[far > reach, :2]
                if len(away) and (
                    elsewhere is None
                    or not len(elsewhere)
                    or distances_to_segments(away, elsewhere).max() > self.chord
                ):
                    self.stats.excursion_failures += 1
                    return None
        uv = np.vstack([uv_a, tr[:, 2:], ev.uv_near(tuple(xyz[b]), tuple(tr[-1, 2:] if len(tr) else uv_a))])
        step = 2.0 * float(np.linalg.norm(np.diff(uv, axis=0), axis=1).max())
        n_seg = max(2, math.ceil(s[-1] / (self.seg_len * SEGMENT_FILL)))
        return _Run(face, s, uv, step, a, b, n_seg, zc, plane, traced=len(tr) > 0)

    def _seeds_toward_exact_ends(self, face: int, uv: np.ndarray, s: np.ndarray, start, end) -> np.ndarray:
        """A run's seed path moved with its ends: where an exact end lies far from its topology
        crossing (``start``/``end`` its position, else None), the (u, v) displacement of that end,
        fading linearly along the run's arc length. The topology path of a plane a few micrometres
        below a ridge runs on the far side of the ridge's top line (its triangles span the ridge), and
        Newton from seeds there lands on the section's other branch; moved with the ends (which were
        solved on the right one), they seed the right branch."""
        ev = self.mesh.faces[face]
        shift = np.zeros((2, 2))
        for k, (end_xyz, idx) in enumerate(((start, 0), (end, -1))):
            if end_xyz is not None:
                # on the seed's period of a periodic surface (uv_near): the same point
                shift[k] = np.subtract(ev.uv_near(tuple(end_xyz), tuple(uv[idx])), uv[idx])
        w = (s / s[-1])[:, None] if s[-1] > 0 else np.zeros((len(s), 1))
        return uv + (1.0 - w) * shift[0] + w * shift[1]

    def pinned_loop(self, li: int) -> list[int]:
        """Ring of a pinned loop: every topology crossing, plus points where a segment breaks the budget.

        A segment joining two nodes that lie in the plane runs along a topology edge lying in it; a
        loop may pass such an edge twice (there and back along a line where the surface touches the
        plane). Its points are sampled once and shared, in ``edge_subdiv``, with both passes and with
        every kept triangle on that edge.
        """
        topo = self.topo
        j, cross = topo.loops[li]
        zc = float(topo.planes[j])
        cl = cross.tolist()
        faces = self.mesh.tri_face[topo.seg_tri[cross]]
        corner = topo.cross_is_corner[cross] | (faces != np.roll(faces, 1))
        vids = [self.crossing(c) for c in cl]
        # per crossing, at once: its successor's position in the loop, the exact segment length, and
        # how far the exact point moved from the topology crossing
        pos = {c: i for i, c in enumerate(cl)}
        nxt_pos = np.array([pos[int(c)] for c in topo.succ[cross].tolist()], dtype=np.int64)
        if self.off_trim:
            self._drop_off_trim(cl, vids, nxt_pos)
        self.corner_vids.update(v for v, k in zip(vids, corner.tolist(), strict=True) if k)
        exact = self.pool.xyz[vids]
        seg_d = np.linalg.norm(exact[nxt_pos] - exact, axis=1).tolist()
        gap = np.linalg.norm(exact - topo.cross_xyz[cross], axis=1)
        far = (gap > SUSPECT_DEFLECTIONS * self.mesh.deflection).tolist()
        step_of = (2.0 * self.tri_uv_scale[topo.seg_tri[cross]]).tolist()
        es = self.edge_subdiv
        runs, sampled, repeats = [], [], []
        for i, c in enumerate(cl):
            if c in self.subdiv:
                continue
            k = int(nxt_pos[i])
            if vids[i] == vids[k] and (c in self.off_trim or cl[k] in self.off_trim):  # _drop_off_trim
                self.subdiv[c] = []
                continue
            nxt = cl[k]
            na, nb = int(topo.cross_node[c]), int(topo.cross_node[nxt])
            key = (min(na, nb), max(na, nb)) if na >= 0 and nb >= 0 and na != nb else None
            if key is not None and key in es:
                self.subdiv[c] = es[key] if na < nb else es[key][::-1]
                continue
            if key is not None and any(q == key for _, q in sampled):
                repeats.append((c, key, na < nb))
                continue
            uv = np.stack([topo.cross_uv_start[c], topo.cross_uv_end[c]])
            t = int(topo.seg_tri[c])
            moved = tuple((exact[q].copy(), float(gap[q]) + self.seg_len) for q in (i, k) if far[q])
            if moved:
                uv = self._seeds_toward_exact_ends(
                    int(self.mesh.tri_face[t]),
                    uv,
                    np.array([0.0, seg_d[i]]),
                    exact[i] if far[i] else None,
                    exact[k] if far[k] else None,
                )
            runs.append(
                _Run(
                    int(self.mesh.tri_face[t]),
                    np.array([0.0, seg_d[i]]),
                    uv,
                    step_of[i],
                    vids[i],
                    vids[k],
                    1,
                    zc,
                    j,
                    moved,
                )
            )
            sampled.append((c, key))
        here: dict[tuple[int, int], list[int]] = {}  # this loop's in-plane edges, low node to high
        for (c, key), run_pts in zip(sampled, self._sample_runs(runs), strict=True):
            inner = run_pts[1:-1]
            self.subdiv[c] = inner
            if key is not None:
                here[key] = inner if int(topo.cross_node[c]) == key[0] else inner[::-1]
                if inner:  # kept triangles on this edge must use the same points
                    es[key] = here[key]
        for c, key, forward in repeats:
            self.subdiv[c] = here[key] if forward else here[key][::-1]
        ring = self._pinned_ring(cl)
        # excursions the crossings skipped: spliced into their segments' points (which the kept
        # triangles on those segments use too). Segments along an edge lying in the plane (their
        # points shared with other passes over that edge) are left alone.
        starts: dict[int, tuple[int, int]] = {}  # vertex id -> (crossing, position in its segment)
        twice: set[int] = set()  # vertices the loop passes twice (a node on the plane)
        for c in cl:
            for at, v in enumerate([self.crossing(c), *self.subdiv[c]]):
                if v in starts:
                    twice.add(v)
                else:
                    starts[v] = (c, at)
        in_plane = (topo.cross_node[cross] >= 0) & (topo.cross_node[topo.succ[cross]] >= 0)
        face_of = {
            v: int(self.mesh.tri_face[topo.seg_tri[c]])
            for v, (c, _) in starts.items()
            if v not in twice and not in_plane[pos[c]]
        }
        if not self.keep_crossings:
            rings = {li: ring}
            self._replace_excursions(rings, face_of)
            return rings[li]
        if self._retrace_segments(li, cl, ring, starts, face_of):
            ring = self._pinned_ring(cl)
        runs = self._excursion_runs(ring, face_of, li, stretches=False)
        if not runs:
            return ring
        for (k, _, run), run_pts in zip(runs, self._sample_traced([r for *_, r in runs]), strict=True):
            if run_pts is None:
                continue
            c, at = starts[ring[k]]
            segment = [self.crossing(c), *self.subdiv[c], self.crossing(int(topo.succ[c]))]
            if segment[at + 1] != run.end:  # the ring's next vertex is not this segment's: leave it
                self.stats.excursion_failures += 1
                continue
            sub = self.subdiv[c]
            self.subdiv[c] = sub[:at] + run_pts[1:-1] + sub[at:]
            self.stats.excursions += 1
        return self._pinned_ring(cl)

    def _retrace_segments(
        self,
        li: int,
        cl: list[int],
        ring: list[int],
        starts: dict[int, tuple[int, int]],
        face_of: dict[int, int],
    ) -> bool:
        """Re-sample (in ``subdiv``) the segments of pinned loop ``li`` (crossings ``cl``, sampled
        ``ring``) whose points go against the exact curve (``_suspect_segments``), each whole from
        its crossing to the next along a trace of the exact curve: its inner points are not
        pinned. Where the plane grazes a crest, a segment's curve can run round the tip of a tongue
        the topology mesh does not reach (r103ec turned (35.3, -158.7, -40.5) at z = 54.3: 0.3 mm
        beyond the crossings), and its seeds, across the tongue, put points on either side of it
        in turn: a zigzag that re-sampling its segments one by one keeps. A segment is replaced only
        where the new points pass within the budget of every old point on the face (the old ones
        are exact points of the curve). Whether any was replaced."""
        ks = self._suspect_segments(ring, face_of)
        if not ks:
            return False
        n = len(ring)
        at_pos = {v: i for i, v in enumerate(ring)}
        succ = self.topo.succ
        segs: dict[int, tuple[int, int]] = {}  # crossing -> ring positions of its segment's ends
        for k in ks:
            c, _ = starts[ring[k]]
            if c in segs or not self.subdiv.get(c):
                continue
            i = at_pos.get(self.crossing(c))
            end = self.crossing(int(succ[c]))
            if i is None or end == ring[i]:
                continue
            j = i + len(self.subdiv[c]) + 1
            if ring[j % n] != end or j - i >= n - 1:  # (the ring deduplicated points of it)
                continue
            # on one face, no vertex of it passed twice (such are not in face_of: trj7_b1-ec-214)
            faces = {face_of.get(ring[q % n]) for q in range(i, j)}
            if None in faces or len(faces) != 1:
                continue
            segs[c] = (i, j)
        xyz = self.pool.xyz
        found = []
        for c, (i, j) in segs.items():
            run = self._stretch_run(li, ring, xyz[ring, :2], face_of[ring[i]], i, j)
            if run is not None and run.traced:
                found.append((c, i, j, run))
        if not found:
            return False
        replaced = False
        for (c, i, j, _), pts in zip(found, self._sample_traced([f[3] for f in found]), strict=True):
            if pts is None:
                continue
            piece = (i, j, pts[1:-1])
            if self._lost_pieces(ring, [piece], _splice(ring, [piece]), face_of):
                self.stats.excursion_failures += 1
                continue
            self.subdiv[c] = pts[1:-1]
            self.stats.excursions += 1
            replaced = True
        return replaced

    def traced_loop(self, li: int) -> list[int] | None:
        """A ring of loop ``li`` from the exact section curve alone, for a loop on one face with no
        corner: traced once round from its first crossing's exact point, then sampled to the budget
        as two traced runs (from there to the trace's middle point and back). None where the loop
        does not qualify or the trace or the sampling fails. (For a pinned loop whose crossings lie
        so far inside a small curve that their exact points come out of order: ``tessellate``.)"""
        topo = self.topo
        j, cross = topo.loops[li]
        faces = np.unique(self.mesh.tri_face[topo.seg_tri[cross]])
        if len(faces) != 1 or topo.cross_is_corner[cross].any() or (topo.cross_node[cross] >= 0).any():
            return None
        face = int(faces[0])
        zc = float(topo.planes[j])
        ev = self.mesh.faces[face]
        a = self.crossing(int(cross[0]))
        xyz = self.pool.xyz
        uv_a = _uv_of(ev, xyz[a])
        direction = ev.section_direction(*uv_a)
        if direction is None:
            return None
        try:
            trace = ev.trace_level(
                *uv_a,
                zc,
                (float(xyz[a, 0]), float(xyz[a, 1])),
                direction,
                step=self.seg_len,
                max_length=self.trace_reach,
                min_length=1e-9,  # leaves its start behind at once: arrives there once round
            )
        except ExactFailure:
            return None
        if len(trace) < 2:
            return None
        x, y, _, _ = trace[len(trace) // 2]
        m = self.pool.add((x, y, zc), j)
        runs = [self._traced_run(face, a, m, zc, j), self._traced_run(face, m, a, zc, j)]
        if any(run is None for run in runs):
            return None
        halves = self._sample_traced(runs)
        if any(h is None for h in halves):
            return None
        return _dedupe_cyclic(halves[0][:-1] + halves[1][:-1], self.pool)

    def _pinned_ring(self, cl: list[int]) -> list[int]:
        """The ring of a pinned loop's crossings ``cl`` (after ``pinned_loop``): each crossing, then
        its segment's inner points."""
        out: list[int] = []
        for c in cl:
            out.append(self.crossing(c))
            out.extend(self.subdiv[c])
        return _dedupe_cyclic(out, self.pool)

    def _drop_off_trim(self, cl: list[int], vids: list[int], nxt_pos: np.ndarray) -> None:
        """Drop (in place, and for every triangle that uses it) each crossing of this loop whose root
        lies beyond its face's trim: it becomes the vertex of the nearer of the ring neighbours that
        bracket it (an edge collapse: the triangles between the two vanish, the others keep the mesh
        closed). Such a root lies on the surface's extension, not on the B-rep; the crossing's
        topology edge is inside one face, so its neighbours' segment runs across that face, and is
        sampled there like any other. (bug27453 at z = 35.9: a root 0.0066 mm off the B-rep between
        the roots of a sliver's two boundary edges, 0.0011 mm apart.)"""
        n = len(cl)
        off = np.array([c in self.off_trim and self.topo.cross_node[c] < 0 for c in cl], dtype=bool)
        if not off.any() or off.all():
            return
        prev_pos = np.empty(n, dtype=np.int64)
        prev_pos[nxt_pos] = np.arange(n)
        xyz = self.pool.xyz
        for i in np.flatnonzero(off).tolist():
            p = q = i
            while off[p]:
                p = int(prev_pos[p])
            while off[q]:
                q = int(nxt_pos[q])
            near = self.topo.cross_xyz[cl[i]]
            a, b = vids[p], vids[q]
            keep = a if np.linalg.norm(xyz[a] - near) <= np.linalg.norm(xyz[b] - near) else b
            self.cross_vid[cl[i]] = vids[i] = keep
            self.stats.off_trim_crossings += 1

    def pinned_segment(self, c: int) -> list[int]:
        """Inner vertices of the pinned segment starting at crossing ``c`` (after ``pinned_loop``)."""
        return self.subdiv[c]

    # --- the batched sampler -------------------------------------------------------------------------
    def _sample_runs(self, runs: list[_Run]) -> list[list[int]]:
        """Vertex ids of each run from start to end inclusive, within the length and chord budgets.

        A run crossing a line where its face's surface is only C0 (a kink inside one B-spline face)
        is first split there at the exact section point on that line: the section has a corner
        there, which a midpoint test on a segment straddling it can miss.
        """
        if not runs:
            return []
        pieces, owner = self._split_at_kinks(runs)
        if len(pieces) == len(runs):
            return self._sample_pieces(runs)
        out: list[list[int]] = [[] for _ in runs]
        for i, ids in zip(owner, self._sample_pieces(pieces), strict=True):
            out[i].extend(ids if not out[i] else ids[1:])
        return out

    def _surface_kinks(self, f: int) -> tuple[np.ndarray, np.ndarray]:
        """Interior parameter lines of face ``f`` where its surface is not C1 (C0 knots of a B-spline)."""
        got = self._kinks.get(f)
        if got is None:
            ad, fe = self._ads[f], self.mesh.faces[f]
            lines = []
            for n, fill, lo, hi in (
                (ad.NbUIntervals(GeomAbs_C1), ad.UIntervals, fe.u0, fe.u1),
                (ad.NbVIntervals(GeomAbs_C1), ad.VIntervals, fe.v0, fe.v1),
            ):
                k = np.empty(0)
                if n > 1:
                    arr = Array1_double(1, n + 1)
                    fill(arr, GeomAbs_C1)
                    k = np.array([arr.Value(i) for i in range(2, n + 1)])
                    margin = KINK_MARGIN_REL * (hi - lo)
                    k = k[(k > lo + margin) & (k < hi - margin)]
                lines.append(k)
            got = self._kinks[f] = (lines[0], lines[1])
        return got

    def _split_at_kinks(self, runs: list[_Run]) -> tuple[list[_Run], list[int]]:
        """Runs cut where their seed path crosses a C0 line of their face, and each piece's run index."""
        pieces: list[_Run] = []
        owner: list[int] = []
        for i, run in enumerate(runs):
            cuts = self._kink_points(run)
            if not cuts:
                pieces.append(run)
                owner.append(i)
                continue
            bounds = [(0.0, run.uv[0], run.start)] + cuts + [(float(run.s[-1]), run.uv[-1], run.end)]
            for (sa, uva, va), (sb, uvb, vb) in zip(bounds[:-1], bounds[1:], strict=True):
                inner = (run.s > sa) & (run.s < sb)
                s_ = np.concatenate([[sa], run.s[inner], [sb]]) - sa
                uv = np.concatenate([[uva], run.uv[inner], [uvb]])
                # the run's segments shared out by length (keeps a tiny loop's minimum count)
                n_seg = max(1, math.ceil(run.n_seg * s_[-1] / max(float(run.s[-1]), 1e-300)))
                pieces.append(
                    _Run(
                        run.face,
                        s_,
                        uv,
                        run.max_step,
                        va,
                        vb,
                        n_seg,
                        run.zc,
                        run.plane,
                        run.moved,
                        run.traced,
                    )
                )
                owner.append(i)
        return pieces, owner

    def _kink_points(self, run: _Run) -> list[tuple[float, np.ndarray, int]]:
        """(arc length, (u, v), vertex id) of the exact section points on the C0 lines the run crosses."""
        ku, kv = self._surface_kinks(run.face)
        if not (ku.size or kv.size):
            return []
        ev = self.mesh.faces[run.face]
        ends_uv: list[tuple[float, float]] = []  # the run's exact ends' (u, v), found when needed

        def ends_straddle(axis: int, k: float) -> bool:
            """Whether the run's exact ends lie on either side of the line (or one on it)."""
            if not ends_uv:
                ends_uv.extend(
                    ev.uv_near(tuple(map(float, self.pool.xyz[v])), tuple(map(float, uv)))
                    for v, uv in ((run.start, run.uv[0]), (run.end, run.uv[-1]))
                )
            return (ends_uv[0][axis] - k) * (ends_uv[1][axis] - k) <= 0.0

        cuts = []
        for axis, lines in ((0, ku), (1, kv)):
            w = run.uv[:, axis]
            for k in lines.tolist():
                side = w - k
                # a seed path crosses the line between two of its points, or at one (the topology
                # mesh has its nodes on the knot lines)
                on = np.abs(side) <= KINK_MARGIN_REL * max(abs(k), 1.0)
                side = np.where(on, 0.0, side)
                cross = np.flatnonzero((side[:-1] * side[1:] < 0) | on[:-1])
                for i in cross.tolist():
                    if on[i] and i == 0:
                        continue  # the run's start
                    t = side[i] / (side[i] - side[i + 1]) if not on[i] else 0.0
                    seed = run.uv[i] + t * (run.uv[i + 1] - run.uv[i])
                    hit = self._on_iso_line(run, axis, k, float(seed[1 - axis]))
                    # beyond the face's trim the line is crossed on the surface's extension, not on
                    # the B-rep (past a corner of the run: tangent_features turned (-178.1, 115.6,
                    # 106.9) had a corner 2.3 um off its faces at z = 9.9)
                    if hit is not None and not ev.contains(*hit[0], tol=TRIM_TOL_MM):
                        self.stats.outside_face_points += 1
                        hit = None
                    # The seed path crosses the line, but the exact curve between the run's exact
                    # ends may not: an end solved past the line (boxed_sphere at z = 0.1, a rounded
                    # corner's C0 line 0.03 mm beyond the crossing) puts the line's point outside the
                    # run, and the ring would step back to it and forth again (a bow tie).
                    if hit is not None and ends_straddle(axis, k):
                        s_at = float(run.s[i] + t * (run.s[i + 1] - run.s[i]))
                        cuts.append((s_at, hit[0], hit[1]))
        cuts.sort(key=lambda c: c[0])
        kept, last = [], 0.0
        end = float(run.s[-1])
        for s_at, uv, xyz in cuts:
            if s_at - last > KINK_MIN_SPACING_REL * end and end - s_at > KINK_MIN_SPACING_REL * end:
                vid = self.pool.add((xyz[0], xyz[1], run.zc), run.plane)
                self.corner_vids.add(vid)
                self.stats.kink_corners += 1
                kept.append((s_at, uv, vid))
                last = s_at
        return kept

    def _on_iso_line(self, run: _Run, axis: int, k: float, w: float) -> tuple[np.ndarray, np.ndarray] | None:
        """The point at the run's height on the face's iso-line (u = k if axis is 0, else v = k),
        by Newton along it from the other parameter ``w``; None if it does not converge nearby."""
        ad = self._ads[run.face]
        p, du, dv = gp_Pnt(), gp_Vec(), gp_Vec()
        w0 = w
        for _ in range(NEWTON_MAX_ITER):
            u, v = (k, w) if axis == 0 else (w, k)
            ad.D1(u, v, p, du, dv)
            f = p.Z() - run.zc
            if abs(f) < LEVEL_TOL_MM:
                if abs(w - w0) > run.max_step:
                    return None
                return np.array([u, v]), np.array(p.Coord())
            dz = (dv if axis == 0 else du).Z()
            if dz == 0.0:
                return None
            step = -f / dz
            w += max(-run.max_step, min(run.max_step, step))
        return None

    def _sample_pieces(self, runs: list[_Run]) -> list[list[int]]:
        # All runs' seed paths in one array, each shifted past the previous, so that one np.interp
        # call seeds every point of every run.
        lengths = np.array([r.s[-1] for r in runs])
        shift = np.concatenate([[0.0], np.cumsum(lengths + 1.0)[:-1]])
        big_s = np.concatenate([r.s + sh for r, sh in zip(runs, shift, strict=True)])
        big_u = np.concatenate([r.uv[:, 0] for r in runs])
        big_v = np.concatenate([r.uv[:, 1] for r in runs])
        run_face = np.array([r.face for r in runs])
        run_step = np.array([r.max_step for r in runs])
        run_z = np.array([r.zc for r in runs])
        run_plane = np.array([r.plane for r in runs], dtype=np.int64)
        run_traced = np.array([r.traced for r in runs], dtype=bool)

        def solve(run_idx: np.ndarray, s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
            g = s + shift[run_idx]
            u, v = np.interp(g, big_s, big_u), np.interp(g, big_s, big_v)
            return self._newton(run_face[run_idx], u, v, run_z[run_idx], run_step[run_idx])

        # Every point of every run in flat arrays (run, arc length, xyz, vertex id or -1 for a new
        # point); segments to check are pairs of points, refined level by level, all runs together.
        n_runs = len(runs)
        first = np.array([r.start for r in runs], dtype=np.int64)
        last = np.array([r.end for r in runs], dtype=np.int64)
        n_inner = np.array([max(r.n_seg - 1, 0) for r in runs], dtype=np.int64)
        seed_run = np.repeat(np.arange(n_runs), n_inner)
        k = np.arange(len(seed_run)) - np.repeat(np.cumsum(n_inner) - n_inner, n_inner) + 1
        n_seg = np.array([r.n_seg for r in runs], dtype=np.float64)
        seed_s = lengths[seed_run] * k / n_seg[seed_run]
        seed_xyz, seed_ok, seed_uv = (
            solve(seed_run, seed_s)
            if len(seed_run)
            else (np.empty((0, 3)), np.empty(0, bool), np.empty((0, 2)))
        )
        seed_run, seed_s, seed_xyz, seed_uv = (
            seed_run[seed_ok],
            seed_s[seed_ok],
            seed_xyz[seed_ok],
            seed_uv[seed_ok],
        )
        pool_xyz = self.pool.xyz
        run_all = [np.arange(n_runs), seed_run, np.arange(n_runs)]
        s_all = [np.zeros(n_runs), seed_s, lengths]
        xyz_all = [pool_xyz[first], seed_xyz, pool_xyz[last]]
        no_uv = np.full((n_runs, 2), np.nan)  # run ends: existing vertices, never checked against the trim
        uv_all = [no_uv, seed_uv, no_uv]
        vid_all = [first, np.full(len(seed_run), -1, dtype=np.int64), last]

        # the first segments: consecutive points of each run (starts, seeds and ends sorted by run, s)
        ri, s_, xyz = np.concatenate(run_all), np.concatenate(s_all), np.concatenate(xyz_all)
        order = np.lexsort((s_, ri))
        ri, s_, xyz = ri[order], s_[order], xyz[order]
        pair = np.flatnonzero(ri[1:] == ri[:-1])
        pending = (ri[pair], s_[pair], s_[pair + 1], xyz[pair], xyz[pair + 1])

        L, e = self.seg_len, self.chord

        finer: list[tuple] = []  # halves (``halving``) whose own check failed: checked as any other

        def refine(pending: tuple, forced: bool = False, halving: bool = False) -> bool:
            # each round: the pending segments checked, the bad ones split into the next round's
            # (``forced``: checked at their quarter points too, wherever their midpoints lie;
            # ``halving``: checked at HALVING_FACTOR times the chord, see ``_halves``)
            worst = ""
            split = False
            budget = HALVING_FACTOR * e if halving else e
            for _ in range(MAX_REFINE_ROUNDS):
                ri, sa, sb, pa, pb = pending
                if not len(ri):
                    return split
                mid, mid_ok, mid_uv = solve(ri, 0.5 * (sa + sb))
                length = np.linalg.norm(pb - pa, axis=1)
                off_path = self._midpoints_off_the_path(
                    run_face[ri], run_z[ri], run_step[ri], mid, mid_ok, pa, pb, length, run_traced[ri], mid_uv
                )
                sag = np.where(mid_ok, point_segment_distance(np.nan_to_num(mid), pa, pb), 0.0)
                # midpoints placed by their path position in their chord's middle half (not solved
                # again from the chord, not on a trace): where a segment may be halved (``_halves``)
                halvable = None
                if halving:
                    t_mid = _chord_position(np.nan_to_num(mid), pa, pb)
                    halvable = ~off_path & ~run_traced[ri] & (t_mid >= 0.25) & (t_mid <= 0.75)
                quarters, q_ok = self._quarter_sags(
                    solve,
                    sag,
                    mid,
                    mid_ok,
                    length,
                    pending,
                    run_traced[ri],
                    everywhere=forced,
                    budget=budget,
                    halvable=halvable,
                )
                bad = (length > L) | (sag > CHORD_FILL * budget)
                deep = ~bad & (sag > 0.25 * e) & (sag > DEEP_BEND_REL * length) & (length > 1e-9)
                self.stats.deep_bends += int(deep.sum())
                bad = (bad | deep) & (length > 1e-9)
                if halving:
                    over = np.flatnonzero(~bad & mid_ok & (sag > CHORD_FILL * e))
                    if len(over):
                        mid_s = 0.5 * (sa[over] + sb[over])
                        kept, again = self._halves(
                            pending, over, mid[over], mid_s, quarters[over], q_ok[over] & halvable[over, None]
                        )
                        run_all.append(ri[over][kept])
                        s_all.append(mid_s[kept])
                        xyz_all.append(mid[over][kept])
                        uv_all.append(mid_uv[over][kept])
                        vid_all.append(np.full(int(kept.sum()), -1, dtype=np.int64))
                        finer.append(again)
                forced = False  # (the parts of a segment checked everywhere: as any other)
                # No exact point halfway: the plane is tangent to the surface along this segment (the
                # section degenerates to a line or a point there). Keep the segment, count it.
                tangent = bad & ~mid_ok
                if tangent.any():
                    self.stats.tangent_segments += int(tangent.sum())
                    bad &= ~tangent
                # A segment whose seed interval has collapsed but which stays long bridges a gap in the
                # B-rep itself: near a plane tangent to a nearly horizontal edge, the face's level set and
                # the edge curve (equal only to the file's tolerance) cross the plane apart. No exact point
                # lies between; keep the segment and report it.
                gap = bad & ((sb - sa) < GAP_SPAN_REL * np.maximum(lengths[ri], 1.0))
                if gap.any():
                    self._record_gaps(gap, length, pa, pb, run_z[ri], run_face[ri])
                    bad &= ~gap
                if not bad.any():
                    return split
                split = True
                q = int(np.argmax(np.where(bad, sag, -1.0)))
                worst = (
                    f" (face {run_face[ri[q]] + 1}: sag {sag[q]:.3g} mm over {length[q]:.3g} mm, "
                    f"s {sa[q]:.6g}..{sb[q]:.6g} of {lengths[ri[q]]:.6g})"
                )
                b_idx = np.flatnonzero(bad)
                m = np.maximum.reduce(
                    [
                        np.full(len(b_idx), 2),
                        np.ceil(length[b_idx] / (L * SEGMENT_FILL)).astype(int),
                        np.ceil(np.sqrt(sag[b_idx] / budget) * 1.05).astype(int),
                    ]
                )
                m = np.minimum(m, MAX_SUBDIVISION)
                # m - 1 new points at equal steps of s inside each bad segment
                seg = np.repeat(np.arange(len(b_idx)), m - 1)
                k = np.arange(len(seg)) - np.repeat(np.cumsum(m - 1) - (m - 1), m - 1) + 1
                bq = b_idx[seg]
                ns = sa[bq] + (sb[bq] - sa[bq]) * k / m[seg]
                new_xyz, new_ok, new_uv = solve(ri[bq], ns)
                # A new point must fall inside its segment, and not onto an end (the k-th of m - 1 is
                # expected near k / m): one the seed path put elsewhere (a (u, v) path through a pole of
                # the face's parametrisation, or round a bend it does not follow) is solved again from
                # the chord's point projected on the face.
                t_new = _chord_position(np.nan_to_num(new_xyz), pa[bq], pb[bq])
                margin = 0.25 / m[seg]
                new_ok &= ((t_new > margin) & (t_new < 1.0 - margin)) | run_traced[ri[bq]]
                if not new_ok.all():
                    miss = np.flatnonzero(~new_ok)
                    frac = (k / m[seg])[miss]
                    guess = pa[bq][miss] + frac[:, None] * (pb[bq][miss] - pa[bq][miss])
                    xyz_m, ok_m, uv_m = self._solve_from_chord(
                        run_face[ri[bq]][miss],
                        run_z[ri[bq]][miss],
                        run_step[ri[bq]][miss],
                        guess,
                        pa[bq][miss],
                        pb[bq][miss],
                    )
                    new_xyz[miss[ok_m]], new_uv[miss[ok_m]], new_ok[miss[ok_m]] = (
                        xyz_m[ok_m],
                        uv_m[ok_m],
                        True,
                    )
                run_all.append(ri[bq][new_ok])
                s_all.append(ns[new_ok])
                xyz_all.append(new_xyz[new_ok])
                uv_all.append(new_uv[new_ok])
                vid_all.append(np.full(int(new_ok.sum()), -1, dtype=np.int64))
                # the chains start, new points, end of each bad segment; consecutive members are the
                # segments of the next round
                nb = len(b_idx)
                c_grp = np.concatenate([np.arange(nb), seg[new_ok], np.arange(nb)])
                c_key = np.concatenate([np.zeros(nb), k[new_ok], m.astype(np.float64)])
                c_s = np.concatenate([sa[b_idx], ns[new_ok], sb[b_idx]])
                c_xyz = np.concatenate([pa[b_idx], new_xyz[new_ok], pb[b_idx]])
                order = np.lexsort((c_key, c_grp))
                c_grp, c_s, c_xyz = c_grp[order], c_s[order], c_xyz[order]
                # no new point could be placed: keep it as a tangent segment
                self.stats.tangent_segments += int((np.bincount(seg[new_ok], minlength=nb) == 0).sum())
                pair = np.flatnonzero(c_grp[1:] == c_grp[:-1])
                pair = pair[np.bincount(seg[new_ok], minlength=nb)[c_grp[pair]] > 0]
                pending = (ri[b_idx][c_grp[pair]], c_s[pair], c_s[pair + 1], c_xyz[pair], c_xyz[pair + 1])
            else:
                raise TessellationError(f"section curves cannot meet the chord budget{worst}")

        refine(pending, halving=self.halving)
        if finer:
            refine(tuple(np.concatenate(parts) for parts in zip(*finer, strict=True)))
        # A run's end segment whose curve leaves the corner more steeply than a shallow arc within
        # the budget leaves its chord hides a bend next to the corner (boxed_sphere turned (36.3,
        # -159.6, 99.5) at z = 8.5: a 0.595 mm segment from a corner, 4 um from its midpoint, its
        # curve 0.0258 mm away 0.1 mm from the corner, where it left at 0.44 rad): checked at its
        # quarter points, and its new end segments again, until they leave as a shallow arc would.
        tangents = np.full((n_runs, 2, 2), np.nan)  # at each run's start and end, where needed
        known = np.zeros((n_runs, 2), dtype=bool)
        forced: set[tuple[int, float, float]] = set()
        for _ in range(MAX_END_BEND_ROUNDS):
            ri, s_, xyz = np.concatenate(run_all), np.concatenate(s_all), np.concatenate(xyz_all)
            order = np.lexsort((s_, ri))
            # the tangents at the ends of segments long enough to leave them too steeply
            ends = _end_segments(ri[order], xyz[order], END_BEND_FACTOR * 4.0 * e)
            run, end = ends[2:]
            todo = ~known[run, end]
            run, end = run[todo], end[todo]
            tangents[run, end] = self._end_tangents([runs[k] for k in run.tolist()], end)
            known[run, end] = True
            a, b = _end_bend_segments(xyz[order], ends, tangents, e)
            a, b = order[a], order[b]
            new = [
                k
                for k, key in enumerate(zip(ri[a].tolist(), s_[a].tolist(), s_[b].tolist(), strict=True))
                if key not in forced
            ]
            if not new:
                break
            a, b = a[new], b[new]
            forced.update(zip(ri[a].tolist(), s_[a].tolist(), s_[b].tolist(), strict=True))
            self.stats.end_bend_checks += len(a)
            refine((ri[a], s_[a], s_[b], xyz[a], xyz[b]), forced=True)
        # A segment whose curve turns one way near one end and the other way near the other has an
        # inflection inside, where its midpoint can lie on the chord with the curve off it on either
        # side: checked again at its quarter points (and split where it fails), until none is left.
        # After the first round only segments at or next to the points it added are looked at.
        checked = 0  # points before this index: their segments checked
        after = _run_successors(first, last)
        for _ in range(MAX_INFLECTION_ROUNDS):
            ri, s_, xyz = np.concatenate(run_all), np.concatenate(s_all), np.concatenate(xyz_all)
            order = np.lexsort((s_, ri))
            inflected = _inflected_segments(ri[order], xyz[order], after)
            if checked:
                new = order >= checked
                near = new | np.roll(new, 1) | np.roll(new, -1)
                inflected = inflected[near[inflected] | near[inflected + 1]]
            if not len(inflected):
                break
            a, b = order[inflected], order[inflected + 1]
            self.stats.inflection_checks += len(inflected)
            checked = len(s_)
            if not refine((ri[a], s_[a], s_[b], xyz[a], xyz[b]), forced=True):
                break

        ri, s_ = np.concatenate(run_all), np.concatenate(s_all)
        xyz, vid, uv = np.concatenate(xyz_all), np.concatenate(vid_all), np.concatenate(uv_all)
        order = np.lexsort((s_, ri))
        ri, xyz, vid, uv = ri[order], xyz[order], vid[order], uv[order]
        # new points must lie on their face: inside its (u, v) box, and near a run end that moved far
        # from its topology crossing, inside its trim
        new = np.flatnonzero(vid < 0)
        outside = self._off_face_box(run_face[ri[new]], uv[new])
        vid[new[outside]] = -2
        self.stats.outside_face_points += int(outside.sum())
        moved_runs = [i for i, r in enumerate(runs) if r.moved]
        if moved_runs:
            bounds = np.searchsorted(ri, np.arange(n_runs + 1))
            for r_i in moved_runs:
                r = runs[r_i]
                q = bounds[r_i] + np.flatnonzero(vid[bounds[r_i] : bounds[r_i + 1]] == -1)
                near = np.zeros(len(q), dtype=bool)
                for end, radius in r.moved:
                    near |= np.linalg.norm(xyz[q, :2] - end[:2], axis=1) <= radius
                for k in q[near].tolist():
                    if not self._inside_face(r, uv[k]):
                        vid[k] = -2
        keep = vid != -2
        dropped_before = np.cumsum(~keep)[keep]
        ri, xyz, vid = ri[keep], xyz[keep], vid[keep]
        if not keep.all():
            # a segment that now spans dropped points may exceed the budget: no exact point of this
            # face lies there, so it is a gap of the B-rep (reported with the others; segments kept
            # over budget during refinement were counted there already)
            spans = (ri[1:] == ri[:-1]) & (dropped_before[1:] != dropped_before[:-1])
            d = np.where(spans, np.linalg.norm(xyz[1:] - xyz[:-1], axis=1), 0.0)
            self._record_gaps(d > L, d, xyz[:-1], xyz[1:], run_z[ri[:-1]], run_face[ri[:-1]])
        new = np.flatnonzero(vid < 0)
        vid[new] = self.pool.extend(xyz[new, :2], run_z[ri[new]], run_plane[ri[new]])
        bounds = np.searchsorted(ri, np.arange(n_runs + 1))
        ids = vid.tolist()
        return [ids[bounds[i] : bounds[i + 1]] for i in range(n_runs)]

    def _off_face_box(self, face: np.ndarray, uv: np.ndarray) -> np.ndarray:
        """Mask of points whose face parameters lie beyond their face's (u, v) box."""
        box, chk = self._uv_box[face], self._box_checked[face]
        tol = 1e-9 * np.maximum(box[:, [1, 3]] - box[:, [0, 2]], 1.0)
        below = uv < box[:, [0, 2]] - tol
        above = uv > box[:, [1, 3]] + tol
        return ((below | above) & chk).any(axis=1)

    def _end_tangents(self, runs: list[_Run], end: np.ndarray) -> np.ndarray:
        """(k, 2): the unit xy tangent (either sense) of each of the runs' section curve at its start
        (``end`` 0) or end vertex (1), on the run's own face (its normal's horizontal part turned a
        quarter); NaN where the vertex is not found within END_TANGENT_TOL_MM of the face (a file's
        tolerance) or the face is nearly horizontal there. The vertices' (u, v) by batched
        Gauss-Newton from the seed path's ends."""
        k = len(runs)
        out = np.full((k, 2), np.nan)
        if not k:
            return out
        face = np.array([r.face for r in runs])
        target = self.pool.xyz[[r.end if w else r.start for r, w in zip(runs, end.tolist(), strict=True)]]
        uv = np.array([r.uv[-1] if w else r.uv[0] for r, w in zip(runs, end.tolist(), strict=True)])
        step = np.array([r.max_step for r in runs])
        p, du, dv = gp_Pnt(), gp_Vec(), gp_Vec()
        u, v = uv[:, 0].copy(), uv[:, 1].copy()
        normal = np.full((k, 3), np.nan)
        gap = np.full(k, np.inf)
        act = np.arange(k)
        for _ in range(END_TANGENT_ITER):
            res = self._d1(face[act], u[act], v[act], self._ads, p, du, dv)
            r = res[:, :3] - target[act]
            su, sv = res[:, 3:6], res[:, 6:9]
            normal[act], gap[act] = np.cross(su, sv), np.linalg.norm(r, axis=1)
            a11, a12, a22 = (su * su).sum(1), (su * sv).sum(1), (sv * sv).sum(1)
            b1, b2 = (su * r).sum(1), (sv * r).sum(1)
            det = a11 * a22 - a12 * a12
            ok = det > 0
            det = np.where(ok, det, 1.0)
            stu, stv = -(a22 * b1 - a12 * b2) / det, -(a11 * b2 - a12 * b1) / det
            norm = np.hypot(stu, stv)
            scale = np.where(ok, np.minimum(1.0, step[act] / np.where(norm > 0, norm, 1.0)), 0.0)
            u[act] += stu * scale
            v[act] += stv * scale
            # converged (the step's move on the surface under a nanometre) or stuck: done
            move = np.linalg.norm(su * (stu * scale)[:, None] + sv * (stv * scale)[:, None], axis=1)
            act = act[ok & (move > 1e-9)]
            if not len(act):
                break
        size = np.linalg.norm(normal, axis=1)
        flat = np.hypot(normal[:, 0], normal[:, 1])
        ok = (gap <= END_TANGENT_TOL_MM) & (flat > END_TANGENT_MIN_SLOPE * size)
        out[ok] = np.column_stack([normal[ok, 1], -normal[ok, 0]]) / flat[ok, None]
        return out

    def _midpoints_off_the_path(
        self, face, zc, step, mid, mid_ok, pa, pb, length, traced, mid_uv
    ) -> np.ndarray:
        """Solve again (in place, with their face parameters ``mid_uv``) the midpoints that the seed path put off their segment's middle.

        A seed path interpolated in (u, v) through a topology triangle with a corner at a pole of
        its face's parametrisation (or across a seam) can run anywhere on the surface: the midpoint
        then lands near an end of its segment, or nowhere, and the segment would pass unchecked (on
        bug29241 two 0.15 mm chords cut across a 0.07 mm boss). Those are solved again from the
        chord's middle projected on the face; a segment whose midpoint still cannot be placed in
        its middle is counted (``unchecked_segments``) and reported. Returns the mask of the
        midpoints solved again (found or not).
        """
        t = _chord_position(np.nan_to_num(mid), pa, pb)
        # A segment no longer than the chord budget is within it whatever its arc (up to a half
        # circle): without a midpoint it passes. But a midpoint off its middle belongs to another
        # piece of the curve (on ec_soapbox-A turned 35 degrees about y, 0.2 mm from a 0.02 mm
        # chord): measured, it would fail the segment, then its parts, and theirs, down to 1e-7 mm
        # (1.5 million segments). So short segments' midpoints are solved again too, and dropped
        # where they are not found (a longer segment's stays: it is counted as unchecked). A traced
        # run's midpoints are on the right piece wherever they project (the tip of a tongue, beyond
        # the chord across it).
        long = length > self.chord
        off_middle = (t < MID_OFF_PATH) | (t > 1.0 - MID_OFF_PATH)
        off = np.flatnonzero((~mid_ok & long) | (mid_ok & off_middle & ~traced))
        again = np.zeros(len(mid), dtype=bool)
        if not len(off):
            return again
        again[off] = True
        p, ok, uv = self._solve_from_chord(
            face[off], zc[off], step[off], 0.5 * (pa[off] + pb[off]), pa[off], pb[off]
        )
        mid[off[ok]], mid_ok[off[ok]], mid_uv[off[ok]] = p[ok], True, uv[ok]
        mid_ok[off[~ok & ~long[off]]] = False
        self.stats.unchecked_segments += int((~ok & long[off]).sum())
        return again

    def _solve_from_chord(self, face, zc, step, guess, pa, pb) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Section points seeded from points ``guess`` on the chords pa-pb projected on their faces
        (not from the seed path): (points, mask of those found strictly between their chord's ends,
        (u, v))."""
        uv = np.array(
            [
                self.mesh.faces[int(f)].uv_near(
                    tuple(g), self.mesh.faces[int(f)].uv_near(tuple(a), (0.0, 0.0))
                )
                for f, g, a in zip(face.tolist(), guess, pa, strict=True)
            ]
        ).reshape(-1, 2)
        p, ok, out_uv = self._newton(np.asarray(face), uv[:, 0], uv[:, 1], zc, np.asarray(step))
        t = _chord_position(np.nan_to_num(p), pa, pb)
        return p, ok & (t > 0.0) & (t < 1.0), out_uv

    def _quarter_sags(
        self,
        solve,
        sag,
        mid,
        mid_ok,
        length,
        pending,
        traced,
        *,
        everywhere=False,
        budget=None,
        halvable=None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Raise ``sag`` (in place) to the curve's distance from the chord at the quarter points of
        the segments where the midpoint alone may miss the largest one; returns the quarter points
        ((n, 2, 3), NaN where not solved) and a mask of those solved on their segment. ``budget``:
        the distance the segments are checked against (the chord, or more where ``halving``): the
        quarter points are solved where the chord's own check would, and beyond the chord up to
        the budget where the segment is ``halvable`` (elsewhere it is checked again at the chord).

        The points are placed by arc length along the topology path (``solve``), and where that path
        and the exact curve part ways (a bend tighter than the topology mesh resolves) the path's
        midpoint can land far from the chord's middle: a 0.27 mm segment round a 0.3 mm fillet on
        bug27693 passed its midpoint test with the curve 0.030 mm from its chord. A convex arc's
        distance from its chord is concave along it, so at the chord's middle it is at least half
        its largest: a segment is checked again at its quarter points when its midpoint's distance
        is above a quarter of the budget or the midpoint projects outside the chord's middle half.
        Between the three points the largest distance is taken from the parabola through them (a
        curve whose bend is off-centre peaks between samples: bug24595's 0.028 mm over 0.025), and
        beyond them from the lines through the outer two (a line running into a small fillet at
        the segment's end: trj4_k1_top's 0.027).
        """
        ri, sa, sb, pa, pb = pending
        e = self.chord
        budget = e if budget is None else budget
        quarters = np.full((len(ri), 2, 3), np.nan)
        q_ok = np.zeros((len(ri), 2), dtype=bool)
        t = _chord_position(np.nan_to_num(mid), pa, pb)
        within = sag <= e
        if budget > e:
            within |= (sag <= budget) & halvable
        check = mid_ok & within & (length <= self.seg_len) & (length > 1e-9)
        if not everywhere:  # (else: segments with an inflection, ``_inflected_segments``)
            check &= (sag > 0.25 * e) | (np.abs(t - 0.5) > 0.25)
        ci = np.flatnonzero(check)
        if not len(ci):
            return quarters, q_ok
        q = np.concatenate([ci, ci])
        frac = np.repeat([0.25, 0.75], len(ci))
        pts, ok, _ = solve(ri[q], sa[q] + frac * (sb[q] - sa[q]))
        pts = np.nan_to_num(pts)
        # a point beyond the chord's ends belongs to the curve past a run's end (the topology path
        # overshooting a corner), not to this segment: it says nothing of the segment's distance
        # (except on a traced run, whose points are all this segment's)
        t_q = _chord_position(pts, pa[q], pb[q])
        ok &= ((t_q > 0.0) & (t_q < 1.0)) | traced[q]
        q_sag = np.where(ok, point_segment_distance(pts, pa[q], pb[q]), 0.0)
        n = len(ci)
        peak = _parabola_peak(
            np.stack([t_q[:n], t[ci], t_q[n:]], axis=1),
            np.stack([q_sag[:n], sag[ci], q_sag[n:]], axis=1),
            ok[:n] & ok[n:],
        )
        np.maximum.at(sag, q, q_sag)
        sag[ci] = np.maximum(sag[ci], peak)
        self.stats.quarter_checks += n
        quarters[ci, 0], quarters[ci, 1] = pts[:n], pts[n:]
        q_ok[ci, 0], q_ok[ci, 1] = ok[:n], ok[n:]
        return quarters, q_ok

    def _halves(self, pending, over, mid, mid_s, quarters, q_ok) -> tuple[np.ndarray, tuple]:
        """Segments ``over`` of ``pending`` (within the ``halving`` budget, beyond the chord) kept as
        their two halves, split at their midpoints ``mid`` (path positions ``mid_s``). Each half is
        checked at its own midpoint, the segment's quarter point, as the chord's check checks a
        segment whose midpoint lies under a quarter of the chord from it: that point in the half's
        middle half, the parabola through it and the half's ends peaking within the chord, and no
        turn through more than ~67 degrees (``DEEP_BEND_REL``). Only where both quarter points were
        found on the segment (``q_ok``: false where the segment is not halvable, see ``refine``);
        elsewhere the path and the curve may part ways, and the whole segment is checked at the
        chord. Returns the mask of the segments whose midpoint is kept, and as pending segments to
        check at the chord: the halves that fail their check and the whole segments not halved."""
        ri, sa, sb, pa, pb = (x[over] for x in pending)
        e = self.chord
        kept = q_ok.all(axis=1)
        # a parabola's halves lie a quarter of its distance from their chords: where the curve's are
        # further from that (its bend changes along the segment), the halves' own one-sample checks are
        # not trusted and they are checked as any segment
        quarter = 0.25 * point_segment_distance(mid, pa, pb)
        starts, ends = np.stack([pa, mid]), np.stack([mid, pb])  # (2, n, 3): the first and second halves
        s_from, s_to = np.stack([sa, mid_s]), np.stack([mid_s, sb])
        q = np.nan_to_num(np.swapaxes(quarters, 0, 1))
        good = np.swapaxes(q_ok, 0, 1) & kept[None, :]
        for h in range(2):
            t = _chord_position(q[h], starts[h], ends[h])
            dist = point_segment_distance(q[h], starts[h], ends[h])
            half = np.linalg.norm(ends[h] - starts[h], axis=1)
            centred = (t >= 0.25) & (t <= 0.75)
            peak = dist / (4.0 * np.where(centred, t * (1.0 - t), 1.0))
            parabolic = np.abs(dist - quarter) <= HALF_SAG_SPREAD * quarter
            good[h] &= centred & parabolic & (peak <= CHORD_FILL * e)
            good[h] &= ~((peak > 0.25 * e) & (peak > DEEP_BEND_REL * half))
        self.stats.halved_segments += int(kept.sum())
        again_h, again_i = np.nonzero(~good & kept[None, :])
        whole = np.flatnonzero(~kept)
        return kept, (
            np.concatenate([ri[again_i], ri[whole]]),
            np.concatenate([s_from[again_h, again_i], sa[whole]]),
            np.concatenate([s_to[again_h, again_i], sb[whole]]),
            np.concatenate([starts[again_h, again_i], pa[whole]]),
            np.concatenate([ends[again_h, again_i], pb[whole]]),
        )

    def _record_gaps(self, gap, length, pa, pb, z, face) -> None:
        """Count the segments ``gap`` (kept over budget: no exact point between their ends), and keep
        them for ``settle_gaps``."""
        if not gap.any():
            return
        self.stats.tolerance_gaps += int(gap.sum())
        g = int(np.argmax(np.where(gap, length, -1.0)))
        if length[g] > self.stats.max_gap_mm:
            self.stats.max_gap_mm, self.stats.max_gap_at = (
                float(length[g]),
                _gap_place(z[g], face[g], pa[g], pb[g]),
            )
        for k in np.flatnonzero(gap).tolist():
            self._gaps.append((float(length[k]), float(z[k]), int(face[k]), pa[k].tolist(), pb[k].tolist()))

    def settle_gaps(self, rings: Iterable[Sequence[int]]) -> None:
        """Count again (``tolerance_gaps``, ``max_gap_*``) only the gaps that are segments of the final
        ``rings``: a segment re-sampled after it was kept over budget (along a trace of the curve
        round an excursion its seeds skipped) is no gap of the mesh."""
        xy = self.pool.xyz[:, :2]
        ends: set[tuple[float, ...]] = set()
        for ring in rings:
            if len(ring) < 2:
                continue
            p = xy[np.asarray(ring)]
            q = np.roll(p, -1, axis=0)
            ends.update(map(tuple, np.column_stack([p, q]).tolist()))
            ends.update(map(tuple, np.column_stack([q, p]).tolist()))
        kept = [g for g in self._gaps if (*g[3][:2], *g[4][:2]) in ends]
        self.stats.tolerance_gaps = len(kept)
        worst = max(kept, default=None, key=lambda g: g[0])
        self.stats.max_gap_mm = 0.0 if worst is None else worst[0]
        self.stats.max_gap_at = (
            "" if worst is None else _gap_place(worst[1], worst[2], *(np.array(worst[k]) for k in (3, 4)))
        )

    def _inside_face(self, run: _Run, uv: np.ndarray) -> bool:
        """Is a point solved on the run's surface (at these face parameters) inside the face's trimmed
        region? Newton works on the untrimmed surface: where the coarse topology crosses a nearly
        tangent edge far from its exact root, seeds can converge beyond the face's boundary. (The
        classifier brings parameters of a periodic surface into its period.)"""
        inside = self.mesh.faces[run.face].contains(float(uv[0]), float(uv[1]), tol=TRIM_TOL_MM)
        if not inside:
            self.stats.outside_face_points += 1
        return inside

    def _d1(
        self, fa: np.ndarray, ua: np.ndarray, va: np.ndarray, ads, p, du, dv, derivatives: bool = True
    ) -> np.ndarray:
        """(n, 9) rows P, Pu, Pv: closed forms for elementary faces, OCCT's D1 for the others.

        With ``derivatives=False`` only P is guaranteed (the B-spline evaluator skips Pu and Pv)."""
        res = np.empty((len(fa), 9))
        an = self._analytic[fa]
        other = np.flatnonzero(~an)
        if other.size:
            rows = []
            for f, uu, vv in zip(fa[other].tolist(), ua[other].tolist(), va[other].tolist(), strict=True):
                ads[f].D1(uu, vv, p, du, dv)
                rows.append(p.Coord() + du.Coord() + dv.Coord())
            res[other] = np.array(rows).reshape(-1, 9)
        idx = np.flatnonzero(an)
        if idx.size:
            order = idx[np.argsort(fa[idx], kind="stable")]
            faces, starts = np.unique(fa[order], return_index=True)
            bounds = np.append(starts, len(order))
            for k, f in enumerate(faces.tolist()):
                sel = order[bounds[k] : bounds[k + 1]]
                P, Pu, Pv = self._evals[f](ua[sel], va[sel], derivatives)
                res[sel, 0:3] = P
                if Pu is not None:
                    res[sel, 3:6], res[sel, 6:9] = Pu, Pv
        return res

    def _newton(
        self, fidx: np.ndarray, u: np.ndarray, v: np.ndarray, zc, max_step: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Batched Newton on ``z(u, v) = zc``, each point in its own face.

        Returns (n, 3) points, an (n,) mask of those that converged (|z - zc| < LEVEL_TOL_MM) and their
        (n, 2) face parameters (on whichever period Newton reached, for periodic surfaces). A seed
        fails where the surface is horizontal there (a plane tangent to it): no point of the level set
        is near, or the level set is degenerate.

        Each step is the smallest move *in 3D* that fixes z to first order: along the surface
        gradient of z, ``d(u, v) = -f G^-1 grad z / (grad z . G^-1 grad z)`` with G the first
        fundamental form. A plain (u, v) gradient step would depend on how the face is parametrised
        (u in [0, 1] and v in millimetres is common) and can wander along the curve.
        """
        n = len(u)
        self.stats.newton_solves += n
        zc = np.broadcast_to(np.asarray(zc, dtype=np.float64), (n,))
        out = np.full((n, 3), np.nan)
        out_uv = np.full((n, 2), np.nan)
        act = np.arange(n)
        u, v = u.astype(np.float64).copy(), v.astype(np.float64).copy()
        p, du, dv = gp_Pnt(), gp_Vec(), gp_Vec()
        ads = self._ads
        for it in range(NEWTON_MAX_ITER):
            if not act.size:
                break
            # After the first step most points have converged: test them on P alone (a third of
            # the cost of P, Pu, Pv for a B-spline) and differentiate only where another step is due.
            res = self._d1(fidx[act], u[act], v[act], ads, p, du, dv, derivatives=it == 0)
            f_ = res[:, 2] - zc[act]
            done = np.abs(f_) < LEVEL_TOL_MM
            out[act[done]] = res[done, :3]
            out_uv[act[done], 0], out_uv[act[done], 1] = u[act[done]], v[act[done]]
            keep = ~done
            act, res, f_ = act[keep], res[keep], f_[keep]
            if not act.size:
                break
            if it:
                res = self._d1(fidx[act], u[act], v[act], ads, p, du, dv)
            su_, sv_ = res[:, 3:6], res[:, 6:9]
            e_ = np.einsum("ij,ij->i", su_, su_)
            f2 = np.einsum("ij,ij->i", su_, sv_)
            g_ = np.einsum("ij,ij->i", sv_, sv_)
            zu, zv = su_[:, 2], sv_[:, 2]
            det = e_ * g_ - f2 * f2
            wu, wv = g_ * zu - f2 * zv, e_ * zv - f2 * zu  # det * G^-1 grad z
            denom = zu * wu + zv * wv  # det * (grad z . G^-1 grad z)
            ok = (det > 0) & (denom > 0)  # else a horizontal or singular point: no Newton direction
            act, f_, wu, wv, denom = act[ok], f_[ok], wu[ok], wv[ok], denom[ok]
            su, sv = -f_ * wu / denom, -f_ * wv / denom
            norm = np.hypot(su, sv)
            scale = np.minimum(1.0, max_step[act] / np.where(norm > 0, norm, 1.0))
            u[act] += su * scale
            v[act] += sv * scale
        converged = ~np.isnan(out[:, 0])
        self.stats.newton_failures += int((~converged).sum())
        return out, converged, out_uv


def _parabola_peak(t: np.ndarray, f: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """Row-wise estimate of the largest distance of a segment's curve from its chord, from three
    samples (t, f) (any order of t): the peak of the parabola through them where it opens downwards
    and peaks between them (capped at 1.5 times the largest sample: nearly collinear samples would
    extrapolate wildly), beyond the outer samples the bound of a concave distance, and the peak of
    the quartic through the samples and the chord's ends (same cap). 0 if none.

    The quartic (zero at t = 0 and 1, where the curve meets its chord) follows a bend off-centre
    that the parabola through the samples alone flattens: boxed_sphere turned (16.7, -95.9, 65.9)
    at z = 8.9, samples 0.0121, 0.0239, 0.0143 at t = 0.30, 0.61, 0.91 of a segment ending in a
    corner, whose curve peaks at 0.0251 at t = 0.72 (a tighter bend towards the corner): the
    parabola says 0.0239, the quartic 0.0252. (At z = 10.9 a 0.055 mm segment across a small lobe,
    sampled at 0.0241, was 0.0257 from its curve.)"""
    order = np.argsort(t, axis=1)
    t, f = np.take_along_axis(t, order, axis=1), np.take_along_axis(f, order, axis=1)
    (t1, t2, t3), (f1, f2, f3) = t.T, f.T
    with np.errstate(divide="ignore", invalid="ignore"):
        d12, d23 = (f2 - f1) / (t2 - t1), (f3 - f2) / (t3 - t2)
        a = (d23 - d12) / (t3 - t1)
        ts = 0.5 * (t1 + t2) - d12 / (2.0 * a)  # where the derivative d12 + a (2 t - t1 - t2) vanishes
        peak = f1 + d12 * (ts - t1) + a * (ts - t1) * (ts - t2)
        # beyond the outer samples, a concave distance (a convex arc) stays under the line through the
        # two samples on that side: a bend at the segment's end (a line running into a small fillet)
        # rises there after three samples on the straight part
        start = np.where(f1 > f2, f1 + (f1 - f2) * np.clip(t1, 0.0, 1.0) / (t2 - t1), 0.0)
        end = np.where(f3 > f2, f3 + (f3 - f2) * np.clip(1.0 - t3, 0.0, 1.0) / (t3 - t2), 0.0)
        # the quartic t (1 - t) g(t), g the parabola through g_i = f_i / (t_i (1 - t_i)), on a grid
        g = f / (t * (1.0 - t))
        x = _QUARTIC_GRID[None, :]
        lag = [
            (x - t2[:, None]) * (x - t3[:, None]) / ((t1 - t2) * (t1 - t3))[:, None],
            (x - t1[:, None]) * (x - t3[:, None]) / ((t2 - t1) * (t2 - t3))[:, None],
            (x - t1[:, None]) * (x - t2[:, None]) / ((t3 - t1) * (t3 - t2))[:, None],
        ]
        quartic = (x * (1.0 - x) * sum(g[:, i, None] * lag[i] for i in range(3))).max(axis=1)
    spaced = (t2 - t1 > 1e-9) & (t3 - t2 > 1e-9)
    good = ok & (a < 0) & (ts > t1) & (ts < t3) & spaced & np.isfinite(peak)
    cap = 1.5 * f.max(axis=1)
    out = np.where(good, np.minimum(peak, cap), 0.0)
    inside = ok & spaced & (t1 > _QUARTIC_END) & (t3 < 1.0 - _QUARTIC_END) & np.isfinite(quartic)
    out = np.maximum(out, np.where(inside, np.minimum(quartic, cap), 0.0))
    return np.maximum(out, np.where(ok & spaced, np.maximum(start, end), 0.0))


# where ``_parabola_peak``'s quartic is evaluated; samples this close to an end give it no shape
_QUARTIC_GRID = np.linspace(0.0, 1.0, 65)
_QUARTIC_END = 0.02


def _chord_position(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise position of the projection of ``p`` on the line a-b (0 at a, 1 at b)."""
    ab = b - a
    denom = np.einsum("ij,ij->i", ab, ab)
    return np.einsum("ij,ij->i", p - a, ab) / np.where(denom > 0, denom, 1.0)


def _segments_beside(p: np.ndarray, i: int, j: int) -> np.ndarray:
    """The segments (m, 2, 2) of the closed ring ``p`` (n, 2) that neither lie in its stretch p[i] ->
    p[j] (indices modulo n, j > i) nor touch it."""
    n = len(p)
    skip = {k % n for k in range(i - 1, j + 1)}
    k = np.array([k for k in range(n) if k not in skip], dtype=np.int64)
    return np.stack([p[k], p[(k + 1) % n]], axis=1) if len(k) else np.zeros((0, 2, 2))


def distances_to_segments(q: np.ndarray, seg: np.ndarray, chunk: int = 256) -> np.ndarray:
    """Distance (mm) from each of the points ``q`` (k, 2) to the nearest of the segments ``seg``
    (m, 2, 2): (k,)."""
    a, ab = seg[:, 0], seg[:, 1] - seg[:, 0]
    denom = np.maximum((ab * ab).sum(axis=1), 1e-300)
    out = np.empty(len(q))
    for s in range(0, len(q), chunk):
        d = q[s : s + chunk, None, :] - a  # (c, m, 2)
        t = np.clip((d * ab).sum(axis=2) / denom, 0.0, 1.0)
        out[s : s + chunk] = np.sqrt(((d - t[..., None] * ab) ** 2).sum(axis=2).min(axis=1))
    return out


def point_segment_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise distance (mm) from points ``p`` to segments ``a``-``b``; all (n, 3)."""
    t = np.clip(_chord_position(p, a, b), 0.0, 1.0)
    return np.linalg.norm(p - (a + t[:, None] * (b - a)), axis=1)


def _dedupe_cyclic(vids: list[int], pool: VertexPool) -> list[int]:
    """Drop consecutive repeats (ids, or points closer than 1 nm) in a closed ring."""
    if len(vids) > 1:
        p = pool.xyz[vids]
        step = np.abs(p - np.roll(p, 1, axis=0)).max(axis=1)
        if step.min() >= 1e-9:  # no repeats (the common case)
            return list(vids)
    out: list[int] = []
    for v in vids:
        if out and (v == out[-1] or _close(pool.xyz[v], pool.xyz[out[-1]])):
            continue
        out.append(v)
    while len(out) > 1 and (out[0] == out[-1] or _close(pool.xyz[out[0]], pool.xyz[out[-1]])):
        out.pop()
    return out


def _clusters(ks: list[int], n: int, gap: int) -> list[tuple[int, int]]:
    """The stretches (i, j), j > i (indices modulo ``n``), from the vertex before the first to the
    vertex after the last of each cluster of the sorted segment indices ``ks`` of a closed ring of
    ``n`` segments, members of a cluster at most ``gap`` apart (round the ring's end too)."""
    groups = [[ks[0]]]
    for k in ks[1:]:
        if k - groups[-1][-1] <= gap:
            groups[-1].append(k)
        else:
            groups.append([k])
    if len(groups) > 1 and groups[0][0] + n - groups[-1][-1] <= gap:
        groups[0] = groups.pop() + [k + n for k in groups[0]]
    out = [(g[0], g[-1] + 1) for g in groups]
    # a stretch must leave one vertex of the ring out (it is traced from one end to the other)
    return [(i, j) for i, j in out if j - i < n]


def _splice(ring: list[int], pieces: list[tuple[int, int, list[int]]]) -> list[int]:
    """``ring`` with the vertices strictly between ring[i] and ring[j] (indices modulo its length, j > i;
    the pieces disjoint) replaced by ``inner``, for each (i, j, inner) of ``pieces``."""
    n = len(ring)
    jump = {i % n: (j % n, inner) for i, j, inner in pieces}
    dropped = {k % n for i, j, _ in pieces for k in range(i + 1, j)}
    start = next(k for k in range(n) if k not in dropped)
    out: list[int] = []
    k = start
    while True:
        out.append(ring[k])
        if k in jump:
            k, inner = jump[k]
            out.extend(inner)
        else:
            k = (k + 1) % n
        if k == start:
            return out


def _end_segments(
    ri: np.ndarray, xyz: np.ndarray, longer: float = 0.0
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The first and last segments of each run (points ``ri``/``xyz`` sorted by run and arc
    length) longer than ``longer``: their first and second points (indices), their run (its id in
    ``ri``) and which end of it (0: start, 1: end)."""
    if len(ri) < 2:
        none = np.zeros(0, dtype=np.int64)
        return none, none, none, none
    first = np.flatnonzero(np.concatenate([[True], ri[1:] != ri[:-1]]))
    last = np.concatenate([first[1:], [len(ri)]]) - 1
    two = last > first  # runs with a segment
    first, last = first[two], last[two]
    a = np.concatenate([first, last - 1])
    b = np.concatenate([first + 1, last])
    end = np.repeat([0, 1], len(first))
    long = np.hypot(*(xyz[b, :2] - xyz[a, :2]).T) > longer
    return a[long], b[long], ri[a[long]], end[long]


def _end_bend_segments(
    xyz: np.ndarray, ends: tuple[np.ndarray, ...], tangents: np.ndarray, chord: float
) -> tuple[np.ndarray, np.ndarray]:
    """Of the runs' end segments ``ends`` (``_end_segments`` of the points ``xyz``, sorted by run
    and arc length), those (first and last points, as indices into ``xyz``) whose curve leaves the
    corner at their end (``tangents``: (n_runs, 2, 2) at start and end, NaN where unknown) at more
    than END_BEND_FACTOR times the angle a shallow arc within ``chord`` of its chord makes with it
    (4 chord / L). Segments no longer than the chord are within it whatever their arc."""
    a, b, run, end = ends
    at = tangents[run, end]
    c = xyz[b, :2] - xyz[a, :2]
    length = np.hypot(c[:, 0], c[:, 1])
    with np.errstate(invalid="ignore", divide="ignore"):
        sin = np.abs(at[:, 0] * c[:, 1] - at[:, 1] * c[:, 0]) / length
        steep = (length > chord) & (sin > END_BEND_FACTOR * 4.0 * chord / length)
    steep &= np.isfinite(sin)
    return a[steep], b[steep]


def _run_successors(first: np.ndarray, last: np.ndarray) -> np.ndarray:
    """For each run (first and last vertex ids), the run that starts where it ends (the next piece
    of its loop past the corner between them; itself for a loop that is one run), or -1 where no
    run or more than one does (a vertex two loops share)."""
    starts: dict[int, list[int]] = {}
    for q, v in enumerate(first.tolist()):
        starts.setdefault(v, []).append(q)
    out = np.full(len(first), -1, dtype=np.int64)
    for r, v in enumerate(last.tolist()):
        if len(qs := starts.get(v, [])) == 1:
            out[r] = qs[0]
    return out


def _inflected_segments(ri: np.ndarray, xyz: np.ndarray, after: np.ndarray | None = None) -> np.ndarray:
    """The segments (index of their first point) of runs ``ri`` (points sorted by run and arc
    length, at ``xyz``) whose polyline turns one way at one end and the other way at the other: the
    curve has an inflection inside, where the midpoint can lie on the chord while the curve is off it
    on either side (r103ec turned (5.4, -134.3, 135.1), the report's reference at z = 12.1: a 1.67 mm
    segment with its midpoint on the chord and the curve 5 um off it at a quarter and three quarters
    of the way). At a run's end the turn is taken with the first segment of the run ``after`` it
    (``_run_successors``; runs numbered 0 .. n - 1, each with two points or more); a segment ending
    where that is not known counts as inflected. Turns of under 1e-9 rad count as none (a straight
    line's points in a row)."""
    if len(ri) < 2:
        return np.empty(0, dtype=np.int64)
    d = np.diff(xyz[:, :2], axis=0)
    same = ri[1:] == ri[:-1]  # segment k: points k, k + 1 of one run
    length = np.hypot(d[:, 0], d[:, 1])

    def sign_of_turn(d0: np.ndarray, d1: np.ndarray) -> np.ndarray:
        cross = d0[..., 0] * d1[..., 1] - d0[..., 1] * d1[..., 0]
        size = np.hypot(d0[..., 0], d0[..., 1]) * np.hypot(d1[..., 0], d1[..., 1])
        return np.where(np.abs(cross) > 1e-9 * size, np.sign(cross), 0.0)

    turn = np.zeros(len(ri))  # at each point, where ``known``
    turn[1:-1] = sign_of_turn(d[:-1], d[1:])
    known = np.concatenate([[False], same[:-1] & same[1:], [False]])  # points inside their run
    if after is not None and len(after):
        bounds = np.searchsorted(ri, np.arange(len(after) + 1))
        linked = np.flatnonzero(after >= 0)
        end, start = bounds[linked + 1] - 1, bounds[after[linked]]  # the same vertex, in two runs
        ok = (end - 1 >= bounds[linked]) & (start + 1 < bounds[after[linked] + 1])
        end, start = end[ok], start[ok]
        across = sign_of_turn(xyz[end, :2] - xyz[end - 1, :2], xyz[start + 1, :2] - xyz[start, :2])
        turn[end], turn[start] = across, across
        known[end], known[start] = True, True
    k = np.flatnonzero(same & (length > 1e-9))
    flip = ~known[k] | ~known[k + 1] | (turn[k] * turn[k + 1] < 0)
    return k[flip]


def _gap_place(z: float, face: int, pa: np.ndarray, pb: np.ndarray) -> str:
    return f"z={z:.4f} mm, face {face + 1}, from {np.round(pa, 4).tolist()} to {np.round(pb, 4).tolist()}"


def _uv_of(ev, p: np.ndarray) -> tuple[float, float]:
    """(u, v) of a point of face ``ev``'s surface (a global projection refined from its own result)."""
    xyz = (float(p[0]), float(p[1]), float(p[2]))
    return ev.uv_near(xyz, ev.uv_near(xyz, (0.0, 0.0)))


def _close(p, q) -> bool:
    return abs(p[0] - q[0]) < 1e-9 and abs(p[1] - q[1]) < 1e-9 and abs(p[2] - q[2]) < 1e-9
