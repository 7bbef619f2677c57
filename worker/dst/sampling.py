"""Exact ring vertices: every section loop sampled under the segment-length and chord-error budget.

Two kinds of loops (see ``sections``):

- *free* loops (an annulus component on both sides) are re-sampled from scratch. Corners of the
  section (where it crosses a B-rep edge, or meets a mesh node lying on the plane) are kept, each
  solved exactly on its edge. Between two corners the section runs inside one face: points are
  seeded at equal arc length along the topology-mesh path and moved onto the exact level set
  ``z(u, v) = plane`` by Newton in that face's parameter space.
- *pinned* loops (a cap or branching component on one side) keep every crossing of a topology-mesh
  edge, each solved exactly (Brent along the edge), because the kept pieces are built on them.

The corners and crossings are solved by ``crossings`` (``Crossings``). Between its ends, each run
(``runs``) of a loop inside one face is sampled under the budget by ``refine`` (``RunRefiner``):
seeds along the topology-mesh path moved onto the exact curve, every segment checked against the
curve and split where it fails.

Last, where a ring turns sharply at a vertex inside a face and a segment there runs against the
section curve's own direction (from the surface normal: the loops keep the material on their left),
the curve makes an excursion the seeds did not follow: the tongue a plane cuts where it grazes a
crest that is not level, whose tip lies beyond the topology mesh's. That piece is traced along the
exact curve from one end to the other and sampled again with the trace as seeds (``traces``).
``RingSampler`` is the three mixins together (their shared state declared in ``sampler_state``), with
the loops' bookkeeping; its vertex pool and statistics are ``sampler_records``'.
"""

from __future__ import annotations

import math
from collections import Counter

import numpy as np

from worker.dst.chords import point_segment_distance
from worker.dst.constants import MIN_LOOP_VERTICES, REPEAT_MM, SEGMENT_FILL
from worker.dst.crossings import Crossings
from worker.dst.errors import TessellationError
from worker.dst.exact import ExactFailure
from worker.dst.face_limits import uv_of
from worker.dst.meshops import unique_ints
from worker.dst.refine import RunRefiner
from worker.dst.runs import SUSPECT_DEFLECTIONS, Run
from worker.dst.sampler_records import SampledShare, SamplingStats, VertexPool
from worker.dst.sections import SectionTopology
from worker.dst.topomesh import TopoMesh
from worker.dst.traces import EXCURSION_MAX_TRACE_MM, Traces


