"""Exact ring vertices: every section loop sampled under the segment-length and chord-error budget.

Two kinds of loops (see ``sections``):

- *free* loops (an annulus component on both sides) are re-sampled from scratch. Corners of the
  section (where it crosses a B-rep edge, or meets a mesh node lying on the plane) are kept, each
  solved exactly on its edge. Between two corners the section runs inside one face: points are
  seeded at equal arc length along the topology-mesh path and moved onto the exact level set
  ``z(u, v) = plane`` by Newton in that face's parameter space.
- *pinned* loops (a cap or branching component on one side) keep every crossing of a topology-mesh
  edge, each solved exactly (Brent along the edge), because the kept pieces are built on them.

Between its ends, each run of a loop inside one face is sampled under the budget by ``refine``
(``RunRefiner``, which ``RingSampler`` is): seeds along the topology-mesh path moved onto the exact
curve, every segment checked against the curve and split where it fails.

Last, where a ring turns sharply at a vertex inside a face and a segment there runs against the
section curve's own direction (from the surface normal: the loops keep the material on their left),
the curve makes an excursion the seeds did not follow: the tongue a plane cuts where it grazes a
crest that is not level, whose tip lies beyond the topology mesh's. That piece is traced along the
exact curve from one end to the other and sampled again with the trace as seeds
(``_excursion_runs``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, fields

import numpy as np

from worker.dst.constants import MIN_LOOP_VERTICES, SEGMENT_FILL
from worker.dst.errors import TessellationError
from worker.dst.exact import ExactFailure, FaceEval, WalkPassed
from worker.dst.refine import CHORD_FILL, TRIM_TOL_MM, RunRefiner, _Run, point_segment_distance
from worker.dst.sections import SectionTopology
from worker.dst.topomesh import TopoMesh

# A run whose exact end lies more than this many topology deflections from its topology crossing has
# its points checked against the face's trim (the ordinary gap is within one deflection)
SUSPECT_DEFLECTIONS = 5.0
# steps (in topology deflections) of a walk along a section curve: short enough that the pull back
# onto the plane cannot reach another branch of the section
WALK_STEP_DEFLECTIONS = 5.0
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
# ring points closer than this in x, y and z are one (a ring drops the repeat: ``_dedupe_cyclic``; a
# pinned loop's crossings that close share their vertex first: ``_merge_coincident``)
REPEAT_MM = 1e-9


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
    pole_points: int = 0  # points Newton put past a pole of their face, solved on it (``_through_poles``)
    excursions: int = 0  # segments re-sampled along an excursion of the curve they skipped
    excursion_failures: int = 0  # segments suspected of skipping one that could not be traced
    spur_vertices: int = 0  # ring vertices dropped as tips of spurs onto a face's extension
    reordered_crossings: int = 0  # crossings put at the section point nearest them (see _solve_crossing)
    kink_corners: int = 0  # corners placed where a section crosses a C0 line inside a face
    deep_bends: int = 0  # segments split for turning through more than ~67 degrees (DEEP_BEND_REL)
    quarter_checks: int = 0  # segments also checked at their quarter points (see _quarter_sags)
    quarter_resolves: int = 0  # quarter points the seed path put past their segment, solved from its chord
    gap_samples: int = 0  # segments whose samples left much of their chord unseen, sampled in the gap
    halved_segments: int = 0  # segments kept as their two halves (see RingSampler._halves)
    inflection_checks: int = 0  # segments checked again for an inflection inside (_inflected_segments)
    end_bend_checks: int = 0  # run end segments checked again for a bend at their corner (END_BEND_FACTOR)
    gap_ends: int = 0  # points added next to run ends off their face's curve (GAP_END_REL)
    trim_entry_points: int = 0  # points put where a section leaves or enters its face (_into_trim)
    unchecked_segments: int = 0  # segments whose midpoint could not be placed (see _midpoints_off_the_path)
    unresolved_segments: int = 0  # segments still over budget after every round (``keep_unresolved``)
    off_trim_crossings: int = 0  # crossings whose root lay beyond their face's trim (see _drop_off_trim)
    off_trim_end_points: int = 0  # points next to a corner beyond their face's trim, dropped
    merged_crossings: int = 0  # crossings at the same point as their loop neighbour (_merge_coincident)
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


def unresolved_summary(unresolved: list[tuple[int, float]]) -> tuple[list[int], int, float]:
    """Of segments kept over budget after the refinement's last round (``RingSampler.unresolved``:
    (plane, length) each, not empty): their planes in order, and the plane and length of the
    longest."""
    j, longest = max(unresolved, key=lambda s: s[1])
    return sorted({p for p, _ in unresolved}), j, longest


@dataclass
class SampledShare:
    """Free loops sampled by a sampler of their own (``RingSampler.sample_share``), as another
    sampler of the same solid takes them in (``RingSampler.adopt``): its vertices, its rings as ids
    into them, and what the sampler keeps of them for the rings and checks that come after."""

    rings: dict[int, list[int]]
    xyz: np.ndarray  # (n, 3) every vertex the share's sampler added, in order
    plane: np.ndarray  # (n,)
    stats: SamplingStats
    gaps: list[tuple]
    unresolved: list[tuple[int, float]]
    corner_vids: set[int]
    gap_vids: set[int]
    node_vid: dict[int, int]
    cross_vid: dict[int, int]


class RingSampler(RunRefiner):
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
        gap_ends: bool = True,
        exact_trim: bool = False,
        keep_unresolved: bool = False,
    ):
        self.mesh, self.topo, self.pool = mesh, topo, pool
        self.seg_len = segment_length
        self.chord = chord_error
        # ``halving``: segments checked at HALVING_FACTOR times the chord first, and one over the
        # chord but within that kept as its two halves, each checked at its own midpoint (the
        # segment's quarter point, solved already; see ``RunRefiner._halves``) instead of split and solved
        # again: the report's dense reference at 1 um, 129.9k -> 72.0k Newton solves on the hemisphere
        self.halving = halving
        # ``gap_ends``: a run's end vertex off its face's curve gets the curve's nearest point next to
        # it (``RunRefiner._gap_end_points``). Not in the report's reference: at its 1 um chord, the
        # micrometres between a file's faces and edges would add such points at most corners of a
        # file with a loose tolerance, each a sharp turn of the ring that can set off the excursion
        # check's traces; its checks at the chord already split a segment that cuts such a corner.
        self.gap_ends = gap_ends
        # ``exact_trim``: every point beyond its face's trim next to a corner is dropped, even where the
        # segment across it strays from it by more than the chord (``RunRefiner._drop_off_trim_ends``):
        # the report's reference, which must lie on the B-rep
        self.exact_trim = exact_trim
        # ``keep_unresolved``: a segment still over budget after the refinement's last round (a
        # file's corner micrometres off its face's curve, where every new point lands at the same
        # place) is kept between the points it has and recorded, (plane, length), in ``unresolved``,
        # instead of failing the sampling (a traced run's still fails it: ``_sample_traced`` falls
        # back); the DST build and the report's reference both say so in their warnings
        self.keep_unresolved = keep_unresolved
        self.unresolved: list[tuple[int, float]] = []
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
        self._gap_keys: tuple = (0, set(), np.empty(0))  # see _gap_segments
        # vertex ids where the section changes face or meets a B-rep edge: its curvature may jump there
        self.corner_vids: set[int] = set()
        self.gap_vids: set[int] = set()  # points added next to run ends off their curve (refine.py)
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

    # --- free loops in shares ----------------------------------------------------------------------
    def sample_share(self, loop_ids: list[int]) -> SampledShare:
        """``free_loops(loop_ids)`` by a new sampler of this one's solid and settings, with its own
        vertex pool (in a forked helper, or here), for ``adopt``."""
        other = RingSampler(
            self.mesh,
            self.topo,
            VertexPool(),
            segment_length=self.seg_len,
            chord_error=self.chord,
            keep_crossings=self.keep_crossings,
            halving=self.halving,
            gap_ends=self.gap_ends,
            exact_trim=self.exact_trim,
            keep_unresolved=self.keep_unresolved,
        )
        rings = other.free_loops(loop_ids)
        return SampledShare(
            rings=rings,
            xyz=other.pool.xyz.copy(),
            plane=other.pool.plane.copy(),
            stats=other.stats,
            gaps=other._gaps,
            unresolved=other.unresolved,
            corner_vids=other.corner_vids,
            gap_vids=other.gap_vids,
            node_vid=other.node_vid,
            cross_vid=other.cross_vid,
        )

    def adopt(self, share: SampledShare) -> dict[int, list[int]]:
        """Take in a share's vertices, counts, gaps and marks; returns its rings as ids into this
        sampler's pool. A topology node this sampler has already placed (one lying in a plane, that
        a loop of the share passes too) keeps this sampler's vertex, so the mesh stays joined there;
        the share's copy is not added."""
        vid = np.full(len(share.plane), -1, dtype=np.int64)
        for n, v in share.node_vid.items():
            own = self.node_vid.get(n)
            if own is not None:
                vid[v] = own
        new = np.flatnonzero(vid < 0)
        vid[new] = self.pool.extend(share.xyz[new, :2], share.xyz[new, 2], share.plane[new])
        for n, v in share.node_vid.items():
            self.node_vid.setdefault(n, int(vid[v]))
        for c, v in share.cross_vid.items():
            self.cross_vid.setdefault(c, int(vid[v]))
        self.corner_vids.update(vid[list(share.corner_vids)].tolist())
        self.gap_vids.update(vid[list(share.gap_vids)].tolist())
        self._gaps.extend(share.gaps)
        self.unresolved.extend(share.unresolved)
        self.stats.add(share.stats)
        return {li: vid[ring].tolist() for li, ring in share.rings.items()}

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
        # at least ``min_seg`` segments in all: a loop of two corners whose two arcs each sag within
        # the chord budget would otherwise be two points (bug29241 turned (52.3, 4.7, 130.6) at 10 mm
        # segments and a 0.5 mm chord: a 4.4 mm lens between two faces)
        least = -(-min_seg // len(starts))
        runs = []
        for r, i0 in enumerate(starts):
            r1 = (r + 1) % len(starts)
            count = (starts[r1] - i0) % n or n
            s = cum[i0 : i0 + count + 1] - cum[i0]
            uv = np.concatenate([uv_start[i0 : i0 + count], uv_end[i0 + count - 1 : i0 + count]])
            n_seg = max(least, math.ceil(s[-1] / (self.seg_len * SEGMENT_FILL)))
            step = 2.0 * float(scale[i0 : i0 + count].max())
            moved = tuple((exact[k].copy(), float(gap[k]) + self.seg_len) for k in (r, r1) if far[k])
            if moved:
                uv = self._seeds_toward_exact_ends(
                    int(faces[i0]), uv, s, exact[r] if far[r] else None, exact[r1] if far[r1] else None
                )
            runs.append(
                _Run(int(faces[i0]), s, uv, step, vids[r], vids[r1], n_seg, zc, j, moved, gap_ends=True)
            )
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
        suspects: set[int] = set(self._gap_segments(ring, p, face_of))
        if not sharp.any():
            return sorted(suspects)
        faces = self.mesh.faces
        # and segments against the curve's direction at an end
        for i in np.flatnonzero(sharp).tolist():
            v = ring[i]
            if v in self.corner_vids or v in self.gap_vids:  # the turn is the B-rep's (or its gap's)
                continue
            for k in (i, (i - 1) % n):  # the segment leaving v, the one reaching it
                face = face_of.get(ring[k])
                if face is None or k in suspects:
                    continue
                direction = faces[face].section_direction(*_uv_of(faces[face], xyz[v]))
                if direction is not None and np.dot(direction, unit[k]) < EXCURSION_TANGENT_COS:
                    suspects.add(k)
        return sorted(suspects)

    def _gap_segments(self, ring: list[int], p: np.ndarray, face_of: dict[int, int]) -> list[int]:
        """The segments of ``ring`` (x/y ``p``; by their start's position) kept over budget as gaps
        (``_record_gaps``: no exact point found between their ends) that join two points inside one
        face: Newton from seeds either side of a watershed lands on either flank of a sharp tip
        the topology mesh cuts across, never on the tip, and the seed interval between them closes
        (bug27453_165-174_piattello turned (89.5, 112.2, -78.9): 1.26 mm segments across 0.37 mm
        tips at three planes, with no sharp turn of the ring). A trace along the face from one end
        reaches the other where the face's curve joins them (``_excursion_runs``); where it does not
        (a gap of the B-rep itself), the trace fails and the segment stays."""
        if not self._gaps:
            return []
        if self._gap_keys[0] != len(self._gaps):  # (the gaps' ends both ways, made again as they grow)
            ends = {(*g[3][:2], *g[4][:2]) for g in self._gaps}
            ends |= {(*g[4][:2], *g[3][:2]) for g in self._gaps}
            self._gap_keys = (len(self._gaps), ends, np.array(sorted({e[0] for e in ends})))
        _, ends, xs = self._gap_keys
        q = np.roll(p, -1, axis=0)
        n = len(ring)
        out = []
        for k in np.flatnonzero(np.isin(p[:, 0], xs)).tolist():
            if (*p[k].tolist(), *q[k].tolist()) not in ends:
                continue
            a, b = ring[k], ring[(k + 1) % n]
            if any(v in self.corner_vids or v in self.gap_vids for v in (a, b)):
                continue
            if face_of.get(a) is not None and face_of.get(a) == face_of.get(b):
                out.append(k)
        return out

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
        self._merge_coincident(cl, vids, nxt_pos)
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
            if vids[i] == vids[k]:  # _drop_off_trim or _merge_coincident: no segment left
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
                    gap_ends=key is None,
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
        lies beyond its face's trim: a stretch of them between two crossings that stay becomes
        those two's vertices, the first half of it (by length along the topology crossings) the
        first one's, the rest the other's (an edge collapse: the triangles between the two vanish,
        the others keep the mesh closed). Such a root lies on the surface's extension, not on the
        B-rep; the crossing's topology edge is inside one face, so its neighbours' segment runs
        across that face, and is sampled there like any other. (bug27453 at z = 35.9: a root 0.0066
        mm off the B-rep between the roots of a sliver's two boundary edges, 0.0011 mm apart. Each
        crossing once took the nearer end's vertex: trj3_s1-al-214 turned (-123, 47, -18) at 0.15 mm
        layers had seven in a fan round one node, the sixth nearer the first end than its
        neighbours, and the ring went to and fro over one edge three times: non-manifold.)"""
        n = len(cl)
        off = np.array([c in self.off_trim and self.topo.cross_node[c] < 0 for c in cl], dtype=bool)
        if not off.any() or off.all():
            return
        prev_pos = np.empty(n, dtype=np.int64)
        prev_pos[nxt_pos] = np.arange(n)
        xyz = self.pool.xyz
        for i in np.flatnonzero(off).tolist():
            if off[int(prev_pos[i])]:
                continue  # not the first of its stretch
            stretch = [i]
            while off[q := int(nxt_pos[stretch[-1]])]:
                stretch.append(q)
            a, b = vids[int(prev_pos[i])], vids[q]
            path = np.vstack([xyz[a], self.topo.cross_xyz[[cl[k] for k in stretch]], xyz[b]])
            along = np.cumsum(np.linalg.norm(np.diff(path, axis=0), axis=1))
            for k, s in zip(stretch, along[:-1].tolist(), strict=True):
                self.cross_vid[cl[k]] = vids[k] = a if s <= 0.5 * along[-1] else b
                self.stats.off_trim_crossings += 1

    def _merge_coincident(self, cl: list[int], vids: list[int], nxt_pos: np.ndarray) -> None:
        """Give (in place, and for every triangle that uses it) each crossing of this loop whose
        exact point lies within 1 nm of the next one's (``_close``) the vertex of that one: the ring
        drops such a repeat (``_dedupe_cyclic``), so the kept triangles must not keep it either. A
        run of repeats takes its node's vertex if it has one (a run with two nodes is left apart),
        else its first crossing's. (bug29241 turned (-71.7, 8.5, -112.9) at z = 372.3: the section
        1e-10 mm from where two topology edges of one triangle cross the plane, the ring with one of
        the two points and the triangles on both sides with both: three open edges.)"""
        xyz = self.pool.xyz[vids]
        near = np.abs(xyz[nxt_pos] - xyz).max(axis=1) < REPEAT_MM
        if not near.any() or near.all():
            return
        cross_node = self.topo.cross_node
        # runs of repeats in the loop's order, each from the vertex before its first repeat
        i = int(np.flatnonzero(~near)[0])  # (a loop all within 1 nm is no ring: left as it is)
        runs: list[list[int]] = []
        for _ in range(len(cl)):
            k = int(nxt_pos[i])
            if near[i]:
                if not runs or runs[-1][-1] != i:
                    runs.append([i])
                runs[-1].append(k)
            i = k
        for run in runs:
            nodes = {vids[m] for m in run if cross_node[cl[m]] >= 0}
            if len(nodes) > 1:
                continue
            keep = nodes.pop() if nodes else vids[run[0]]
            for m in run:
                if vids[m] != keep and cross_node[cl[m]] < 0:
                    self.cross_vid[cl[m]] = vids[m] = keep
                    self.stats.merged_crossings += 1

    def pinned_segment(self, c: int) -> list[int]:
        """Inner vertices of the pinned segment starting at crossing ``c`` (after ``pinned_loop``)."""
        return self.subdiv[c]


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


def _dedupe_cyclic(vids: list[int], pool: VertexPool) -> list[int]:
    """Drop consecutive repeats (ids, or points closer than 1 nm) in a closed ring."""
    if len(vids) > 1:
        p = pool.xyz[vids]
        step = np.abs(p - np.roll(p, 1, axis=0)).max(axis=1)
        if step.min() >= REPEAT_MM:  # no repeats (the common case)
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


def _uv_of(ev, p: np.ndarray) -> tuple[float, float]:
    """(u, v) of a point of face ``ev``'s surface (a global projection refined from its own result)."""
    xyz = (float(p[0]), float(p[1]), float(p[2]))
    return ev.uv_near(xyz, ev.uv_near(xyz, (0.0, 0.0)))


def _close(p, q) -> bool:
    return abs(p[0] - q[0]) < REPEAT_MM and abs(p[1] - q[1]) < REPEAT_MM and abs(p[2] - q[2]) < REPEAT_MM
