"""Sampling a run of a section curve under the segment-length and chord-error budget.

A run is a piece of a section curve inside one face between two exact end points, with a seed path
from the topology mesh (``sampling`` finds the runs). Points are seeded at equal arc length along
the path and moved onto the exact level set ``z(u, v) = plane`` by Newton in the face's parameter
space. Then every segment is checked against the exact curve: the curve point halfway along it
(Newton again) must lie within ``chord_error`` of the chord, and the chord must be no longer than
``segment_length``; a failing segment is split and its parts checked again. The midpoint test is
exact for circles and measures the sagitta to second order in the segment length for other smooth
curves; a segment whose midpoint may not show its largest distance (see ``_quarter_sags``) is also
checked at its quarter points, a segment with an inflection inside (``_inflected_segments``) and a
run's end segment leaving its corner too steeply (``_end_bend_segments``) again. A run's end vertex
lying off its face's curve (the face and the edge the vertex is on apart within the file's
tolerance) gets the curve's point nearest it as the run's next point (``_add_gap_points``).

All Newton solves of one batch of runs run together (numpy bookkeeping, one OCCT ``D1`` per point
and iteration), which keeps the Python overhead per ring vertex to a few microseconds.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np
from OCP.collections import Array1_double
from OCP.GeomAbs import GeomAbs_C1
from OCP.gp import gp_Pnt, gp_Vec

from worker.dst.constants import (
    LEVEL_TOL_MM,
    MAX_SUBDIVISION,
    NEWTON_MAX_ITER,
    SEGMENT_FILL,
)
from worker.dst.errors import TessellationError

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
# A segment whose midpoint and quarter points leave more of its chord than this share unseen between
# them (or its ends) is sampled in the middle of that gap too (``_gap_sags``)
MAX_SAMPLE_GAP = 0.5
TRIM_TOL_MM = 1e-6
TRIM_ENTRY_TOL_MM = 1e-5  # where a section crosses its face's trim: found to this (``_into_trim``)
POLE_TOL_MM = 1e-7  # an iso-line this short is a pole of its face's parametrisation
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
# A run's end vertex farther than this many chord budgets from its face's section curve (the face
# and the edge the vertex lies on apart within the file's tolerance, on a shallow face) gets the
# curve's point nearest it as the run's next point (``_gap_end_points``)
GAP_END_REL = 0.25
_GAP_POINT = -3  # (vertex id placeholder of a point added by ``_gap_end_points``)
MAX_REFINE_ROUNDS = 40  # halving a segment 24 times takes 1 m down to 60 nm: still failing means broken


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
    # an end vertex off the face's curve gets the curve's nearest point next to it (``_add_gap_points``;
    # the runs of free loops: a pinned loop's kept triangles take its segments' points as they are)
    gap_ends: bool = False


class RunRefiner:
    """``RingSampler``'s sampling of runs under the budget (a mixin: the sampler's faces, vertex
    pool, budgets and statistics are its own)."""

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
                        run.gap_ends,
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
                    (run_face[ri], run_z[ri], run_step[ri]),
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
                last = ri[b_idx]  # the segments that failed the last round (split once more, unchecked)
                if not self.keep_unresolved or run_traced[last].any():
                    raise TessellationError(f"section curves cannot meet the chord budget{worst}")
                # kept between the exact points they have, counted, and reported with their planes
                # and lengths (``unresolved``) rather than failing the build or the report
                self.stats.unresolved_segments += len(last)
                self.unresolved.extend(zip(run_plane[last].tolist(), length[b_idx].tolist(), strict=True))
            return split

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
        # First, a run's end vertex off its face's section curve (a face and the edge the vertex lies
        # on apart within the file's tolerance, on a shallow face: bug24595_281390 turned (157.5,
        # -47.8, -129.9) at z = 95.7, a corner 5.6 um above face 3, which rises 0.16 there, its curve
        # 0.035 mm from the corner) joins the curve where the curve comes nearest it, and the segment
        # from the corner to the next point passes that place by up to the distance: that point of
        # the curve is added next to the corner (``_add_gap_points``).
        if self.gap_ends and any(r.gap_ends for r in runs):
            self._add_gap_points(
                runs, lengths, run_all, s_all, xyz_all, uv_all, vid_all, tangents, known, refine
            )
        forced: set[tuple[int, float, float]] = set()
        for _ in range(MAX_END_BEND_ROUNDS):
            ri, s_, xyz = np.concatenate(run_all), np.concatenate(s_all), np.concatenate(xyz_all)
            order = np.lexsort((s_, ri))
            # the tangents at the ends of segments long enough to leave them too steeply
            ends = _end_segments(ri[order], xyz[order], END_BEND_FACTOR * 4.0 * e)
            run, end = ends[2:]
            todo = ~known[run, end]
            run, end = run[todo], end[todo]
            tangents[run, end] = self._end_tangents([runs[k] for k in run.tolist()], end)[0]
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
            gap_pt = np.concatenate(vid_all)[order] == _GAP_POINT
            inflected = _inflected_segments(ri[order], xyz[order], after, gap_pt if gap_pt.any() else None)
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
        # new points must lie on their face: inside its (u, v) box, near a run end that moved far
        # from its topology crossing inside its trim, and next to a corner inside its trim too
        new = np.flatnonzero(vid < 0)
        outside = self._off_face_box(run_face[ri[new]], uv[new])
        if outside.any():
            outside[outside] = ~self._through_poles(runs, ri, xyz, uv, new[outside])
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
        self._drop_off_trim_ends(runs, ri, xyz, vid, uv)
        ri, xyz, vid, uv = self._trim_borders(ri, xyz, vid, uv, run_face, run_z, run_step)
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
        gap_pt = new[vid[new] == _GAP_POINT]
        vid[new] = self.pool.extend(xyz[new, :2], run_z[ri[new]], run_plane[ri[new]])
        # where the curve meets the jump from a run's end vertex off it (the ring turns there)
        self.gap_vids.update(vid[gap_pt].tolist())
        bounds = np.searchsorted(ri, np.arange(n_runs + 1))
        ids = vid.tolist()
        return [ids[bounds[i] : bounds[i + 1]] for i in range(n_runs)]

    def _add_gap_points(
        self, runs, lengths, run_all, s_all, xyz_all, uv_all, vid_all, tangents, known, refine
    ):
        """``_sample_pieces``' points (``run_all`` ... ``vid_all``, appended to) with the section
        curve's point nearest each end vertex (of a run with ``gap_ends``) that lies off its face's
        curve by more than GAP_END_REL chord budgets (``_gap_end_points``), and the segment from each
        such point on checked at its quarter points too (``refine``). ``tangents`` and ``known`` (the
        run ends' section tangents) are filled in for those runs' ends of segments longer than the
        chord (NaN where a point was added: the end's tangent is not the curve's)."""
        e = self.chord
        ri, s_, xyz = np.concatenate(run_all), np.concatenate(s_all), np.concatenate(xyz_all)
        order = np.lexsort((s_, ri))
        a, b, run, end = _end_segments(ri[order], xyz[order], e)
        mine = np.array([runs[k].gap_ends for k in run.tolist()], dtype=bool)
        a, b, run, end = a[mine], b[mine], run[mine], end[mine]
        tangents[run, end], foot_uv, off = self._end_tangents(
            [runs[k] for k in run.tolist()], end, offsets=True
        )
        known[run, end] = True
        far = np.flatnonzero(off > GAP_END_REL * e)
        if not len(far):
            return
        run, end, a, b = run[far], end[far], order[a[far]], order[b[far]]
        segment = np.linalg.norm(xyz[b, :2] - xyz[a, :2], axis=1)
        inner = np.where(end == 0, b, a)  # (the end segment's other point)
        g_xyz, g_ok, g_uv = self._gap_end_points(
            runs, run, end, foot_uv[far], off[far], 0.5 * segment, xyz[inner], np.concatenate(uv_all)[inner]
        )
        if not g_ok.any():
            return
        run, end, inner = run[g_ok], end[g_ok], inner[g_ok]
        tangents[run, end] = np.nan
        # next to the end in s (a segment between the two is a gap if it is ever found over budget)
        at = np.where(end == 0, 0.0, lengths[run])
        ds = np.minimum(0.5 * GAP_SPAN_REL * np.maximum(lengths[run], 1.0), 0.25 * np.abs(s_[inner] - at))
        first_new = len(ri)
        run_all.append(run)
        s_all.append(np.where(end == 0, at + ds, at - ds))
        xyz_all.append(g_xyz[g_ok])
        uv_all.append(g_uv[g_ok])
        vid_all.append(np.full(len(run), _GAP_POINT, dtype=np.int64))
        self.stats.gap_ends += len(run)
        ri, s_, xyz = np.concatenate(run_all), np.concatenate(s_all), np.concatenate(xyz_all)
        order = np.lexsort((s_, ri))
        pos = np.empty(len(order), dtype=np.int64)
        pos[order] = np.arange(len(order))
        p = pos[first_new:]  # the added points' places in run order, and their segments on the curve
        pairs = sorted(
            set(
                zip(np.where(end == 0, p, p - 1).tolist(), np.where(end == 0, p + 1, p).tolist(), strict=True)
            )
        )
        a, b = order[[q for q, _ in pairs]], order[[q for _, q in pairs]]
        self.stats.end_bend_checks += len(a)
        refine((ri[a], s_[a], s_[b], xyz[a], xyz[b]), forced=True)

    def _through_poles(
        self, runs: list[_Run], ri: np.ndarray, xyz: np.ndarray, uv: np.ndarray, out: np.ndarray
    ) -> np.ndarray:
        """Mask over ``out`` (points beyond their face's (u, v) box, in ``ri``, ``xyz``, ``uv`` sorted
        by run and arc length) of those solved again (in place) on the face: where the box's edge
        they lie beyond is a pole of the face's parametrisation (``_is_pole``) and the segment
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
            if not self._is_pole(run.face, axis, bound):
                continue
            hit = self._through_pole(run, axis, bound, uv[k], xyz[k])
            if hit is None or not self.mesh.faces[run.face].contains(*hit[0].tolist(), tol=TRIM_TOL_MM):
                continue
            uv[k], xyz[k] = hit
            moved[m] = True
        self.stats.pole_points += int(moved.sum())
        return moved

    def _is_pole(self, f: int, axis: int, bound: float) -> bool:
        """Is the iso-line at ``bound`` of face ``f``'s parameter ``axis`` (0: u, 1: v) one point of
        its surface (a pole: the apex of a cap of revolution)?"""
        box = self._uv_box[f]
        lo, hi = box[2 * (1 - axis)], box[2 * (1 - axis) + 1]
        p = gp_Pnt()
        pts = []
        for w in (lo, 0.5 * (lo + hi), hi):
            self._ads[f].D0(*((bound, w) if axis == 0 else (w, bound)), p)
            pts.append(p.Coord())
        pts = np.array(pts)
        return bool(np.linalg.norm(pts - pts[0], axis=1).max() < POLE_TOL_MM)

    def _through_pole(
        self, run: _Run, axis: int, bound: float, uv: np.ndarray, xyz: np.ndarray
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
        box, chk = self._uv_box[face], self._box_checked[face]
        tol = 1e-9 * np.maximum(box[:, [1, 3]] - box[:, [0, 2]], 1.0)
        return (uv < box[:, [0, 2]] - tol) & chk, (uv > box[:, [1, 3]] + tol) & chk

    def _end_tangents(
        self, runs: list[_Run], end: np.ndarray, offsets: bool = False
    ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
        """(k, 2): the unit xy tangent (either sense) of each of the runs' section curve at its start
        (``end`` 0) or end vertex (1), on the run's own face (its normal's horizontal part turned a
        quarter); NaN where the vertex is not found within END_TANGENT_TOL_MM of the face (a file's
        tolerance) or the face is nearly horizontal there. The vertices' (u, v) by batched
        Gauss-Newton from the seed path's ends.

        With ``offsets``, also the (k, 2) (u, v) found (the vertex's foot on the face) and the (k,)
        horizontal distance from the vertex to where one Newton step from its foot onto the run's
        plane lands (the curve's nearest point to first order; inf where the face is horizontal at
        the foot, NaN where the foot was not found: Gauss-Newton stuck or not converged, as at
        bug27453_165-174_piattello's z = 14.1, where points put 0.33 mm off from such feet made the
        ring cross itself); else None for both."""
        k = len(runs)
        out = np.full((k, 2), np.nan)
        if not k:
            return out, np.zeros((0, 2)), np.zeros(0)
        face = np.array([r.face for r in runs])
        target = self.pool.xyz[[r.end if w else r.start for r, w in zip(runs, end.tolist(), strict=True)]]
        uv = np.array([r.uv[-1] if w else r.uv[0] for r, w in zip(runs, end.tolist(), strict=True)])
        step = np.array([r.max_step for r in runs])
        p, du, dv = gp_Pnt(), gp_Vec(), gp_Vec()
        u, v = uv[:, 0].copy(), uv[:, 1].copy()
        normal = np.full((k, 3), np.nan)
        gap = np.full(k, np.inf)
        foot = np.full((k, 3), np.nan)  # the surface point at the last (u, v) evaluated
        act = np.arange(k)
        found = np.ones(k, dtype=bool)  # the foot converged (the nearest point of the surface)
        for _ in range(END_TANGENT_ITER):
            res = self._d1(face[act], u[act], v[act], self._ads, p, du, dv)
            r = res[:, :3] - target[act]
            su, sv = res[:, 3:6], res[:, 6:9]
            normal[act], gap[act], foot[act] = np.cross(su, sv), np.linalg.norm(r, axis=1), res[:, :3]
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
            found[act[~ok]] = False
            act = act[ok & (move > 1e-9)]
            if not len(act):
                break
        found[act] = False
        size = np.linalg.norm(normal, axis=1)
        flat = np.hypot(normal[:, 0], normal[:, 1])
        ok = (gap <= END_TANGENT_TOL_MM) & (flat > END_TANGENT_MIN_SLOPE * size)
        out[ok] = np.column_stack([normal[ok, 1], -normal[ok, 0]]) / flat[ok, None]
        if not offsets:
            return out, None, None
        # the Newton step from the foot onto the plane: horizontally f n_z n_h / |n_h|^2 (unit normal;
        # a found foot's last step moved it under a nanometre: its last evaluation serves)
        n = normal / np.maximum(size, 1e-300)[:, None]
        h2 = n[:, 0] ** 2 + n[:, 1] ** 2
        zc = np.array([r.zc for r in runs])
        with np.errstate(divide="ignore", invalid="ignore"):
            step_xy = ((foot[:, 2] - zc) * n[:, 2] / h2)[:, None] * n[:, :2]
            off = np.linalg.norm(foot[:, :2] + step_xy - target[:, :2], axis=1)
        off = np.where(np.isfinite(off), off, np.inf)
        return out, np.column_stack([u, v]), np.where(found, off, np.nan)

    def _gap_end_points(
        self,
        runs: list[_Run],
        run: np.ndarray,
        end: np.ndarray,
        uv: np.ndarray,
        off: np.ndarray,
        reach: np.ndarray,
        inner: np.ndarray,
        inner_uv: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The section curve's point nearest each run end vertex that lies off its face's curve
        (``off``: its estimated distance, ``uv``: its foot on the face), by Newton onto the run's
        plane from the foot: (k, 3) points, (k,) mask of those found, (k, 2) their (u, v). Found:
        converged within 2 ``off`` + the chord of the vertex and within ``reach`` (half its end
        segment: a point farther along would not come next to the vertex), and inside the face's
        trim. Where the face's curve runs on the surface's extension past the edge there instead
        (bug24595_281390 turned (-119.7, -47.5, -168.3) at z = 43.5, a corner 0.033 mm from face 0's
        curve, which there lies 0.030 mm beyond the face), the point where the curve enters the trim
        on its way to the end segment's other point ``inner`` (``_into_trim``), within the same
        reach: bug24595_281390 turned (14.5, -140.6, 37.4) at z = 103.1 had a corner 0.030 mm from
        face 15's curve, whose nearest point lay beyond the trim, and the 0.78 mm segment from the
        corner passed 0.028 mm from the curve where it entered the face 0.011 mm further on."""
        face = np.array([runs[r].face for r in run.tolist()])
        zc = np.array([runs[r].zc for r in run.tolist()])
        step = np.array([runs[r].max_step for r in run.tolist()])
        xyz, ok, out_uv = self._newton(face, uv[:, 0].copy(), uv[:, 1].copy(), zc, step)
        vid = np.array(
            [runs[r].end if w else runs[r].start for r, w in zip(run.tolist(), end.tolist(), strict=True)]
        )
        near = np.minimum(2.0 * np.where(np.isfinite(off), off, 0.0) + self.chord, reach)
        dist = np.linalg.norm(np.nan_to_num(xyz[:, :2]) - self.pool.xyz[vid, :2], axis=1)
        ok &= dist <= near
        for i in np.flatnonzero(ok).tolist():
            if self.mesh.faces[face[i]].contains(float(out_uv[i, 0]), float(out_uv[i, 1]), tol=TRIM_TOL_MM):
                continue
            ok[i] = False
            entry = self._into_trim(
                int(face[i]), float(zc[i]), float(step[i]), xyz[i], inner[i], out_uv[i], inner_uv[i]
            )
            if entry is not None and np.linalg.norm(entry[0][:2] - self.pool.xyz[vid[i], :2]) <= near[i]:
                xyz[i], out_uv[i], ok[i] = entry[0], entry[1], True
                self.stats.trim_entry_points += 1
        return xyz, ok, out_uv

    def _into_trim(
        self,
        f: int,
        zc: float,
        step: float,
        outside: np.ndarray,
        inside: np.ndarray,
        uv_out: np.ndarray,
        uv_in: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray] | None:
        """The point (xyz, (u, v)) where face ``f``'s section curve at height ``zc`` enters the face's
        trim between ``outside`` (a point of the curve beyond the trim, Newton's, at ``uv_out``) and
        ``inside`` (one inside it, at ``uv_in``; NaN for a run's end vertex, which has none):
        bisection between them, each point solved by Newton from a seed between their (u, v) (and
        kept between them along their chord), down to TRIM_ENTRY_TOL_MM; the outermost point found
        inside, or None where no point between them is found inside.

        Inside is strictly inside the (u, v) trim (the classifier counts as on the boundary a band
        as wide as the edges' tolerances, whose outer side lies off the B-rep by as much: 0.011 mm
        on bug24595_281390 turned (-119.7, -47.5, -168.3) at z = 43.5), and on the face as
        ``BRepExtrema`` measures it: near a loose file's edge a point inside the (u, v) trim can
        still lie off the face by up to the edge's tolerance (0.005 mm on trj4_k1_top-pe-214 at z =
        1.5, edge tolerances of 0.006 mm). That second test is costly (~0.3 ms), so the bisection
        runs on the first, and only where its point fails the second goes on inward with both."""
        ev = self.mesh.faces[f]
        span = float(np.linalg.norm(inside - outside))
        # the two points' (u, v) on one branch: each step seeds Newton between them. Those Newton
        # found, not fresh projections: one seeded far from its point can come back at another
        # point of the surface (bug24595_281390 turned (53.4, -11.0, 47.0) at z = 7.5: seeded at
        # (0, 0), both came back at v = 0.05, off the face's box, v 0.70 to 1.08; the first seed
        # between them took Newton 5 mm away, and no entry was found). A run's end vertex is
        # projected from the other point's (u, v).
        uv_out = np.asarray(uv_out, dtype=np.float64)
        if np.isnan(uv_in).any():
            uv_in = ev.uv_near(tuple(map(float, inside)), tuple(map(float, uv_out)))
        uv_in = np.array(ev.same_branch(tuple(map(float, uv_in)), tuple(map(float, uv_out))))
        face, plane, trust = np.array([f]), np.array([zc]), np.array([step])

        def bisect(lo: float, hi: float, exact: bool) -> tuple[float, tuple[np.ndarray, np.ndarray] | None]:
            best = None
            while (hi - lo) * span > TRIM_ENTRY_TOL_MM:
                mid = 0.5 * (lo + hi)
                seed = uv_out + mid * (uv_in - uv_out)
                p, ok, uv = self._newton(face, seed[:1], seed[1:], plane, trust)
                t = _chord_position(np.nan_to_num(p), outside[None], inside[None])[0]
                if not ok[0] or not 0.0 < t < 1.0:
                    break
                if ev.strictly_contains(float(uv[0, 0]), float(uv[0, 1]), tol=TRIM_TOL_MM) and (
                    not exact or ev.holds(tuple(p[0]), TRIM_TOL_MM)
                ):
                    hi, best = mid, (p[0], uv[0])
                else:
                    lo = mid
            return hi, best

        at, best = bisect(0.0, 1.0, False)
        if best is None or ev.holds(tuple(best[0]), TRIM_TOL_MM):
            return best
        return bisect(at, 1.0, True)[1]

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
        on,
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
        the segment's end: trj4_k1_top's 0.027). A quarter point the path puts past the segment's
        ends is solved again from the chord's quarter point projected on the face (``on``: each
        segment's face, plane height and Newton step), as a midpoint is (``_midpoints_off_the_path``;
        trj6_k1-al-214 turned (112.9, 27.5, -64.7) at z = 44.5: both of a 0.167 mm segment's quarter
        points landed past its ends round a 0.5 mm loop, its midpoint 0.024 mm from the chord, and
        it passed with the curve 0.028 mm from it). Where one quarter point is still lost, the
        midpoint and the other give the peak (``_zero_end_peak``). The quarter points solved again
        serve the peak only (``q_ok`` false: not a half's midpoint for ``_halves``).
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
        on_path = ok.copy()
        if (lost := np.flatnonzero(~ok)).size:
            qq = q[lost]
            guess = pa[qq] + frac[lost, None] * (pb[qq] - pa[qq])
            face, zc, step = (a[qq] for a in on)
            p2, ok2, _ = self._solve_from_chord(face, zc, step, guess, pa[qq], pb[qq])
            found = lost[ok2]
            pts[found], t_q[found], ok[found] = (
                p2[ok2],
                _chord_position(p2[ok2], pa[q[found]], pb[q[found]]),
                True,
            )
            self.stats.quarter_resolves += len(lost)
        q_sag = np.where(ok, point_segment_distance(pts, pa[q], pb[q]), 0.0)
        n = len(ci)
        peak = _parabola_peak(
            np.stack([t_q[:n], t[ci], t_q[n:]], axis=1),
            np.stack([q_sag[:n], sag[ci], q_sag[n:]], axis=1),
            ok[:n] & ok[n:],
        )
        # one quarter point off the chord (the path overshooting the segment's end round a tight
        # bend): the midpoint and the other quarter point give the peak (Ventilator turned (105.4,
        # 22.5, -109.3) at z = 78.9: samples 0.0187 and 0.0242 at t = 0.24 and 0.62 of a 0.197 mm
        # segment round a 0.19 mm bend, whose curve peaks at 0.0253 near its middle)
        one = ok[:n] ^ ok[n:]
        if one.any():
            pair_t = np.stack([t[ci], np.where(ok[:n], t_q[:n], t_q[n:])], axis=1)
            pair_f = np.stack([sag[ci], np.where(ok[:n], q_sag[:n], q_sag[n:])], axis=1)
            peak = np.maximum(peak, np.where(one, _zero_end_peak(pair_t, pair_f), 0.0))
        np.maximum.at(sag, q, q_sag)
        sag[ci] = np.maximum(sag[ci], peak)
        self.stats.quarter_checks += n
        self._gap_sags(on, sag, ci, t, t_q, q_sag, ok, length, pa, pb)
        quarters[ci, 0], quarters[ci, 1] = pts[:n], pts[n:]
        q_ok[ci, 0], q_ok[ci, 1] = on_path[:n], on_path[n:]
        return quarters, q_ok

    def _gap_sags(self, on, sag, ci, t, t_q, q_sag, ok, length, pa, pb) -> None:
        """Raise ``sag`` (in place) where the samples of segments ``ci`` (the midpoint at chord
        position ``t``, the quarter points at ``t_q`` with distances ``q_sag`` where ``ok``; laid
        out as ``_quarter_sags`` has them) leave more than ``MAX_SAMPLE_GAP`` of the chord unseen:
        the curve's point in the middle of that gap, solved from the chord (``_solve_from_chord``),
        and the peak of the parabola through it and the samples (or chord ends) either side.

        Where the seed path and the curve part ways the path's arc length maps unevenly onto the
        curve: bug29241 turned (26.5, -17.6, -116.2) at z = 321.3 had a 0.276 mm segment round a
        bend of a cone's section sampled at t = 0.035, 0.893 and 0.929 (0.010 mm at most), its curve
        0.028 mm from the chord at t = 0.5. A point farther from the chord than half its length is
        on another piece of the section (no arc between the ends goes there) and is not used."""
        n = len(ci)
        nan = np.full(n, np.nan)
        ts = np.stack(
            [np.zeros(n), np.where(ok[:n], t_q[:n], nan), t[ci], np.where(ok[n:], t_q[n:], nan), np.ones(n)],
            axis=1,
        )
        fs = np.stack([np.zeros(n), q_sag[:n], sag[ci], q_sag[n:], np.zeros(n)], axis=1)
        ts = np.clip(ts, 0.0, 1.0)
        order = np.argsort(np.where(np.isnan(ts), np.inf, ts), axis=1)
        ts, fs = np.take_along_axis(ts, order, axis=1), np.take_along_axis(fs, order, axis=1)
        filled = np.where(np.isnan(ts), 1.0, ts)  # (the lost samples sort last, onto the chord's end)
        gaps = np.diff(filled, axis=1)
        g = np.argmax(gaps, axis=1)
        rows = np.flatnonzero((gaps[np.arange(n), g] > MAX_SAMPLE_GAP) & (length[ci] > self.chord))
        if not len(rows):
            return
        seg, g = ci[rows], g[rows]
        t_lo, t_hi = filled[rows, g], filled[rows, g + 1]
        t_new = 0.5 * (t_lo + t_hi)
        face, zc, step = (a[seg] for a in on)
        guess = pa[seg] + t_new[:, None] * (pb[seg] - pa[seg])
        p, found, _ = self._solve_from_chord(face, zc, step, guess, pa[seg], pb[seg])
        p = np.nan_to_num(p)
        d = point_segment_distance(p, pa[seg], pb[seg])
        found &= d <= 0.5 * length[seg]
        self.stats.gap_samples += len(rows)
        if not found.any():
            return
        rows, seg, g, p, d = rows[found], seg[found], g[found], p[found], d[found]
        t_p = _chord_position(p, pa[seg], pb[seg])
        peak = _parabola_peak(
            np.stack([filled[rows, g], t_p, filled[rows, g + 1]], axis=1),
            np.stack([fs[rows, g], d, fs[rows, g + 1]], axis=1),
            np.ones(len(rows), dtype=bool),
        )
        sag[seg] = np.maximum(sag[seg], np.maximum(d, peak))

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

    def _drop_off_trim_ends(
        self, runs: list[_Run], ri: np.ndarray, xyz: np.ndarray, vid: np.ndarray, uv: np.ndarray
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
                dropped = []
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
        (``_into_trim``) take the stretch's end points' places (a stretch of one point gets a second):
        the ring leaves the face's curve at the face's boundary, a point of the B-rep, not at
        whichever of its samples came last inside. Where the surface's curve leaves the face between
        two of its edges' crossings that the file's tolerance lets apart (boxed_sphere turned (30.7,
        26.2, 59.9) at z = 0.1: edge tolerances of 0.055 mm, a curve leaving the face and coming back
        0.3 mm further on), the ring bridges the gap from boundary to boundary. A stretch that
        ``_drop_off_trim_ends`` dropped next to a corner moves only at its side away from the
        corner: the corner joins the face's curve where it enters the trim. Returns the four arrays
        (with the added points)."""
        gone = vid == -2
        if not gone.any():
            return ri, xyz, vid, uv
        n = len(ri)
        ks = np.flatnonzero(gone)
        # the stretches: runs of consecutive dropped points of one run
        breaks = np.flatnonzero((np.diff(ks) != 1) | (ri[ks[1:]] != ri[ks[:-1]]))
        starts, stops = ks[np.concatenate([[0], breaks + 1])], ks[np.concatenate([breaks, [len(ks) - 1]])]
        added: list[tuple[int, np.ndarray, np.ndarray]] = []  # (insert before, xyz, uv)
        for a, b in zip(starts.tolist(), stops.tolist(), strict=True):
            beyond = {k: (xyz[k].copy(), uv[k].copy()) for k in (a, b)}  # (where they were dropped)
            moved = False
            for k, beside in ((a, a - 1), (b, b + 1)):
                if not (0 <= beside < n and ri[beside] == ri[k] and vid[beside] != -2):
                    continue
                if vid[beside] in self.corner_vids:
                    continue
                r = int(ri[k])
                out_xyz, out_uv = beyond[k]
                entry = self._into_trim(
                    int(run_face[r]),
                    float(run_z[r]),
                    float(run_step[r]),
                    out_xyz,
                    xyz[beside],
                    out_uv,
                    uv[beside],
                )
                if entry is None:
                    continue
                self.stats.trim_entry_points += 1
                if moved:  # a stretch of one point, moved already: one more after it
                    added.append((k + 1, *entry))
                else:
                    xyz[k], uv[k] = entry
                    vid[k] = -1
                    moved = a == b
        if added:
            at = np.array([p for p, _, _ in added])
            ri = np.insert(ri, at, ri[at - 1])
            vid = np.insert(vid, at, -1)
            xyz = np.insert(xyz, at, np.array([q for _, q, _ in added]), axis=0)
            uv = np.insert(uv, at, np.array([w for _, _, w in added]), axis=0)
        return ri, xyz, vid, uv

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
    spaced = (t2 - t1 > 1e-9) & (t3 - t2 > 1e-9)
    good = ok & (a < 0) & (ts > t1) & (ts < t3) & spaced & np.isfinite(peak)
    cap = 1.5 * f.max(axis=1)
    out = np.where(good, np.minimum(peak, cap), 0.0)
    out = np.maximum(out, np.where(ok, _zero_end_peak(t, f), 0.0))  # the quartic
    return np.maximum(out, np.where(ok & spaced, np.maximum(start, end), 0.0))


def _zero_end_peak(t: np.ndarray, f: np.ndarray) -> np.ndarray:
    """Row-wise estimate of the largest distance of a segment's curve from its chord from k samples
    (t, f) ((n, k), t ascending or not): the peak of t (1 - t) g(t), g the polynomial of degree k - 1
    through g_i = f_i / (t_i (1 - t_i)), zero at the chord's ends as the curve is (a circular arc's
    distance is c t (1 - t) to second order: g constant), evaluated on a grid and capped at 1.5 times
    the largest sample. Three samples give ``_parabola_peak``'s quartic; two (a quarter point lost)
    a cubic. 0 where two samples are not apart or one lies within ``_QUARTIC_END`` of an end (no
    shape there)."""
    order = np.argsort(t, axis=1)
    t, f = np.take_along_axis(t, order, axis=1), np.take_along_axis(f, order, axis=1)
    k = t.shape[1]
    x = _QUARTIC_GRID[None, :]
    with np.errstate(divide="ignore", invalid="ignore"):
        g = f / (t * (1.0 - t))
        lag = []  # the Lagrange basis on the samples, on the grid
        for i in range(k):
            num, den = 1.0, 1.0
            for j in range(k):
                if j != i:
                    num = num * (x - t[:, j, None])
                    den = den * (t[:, i] - t[:, j])
            lag.append(num / den[:, None])
        value = (x * (1.0 - x) * sum(g[:, i, None] * lag[i] for i in range(k))).max(axis=1)
    spaced = (np.diff(t, axis=1) > 1e-9).all(axis=1)
    good = spaced & (t[:, 0] > _QUARTIC_END) & (t[:, -1] < 1.0 - _QUARTIC_END) & np.isfinite(value)
    return np.where(good, np.minimum(value, 1.5 * f.max(axis=1)), 0.0)


# where ``_zero_end_peak`` is evaluated; samples this close to an end give it no shape
_QUARTIC_GRID = np.linspace(0.0, 1.0, 65)
_QUARTIC_END = 0.02


def _chord_position(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise position of the projection of ``p`` on the line a-b (0 at a, 1 at b)."""
    ab = b - a
    denom = np.einsum("ij,ij->i", ab, ab)
    return np.einsum("ij,ij->i", p - a, ab) / np.where(denom > 0, denom, 1.0)


def point_segment_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise distance (mm) from points ``p`` to segments ``a``-``b``; all (n, 3)."""
    t = np.clip(_chord_position(p, a, b), 0.0, 1.0)
    return np.linalg.norm(p - (a + t[:, None] * (b - a)), axis=1)


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


def _inflected_segments(
    ri: np.ndarray, xyz: np.ndarray, after: np.ndarray | None = None, gap: np.ndarray | None = None
) -> np.ndarray:
    """The segments (index of their first point) of runs ``ri`` (points sorted by run and arc
    length, at ``xyz``) whose polyline turns one way at one end and the other way at the other: the
    curve has an inflection inside, where the midpoint can lie on the chord while the curve is off it
    on either side (r103ec turned (5.4, -134.3, 135.1), the report's reference at z = 12.1: a 1.67 mm
    segment with its midpoint on the chord and the curve 5 um off it at a quarter and three quarters
    of the way). At a run's end the turn is taken with the first segment of the run ``after`` it
    (``_run_successors``; runs numbered 0 .. n - 1, each with two points or more); a segment ending
    where that is not known counts as inflected. Turns of under 1e-9 rad count as none (a straight
    line's points in a row). ``gap``: the points added next to run ends off their curve
    (``_gap_end_points``): the turn there is not known, and the jump from the run's end to one is
    no curve to check."""
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
    if gap is not None:
        known &= ~gap
        run_end = np.concatenate([[True], ~same]) | np.concatenate([~same, [True]])
        jump = np.concatenate([(gap[1:] & run_end[:-1]) | (gap[:-1] & run_end[1:]), [False]])
        same = same & ~jump[:-1]
    k = np.flatnonzero(same & (length > 1e-9))
    flip = ~known[k] | ~known[k + 1] | (turn[k] * turn[k + 1] < 0)
    return k[flip]


def _gap_place(z: float, face: int, pa: np.ndarray, pb: np.ndarray) -> str:
    return f"z={z:.4f} mm, face {face + 1}, from {np.round(pa, 4).tolist()} to {np.round(pb, 4).tolist()}"
