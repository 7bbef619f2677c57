"""Excursions and traces: where a sampled ring turns sharply inside a face and a segment runs against
the section curve's own direction (from the surface normal: the loops keep the material on their
left), the curve makes an excursion the seeds did not follow (the tongue a plane cuts where it
grazes a crest that is not level, whose tip lies beyond the topology mesh's). That piece is traced
along the exact curve from one end to the other and sampled again with the trace as seeds; a pinned
loop's stretch of crossings out of order is traced again the same way (``Traces``, a mixin of
``RingSampler``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from scipy.spatial import cKDTree

from worker.dst.chords import CHORD_FILL, distances_to_segments, point_segment_distance
from worker.dst.constants import MIN_LOOP_VERTICES, SEGMENT_FILL
from worker.dst.errors import TessellationError
from worker.dst.exact import ExactFailure
from worker.dst.face_limits import TRIM_TOL_MM, uv_of
from worker.dst.runs import Run
from worker.dst.sampler_state import SamplerState

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


class Traces(SamplerState):
    """``RingSampler``'s excursion checks and traces along the exact curve (a mixin)."""

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
        seg_lo, seg_hi = seg.min(axis=1), seg.max(axis=1)
        lost = []
        for piece in pieces:
            i, j, _ = piece
            dropped = [
                v
                for v in (ring[k % n] for k in range(i + 1, j))
                if v not in kept and face_of.get(v) is not None
            ]
            if not dropped:
                continue
            # only the segments within the budget of the dropped points' box can be within it of
            # one of them (twice the budget: clear of rounding): the same distances past the budget
            # as against the whole ring (23 s of trj7_b1-ec-214's reference under cProfile: rings
            # of 1 um spans)
            q = self.pool.xyz[dropped, :2]
            lo, hi = q.min(axis=0) - 2.0 * self.chord, q.max(axis=0) + 2.0 * self.chord
            near = ((seg_hi >= lo) & (seg_lo <= hi)).all(axis=1)
            far = (
                np.ones(len(q), dtype=bool)
                if not near.any()
                else distances_to_segments(q, seg[near]) > self.chord
            )
            # of those farther than the budget, one inside its face's trim (the trim check, ~40 us
            # a point, only for them: 74,000 checks of trj3_s1-al's reference were of points the
            # new ring passes within the budget)
            if any(self._in_trim(face_of[v], v) for v in np.asarray(dropped)[far].tolist()):
                lost.append(piece)
        return lost

    def _in_trim(self, face: int, v: int) -> bool:
        """Whether vertex ``v`` lies on ``face`` within its trim (not on its surface's extension).
        Kept per (face, vertex): a pool vertex never moves, and some vertices are asked about again
        as the rings' stretches are re-sampled (18% of the 165,533 calls, 41 s in all under cProfile,
        in trj7_b1-ec-214's reference)."""
        key = (face, v)
        known = self._trim_memo.get(key)
        if known is None:
            known = self._trim_memo[key] = self.mesh.faces[face].contains(
                *self._uv_at(face, v), tol=TRIM_TOL_MM
            )
        return known

    def _uv_at(self, face: int, v: int) -> tuple[float, float]:
        """(u, v) of pool vertex ``v`` on ``face``'s surface: projected from the (u, v) it was solved
        at on that face, where it was (from (0, 0), mostly OCCT's projection at ~0.3 ms a point, 28 s
        of trj3_s1-al's 70 s reference went to the trim checks' alone), else from the face's
        topology node nearest it (``_node_uv``)."""
        ev = self.mesh.faces[face]
        seed = self.pool.uv_on(face, v)
        if seed is None:
            return self._node_uv(face, self.pool.xyz[v])
        return ev.uv_near(tuple(map(float, self.pool.xyz[v])), seed)

    def _node_uv(self, face: int, p: np.ndarray) -> tuple[float, float]:
        """(u, v) of point ``p`` on ``face``'s surface, found from the (u, v) of the face's topology
        node nearest it, on the parameter branch nearest (0, 0): ``uv_of``'s answer (the same point to
        1e-13 on trj3_s1-al) with one projection where it makes two, the first from (0, 0) (5,300
        vertices of that file's reference, a B-rep edge's or a node's, 2.7 s against 1.1)."""
        ev = self.mesh.faces[face]
        if face not in self._face_nodes:
            tris = np.flatnonzero(self.mesh.tri_face == face)
            self._face_nodes[face] = (
                (
                    cKDTree(self.mesh.xyz[self.mesh.tris[tris]].reshape(-1, 3)),
                    self.mesh.tri_uv[tris].reshape(-1, 2),
                )
                if len(tris)
                else None
            )
        nodes = self._face_nodes[face]
        if nodes is None:  # a face without triangles of its own
            return uv_of(ev, p)
        tree, uvs = nodes
        seed = uvs[int(tree.query(p)[1])]
        xyz = (float(p[0]), float(p[1]), float(p[2]))
        return ev.same_branch(ev.uv_near(xyz, (float(seed[0]), float(seed[1]))), (0.0, 0.0))

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

    def _sample_traced(self, runs: list[Run]) -> Sequence[list[int] | None]:
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
                direction = faces[face].section_direction(*self._uv_at(face, v))
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
    ) -> list[tuple[int, int, Run]]:
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
            between = np.searchsorted(cidx, ks, side="right") % max(1, len(cidx))  # corners before
            for r in sorted(set(between.tolist())):
                pieces += _clusters(
                    [k for k, q in zip(ks, between.tolist(), strict=True) if q == r], n, EXCURSION_CLUSTER_GAP
                )
            pieces.sort()
        else:
            pieces = [(k, k + 1) for k in ks]
        out: list[tuple[int, int, Run]] = []
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

    def _stretch_run(self, li: int, ring: list[int], p: np.ndarray, face: int, i: int, j: int) -> Run | None:
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
    ) -> Run | None:
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
        uv_a = self._uv_at(face, a)
        b_direction = ev.section_direction(*self._uv_at(face, b))
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
        return Run(face, s, uv, step, a, b, n_seg, zc, plane, traced=len(tr) > 0)

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


def _segments_beside(p: np.ndarray, i: int, j: int) -> np.ndarray:
    """The segments (m, 2, 2) of the closed ring ``p`` (n, 2) that neither lie in its stretch p[i] ->
    p[j] (indices modulo n, j > i) nor touch it."""
    n = len(p)
    skip = {k % n for k in range(i - 1, j + 1)}
    k = np.array([k for k in range(n) if k not in skip], dtype=np.int64)
    return np.stack([p[k], p[(k + 1) % n]], axis=1) if len(k) else np.zeros((0, 2, 2))


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
