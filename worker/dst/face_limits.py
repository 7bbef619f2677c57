"""Where a run meets the limits of its face: lines where the face's surface is only C0 (the section
has a corner there), poles of its parametrisation, its (u, v) box and its trim (the B-rep edges).

Newton works on the untrimmed surface, so a point solved for a run can lie on the surface's
extension past the face; in a file whose faces and edges part within its tolerance the section
curve itself runs on past the trim. These are the sampler's checks and repairs for that
(``FaceLimits``, a mixin of ``RunRefiner``: the faces, vertex pool, budget and statistics are the
sampler's).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from OCP.collections import Array1_double
from OCP.GeomAbs import GeomAbs_C1
from OCP.gp import gp_Pnt, gp_Vec

from worker.dst.chords import CHORD_FILL, chord_position, point_segment_distance
from worker.dst.constants import LEVEL_TOL_MM, NEWTON_MAX_ITER
from worker.dst.runs import BRIDGE_POINT, Run
from worker.dst.sampler_state import SamplerState

TRIM_TOL_MM = 1e-6
TRIM_ENTRY_TOL_MM = 1e-5  # where a section crosses its face's trim: found to this (``_into_trims``)
# C0 lines of a face this close to its (u, v) box's sides are its edges' business (relative to the box)
KINK_MARGIN_REL = 1e-9
KINK_MIN_SPACING_REL = 1e-9  # a kink this close to a run's end (relative to its length) is that end


def uv_of(ev, p: np.ndarray) -> tuple[float, float]:
    """(u, v) of a point of face ``ev``'s surface (a global projection refined from its own result)."""
    xyz = (float(p[0]), float(p[1]), float(p[2]))
    return ev.uv_near(xyz, ev.uv_near(xyz, (0.0, 0.0)))


