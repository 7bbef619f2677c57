"""Batched solves on the faces of a ring sampler: points of a face's level set ``z(u, v) = plane``
(Newton), the (u, v) of points on or near a face (Gauss-Newton on the distance, feet within the
surface's bounds) and the face evaluations they share.

A mixin of ``RingSampler`` (its faces' evaluators, boxes, periods and statistics are the sampler's
own). A batch holds points of many faces: each step is a few numpy calls on the whole batch, the
surfaces evaluated per face by their vectorised evaluators (``analytic``) or, for a few points or a
face those do not cover, by OCCT's ``D1`` point by point.
"""

from __future__ import annotations

import numpy as np
from OCP.gp import gp_Pnt, gp_Vec

from worker.dst.constants import LEVEL_TOL_MM, NEWTON_MAX_ITER
from worker.dst.exact import SETTLED_GAP_MM, SETTLED_STEP_REL, UV_NEAR_MAX_ITER, UV_NEAR_TOL_MM
from worker.dst.face_limits import beyond_box
from worker.dst.sampler_state import SamplerState

# ``_d1``: a face's points are evaluated by its vectorised evaluator in batches of at least this
# many (with derivatives; the point alone), one by one by OCCT's D1 below that: scipy's NdBSpline
# costs ~30 us a call whatever the batch (three calls with derivatives), OCCT's D1 ~3-8 us a point,
# and most of a big part's batches are of one to four points (trj7_b1-ec-214's reference: 152,000
# of its 512,000 B-spline batches hold one point, 107,000 two)
BATCH_MIN_D1 = 8
BATCH_MIN_P = 4
# ``_bounded_feet``: Gauss-Newton steps at most (trj7_b1-ec-214's feet settle in 2-4)
BOUNDED_FOOT_ITER = 12


