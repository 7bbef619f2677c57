"""A run's end vertices as its face sees them: the face's section tangent there (the end-bend
check, ``chords.end_bend_segments``) and, where an end vertex lies off its face's section curve
(the face and the edge the vertex is on apart within the file's tolerance), the curve's point
nearest it as the run's next point (``RunEnds``, a mixin of ``RunRefiner``).
"""

from __future__ import annotations

import numpy as np
from OCP.gp import gp_Pnt, gp_Vec

from worker.dst.chords import end_segments
from worker.dst.face_limits import TRIM_TOL_MM
from worker.dst.runs import GAP_POINT, GAP_SPAN_REL, Run
from worker.dst.sampler_state import SamplerState

END_TANGENT_ITER = 6  # Gauss-Newton steps placing a run's end vertex on its face (from its seed path)
# ... where it lies within this of the face (a file's tolerance): the face's tangent
END_TANGENT_TOL_MM = 0.01
END_TANGENT_MIN_SLOPE = 1e-3  # a face steeper than this (normal's horizontal share) has a section tangent
# A run's end vertex farther than this many chord budgets from its face's section curve (the face
# and the edge the vertex lies on apart within the file's tolerance, on a shallow face) gets the
# curve's point nearest it as the run's next point (``_gap_end_points``)
GAP_END_REL = 0.25


class RunEnds(SamplerState):
    """``RunRefiner``'s handling of run end vertices (a mixin)."""

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
        a, b, run, end = end_segments(ri[order], xyz[order], e)
        mine = np.array([runs[k].gap_ends for k in run.tolist()], dtype=bool)
        a, b, run, end = a[mine], b[mine], run[mine], end[mine]
        tangents[run, end], foot_uv, off = self._end_tangents(
            [runs[k] for k in run.tolist()], end, offsets=True
        )
        known[run, end] = True
        assert foot_uv is not None and off is not None  # (asked for)
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
        vid_all.append(np.full(len(run), GAP_POINT, dtype=np.int64))
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

    def _end_tangents(
        self, runs: list[Run], end: np.ndarray, offsets: bool = False
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
        runs: list[Run],
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
        on its way to the end segment's other point ``inner`` (``_into_trims``), within the same
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
        off_trim = [
            i
            for i in np.flatnonzero(ok).tolist()
            if not self.mesh.faces[face[i]].contains(
                float(out_uv[i, 0]), float(out_uv[i, 1]), tol=TRIM_TOL_MM
            )
        ]
        ok[off_trim] = False
        entries = self._into_trims(
            [
                (
                    int(face[i]),
                    float(zc[i]),
                    float(step[i]),
                    xyz[i],
                    inner[i],
                    out_uv[i],
                    inner_uv[i],
                )
                for i in off_trim
            ]
        )
        for i, entry in zip(off_trim, entries, strict=True):
            if entry is not None and np.linalg.norm(entry[0][:2] - self.pool.xyz[vid[i], :2]) <= near[i]:
                xyz[i], out_uv[i], ok[i] = entry[0], entry[1], True
                self.stats.trim_entry_points += 1
        return xyz, ok, out_uv
