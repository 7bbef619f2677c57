"""Exact evaluation on the B-rep: points of a face or an edge at a given height.

Corner points and crossings of the topology mesh come from here (the batched Newton on level sets
that places all other ring vertices lives in ``sampling`` and ``refine``). Two primitives:

- :func:`root_on_uv_segment`: the point at height ``c`` on the surface along a straight (u, v) segment
  whose ends bracket ``c`` (Brent): used for the crossings of topology-mesh edges inside a face.
- :func:`root_on_curve`: the point at height ``c`` on an edge's 3D curve between two parameters that
  bracket it (Brent): used where a section crosses a B-rep edge (a corner of the section).

All points are in millimetres in the part's placement (``BRepAdaptor_*`` apply face and edge locations).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from OCP.BRep import BRep_Tool
from OCP.BRepAdaptor import BRepAdaptor_Curve, BRepAdaptor_Surface
from OCP.BRepBuilderAPI import BRepBuilderAPI_MakeVertex
from OCP.BRepClass import BRepClass_FaceClassifier
from OCP.BRepExtrema import BRepExtrema_DistShapeShape
from OCP.Extrema import Extrema_ExtPC
from OCP.GeomAbs import GeomAbs_Sphere
from OCP.gp import gp_Pnt, gp_Pnt2d, gp_Vec
from OCP.IntTools import IntTools_FClass2d
from OCP.ShapeAnalysis import ShapeAnalysis_Surface
from OCP.TopAbs import TopAbs_IN, TopAbs_ON, TopAbs_REVERSED
from scipy.optimize import brentq, minimize_scalar

from worker.dst.analytic import Evaluator, evaluator
from worker.dst.constants import POLE_TOL_MM, ROOT_XTOL

# a walk along a section curve stops this close (mm, along the curve) to the point nearest its target
WALK_TOL_MM = 1e-7
# a trace along a section curve (``FaceEval.trace_level``) takes a step only where the curve's direction
# turns by less than this over it (else the step is halved): it follows a bend of any radius
TRACE_MAX_TURN_COS = math.cos(math.radians(15.0))
# ... and arrives where the chord to its target is within 30 degrees of the curve at both ends
TRACE_ARRIVAL_COS = math.cos(math.radians(30.0))
TRACE_MIN_STEP_MM = 1e-6  # a bend needing shorter steps is a cusp of the section: the trace gives up
TRACE_MAX_STEPS = 20_000

# ``FaceEval.uv_near``: a point this close to the surface (mm) is taken as lying on it, its (u, v)
# found by Newton (at most this many steps) from the seed
UV_NEAR_TOL_MM = 1e-9
UV_NEAR_MAX_ITER = 8
# ... and gives up early where a step moves the surface point less than this share of its distance
# from the point, itself over this (mm): settled at the foot of a point off the surface
SETTLED_STEP_REL = 1e-3
SETTLED_GAP_MM = 1e-6

_RTOL = 4.5 * 2.220446049250313e-16  # brentq refuses anything below 4 * machine epsilon


class ExactFailure(Exception):
    """Newton or a bracketed root did not converge (internal; callers fall back or report)."""


class WalkPassed(ExactFailure):
    """A walk along a section curve passed one of the points it was to avoid."""


class FaceEval:
    """A face's surface with the bookkeeping Newton needs.

    Parameters
    ----------
    adaptor : BRepAdaptor_Surface of the face (location applied)
    """

    __slots__ = (
        "ad",
        "face",
        "u0",
        "u1",
        "v0",
        "v1",
        "bounded",
        "outward",
        "_p",
        "_du",
        "_dv",
        "_sas",
        "_fclass",
        "_batch",
        "_batch_built",
        "_poles",
    )

    def __init__(self, adaptor: BRepAdaptor_Surface):
        self.ad = adaptor
        self.face = adaptor.Face()
        self.u0, self.u1 = adaptor.FirstUParameter(), adaptor.LastUParameter()
        self.v0, self.v1 = adaptor.FirstVParameter(), adaptor.LastVParameter()
        # whether a point beyond the (u, v) box in u (in v) is certainly off the face: not in a
        # periodic direction (parameters wrap), nor along a sphere's meridian (v past a pole is still
        # on the sphere); elsewhere it lies on the surface's extension, not on the B-rep
        self.bounded = (
            not adaptor.IsUPeriodic(),
            not adaptor.IsVPeriodic() and adaptor.GetType() != GeomAbs_Sphere,
        )
        # Pu x Pv times this is the outward normal (the adaptor evaluates the surface, whatever the
        # face's orientation)
        self.outward = -1.0 if self.face.Orientation() == TopAbs_REVERSED else 1.0
        self._p, self._du, self._dv = gp_Pnt(), gp_Vec(), gp_Vec()
        self._sas: ShapeAnalysis_Surface | None = None
        self._fclass: dict[float, IntTools_FClass2d] = {}
        self._batch: Evaluator | None = None
        self._batch_built = False
        self._poles: dict[tuple[int, float], bool] = {}

    @property
    def batch(self) -> Evaluator | None:
        """The surface's vectorised evaluator (``analytic.evaluator``: None for a kind it does not
        cover), built on first use and kept."""
        if not self._batch_built:
            self._batch, self._batch_built = evaluator(self.ad), True
        return self._batch

    def uv_near(
        self, xyz: Sequence[float], seed: Sequence[float], *, foot: bool = False
    ) -> tuple[float, float]:
        """(u, v) of a point on the surface, on the parameter branch nearest ``seed`` (periodic surfaces).

        A point lying on the surface (within ``UV_NEAR_TOL_MM``) is found by Newton from the seed;
        any other (off the surface by an edge's tolerance, or Newton failing: a pole, a seed too far)
        by ``ShapeAnalysis_Surface.NextValueOfUV``, which took 0.3 ms a point on a B-spline surface
        even for points on it (0.06 s of the hemisphere's 0.41 s DST build).
        ``foot``: for a point off the surface, where Newton settles at its foot inside the parameter
        box, that foot (its step on the surface then under ``SETTLED_STEP_REL`` of the gap: a seed
        for another solve, not a projection to rounding) instead of ``NextValueOfUV``'s."""
        uv = self._newton_uv(xyz, seed, foot)
        if uv is not None:
            return self.same_branch(uv, seed)
        return self.project(xyz, seed)

    def surface_bounds(self) -> tuple[float, float, float, float]:
        """(u0, u1, v0, v1): the parameter bounds of the face's whole surface (+-2e100 where it is
        unbounded), within which ``project`` finds its points."""
        return tuple(BRep_Tool.Surface_s(self.face).Bounds())

    def project(self, xyz: Sequence[float], seed: Sequence[float]) -> tuple[float, float]:
        """(u, v) of the point's projection on the surface (``NextValueOfUV`` from ``seed``), on the
        parameter branch nearest the seed: ``uv_near``'s way where Newton does not get there."""
        if self._sas is None:
            self._sas = ShapeAnalysis_Surface(BRep_Tool.Surface_s(self.face))
        p = self._sas.NextValueOfUV(
            gp_Pnt2d(float(seed[0]), float(seed[1])), gp_Pnt(*map(float, xyz)), 1e-9, -1.0
        )
        # the projection can come back on another period than the seed's (a torus face running past
        # v = 2 pi: seeded at v = 6.32, it gave v = 0)
        return self.same_branch((p.X(), p.Y()), seed)

    def _newton_uv(
        self, xyz: Sequence[float], seed: Sequence[float], foot: bool = False
    ) -> tuple[float, float] | None:
        """(u, v) where the surface passes within ``UV_NEAR_TOL_MM`` of ``xyz``, by Gauss-Newton on
        the distance from ``seed`` (one step more once there: the projection refines to rounding).
        None if it does not get there in ``UV_NEAR_MAX_ITER`` steps, the surface's tangents are
        degenerate on the way, or it ends beyond the parameter box in a direction that does not
        wrap (on the surface's extension, or at another parameter of the same point, as a sphere's
        v past a pole, which the face's trim does not hold). ``foot``: where it settles at the foot
        of a point off the surface (see below), that foot, subject to the same box."""
        p, du, dv = self._p, self._du, self._dv
        px, py, pz = xyz
        u, v = float(seed[0]), float(seed[1])
        there: tuple[float, float, float] | None = None  # (u, v, squared gap) within the tolerance
        for _ in range(UV_NEAR_MAX_ITER):
            self.ad.D1(u, v, p, du, dv)
            rx, ry, rz = px - p.X(), py - p.Y(), pz - p.Z()
            gap2 = rx * rx + ry * ry + rz * rz
            if there is not None:
                if gap2 < there[2]:
                    there = (u, v, gap2)
                break
            if gap2 <= UV_NEAR_TOL_MM * UV_NEAR_TOL_MM:
                there = (u, v, gap2)
            ux, uy, uz, vx, vy, vz = du.X(), du.Y(), du.Z(), dv.X(), dv.Y(), dv.Z()
            a11 = ux * ux + uy * uy + uz * uz
            a12 = ux * vx + uy * vy + uz * vz
            a22 = vx * vx + vy * vy + vz * vz
            det = a11 * a22 - a12 * a12
            if not det > 1e-12 * a11 * a22:  # (also NaN) a pole, or tangents nearly parallel
                break
            b1, b2 = ux * rx + uy * ry + uz * rz, vx * rx + vy * ry + vz * rz
            su, sv = (a22 * b1 - a12 * b2) / det, (a11 * b2 - a12 * b1) / det
            if there is None and gap2 > SETTLED_GAP_MM * SETTLED_GAP_MM:
                # the step's length on the surface: where it is a sliver of the gap, the residual is
                # along the normal (a foot point off the surface): it will not come within the
                # tolerance: ``uv_near`` projects instead, or takes this foot as a seed (``foot``:
                # the chord points ``refine`` solves from, off the curve by their chord's sag)
                step2 = su * su * a11 + 2.0 * su * sv * a12 + sv * sv * a22
                if step2 < SETTLED_STEP_REL * SETTLED_STEP_REL * gap2:
                    if not foot:
                        return None
                    there = (u + su, v + sv, gap2)
                    break
            u += su
            v += sv
        if there is None:
            return None
        u, v = there[0], there[1]
        for w, lo, hi, wraps in (
            (u, self.u0, self.u1, self.ad.IsUPeriodic()),
            (v, self.v0, self.v1, self.ad.IsVPeriodic()),
        ):
            margin = 1e-9 * max(hi - lo, 1.0)
            if not wraps and not lo - margin <= w <= hi + margin:
                return None
        return u, v

    def period(self, axis: int) -> float:
        """The surface's period in u (``axis`` 0) or v (1), 0 if it is not periodic there."""
        if axis == 0:
            return self.ad.UPeriod() if self.ad.IsUPeriodic() else 0.0
        return self.ad.VPeriod() if self.ad.IsVPeriodic() else 0.0

    def same_branch(self, uv: Sequence[float], near: Sequence[float]) -> tuple[float, float]:
        """``uv`` moved by whole periods of a periodic surface to the branch nearest ``near``."""
        out = [float(uv[0]), float(uv[1])]
        for axis in (0, 1):
            step = self.period(axis)
            if step:
                out[axis] += round((near[axis] - out[axis]) / step) * step
        return out[0], out[1]

    def point(self, u: float, v: float) -> tuple[float, float, float]:
        p = self.ad.Value(u, v)
        return p.X(), p.Y(), p.Z()

    def point_and_normal(self, u: float, v: float) -> tuple[np.ndarray, np.ndarray]:
        """The surface's point at (u, v) and its unit normal there (NaN where Pu x Pv vanishes)."""
        self.ad.D1(u, v, self._p, self._du, self._dv)
        n = self._du.Crossed(self._dv)
        size = n.Magnitude()
        normal = np.array([n.X(), n.Y(), n.Z()]) / size if size > 0.0 else np.full(3, np.nan)
        return np.array([self._p.X(), self._p.Y(), self._p.Z()]), normal

    def is_pole(self, axis: int, bound: float) -> bool:
        """Is the iso-line at ``bound`` of parameter ``axis`` (0: u, 1: v), across the face's (u, v)
        box, one point of the surface (a pole: the apex of a cap of revolution)? Three points along
        it, at the box's ends and middle, within ``POLE_TOL_MM`` of each other (kept per side)."""
        key = (axis, bound)
        if (known := self._poles.get(key)) is not None:
            return known
        lo, hi = (self.v0, self.v1) if axis == 0 else (self.u0, self.u1)
        pts = np.array(
            [self.point(*((bound, w) if axis == 0 else (w, bound))) for w in (lo, 0.5 * (lo + hi), hi)]
        )
        self._poles[key] = pole = bool(np.linalg.norm(pts - pts[0], axis=1).max() < POLE_TOL_MM)
        return pole

    def z_and_grad(self, u: float, v: float) -> tuple[float, float, float]:
        """z(u, v) and its partial derivatives (for minimising the height over the face)."""
        self.ad.D1(u, v, self._p, self._du, self._dv)
        return self._p.Z(), self._du.Z(), self._dv.Z()

    def contains(self, u: float, v: float, tol: float = 1e-9) -> bool:
        """True if (u, v) is inside the trimmed face or on its boundary (a classifier kept per face)."""
        return self._state(u, v, tol) in (TopAbs_IN, TopAbs_ON)

    def holds(
        self, xyz: tuple[float, float, float], tol: float, uv: tuple[float, float] | None = None
    ) -> bool:
        """True if the point lies within ``tol`` of the face (the surface inside its boundary, as
        ``BRepExtrema`` measures it: near a loose file's edge, a point the (u, v) classifiers put
        inside can lie off the face by up to the edge's tolerance).

        ``uv``: parameters where the surface passes near the point (Newton's). ``BRepExtrema``
        counts as the face the surface's points inside the face's (u, v) box that its classifier
        (``BRepClass_FaceClassifier`` at the face's tolerance) puts IN, and measures the distance to
        the nearest of them, of the edges and of the vertices. So where the surface's point at
        ``uv`` is such a point and lies within ``tol`` of ``xyz``, the point holds without the
        distance computation, whose projection on the surface took ~5 ms a call on trj7_b1-ec-214's
        35-edge B-spline face (2,400 calls in its build); elsewhere the distance decides."""
        if uv is not None and self._surface_point_in_face(xyz, uv, tol):
            return True
        vertex = BRepBuilderAPI_MakeVertex(gp_Pnt(*xyz)).Vertex()
        return BRepExtrema_DistShapeShape(vertex, self.face).Value() <= tol

    def _surface_point_in_face(
        self, xyz: tuple[float, float, float], uv: tuple[float, float], tol: float
    ) -> bool:
        """Is the surface's point at ``uv`` (moved to the branch of the face's box on a periodic
        surface) within ``tol`` of ``xyz``, strictly inside the face's (u, v) box, and IN by the
        classifier ``BRepExtrema`` uses (a point of the face as it counts one)?"""
        u, v = self.same_branch(uv, (0.5 * (self.u0 + self.u1), 0.5 * (self.v0 + self.v1)))
        if not (self.u0 < u < self.u1 and self.v0 < v < self.v1):
            return False
        x, y, z = self.point(u, v)
        if (x - xyz[0]) ** 2 + (y - xyz[1]) ** 2 + (z - xyz[2]) ** 2 > tol * tol:
            return False
        state = BRepClass_FaceClassifier(self.face, gp_Pnt2d(u, v), BRep_Tool.Tolerance_s(self.face)).State()
        return state == TopAbs_IN

    def strictly_contains(self, u: float, v: float, tol: float = 1e-9) -> bool:
        """True if (u, v) is inside the trimmed face and not on its boundary: the classifier's ON
        band follows the tolerances of the face's edges, as wide as a loose file's 0.03 mm."""
        return self._state(u, v, tol) == TopAbs_IN

    def _state(self, u: float, v: float, tol: float):
        """The trim classifier's state of (u, v) (a classifier kept per face and tolerance)."""
        fc = self._fclass.get(tol)
        if fc is None:
            fc = self._fclass[tol] = IntTools_FClass2d(self.face, tol)
        return fc.Perform(gp_Pnt2d(u, v))

    def root_on_uv_segment(
        self, ua: float, va: float, ub: float, vb: float, c: float
    ) -> tuple[float, float, float, float, float]:
        """The point at height ``c`` on the surface along the (u, v) segment a->b (ends must bracket c)."""
        ad = self.ad

        def g(t: float) -> float:
            return ad.Value(ua + t * (ub - ua), va + t * (vb - va)).Z() - c

        ga, gb = g(0.0), g(1.0)
        if ga == 0.0:
            t = 0.0
        elif gb == 0.0:
            t = 1.0
        elif (ga < 0.0) == (gb < 0.0):
            raise ExactFailure("segment ends do not bracket the plane")
        else:
            t = brentq(g, 0.0, 1.0, xtol=ROOT_XTOL, rtol=_RTOL)
        u, v = ua + t * (ub - ua), va + t * (vb - va)
        x, y, z = self.point(u, v)
        return x, y, z, u, v

    def height_extreme_on_uv_segment(self, ua: float, va: float, ub: float, vb: float, sign: float) -> float:
        """The fraction along the (u, v) segment a->b of the surface's lowest (``sign`` +1) or highest
        (-1) point on it (bounded Brent: the one in the basin it finds), to ~1e-7: the height there is
        the extreme's to ~1e-14 of the segment's sag (and the point at it exact)."""
        ad = self.ad
        du, dv = ub - ua, vb - va
        res = minimize_scalar(
            lambda x: sign * ad.Value(ua + x * du, va + x * dv).Z(),
            bounds=(0.0, 1.0),
            method="bounded",
            options={"xatol": 1e-7},
        )
        return float(res.x)

    def walk_level(
        self,
        u: float,
        v: float,
        c: float,
        target: tuple[float, float],
        *,
        step: float,
        max_steps: int,
        avoid: Sequence[tuple[float, float]] = (),
    ) -> tuple[float, float, float, float]:
        """From (u, v) on the section ``z = c``, walk along that section curve (the branch through the
        start, never jumping to another) to its point nearest ``target`` (x, y): steps of at most
        ``step`` mm along the curve's tangent, each pulled back onto ``z = c`` along the height
        gradient. Returns (x, y, u, v). Raises ExactFailure if the walk leaves the surface's
        parameter range, meets a horizontal point (no tangent), does not arrive, or passes one of
        the points ``avoid`` (x, y; points of the section: within a tenth of a step of one of its
        steps, between the step's ends)."""
        p, du, dv = self._p, self._du, self._dv
        tx, ty = target
        far = np.asarray(avoid, dtype=np.float64).reshape(-1, 2)
        for _ in range(max_steps):
            self.ad.D1(u, v, p, du, dv)
            gu, gv = du.Z(), dv.Z()
            su, sv = -gv, gu  # along the level curve in (u, v): normal to the height gradient
            tan_x, tan_y = du.X() * su + dv.X() * sv, du.Y() * su + dv.Y() * sv
            speed = math.hypot(tan_x, tan_y)
            if speed < 1e-12:
                raise ExactFailure("the section curve has no tangent here")
            along = ((tx - p.X()) * tan_x + (ty - p.Y()) * tan_y) / speed
            if abs(along) < WALK_TOL_MM:
                return p.X(), p.Y(), u, v
            h = math.copysign(min(abs(along), step), along) / speed
            x0, y0 = p.X(), p.Y()
            nu, nv = self._onto_level(u + su * h, v + sv * h, c)
            if nu is None or nv is None:
                raise ExactFailure("the walk lost the section curve (or met a flat spot)")
            u, v = nu, nv
            if not (self.u0 <= u <= self.u1 and self.v0 <= v <= self.v1):
                raise ExactFailure("the walk left the surface")
            if len(far):
                self.ad.D0(u, v, p)
                if _passes(far, (x0, y0), (p.X(), p.Y())):
                    raise WalkPassed("the walk passed a point to avoid")
        raise ExactFailure("the walk did not arrive")

    def section_direction(self, u: float, v: float) -> tuple[float, float] | None:
        """The unit (x, y) direction of the section curve through (u, v) that keeps the solid's material
        on its left seen from above (the sections' loop orientation): ez x the outward normal. None
        where the surface is horizontal (no section direction)."""
        p, du, dv = self._p, self._du, self._dv
        self.ad.D1(u, v, p, du, dv)
        n = du.Crossed(dv)
        nx, ny = self.outward * n.X(), self.outward * n.Y()
        h = math.hypot(nx, ny)
        if h < 1e-12 * max(du.Magnitude() * dv.Magnitude(), 1e-300):
            return None
        return -ny / h, nx / h

    def trace_level(
        self,
        u: float,
        v: float,
        c: float,
        target: tuple[float, float],
        target_direction: tuple[float, float],
        *,
        step: float,
        max_length: float,
        min_length: float = 0.0,
    ) -> list[tuple[float, float, float, float]]:
        """From (u, v) on the section ``z = c``, follow that section curve forward (the loops'
        direction, ``section_direction``) until ``target`` (x, y) lies ahead of it within a step, the
        chord to it within 30 degrees of the curve's direction at both ends (``target_direction`` at
        the target: the far side of a narrow tongue is just as near, but runs the other way). It
        does not arrive before ``min_length`` mm (a target at the start: once round a closed curve).

        Returns the points passed, (x, y, u, v), without the start and the target. Each step goes at
        most ``step`` mm along the tangent and is pulled back onto ``z = c``; a step over which the
        curve's direction turns by more than 15 degrees is halved, so a bend of any radius is
        followed on its own branch (the tip of a narrow tongue of the section, 0.07 mm wide, where
        the plane grazes a crest). Raises ExactFailure if the trace leaves the face (its parameter
        box where that bounds the surface, or its trim), meets a horizontal point, needs steps
        under 1 nm or runs ``max_length`` mm without arriving.
        """
        p, du, dv = self._p, self._du, self._dv
        tx, ty = target
        box_u, box_v = self.bounded
        d = self.section_direction(u, v)
        if d is None:
            raise ExactFailure("the section curve has no direction here")
        x, y = self.point(u, v)[:2]
        h = 0.25 * step
        out: list[tuple[float, float, float, float]] = []
        length = 0.0
        for _ in range(TRACE_MAX_STEPS):
            qx, qy = tx - x, ty - y
            dist = math.hypot(qx, qy)
            along = qx * d[0] + qy * d[1]
            ahead = (
                along >= TRACE_ARRIVAL_COS * dist
                and qx * target_direction[0] + qy * target_direction[1] >= TRACE_ARRIVAL_COS * dist
            )
            ahead = ahead and length >= min_length
            if ahead and dist <= h:
                return out
            if ahead and dist <= 2.0 * h:
                h = 0.5 * dist  # not past it: the next point is then within a step
            if length > max_length:
                break
            self.ad.D1(u, v, p, du, dv)
            su, sv = -dv.Z(), du.Z()  # along the level curve in (u, v)
            tan_x, tan_y = du.X() * su + dv.X() * sv, du.Y() * su + dv.Y() * sv
            speed = math.hypot(tan_x, tan_y)
            if speed < 1e-300:
                raise ExactFailure("flat spot on the trace")
            if tan_x * d[0] + tan_y * d[1] < 0.0:
                su, sv = -su, -sv
            while True:
                un, vn = self._onto_level(u + su * h / speed, v + sv * h / speed, c)
                dn = self.section_direction(un, vn) if un is not None and vn is not None else None
                if dn is not None and dn[0] * d[0] + dn[1] * d[1] > TRACE_MAX_TURN_COS:
                    break
                h *= 0.5
                if h < TRACE_MIN_STEP_MM:
                    raise ExactFailure("a cusp on the trace")
            assert un is not None and vn is not None and dn is not None  # (a direction: a point)
            if (box_u and not self.u0 <= un <= self.u1) or (box_v and not self.v0 <= vn <= self.v1):
                raise ExactFailure("the trace left the face (its parameter range)")
            if not self.contains(un, vn, tol=1e-6):
                raise ExactFailure("the trace left the face (its trim)")
            xn, yn = self.point(un, vn)[:2]
            length += math.hypot(xn - x, yn - y)
            u, v, x, y, d = un, vn, xn, yn, dn
            out.append((x, y, u, v))
            h = min(1.5 * h, step)
        raise ExactFailure("the trace did not arrive")

    def _onto_level(self, u: float, v: float, c: float) -> tuple[float, float] | tuple[None, None]:
        """(u, v) moved onto ``z = c`` along the height gradient (Newton), or (None, None)."""
        p, du, dv = self._p, self._du, self._dv
        for _ in range(30):
            self.ad.D1(u, v, p, du, dv)
            g = p.Z() - c
            if abs(g) < 1e-12:
                return u, v
            gu, gv = du.Z(), dv.Z()
            n2 = gu * gu + gv * gv
            if n2 < 1e-24:
                return None, None
            u, v = u - g * gu / n2, v - g * gv / n2
        return None, None


class EdgeEval:
    """An edge's 3D curve (location applied) for corner points of the sections."""

    __slots__ = ("ad", "s0", "s1", "closed")

    def __init__(self, adaptor: BRepAdaptor_Curve):
        self.ad = adaptor
        self.s0, self.s1 = adaptor.FirstParameter(), adaptor.LastParameter()
        # closed: its two ends are one point, so a node there has two parameters
        self.closed = adaptor.Value(self.s0).Distance(adaptor.Value(self.s1)) < 1e-7

    def parameter_of(self, xyz: tuple[float, float, float]) -> float:
        """The curve parameter of the point nearest ``xyz`` (a topology-mesh node on this edge)."""
        p = gp_Pnt(*xyz)
        best_d, best_s = p.SquareDistance(self.ad.Value(self.s0)), self.s0
        d1 = p.SquareDistance(self.ad.Value(self.s1))
        if d1 < best_d:
            best_d, best_s = d1, self.s1
        ext = Extrema_ExtPC(p, self.ad, self.s0, self.s1)
        if ext.IsDone():
            for i in range(1, ext.NbExt() + 1):
                if ext.IsMin(i) and ext.SquareDistance(i) < best_d:
                    best_d, best_s = ext.SquareDistance(i), ext.Point(i).Parameter()
        return best_s

    def point(self, s: float) -> tuple[float, float, float]:
        p = self.ad.Value(s)
        return p.X(), p.Y(), p.Z()

    def height_extreme(self, lo: float, hi: float, sign: float) -> float:
        """The parameter of the curve's lowest (``sign`` +1) or highest (-1) point between ``lo`` and
        ``hi`` (bounded Brent: the one in the basin it finds)."""
        ad = self.ad
        res = minimize_scalar(
            lambda x: sign * ad.Value(float(x)).Z(),
            bounds=(lo, hi),
            method="bounded",
            options={"xatol": 1e-13 * max(1.0, abs(self.s1 - self.s0))},
        )
        return float(res.x)

    def root(self, sa: float, sb: float, c: float) -> tuple[float, float, float]:
        """The point at height ``c`` on the curve between parameters ``sa`` and ``sb`` (bracketing)."""
        ad = self.ad

        def g(s: float) -> float:
            return ad.Value(s).Z() - c

        ga, gb = g(sa), g(sb)
        if ga == 0.0:
            s = sa
        elif gb == 0.0:
            s = sb
        elif (ga < 0.0) == (gb < 0.0):
            raise ExactFailure("curve span does not bracket the plane")
        else:
            s = brentq(g, sa, sb, xtol=ROOT_XTOL * max(1.0, abs(sb - sa)), rtol=_RTOL)
        p = ad.Value(s)
        return p.X(), p.Y(), p.Z()


def _passes(pts: np.ndarray, a: tuple[float, float], b: tuple[float, float]) -> bool:
    """Whether a step a -> b of a walk along a section curve passes one of ``pts`` (points of the
    section): one projects strictly between a and b, within a tenth of the step's length of it
    (the curve's arc over a step of the walk stays closer to its chord; another branch of the
    section that close would be a pinch, where the walk's answer is not trusted either)."""
    ab = np.subtract(b, a)
    length2 = float(ab @ ab)
    if length2 <= 0.0:
        return False
    ap = pts - np.asarray(a)
    t = ap @ ab / length2
    off = np.abs(ap[:, 0] * ab[1] - ap[:, 1] * ab[0]) / math.sqrt(length2)
    return bool(np.any((t > 0.0) & (t < 1.0) & (off <= 0.1 * math.sqrt(length2))))
