"""Sampling a run of a section curve under the segment-length and chord-error budget.

A run is a piece of a section curve inside one face between two exact end points, with a seed path
from the topology mesh (``sampling`` finds the runs). Points are seeded at equal arc length along
the path and moved onto the exact level set ``z(u, v) = plane`` by Newton in the face's parameter
space. Then every segment is checked against the exact curve: the curve point halfway along it
(Newton again) must lie within ``chord_error`` of the chord, and the chord must be no longer than
``segment_length``; a failing segment is split and its parts checked again. The midpoint test is
exact for circles and measures the sagitta to second order in the segment length for other smooth
curves; a segment whose midpoint may not show its largest distance (see ``_quarter_sags``) is also
checked at its quarter points, a segment with an inflection inside (``inflected_segments``) and a
run's end segment leaving its corner too steeply (``end_bend_segments``) again (those estimates and
selections: ``chords``). A run's end vertex lying off its face's curve (the face and the edge the
vertex is on apart within the file's tolerance) gets the curve's point nearest it as the run's next
point (``run_ends``); points beyond the face's trim, poles and C0 lines of its surface are
``face_limits``' business.

All Newton solves of one batch of runs run together (``solves``: numpy bookkeeping, one ``D1`` per point
and iteration), which keeps the Python overhead per ring vertex to a few microseconds.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import numpy as np

from worker.dst.chords import (
    CHORD_FILL,
    END_BEND_FACTOR,
    chord_position,
    end_bend_segments,
    end_segments,
    inflected_segments,
    parabola_peak,
    point_segment_distance,
    run_successors,
    zero_end_peak,
)
from worker.dst.constants import (
    MAX_SUBDIVISION,
    REPEAT_MM,
    SEGMENT_FILL,
)
from worker.dst.errors import TessellationError
from worker.dst.face_limits import FaceLimits
from worker.dst.run_ends import RunEnds
from worker.dst.runs import BRIDGE_POINT, GAP_POINT, GAP_SPAN_REL, Run
from worker.dst.solves import BatchedSolves

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
# A segment's midpoint (placed by arc length along the seed path) this close to either end, relative
# to the segment, is off the path: solved again from the chord's middle (``_midpoints_off_the_path``)
MID_OFF_PATH = 0.1
# A segment whose midpoint and quarter points leave more of its chord than this share unseen between
# them (or its ends) is sampled in the middle of that gap too (``_gap_sags``)
MAX_SAMPLE_GAP = 0.5
# rounds of the check of segments with an inflection inside (each: those the last round split)
MAX_INFLECTION_ROUNDS = 4
MAX_END_BEND_ROUNDS = 6
MAX_REFINE_ROUNDS = 40  # halving a segment 24 times takes 1 m down to 60 nm: still failing means broken


class RunRefiner(FaceLimits, RunEnds, BatchedSolves):
    """``RingSampler``'s sampling of runs under the budget (a mixin: the sampler's faces, vertex
    pool, budgets and statistics are its own). The checks at its faces' limits are ``FaceLimits``',
    those at its runs' end vertices ``RunEnds``', the batched solves on its faces ``BatchedSolves``'."""

    # --- the batched sampler -------------------------------------------------------------------------
    def _sample_runs(self, runs: list[Run]) -> list[list[int]]:
        """Vertex ids of each run from start to end inclusive, within the length and chord budgets.

        A run crossing a line where its face's surface is only C0 (a kink inside one B-spline face)
        is first split there at the exact section point on that line: the section has a corner
        there, which a midpoint test on a segment straddling it can miss.
        """
        if not runs:
            return []
        pieces, owner = self._split_at_kinks(runs)
        if len(pieces) == len(runs):
            return self._without_repeats(self._sample_pieces(runs))
        out: list[list[int]] = [[] for _ in runs]
        for i, ids in zip(owner, self._sample_pieces(pieces), strict=True):
            out[i].extend(ids if not out[i] else ids[1:])
        return self._without_repeats(out)

    def _without_repeats(self, runs_ids: list[list[int]]) -> list[list[int]]:
        """Each run's vertex ids without an inner point at the same point (within ``REPEAT_MM`` in x,
        y and z) as the point kept before it or as the run's end. A ring drops such a repeat
        (``_dedupe_cyclic``) while the kept triangles of a pinned loop take its segments' points as
        they are: a repeat kept there and not in the ring leaves a hole (bug27453_165-174 turned
        (22.6, 52.9, -123.0) at chord_error 0.005 mm, z = 20.3: a curve 31 um across round a dimple
        sampled to 191 points, two pairs of them 0.4 nm and 8 pm apart; six open edges)."""
        xyz = self.pool.xyz
        flat = np.fromiter((v for ids in runs_ids for v in ids), dtype=np.int64)
        if len(flat) < 2:
            return runs_ids
        step = np.abs(np.diff(xyz[flat], axis=0)).max(axis=1)
        # (not the step from a run's end to the next run's start: often the same vertex)
        ends = np.cumsum([len(ids) for ids in runs_ids])[:-1] - 1
        step[ends[ends >= 0]] = np.inf
        if step.min() >= REPEAT_MM:
            return runs_ids
        out = []
        for ids in runs_ids:
            p = xyz[ids]
            if len(ids) < 3 or np.abs(np.diff(p, axis=0)).max(axis=1).min() >= REPEAT_MM:
                out.append(ids)
                continue
            kept = [ids[0]]
            for k in range(1, len(ids) - 1):
                if np.abs(p[k] - xyz[kept[-1]]).max() >= REPEAT_MM:
                    kept.append(ids[k])
            while len(kept) > 1 and np.abs(xyz[kept[-1]] - p[-1]).max() < REPEAT_MM:
                kept.pop()
            self.stats.repeat_samples += len(ids) - 1 - len(kept)
            out.append([*kept, ids[-1]])
        return out

    def _sample_pieces(self, runs: list[Run]) -> list[list[int]]:
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

        def path_uv(run_idx: np.ndarray, s: np.ndarray) -> np.ndarray:
            """(n, 2): the seed path's (u, v) at arc length ``s`` of each run."""
            g = s + shift[run_idx]
            return np.column_stack([np.interp(g, big_s, big_u), np.interp(g, big_s, big_v)])

        def solve(run_idx: np.ndarray, s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
            uv = path_uv(run_idx, s)
            return self._newton(run_face[run_idx], uv[:, 0], uv[:, 1], run_z[run_idx], run_step[run_idx])

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
                # where a chord's point is solved again from the chord: the path's (u, v) at its start,
                # to find that start's (u, v) on the face from (``_chord_ends_on``)
                on = (run_face[ri], run_z[ri], run_step[ri], path_uv(ri, sa))
                off_path = self._midpoints_off_the_path(
                    on, mid, mid_ok, pa, pb, length, run_traced[ri], mid_uv
                )
                sag = np.where(mid_ok, point_segment_distance(np.nan_to_num(mid), pa, pb), 0.0)
                # midpoints placed by their path position in their chord's middle half (not solved
                # again from the chord, not on a trace): where a segment may be halved (``_halves``)
                halvable = None
                if halving:
                    t_mid = chord_position(np.nan_to_num(mid), pa, pb)
                    halvable = ~off_path & ~run_traced[ri] & (t_mid >= 0.25) & (t_mid <= 0.75)
                quarters, q_ok = self._quarter_sags(
                    solve,
                    on,
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
                    assert halvable is not None  # (set where ``halving``)
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
                    self._record_gaps(gap, length, pa, pb, run_plane[ri], run_face[ri])
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
                t_new = chord_position(np.nan_to_num(new_xyz), pa[bq], pb[bq])
                margin = 0.25 / m[seg]
                new_ok &= ((t_new > margin) & (t_new < 1.0 - margin)) | run_traced[ri[bq]]
                if not new_ok.all():
                    miss = np.flatnonzero(~new_ok)
                    frac = (k / m[seg])[miss]
                    guess = pa[bq][miss] + frac[:, None] * (pb[bq][miss] - pa[bq][miss])
                    xyz_m, ok_m, uv_m = self._solve_from_chord(
                        tuple(a[bq][miss] for a in on), guess, pa[bq][miss], pb[bq][miss]
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
            ends = end_segments(ri[order], xyz[order], END_BEND_FACTOR * 4.0 * e)
            run, end = ends[2:]
            todo = ~known[run, end]
            run, end = run[todo], end[todo]
            tangents[run, end] = self._end_tangents([runs[k] for k in run.tolist()], end)[0]
            known[run, end] = True
            a, b = end_bend_segments(xyz[order], ends, tangents, e)
            a, b = order[a], order[b]
            unchecked = [
                k
                for k, key in enumerate(zip(ri[a].tolist(), s_[a].tolist(), s_[b].tolist(), strict=True))
                if key not in forced
            ]
            if not unchecked:
                break
            a, b = a[unchecked], b[unchecked]
            forced.update(zip(ri[a].tolist(), s_[a].tolist(), s_[b].tolist(), strict=True))
            self.stats.end_bend_checks += len(a)
            refine((ri[a], s_[a], s_[b], xyz[a], xyz[b]), forced=True)
        # A segment whose curve turns one way near one end and the other way near the other has an
        # inflection inside, where its midpoint can lie on the chord with the curve off it on either
        # side: checked again at its quarter points (and split where it fails), until none is left.
        # After the first round only segments at or next to the points it added are looked at.
        checked = 0  # points before this index: their segments checked
        after = run_successors(first, last)
        for _ in range(MAX_INFLECTION_ROUNDS):
            ri, s_, xyz = np.concatenate(run_all), np.concatenate(s_all), np.concatenate(xyz_all)
            order = np.lexsort((s_, ri))
            gap_pt = np.concatenate(vid_all)[order] == GAP_POINT
            inflected = inflected_segments(ri[order], xyz[order], after, gap_pt if gap_pt.any() else None)
            if checked:
                fresh = order >= checked
                near = fresh | np.roll(fresh, 1) | np.roll(fresh, -1)
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
        ri, xyz, vid, uv = ri[keep], xyz[keep], vid[keep], uv[keep]
        if not keep.all():
            # a segment that now spans dropped points may exceed the budget: no exact point of this
            # face lies there, so it is a gap of the B-rep (reported with the others; segments kept
            # over budget during refinement were counted there already)
            spans = (ri[1:] == ri[:-1]) & (dropped_before[1:] != dropped_before[:-1])
            d = np.where(spans, np.linalg.norm(xyz[1:] - xyz[:-1], axis=1), 0.0)
            self._record_gaps(d > L, d, xyz[:-1], xyz[1:], run_z[ri[:-1]], run_face[ri[:-1]])
        new = np.flatnonzero(vid < 0)
        gap_pt = new[vid[new] == GAP_POINT]
        bridge_pt = new[vid[new] == BRIDGE_POINT]
        vid[new] = self.pool.extend(
            xyz[new, :2], run_z[ri[new]], run_plane[ri[new]], run_face[ri[new]], uv[new]
        )
        # where the curve meets the jump from a run's end vertex off it (the ring turns there)
        self.gap_vids.update(vid[gap_pt].tolist())
        self.bridge_vids.update(vid[bridge_pt].tolist())
        bounds = np.searchsorted(ri, np.arange(n_runs + 1))
        ids = vid.tolist()
        return [ids[bounds[i] : bounds[i + 1]] for i in range(n_runs)]

    def _midpoints_off_the_path(self, on, mid, mid_ok, pa, pb, length, traced, mid_uv) -> np.ndarray:
        """Solve again (in place, with their face parameters ``mid_uv``) the midpoints that the seed path put off their segment's middle.

        A seed path interpolated in (u, v) through a topology triangle with a corner at a pole of
        its face's parametrisation (or across a seam) can run anywhere on the surface: the midpoint
        then lands near an end of its segment, or nowhere, and the segment would pass unchecked (on
        bug29241 two 0.15 mm chords cut across a 0.07 mm boss). Those are solved again from the
        chord's middle projected on the face; a segment whose midpoint still cannot be placed in
        its middle is counted (``unchecked_segments``) and reported. Returns the mask of the
        midpoints solved again (found or not).
        """
        t = chord_position(np.nan_to_num(mid), pa, pb)
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
            tuple(a[off] for a in on), 0.5 * (pa[off] + pb[off]), pa[off], pb[off]
        )
        mid[off[ok]], mid_ok[off[ok]], mid_uv[off[ok]] = p[ok], True, uv[ok]
        mid_ok[off[~ok & ~long[off]]] = False
        self.stats.unchecked_segments += int((~ok & long[off]).sum())
        return again

    def _solve_from_chord(self, on, guess, pa, pb) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Section points seeded from points ``guess`` on the chords pa-pb projected on their faces
        (not from the seed path; ``on``: each chord's face, plane height, Newton step and the seed
        path's (u, v) at pa): (points, mask of those found strictly between their chord's ends,
        (u, v))."""
        face, zc, step, at_a = on
        face = np.asarray(face, dtype=np.int64)
        seeds = self._chord_ends_on(face, pa, np.asarray(at_a, dtype=np.float64).reshape(-1, 2))
        uv = self._uv_near(face, np.asarray(guess, dtype=np.float64).reshape(-1, 3), seeds, foot=True)
        p, ok, out_uv = self._newton(face, uv[:, 0], uv[:, 1], zc, np.asarray(step))
        t = chord_position(np.nan_to_num(p), pa, pb)
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
        segment's face, plane height, Newton step and the seed path's (u, v) at its start), as a
        midpoint is (``_midpoints_off_the_path``; trj6_k1-al-214 turned (112.9, 27.5, -64.7) at z
        = 44.5: both of a 0.167 mm segment's quarter points landed past its ends round a 0.5 mm
        loop, its midpoint 0.024 mm from the chord, and it passed with the curve 0.028 mm from it).
        Where one quarter point is still lost, the midpoint and the other give the peak
        (``zero_end_peak``). The quarter points solved again serve the peak only (``q_ok`` false:
        not a half's midpoint for ``_halves``).
        """
        ri, sa, sb, pa, pb = pending
        e = self.chord
        budget = e if budget is None else budget
        quarters = np.full((len(ri), 2, 3), np.nan)
        q_ok = np.zeros((len(ri), 2), dtype=bool)
        t = chord_position(np.nan_to_num(mid), pa, pb)
        within = sag <= e
        if budget > e:
            within |= (sag <= budget) & halvable
        check = mid_ok & within & (length <= self.seg_len) & (length > 1e-9)
        if not everywhere:  # (else: segments with an inflection, ``inflected_segments``)
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
        t_q = chord_position(pts, pa[q], pb[q])
        ok &= ((t_q > 0.0) & (t_q < 1.0)) | traced[q]
        on_path = ok.copy()
        if (lost := np.flatnonzero(~ok)).size:
            qq = q[lost]
            guess = pa[qq] + frac[lost, None] * (pb[qq] - pa[qq])
            p2, ok2, _ = self._solve_from_chord(tuple(a[qq] for a in on), guess, pa[qq], pb[qq])
            found = lost[ok2]
            pts[found], t_q[found], ok[found] = (
                p2[ok2],
                chord_position(p2[ok2], pa[q[found]], pb[q[found]]),
                True,
            )
            self.stats.quarter_resolves += len(lost)
        q_sag = np.where(ok, point_segment_distance(pts, pa[q], pb[q]), 0.0)
        n = len(ci)
        peak = parabola_peak(
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
            peak = np.maximum(peak, np.where(one, zero_end_peak(pair_t, pair_f), 0.0))
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
        guess = pa[seg] + t_new[:, None] * (pb[seg] - pa[seg])
        p, found, _ = self._solve_from_chord(tuple(a[seg] for a in on), guess, pa[seg], pb[seg])
        p = np.nan_to_num(p)
        d = point_segment_distance(p, pa[seg], pb[seg])
        found &= d <= 0.5 * length[seg]
        self.stats.gap_samples += len(rows)
        if not found.any():
            return
        rows, seg, g, p, d = rows[found], seg[found], g[found], p[found], d[found]
        t_p = chord_position(p, pa[seg], pb[seg])
        peak = parabola_peak(
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
            t = chord_position(q[h], starts[h], ends[h])
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

    def _record_gaps(self, gap, length, pa, pb, plane, face) -> None:
        """Count the segments ``gap`` (kept over budget: no exact point between their ends; at plane
        indices ``plane``), and keep them for ``settle_gaps``."""
        if not gap.any():
            return
        self.stats.tolerance_gaps += int(gap.sum())
        g = int(np.argmax(np.where(gap, length, -1.0)))
        if length[g] > self.stats.max_gap_mm:
            self.stats.max_gap_mm, self.stats.max_gap_plane, self.stats.max_gap_at = (
                float(length[g]),
                int(plane[g]),
                _gap_place(face[g], pa[g], pb[g]),
            )
        for k in np.flatnonzero(gap).tolist():
            self._gaps.append((float(length[k]), int(plane[k]), int(face[k]), pa[k].tolist(), pb[k].tolist()))

    def settle_gaps(self, rings: Iterable[Sequence[int]]) -> None:
        """Count again (``tolerance_gaps``, ``max_gap_*``) only the gaps that are segments of the final
        ``rings``: a segment re-sampled after it was kept over budget (along a trace of the curve
        round an excursion its seeds skipped) is no gap of the mesh."""
        kept = []
        if self._gaps:
            # the rings' segments (both ways) with an end at a gap's x: a gap's own segment is one
            # (the rings of a big part hold millions: a set of them all took 0.5 s on trj3_s1-al)
            gap_x = np.array([g[k][0] for g in self._gaps for k in (3, 4)])
            ring_list = [np.asarray(r) for r in rings if len(r) >= 2]
            at = np.concatenate(ring_list) if ring_list else np.zeros(0, dtype=np.int64)
            after = np.concatenate([np.roll(r, -1) for r in ring_list]) if ring_list else at
            xy = self.pool.xyz[:, :2]
            p, q = xy[at], xy[after]
            near = np.isin(p[:, 0], gap_x) | np.isin(q[:, 0], gap_x)
            p, q = p[near], q[near]
            ends = set(map(tuple, np.column_stack([p, q]).tolist()))
            ends.update(map(tuple, np.column_stack([q, p]).tolist()))
            kept = [g for g in self._gaps if (*g[3][:2], *g[4][:2]) in ends]
        self.stats.tolerance_gaps = len(kept)
        worst = max(kept, default=None, key=lambda g: g[0])
        self.stats.max_gap_mm = 0.0 if worst is None else worst[0]
        self.stats.max_gap_plane = -1 if worst is None else worst[1]
        self.stats.max_gap_at = (
            "" if worst is None else _gap_place(worst[2], *(np.array(worst[k]) for k in (3, 4)))
        )


def _gap_place(face: int, pa: np.ndarray, pb: np.ndarray) -> str:
    """A gap's face and ends in x, y (as the mesh has them; its plane gives z above the bed)."""
    return f"face {face + 1}, from {np.round(pa[:2], 4).tolist()} to {np.round(pb[:2], 4).tolist()}"