class RingSampler(Crossings, Traces, RunRefiner):
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
        # (each field's type is declared once, in ``SamplerState``)
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
        self.unresolved = []
        self.trace_reach = max(EXCURSION_MAX_TRACE_MM, 100.0 * segment_length)  # a trace's longest
        # a pinned loop's crossings are kept (the kept triangles use them): False where only the
        # loops are wanted (the deviation report's reference), so that a stretch of them in the
        # wrong order can be traced again
        self.keep_crossings = keep_crossings
        self.stats = SamplingStats()
        self.node_vid = {}
        self.cross_vid = {}
        # crossings whose root on their face lies beyond the face's trim (on the surface's extension,
        # not on the B-rep): see pinned_loop
        self.off_trim = set()
        self._on_brep_edge = np.zeros(mesh.n_nodes, dtype=bool)  # nodes on a B-rep edge
        if mesh.edge_of:
            self._on_brep_edge[np.fromiter((n for key in mesh.edge_of for n in key), dtype=np.int64)] = True
        self.subdiv = {}  # start crossing of a pinned segment -> inner vertex ids
        # topology edges lying in a plane (both ends are nodes on it) whose ring segment was
        # subdivided: (a, b) with a < b -> inner vertex ids from a to b
        self.edge_subdiv = {}
        self._edge_param = {}
        self._pred = None  # previous crossing along its loop (``topo.succ`` inverted)
        self._solving = set()  # crossings whose neighbours are being solved
        self._gaps = []  # (length, z, face, one end, the other): see settle_gaps
        self._gap_keys = (0, set(), np.empty(0))  # see _gap_segments
        # vertex ids where the section changes face or meets a B-rep edge: its curvature may jump there
        self.corner_vids = set()
        self.gap_vids = set()  # points added next to run ends off their curve (refine.py)
        # points where a run's curve leaves its face for good before the corner at its end: the
        # ring bridges from there to the corner (``FaceLimits._trim_borders``; ``_corner_handovers``)
        self.bridge_vids = set()
        self._kinks = {}  # face -> interior C0 u and v lines
        self._ads = [f.ad for f in mesh.faces]
        self._evals = [f.batch for f in mesh.faces]
        self._analytic = np.array([e is not None for e in self._evals], dtype=bool)
        # each face's (u, v) box, and whether a point beyond it in u or v is certainly off the face
        # (``FaceEval.bounded``)
        fs = mesh.faces
        self._uv_box = np.array([(f.u0, f.u1, f.v0, f.v1) for f in fs], dtype=np.float64).reshape(-1, 4)
        self._box_checked = np.array([f.bounded for f in fs], dtype=bool).reshape(-1, 2)
        # each face's period in u and v (0 where it does not wrap: ``FaceEval.period``)
        self._period = np.array([(f.period(0), f.period(1)) for f in fs], dtype=np.float64).reshape(-1, 2)
        self._surface_box = np.array([f.surface_bounds() for f in fs], dtype=np.float64).reshape(-1, 4)
        # per face: a k-d tree of its topology triangles' corners and their (u, v) (``_node_uv``)
        self._face_nodes = {}
        self._trim_memo = {}  # (face, vertex) -> in its trim (``_in_trim``)
        # (face, chord end's xyz bytes) -> its (u, v) on the face (``_solve_from_chord``)
        self._chord_end_uv = {}
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
            face=other.pool.faces.copy(),
            uv=other.pool.uvs.copy(),
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
        vid[new] = self.pool.extend(
            share.xyz[new, :2], share.xyz[new, 2], share.plane[new], share.face[new], share.uv[new]
        )
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

    # --- loops -------------------------------------------------------------------------------------
    def free_loops(self, loop_ids: list[int]) -> dict[int, list[int]]:
        """Re-sampled rings of free loops (corners kept, budget-driven points between them), all in one batch."""
        out: dict[int, list[int]] = {}
        runs: list[Run] = []
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

    def _loop_runs(self, li: int, *, min_seg: int) -> list[Run]:
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
                Run(int(faces[i0]), s, uv, step, vids[r], vids[r1], n_seg, zc, j, moved, gap_ends=True)
            )
        return runs

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
        runs: list[Run] = []
        sampled: list[tuple[int, tuple[int, int] | None]] = []  # (crossing, its in-plane edge)
        repeats: list[tuple[int, tuple[int, int], bool]] = []
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
                Run(
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
        starts, twice = ring_passes(cl, vids, self.subdiv, nxt_pos)
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
        excursions = self._excursion_runs(ring, face_of, li, stretches=False)
        traced = self._sample_traced([run for *_, run in excursions])
        for (k, _, run), traced_pts in zip(excursions, traced, strict=True):
            if traced_pts is None:
                continue
            c, at = starts[ring[k]]
            segment = [self.crossing(c), *self.subdiv[c], self.crossing(int(topo.succ[c]))]
            if segment[at + 1] != run.end:  # the ring's next vertex is not this segment's: leave it
                self.stats.excursion_failures += 1
                continue
            sub = self.subdiv[c]
            self.subdiv[c] = sub[:at] + traced_pts[1:-1] + sub[at:]
            self.stats.excursions += 1
        if excursions:
            ring = self._pinned_ring(cl)
        return self._corner_handovers(li, cl, nxt_pos, ring)

    def _corner_handovers(self, li: int, cl: list[int], nxt_pos: np.ndarray, ring: list[int]) -> list[int]:
        """Loop ``li``'s ring (crossings ``cl``, their successors' positions ``nxt_pos``) with the
        bridges to its corners sampled on the face beyond them.

        Where a segment's curve leaves its face's trim for good before the corner at its end, the
        ring bridges from where it leaves to the corner (``FaceLimits._trim_borders``). On a loose
        file the section there runs on the corner's other face, which can bend away from the bridge:
        trj7_b1-ec-214 turned (-99.8, 126.0, -162.8) at z = 259.1, face 26's curve left its trim
        0.17 mm before the crossing of edge 189 (tolerance 0.014 mm), and face 25's section between
        bent 0.031 mm off the bridge. Each bridge is sampled on that face as a run seeded along the
        straight (u, v) line between its ends (``_sample_runs``: the budget's every check). Where
        that fails, or a sample lies farther from the bridge than half its length (no arc between
        its ends goes there: another piece of that face's section), the bridge stays as it was.
        Segments along in-plane edges (their points shared with other passes) and corners the ring
        passes twice are left alone. (The report's reference still bridges: on that turn its
        bridges were up to 8.6 um off the section, over its 1 um; sampled so at its 1 um, one of
        them piled hundreds of points 0.1 mm off the ring on trj7 turned (32.9, 100.0, -141.2) at
        z = 80.1, so the reference keeps its bridges for now.)"""
        if not self.bridge_vids or not any(v in self.bridge_vids for v in ring):
            return ring
        topo = self.topo
        n = len(ring)
        position = {v: k for k, v in enumerate(ring)}
        if len(position) < n:  # (a vertex the ring passes twice has no one place)
            twice = {v for v, m in Counter(ring).items() if m > 1}
            position = {v: k for v, k in position.items() if v not in twice}
        prev_pos = np.empty_like(nxt_pos)
        prev_pos[nxt_pos] = np.arange(len(nxt_pos))
        node = topo.cross_node

        def face(i: int) -> int:  # the face of the segment from crossing cl[i]
            return int(self.mesh.tri_face[topo.seg_tri[cl[i]]])

        xyz = self.pool.xyz
        plane = int(topo.loops[li][0])
        zc = float(topo.planes[plane])
        found: list[tuple[int, bool, Run]] = []  # (crossing, at the segment's end, run)
        for i, c in enumerate(cl):
            sub = self.subdiv.get(c, [])
            k = int(nxt_pos[i])
            if not sub or (node[c] >= 0 and node[cl[k]] >= 0):
                continue
            for at_end, bridge, corner, beyond in (
                (True, sub[-1], self.crossing(cl[k]), k),
                (False, sub[0], self.crossing(c), int(prev_pos[i])),
            ):
                if bridge not in self.bridge_vids or corner not in self.corner_vids:
                    continue
                f = face(beyond)
                if bridge not in position or corner not in position or f == face(i):
                    continue
                a, b = (
                    (position[bridge], position[corner]) if at_end else (position[corner], position[bridge])
                )
                if (a + 1) % n != b:
                    continue
                ev = self.mesh.faces[f]
                va, vb = ring[a], ring[b]
                uv_a = uv_of(ev, xyz[va])
                seed = np.array([uv_a, ev.same_branch(uv_of(ev, xyz[vb]), uv_a)])
                length = float(np.linalg.norm(xyz[vb] - xyz[va]))
                step = 2.0 * float(self.tri_uv_scale[topo.seg_tri[cl[beyond]]])
                run = Run(f, np.array([0.0, length]), seed, step, va, vb, 1, zc, plane)
                found.append((c, at_end, run))
        changed = False
        for c, at_end, run in found:
            try:
                run_pts = self._sample_runs([run])[0]
            except TessellationError:
                self.stats.corner_handover_failures += 1
                continue
            if len(run_pts) < 3:  # the face's curve keeps to the bridge
                continue
            now = self.pool.xyz  # (grown by the run's samples)
            pts = now[run_pts[1:-1]]
            ends = (np.broadcast_to(now[q], pts.shape) for q in (run.start, run.end))
            if point_segment_distance(pts, *ends).max() > 0.5 * run.s[-1]:
                self.stats.corner_handover_failures += 1
                continue
            sub = self.subdiv[c]
            self.subdiv[c] = sub + run_pts[1:-1] if at_end else run_pts[1:-1] + sub
            self.stats.corner_handovers += 1
            changed = True
        return self._pinned_ring(cl) if changed else ring

    def traced_loop(self, li: int) -> list[int] | None:
        """A ring of loop ``li`` from the exact section curve alone, for a loop on one face with no
        corner: traced once round from its first crossing's exact point, then sampled to the budget
        as two traced runs (from there to the trace's middle point and back). None where the loop
        does not qualify or the trace or the sampling fails. (For a pinned loop whose crossings lie
        so far inside a small curve that their exact points come out of order: ``tessellate``.)"""
        topo = self.topo
        j, cross = topo.loops[li]
        faces = unique_ints(self.mesh.tri_face[topo.seg_tri[cross]])
        if len(faces) != 1 or topo.cross_is_corner[cross].any() or (topo.cross_node[cross] >= 0).any():
            return None
        face = int(faces[0])
        zc = float(topo.planes[j])
        ev = self.mesh.faces[face]
        a = self.crossing(int(cross[0]))
        xyz = self.pool.xyz
        uv_a = uv_of(ev, xyz[a])
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
        there, back = self._traced_run(face, a, m, zc, j), self._traced_run(face, m, a, zc, j)
        if there is None or back is None:
            return None
        first, second = self._sample_traced([there, back])
        if first is None or second is None:
            return None
        return _dedupe_cyclic(first[:-1] + second[:-1], self.pool)

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


def ring_passes(
    cl: list[int], vid: list[int], subdiv: dict[int, list[int]], nxt_pos: np.ndarray
) -> tuple[dict[int, tuple[int, int]], set[int]]:
    """Where a pinned loop's ring passes each of its vertices: per vertex id, the crossing whose
    segment starts there and its position in that segment (``vid``: each crossing's vertex,
    ``subdiv``: each crossing's inner points, ``nxt_pos``: its successor's position in ``cl``),
    and the vertices it passes more than once (an in-plane edge's shared points, a node the loop
    comes back to), which have no one place.

    A crossing with no segment (its vertex the next one's: a node on the plane, or merged
    coincident crossings) is one pass over that vertex with the next crossing, whose segment
    leaves it: that one is its start. (trj7_b1-ec-214 turned (-99.8, 126.0, -162.8) at z = 259.1:
    seven crossings at a node 0.3 um above the plane were counted as seven passes, and the
    segment leaving the node, folded back on itself, was never traced again.)"""
    into_next = [not subdiv[c] and vid[i] == vid[int(nxt_pos[i])] for i, c in enumerate(cl)]
    if all(into_next):  # (a loop all at one vertex: no segment to start from)
        into_next = [False] * len(cl)
    starts: dict[int, tuple[int, int]] = {}
    twice: set[int] = set()
    for i, c in enumerate(cl):
        for at, v in enumerate([vid[i], *subdiv[c]]):
            if at == 0 and into_next[i]:
                continue  # the same pass over v as the next crossing's: counted there
            if v in starts:
                twice.add(v)
            else:
                starts[v] = (c, at)
    return starts, twice


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


def _close(p, q) -> bool:
    return abs(p[0] - q[0]) < REPEAT_MM and abs(p[1] - q[1]) < REPEAT_MM and abs(p[2] - q[2]) < REPEAT_MM