class BatchedSolves(SamplerState):
    """``RingSampler``'s batched solves on its faces (a mixin)."""

    def _d1(
        self, fa: np.ndarray, ua: np.ndarray, va: np.ndarray, ads, p, du, dv, derivatives: bool = True
    ) -> np.ndarray:
        """(n, 9) rows P, Pu, Pv: the face's vectorised evaluator (``analytic``) for a batch of a
        face's points, OCCT's D1 point by point for a face it does not cover and for a few points
        (``BATCH_MIN_D1``, ``BATCH_MIN_P``).

        With ``derivatives=False`` only P is guaranteed (the B-spline evaluator skips Pu and Pv)."""
        res = np.empty((len(fa), 9))
        an = self._analytic[fa]
        idx = np.flatnonzero(an)
        few = np.zeros(len(fa), dtype=bool)
        if idx.size:
            order = idx[np.argsort(fa[idx], kind="stable")]
            faces, starts = np.unique(fa[order], return_index=True)
            bounds = np.append(starts, len(order))
            least = BATCH_MIN_D1 if derivatives else BATCH_MIN_P
            for k, f in enumerate(faces.tolist()):
                sel = order[bounds[k] : bounds[k + 1]]
                if len(sel) < least:
                    few[sel] = True
                    continue
                P, Pu, Pv = self._evals[f](ua[sel], va[sel], derivatives)
                res[sel, 0:3] = P
                if Pu is not None:
                    res[sel, 3:6], res[sel, 6:9] = Pu, Pv
        other = np.flatnonzero(~an | few)
        if other.size:
            rows = []
            for f, uu, vv in zip(fa[other].tolist(), ua[other].tolist(), va[other].tolist(), strict=True):
                ads[f].D1(uu, vv, p, du, dv)
                rows.append(p.Coord() + du.Coord() + dv.Coord())
            res[other] = np.array(rows).reshape(-1, 9)
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

    def _uv_near(
        self, face: np.ndarray, xyz: np.ndarray, seed: np.ndarray, *, foot: bool = False
    ) -> np.ndarray:
        """``FaceEval.uv_near`` of many points at once ((n, 2) (u, v) of ``xyz`` (n, 3) on faces
        ``face``, from ``seed`` (n, 2)): its Gauss-Newton on the distance batched (``_d1``: a few
        numpy calls a step instead of OCCT's D1 and a dozen Python lines a point and step), with
        the same steps, stops and box check; the points it does not place are projected one by
        one (``FaceEval.project``), as ``uv_near`` projects them. With ``foot``, a foot is taken
        also where it settles within SETTLED_GAP_MM of the surface, and within the surface's own
        bounds rather than the face's box (beyond them: ``_bounded_feet``), as that projection
        would place it."""
        n = len(face)
        u, v = seed[:, 0].astype(np.float64), seed[:, 1].astype(np.float64)
        there = np.full((n, 3), np.nan)  # (u, v, squared gap) within the tolerance, or the settled foot
        has = np.zeros(n, dtype=bool)
        act = np.arange(n)
        p, du, dv = gp_Pnt(), gp_Vec(), gp_Vec()
        for _ in range(UV_NEAR_MAX_ITER):
            if not act.size:
                break
            res = self._d1(face[act], u[act], v[act], self._ads, p, du, dv)
            r = xyz[act] - res[:, :3]
            gap2 = np.einsum("ij,ij->i", r, r)
            # within the tolerance at the last step: this step's point where it is closer, and done
            last = has[act]
            closer = last & (gap2 < there[act, 2])
            i = act[closer]
            there[i] = np.column_stack([u[i], v[i], gap2[closer]])
            go = ~last
            act, res, r, gap2 = act[go], res[go], r[go], gap2[go]
            within = gap2 <= UV_NEAR_TOL_MM * UV_NEAR_TOL_MM
            i = act[within]
            there[i] = np.column_stack([u[i], v[i], gap2[within]])
            has[i] = True
            su_, sv_ = res[:, 3:6], res[:, 6:9]
            a11 = np.einsum("ij,ij->i", su_, su_)
            a12 = np.einsum("ij,ij->i", su_, sv_)
            a22 = np.einsum("ij,ij->i", sv_, sv_)
            det = a11 * a22 - a12 * a12
            ok = det > 1e-12 * a11 * a22  # else (also NaN) a pole, or tangents nearly parallel: stop
            act, r, gap2, within = act[ok], r[ok], gap2[ok], within[ok]
            su_, sv_, a11, a12, a22, det = su_[ok], sv_[ok], a11[ok], a12[ok], a22[ok], det[ok]
            b1, b2 = np.einsum("ij,ij->i", su_, r), np.einsum("ij,ij->i", sv_, r)
            su, sv = (a22 * b1 - a12 * b2) / det, (a11 * b2 - a12 * b1) / det
            # settled at the foot of a point off the surface (see ``FaceEval._newton_uv``): the
            # foot, or (not ``foot``) no answer from Newton; either way no more steps
            step2 = su * su * a11 + 2.0 * su * sv * a12 + sv * sv * a22
            # (a foot, a seed for another solve, also where the gap is under SETTLED_GAP_MM: points
            # of a B-rep edge 2-4 nm off the face stalled there until the last step, then went to
            # OCCT's projection: 6,900 of trj7_b1-ec-214's reference)
            settled = (
                ~within
                & ((gap2 > SETTLED_GAP_MM * SETTLED_GAP_MM) | foot)
                & (step2 < SETTLED_STEP_REL * SETTLED_STEP_REL * gap2)
            )
            if foot:
                i = act[settled]
                there[i] = np.column_stack([u[i] + su[settled], v[i] + sv[settled], gap2[settled]])
                has[i] = True
            go = ~settled
            act = act[go]
            u[act] += su[go]
            v[act] += sv[go]
        period = self._period[face]
        if foot:
            # A foot beyond the surface's own bounds: the nearest point within them, as OCCT's
            # projection gives it (within the bounds, the projection from the seed is Newton's foot,
            # also beyond the face's box). Chords along a B-spline patch's side had 32,000 of the
            # 422,000 feet of trj7_b1-ec-214's reference beyond it, at ~0.2 ms a projection.
            # (Past a sphere's pole the point is on the sphere at other parameters: projected.)
            bounds = self._surface_box[face]
            out_of = has & ~_in_box(there[:, :2], bounds, period == 0.0)
            pole = out_of & _in_box(there[:, :2], bounds, self._box_checked[face])
            has &= ~pole
            beyond = np.flatnonzero(out_of & ~pole)
            if len(beyond):
                uv_b, ok_b = self._bounded_feet(face[beyond], xyz[beyond], there[beyond, :2], bounds[beyond])
                there[beyond[ok_b], :2] = uv_b[ok_b]
                has[beyond[~ok_b]] = False
        else:
            # a point beyond the face's (u, v) box in a direction that does not wrap is not taken
            # from Newton
            has &= _in_box(there[:, :2], self._uv_box[face], period == 0.0)
        out = np.empty((n, 2))
        # on the branch nearest the seed (``FaceEval.same_branch``)
        shift = np.where(period > 0, np.round((seed - there[:, :2]) / np.where(period > 0, period, 1.0)), 0.0)
        out[has] = (there[:, :2] + shift * period)[has]
        for k in np.flatnonzero(~has).tolist():
            out[k] = self.mesh.faces[int(face[k])].project(tuple(xyz[k].tolist()), tuple(seed[k].tolist()))
        return out

    def _bounded_feet(
        self, face: np.ndarray, xyz: np.ndarray, uv: np.ndarray, bounds: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """The nearest points to ``xyz`` of their faces' surfaces within the surfaces' parameter
        ``bounds`` ((n, 4): u0, u1, v0, v1; the periodic directions are not bounded), from feet
        ``uv`` beyond them: Gauss-Newton on the distance with each parameter held at a bound while
        the distance would shrink past it (a 1D step along the bound's iso-curve for the other),
        until a step moves the surface point less than ``SETTLED_STEP_REL`` of the gap (a seed for
        another solve, as the free feet). Returns the (u, v) and a mask of those that settled."""
        m = len(face)
        lo = bounds[:, [0, 2]]
        hi = bounds[:, [1, 3]]
        held = self._period[face] == 0.0  # the directions with bounds
        lo = np.where(held, lo, -np.inf)
        hi = np.where(held, hi, np.inf)
        w = np.clip(uv, lo, hi)
        settled = np.zeros(m, dtype=bool)
        act = np.arange(m)
        p, du, dv = gp_Pnt(), gp_Vec(), gp_Vec()
        for _ in range(BOUNDED_FOOT_ITER):
            res = self._d1(face[act], w[act, 0], w[act, 1], self._ads, p, du, dv)
            r = xyz[act] - res[:, :3]
            su_, sv_ = res[:, 3:6], res[:, 6:9]
            a11 = np.einsum("ij,ij->i", su_, su_)
            a12 = np.einsum("ij,ij->i", su_, sv_)
            a22 = np.einsum("ij,ij->i", sv_, sv_)
            b = np.column_stack([np.einsum("ij,ij->i", su_, r), np.einsum("ij,ij->i", sv_, r)])
            wa = w[act]
            # at a bound, with the distance shrinking past it: held there
            stop = ((wa <= lo[act]) & (b <= 0.0)) | ((wa >= hi[act]) & (b >= 0.0))
            det = a11 * a22 - a12 * a12
            # (a degenerate iso-line, a B-spline's pole, is no bound to stop at: projected instead)
            ok = (det > 1e-12 * a11 * a22) & (a11 > 1e-12 * a22) & (a22 > 1e-12 * a11)
            with np.errstate(divide="ignore", invalid="ignore"):
                free = (
                    np.column_stack([a22 * b[:, 0] - a12 * b[:, 1], a11 * b[:, 1] - a12 * b[:, 0]])
                    / det[:, None]
                )
                one = b / np.column_stack([a11, a22])  # along the other's bound
            step = np.where(stop.any(axis=1)[:, None], np.where(stop, 0.0, one), free)
            nw = np.clip(wa + step, lo[act], hi[act])
            d = nw - wa
            move2 = d[:, 0] ** 2 * a11 + 2.0 * d[:, 0] * d[:, 1] * a12 + d[:, 1] ** 2 * a22
            gap2 = np.einsum("ij,ij->i", r, r)
            w[act] = nw
            done = ok & (move2 <= SETTLED_STEP_REL * SETTLED_STEP_REL * gap2)
            settled[act[done]] = True
            act = act[ok & ~done]
            if not len(act):
                break
        return w, settled

    def _chord_ends_on(self, face: np.ndarray, a: np.ndarray, seed: np.ndarray) -> np.ndarray:
        """(n, 2): the (u, v) of chord ends ``a`` (n, 3) on faces ``face``, found from ``seed`` (the
        seed path's (u, v) where each point was solved from, or for a run's end, where the run
        starts or ends: Newton gets there in a step or two, where from (0, 0) it mostly failed and
        OCCT's projection took ~0.5 ms a point), kept per face and point: the same chord ends are
        solved from again round after round (121,000 distinct ones for 421,000 points of
        trj7_b1-ec-214's reference). Those not kept yet are placed together (``_uv_near``), each
        from the seed of its first appearance."""
        known = self._chord_end_uv
        a = np.ascontiguousarray(a, dtype=np.float64)
        keys = list(zip(face.tolist(), (row.tobytes() for row in a), strict=True))
        new: dict[tuple[int, bytes], int] = {}
        for k, key in enumerate(keys):
            if key not in known:
                new.setdefault(key, k)
        if new:
            at = np.fromiter(new.values(), dtype=np.int64, count=len(new))
            uv = self._uv_near(face[at], a[at], seed[at])
            known.update(zip(new, map(tuple, uv.tolist()), strict=True))
        return np.array([known[key] for key in keys], dtype=np.float64).reshape(-1, 2)


def _in_box(uv: np.ndarray, box: np.ndarray, checked: np.ndarray) -> np.ndarray:
    """(n,): whether each (u, v) lies within its box in the directions ``checked`` (``beyond_box``)."""
    below, above = beyond_box(uv, box, checked)
    return ~(below | above).any(axis=1)