def beyond_box(uv: np.ndarray, box: np.ndarray, checked: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(k, 2) masks of (u, v) ``uv`` (k, 2) below and above their (u0, u1, v0, v1) ``box`` (k, 4)
    by more than a relative 1e-9, in the directions ``checked`` (k, 2) (NaN is within)."""
    tol = 1e-9 * np.maximum(box[:, [1, 3]] - box[:, [0, 2]], 1.0)
    return (uv < box[:, [0, 2]] - tol) & checked, (uv > box[:, [1, 3]] + tol) & checked


class FaceLimits(SamplerState):
    """``RunRefiner``'s handling of face limits (a mixin)."""

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

    def _split_at_kinks(self, runs: list[Run]) -> tuple[list[Run], list[int]]:
        """Runs cut where their seed path crosses a C0 line of their face, and each piece's run index."""
        pieces: list[Run] = []
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
                    Run(
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
                        run.gap_ends,
                    )
                )
                owner.append(i)
        return pieces, owner

    def _kink_points(self, run: Run) -> list[tuple[float, np.ndarray, int]]:
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
                    if hit is not None and not ev.contains(hit[0][0], hit[0][1], tol=TRIM_TOL_MM):
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

    def _on_iso_line(self, run: Run, axis: int, k: float, w: float) -> tuple[np.ndarray, np.ndarray] | None:
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

    def _through_poles(
        self, runs: list[Run], ri: np.ndarray, xyz: np.ndarray, uv: np.ndarray, out: np.ndarray
    ) -> np.ndarray:
        """Mask over ``out`` (points beyond their face's (u, v) box, in ``ri``, ``xyz``, ``uv`` sorted
        by run and arc length) of those solved again (in place) on the face: where the box's edge
        they lie beyond is a pole of the face's parametrisation (``FaceEval.is_pole``) and the segment
        joining the points either side of them would pass farther than the chord budget from them,
        from their parameters mirrored through the pole (``_through_pole``). Dropped, such a point
        left a chord across the tip of a section round the apex of a cap (bug27453_165-174_piattello
        turned (89.5, 112.2, -78.9) at z = 86.5, 2 um below an apex: the point 2 um past the pole, 3 um
        from the tip; the 0.25 mm segment across it 0.036 mm from the tip). Past an edge that is no
        pole a point stays dropped: kept, it would lie off the B-rep (boxed_sphere turned (16.7,
        -95.9, 65.9) at z = 1.5: 0.022 mm), and moved onto the edge's iso-line, a stretch of them
        collapses onto one point (Ventilator turned (105.4, 22.5, -109.3): a mesh with open edges)."""
        moved = np.zeros(len(out), dtype=bool)
        gone = np.zeros(len(ri), dtype=bool)
        gone[out] = True
        n = len(ri)
        for m, k in enumerate(out.tolist()):
            a, b = k - 1, k + 1
            while a >= 0 and gone[a] and ri[a] == ri[k]:
                a -= 1
            while b < n and gone[b] and ri[b] == ri[k]:
                b += 1
            if a < 0 or b >= n or ri[a] != ri[k] or ri[b] != ri[k]:
                continue
            if (
                point_segment_distance(xyz[k : k + 1], xyz[a : a + 1], xyz[b : b + 1])[0]
                <= CHORD_FILL * self.chord
            ):
                continue
            run = runs[int(ri[k])]
            below, above = self._beyond_face_box(np.array([run.face]), uv[k : k + 1])
            below, above = below[0], above[0]
            axes = np.flatnonzero(below | above)
            if len(axes) != 1:
                continue
            axis = int(axes[0])
            box = self._uv_box[run.face]
            bound = float(box[2 * axis] if below[axis] else box[2 * axis + 1])
            if not self.mesh.faces[run.face].is_pole(axis, bound):
                continue
            hit = self._through_pole(run, axis, bound, uv[k], xyz[k])
            if hit is None or not self.mesh.faces[run.face].contains(
                float(hit[0][0]), float(hit[0][1]), tol=TRIM_TOL_MM
            ):
                continue
            uv[k], xyz[k] = hit
            moved[m] = True
        self.stats.pole_points += int(moved.sum())
        return moved

    def _through_pole(
        self, run: Run, axis: int, bound: float, uv: np.ndarray, xyz: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray] | None:
        """The section point on the face near ``xyz``, a point Newton put past a pole of the face's
        parametrisation (beyond its (u, v) box at ``bound`` of parameter ``axis``): solved from the
        parameters mirrored through the pole, half a period round (the same place, to second order,
        on a smooth cap); None where the other parameter is not periodic or no point is found near."""
        f = run.face
        ad = self._ads[f]
        periodic = ad.IsVPeriodic() if axis == 0 else ad.IsUPeriodic()
        if not periodic:
            return None
        half = 0.5 * (ad.VPeriod() if axis == 0 else ad.UPeriod())
        mirrored = uv.copy()
        mirrored[axis] = 2.0 * bound - uv[axis]
        mirrored[1 - axis] = uv[1 - axis] + half
        p, ok, out_uv = self._newton(
            np.array([f]), mirrored[:1], mirrored[1:], np.array([run.zc]), np.array([run.max_step])
        )
        if not ok[0] or np.linalg.norm(p[0] - xyz) > self.chord:
            return None
        return out_uv[0], p[0]

    def _off_face_box(self, face: np.ndarray, uv: np.ndarray) -> np.ndarray:
        """Mask of points whose face parameters lie beyond their face's (u, v) box."""
        below, above = self._beyond_face_box(face, uv)
        return (below | above).any(axis=1)

    def _beyond_face_box(self, face: np.ndarray, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(k, 2) masks of points' u and v below and above their face's (u, v) box, where a point
        beyond it in that parameter is certainly off the face (``FaceEval.bounded``)."""
        return beyond_box(uv, self._uv_box[face], self._box_checked[face])

    def _into_trims(
        self, jobs: Sequence[tuple[int, float, float, np.ndarray, np.ndarray, np.ndarray, np.ndarray]]
    ) -> list[tuple[np.ndarray, np.ndarray] | None]:
        """For each job (f, zc, step, outside, inside, uv_out, uv_in), the point (xyz, (u, v)) where
        face ``f``'s section curve at height ``zc`` enters the face's trim between ``outside`` (a point
        of the curve beyond the trim, Newton's, at ``uv_out``) and ``inside`` (one inside it, at
        ``uv_in``; NaN for a run's end vertex, which has none): bisection between them, each point
        solved by Newton from a seed between their (u, v) (and kept between them along their chord),
        down to TRIM_ENTRY_TOL_MM; the outermost point found inside, or None where no point between them
        is found inside.

        Inside is strictly inside the (u, v) trim (the classifier counts as on the boundary a band
        as wide as the edges' tolerances, whose outer side lies off the B-rep by as much: 0.011 mm
        on bug24595_281390 turned (-119.7, -47.5, -168.3) at z = 43.5), and on the face as
        ``BRepExtrema`` measures it: near a loose file's edge a point inside the (u, v) trim can
        still lie off the face by up to the edge's tolerance (0.005 mm on trj4_k1_top-pe-214 at z =
        1.5, edge tolerances of 0.006 mm). That second test is costly (~0.3 ms), so the bisection
        runs on the first, and only where its point fails the second goes on inward with both.

        The jobs' bisections run side by side: each step's Newton solves of all the jobs still
        bisecting go in one batch (a single point's Newton call cost ~0.2 ms: 11,000 of them in
        trj7_b1-ec-214's build); each job's steps, tests and answer are its own."""
        n = len(jobs)
        if not n:
            return []
        faces = [self.mesh.faces[int(j[0])] for j in jobs]
        outside = np.array([j[3] for j in jobs], dtype=np.float64).reshape(n, 3)
        inside = np.array([j[4] for j in jobs], dtype=np.float64).reshape(n, 3)
        span = np.linalg.norm(inside - outside, axis=1)
        # the two points' (u, v) on one branch: each step seeds Newton between them. Those Newton
        # found, not fresh projections: one seeded far from its point can come back at another
        # point of the surface (bug24595_281390 turned (53.4, -11.0, 47.0) at z = 7.5: seeded at
        # (0, 0), both came back at v = 0.05, off the face's box, v 0.70 to 1.08; the first seed
        # between them took Newton 5 mm away, and no entry was found). A run's end vertex is
        # projected from the other point's (u, v).
        uv_out = np.array([j[5] for j in jobs], dtype=np.float64).reshape(n, 2)
        uv_in = np.array([j[6] for j in jobs], dtype=np.float64).reshape(n, 2)
        for k, ev in enumerate(faces):
            w_out = tuple(map(float, uv_out[k]))
            w_in = uv_in[k]
            if np.isnan(w_in).any():
                w_in = ev.uv_near(tuple(map(float, inside[k])), w_out)
            uv_in[k] = ev.same_branch(tuple(map(float, w_in)), w_out)
        face = np.array([int(j[0]) for j in jobs], dtype=np.int64)
        plane = np.array([float(j[1]) for j in jobs])
        trust = np.array([float(j[2]) for j in jobs])

        def bisect(ids: list[int], lo: np.ndarray, exact: bool) -> tuple[np.ndarray, list]:
            hi = np.ones(len(ids))
            best: list[tuple[np.ndarray, np.ndarray] | None] = [None] * len(ids)
            active = list(range(len(ids)))
            while True:
                active = [i for i in active if (hi[i] - lo[i]) * span[ids[i]] > TRIM_ENTRY_TOL_MM]
                if not active:
                    return hi, best
                at = np.array([ids[i] for i in active])
                mid = 0.5 * (lo[active] + hi[active])
                seed = uv_out[at] + mid[:, None] * (uv_in[at] - uv_out[at])
                p, ok, uv = self._newton(face[at], seed[:, 0], seed[:, 1], plane[at], trust[at])
                t = chord_position(np.nan_to_num(p), outside[at], inside[at])
                going = []
                for q, i in enumerate(active):
                    if not ok[q] or not 0.0 < t[q] < 1.0:
                        continue  # this one's bisection stops
                    ev = faces[ids[i]]
                    if ev.strictly_contains(float(uv[q, 0]), float(uv[q, 1]), tol=TRIM_TOL_MM) and (
                        not exact or ev.holds(tuple(p[q]), TRIM_TOL_MM, tuple(uv[q]))
                    ):
                        hi[i], best[i] = mid[q], (p[q], uv[q])
                    else:
                        lo[i] = mid[q]
                    going.append(i)
                active = going

        everyone = list(range(n))
        at, best = bisect(everyone, np.zeros(n), False)
        out: list[tuple[np.ndarray, np.ndarray] | None] = list(best)
        # inside the (u, v) trim but off the face as BRepExtrema measures it: on inward with both tests
        again = [
            k
            for k in everyone
            if best[k] is not None and not faces[k].holds(tuple(best[k][0]), TRIM_TOL_MM, tuple(best[k][1]))
        ]
        if again:
            _, best2 = bisect(again, at[again], True)
            for k, b in zip(again, best2, strict=True):
                out[k] = b
        return out

    def _drop_off_trim_ends(
        self, runs: list[Run], ri: np.ndarray, xyz: np.ndarray, vid: np.ndarray, uv: np.ndarray
    ) -> None:
        """Marks dropped (``vid`` -2) the new points next to each corner end of a run (``ri``, ``xyz``,
        ``vid`` and ``uv`` sorted by run and arc length) that lie beyond the run's face's trim,
        walking in from the corner up to the first point inside it: usually that is the first
        point, one check a corner. The corner then joins the first point on the face. Unless
        ``exact_trim``, they stay where the segment from the corner to that point would pass
        farther than the chord budget from any of them.

        At a corner where a face's surface lies off the B-rep edge within the file's tolerance, its
        curve at the plane runs on past the face's trim, on the surface's extension: the report's
        reference, sampled to 1 um, had a tongue of ~100 points up to 0.03 mm beyond the trim there
        (bug24595_281390 turned (-119.7, -47.5, -168.3) at z = 43.5: a chord_dev of 0.0323 mm read
        for a ring within its 0.025), and a DST ring's last point before a corner could lie 0.011 mm
        along a straight section past the trim, 0.004 mm off the B-rep (trj4_k1_top-pe-214 at z =
        11.1). But where the build's topology mesh gives the run the wrong face next to a corner (a
        narrow face it missed), its points on the wrong surface's extension are nearer the B-rep's
        curve than the chord across them (boxed_sphere turned (-85.5, 94.7, -31.9) at z = 0.3: 0.03
        mm off the B-rep, the chord 0.085 mm off): the build keeps them there.

        Where points are dropped, ``_trim_borders`` then moves the one next to the first point
        inside to where the curve enters the trim between the two: the ring and the reference both
        join the corner to the face's curve at the face's boundary, a point of the B-rep, not to
        whichever of their samples came first inside it (0.003 mm apart on bug24595_281390 at z =
        2.9)."""
        bounds = np.searchsorted(ri, np.arange(len(runs) + 1)).tolist()
        corners = self.corner_vids
        for i, r in enumerate(runs):
            b0, b1 = bounds[i], bounds[i + 1]
            face = self.mesh.faces[r.face]
            for end, at, walk in (
                (r.start, b0, range(b0 + 1, b1)),
                (r.end, b1 - 1, range(b1 - 2, b0 - 1, -1)),
            ):
                if end not in corners:
                    continue
                dropped: list[int] = []
                for k in walk:
                    if vid[k] == -2:
                        continue
                    if vid[k] >= 0 or face.contains(float(uv[k, 0]), float(uv[k, 1]), tol=TRIM_TOL_MM):
                        if dropped and not self.exact_trim:
                            pts = xyz[dropped]
                            ends = (np.broadcast_to(xyz[at], pts.shape), np.broadcast_to(xyz[k], pts.shape))
                            if point_segment_distance(pts, *ends).max() > self.chord:
                                dropped = []
                        break
                    dropped.append(k)
                vid[dropped] = -2
                self.stats.off_trim_end_points += len(dropped)

    def _trim_borders(self, ri, xyz, vid, uv, run_face, run_z, run_step):
        """Where a stretch of a run's new points (``ri``, ``xyz``, ``vid``, ``uv`` sorted by run and
        arc length) is dropped (``vid`` -2: beyond the face's (u, v) box or trim), the curve's points
        where it crosses the trim between the stretch and the kept points either side of it
        (``_into_trims``) take the stretch's end points' places (a stretch of one point gets a second):
        the ring leaves the face's curve at the face's boundary, a point of the B-rep, not at
        whichever of its samples came last inside. Where the surface's curve leaves the face between
        two of its edges' crossings that the file's tolerance lets apart (boxed_sphere turned (30.7,
        26.2, 59.9) at z = 0.1: edge tolerances of 0.055 mm, a curve leaving the face and coming back
        0.3 mm further on), the ring bridges the gap from boundary to boundary. A stretch that
        ``_drop_off_trim_ends`` dropped next to a corner moves only at its side away from the
        corner: the corner joins the face's curve where it enters the trim, and the ring bridges
        from that entry to the corner (its vertex id ``BRIDGE_POINT`` until it has one: the pinned
        loop samples the bridge on the corner's other face, ``RingSampler._corner_handovers``).
        Returns the four arrays (with the added points)."""
        gone = vid == -2
        if not gone.any():
            return ri, xyz, vid, uv
        n = len(ri)
        ks = np.flatnonzero(gone)
        # the stretches: runs of consecutive dropped points of one run
        breaks = np.flatnonzero((np.diff(ks) != 1) | (ri[ks[1:]] != ri[ks[:-1]]))
        starts, stops = ks[np.concatenate([[0], breaks + 1])], ks[np.concatenate([breaks, [len(ks) - 1]])]
        added: list[tuple[int, np.ndarray, np.ndarray]] = []  # (insert before, xyz, uv)
        # each stretch's ends with a kept neighbour on their run: at a corner, or an entry to find
        # from where the end was dropped towards that neighbour (no other stretch moves it); the
        # entries all bisected together (``_into_trims`` reads the points before any moves)
        sides: list[list[tuple[int, bool]]] = []  # per stretch: (its end, beside a corner)
        jobs = []
        for a, b in zip(starts.tolist(), stops.tolist(), strict=True):
            sides.append([])
            for k, beside in ((a, a - 1), (b, b + 1)):
                if not (0 <= beside < n and ri[beside] == ri[k] and vid[beside] != -2):
                    continue
                corner = vid[beside] in self.corner_vids
                sides[-1].append((k, corner))
                if not corner:
                    r = int(ri[k])
                    jobs.append(
                        (
                            int(run_face[r]),
                            float(run_z[r]),
                            float(run_step[r]),
                            xyz[k],
                            xyz[beside],
                            uv[k],
                            uv[beside],
                        )
                    )
        entries = iter(self._into_trims(jobs))
        for (a, b), ends in zip(zip(starts.tolist(), stops.tolist(), strict=True), sides, strict=True):
            moved = False
            at_corner, entered = False, None
            for k, corner in ends:
                if corner:
                    at_corner = True
                    continue
                entry = next(entries)
                if entry is None:
                    continue
                self.stats.trim_entry_points += 1
                if moved:  # a stretch of one point, moved already: one more after it
                    added.append((k + 1, *entry))
                else:
                    xyz[k], uv[k] = entry
                    vid[k] = -1
                    moved = a == b
                    entered = k
            if at_corner and entered is not None:
                vid[entered] = BRIDGE_POINT  # the ring bridges from here to the corner
        if added:
            at = np.array([p for p, _, _ in added])
            ri = np.insert(ri, at, ri[at - 1])
            vid = np.insert(vid, at, -1)
            xyz = np.insert(xyz, at, np.array([q for _, q, _ in added]), axis=0)
            uv = np.insert(uv, at, np.array([w for _, _, w in added]), axis=0)
        return ri, xyz, vid, uv

    def _inside_face(self, run: Run, uv: np.ndarray) -> bool:
        """Is a point solved on the run's surface (at these face parameters) inside the face's trimmed
        region? Newton works on the untrimmed surface: where the coarse topology crosses a nearly
        tangent edge far from its exact root, seeds can converge beyond the face's boundary. (The
        classifier brings parameters of a periodic surface into its period.)"""
        inside = self.mesh.faces[run.face].contains(float(uv[0]), float(uv[1]), tol=TRIM_TOL_MM)
        if not inside:
            self.stats.outside_face_points += 1
        return inside
