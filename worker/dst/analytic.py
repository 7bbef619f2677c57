"""Vectorised evaluation of a face's surface and first derivatives, matching OCCT's ``D1``.

Elementary surfaces (plane, cylinder, cone, sphere, torus) in closed form with OCCT's ``ElSLib``
parametrisations; B-spline surfaces (rational or not, periodic or not) as tensor-product B-splines of
their poles (homogeneous coordinates for rational ones) with scipy's ``NdBSpline``. Face location is
included (``BRepAdaptor_Surface`` applies it). A batch of Newton iterates then costs a few numpy
calls instead of one Python-level OCCT call per point. Checked against ``D1`` in
``tests/worker/dst/test_analytic.py``; any other surface kind returns None and is evaluated by OCCT.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from OCP.BRepAdaptor import BRepAdaptor_Surface
from OCP.GeomAbs import (
    GeomAbs_BSplineSurface,
    GeomAbs_Cone,
    GeomAbs_Cylinder,
    GeomAbs_Plane,
    GeomAbs_Sphere,
    GeomAbs_Torus,
)
from scipy.interpolate import NdBSpline

# (u, v, derivatives) -> (P, Pu, Pv), each (n, 3); Pu and Pv may be None when derivatives is False
Evaluator = Callable[[np.ndarray, np.ndarray, bool], tuple[np.ndarray, np.ndarray | None, np.ndarray | None]]


def _frame(ax3) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    return (
        np.array(ax3.Location().Coord()),
        np.array(ax3.XDirection().Coord()),
        np.array(ax3.YDirection().Coord()),
        np.array(ax3.Direction().Coord()),
    )


def evaluator(ad: BRepAdaptor_Surface) -> Evaluator | None:
    """A vectorised D1 for an elementary surface, or None for any other kind."""
    kind = ad.GetType()
    if kind == GeomAbs_Plane:
        o, x, y, _ = _frame(ad.Plane().Position())

        def plane(u, v, derivatives=True):
            n = len(u)
            return o + u[:, None] * x + v[:, None] * y, np.tile(x, (n, 1)), np.tile(y, (n, 1))

        return plane
    # Cylinder, cone, sphere and torus are surfaces of revolution about the frame's z axis:
    # P = o + rho(v) (cos u x + sin u y) + h(v) z, so only the profile (rho, h, rho', h') differs.
    if kind == GeomAbs_Cylinder:
        cyl = ad.Cylinder()
        r = cyl.Radius()
        return _revolution(
            cyl.Position(), lambda v: (np.full_like(v, r), v, np.zeros_like(v), np.ones_like(v))
        )
    if kind == GeomAbs_Cone:
        cone = ad.Cone()
        r, sa, ca = cone.RefRadius(), np.sin(cone.SemiAngle()), np.cos(cone.SemiAngle())
        return _revolution(
            cone.Position(), lambda v: (r + v * sa, v * ca, np.full_like(v, sa), np.full_like(v, ca))
        )
    if kind == GeomAbs_Sphere:
        sph = ad.Sphere()
        r = sph.Radius()
        return _revolution(
            sph.Position(), lambda v: (r * np.cos(v), r * np.sin(v), -r * np.sin(v), r * np.cos(v))
        )
    if kind == GeomAbs_Torus:
        tor = ad.Torus()
        big, small = tor.MajorRadius(), tor.MinorRadius()
        return _revolution(
            tor.Position(),
            lambda v: (big + small * np.cos(v), small * np.sin(v), -small * np.sin(v), small * np.cos(v)),
        )
    if kind == GeomAbs_BSplineSurface:
        return _bspline(ad)
    return None


def _revolution(ax3, profile) -> Evaluator:
    """Surface of revolution about ``ax3``'s z axis with meridian ``profile(v) -> (rho, h, rho', h')``."""
    o, x, y, z = _frame(ax3)

    def evaluate(u, v, derivatives=True):
        c, s = np.cos(u)[:, None], np.sin(u)[:, None]
        radial, tangent = c * x + s * y, -s * x + c * y
        rho, h, drho, dh = (a[:, None] for a in profile(v))
        return o + rho * radial + h * z, rho * tangent, drho * radial + dh * z

    return evaluate


def _bspline(ad: BRepAdaptor_Surface) -> Evaluator:
    bs = ad.BSpline()  # a copy with the face location applied
    # one period of a periodic direction, where parameters beyond it are brought back (the clamped
    # copy below would extrapolate there instead of wrapping)
    u_period = (bs.Bounds()[0], bs.UPeriod()) if bs.IsUPeriodic() else None
    v_period = (bs.Bounds()[2], bs.VPeriod()) if bs.IsVPeriodic() else None
    if bs.IsUPeriodic() or bs.IsVPeriodic():
        bs = bs.Copy()
        if bs.IsUPeriodic():
            bs.SetUNotPeriodic()  # same geometry and parametrisation, clamped knot vector
        if bs.IsVPeriodic():
            bs.SetVNotPeriodic()
    tu = _array1(bs.UKnotSequence())
    tv = _array1(bs.VKnotSequence())
    nu, nv = bs.NbUPoles(), bs.NbVPoles()
    poles = np.array([[bs.Pole(i, j).Coord() for j in range(1, nv + 1)] for i in range(1, nu + 1)])
    rational = bs.IsURational() or bs.IsVRational()
    if rational:
        w = np.array([[bs.Weight(i, j) for j in range(1, nv + 1)] for i in range(1, nu + 1)])
        coef = np.concatenate([poles * w[..., None], w[..., None]], axis=2)
    else:
        coef = poles
    spline = NdBSpline((tu, tv), coef, (bs.UDegree(), bs.VDegree()), extrapolate=True)

    def evaluate(u, v, derivatives=True):
        if u_period is not None:
            u = u_period[0] + np.mod(u - u_period[0], u_period[1])
        if v_period is not None:
            v = v_period[0] + np.mod(v - v_period[0], v_period[1])
        xi = np.stack([u, v], axis=1)
        a = spline(xi)
        p = a[:, :3] / a[:, 3:4] if rational else a
        if not derivatives:
            return p, None, None
        au, av = spline(xi, nu=(1, 0)), spline(xi, nu=(0, 1))
        if not rational:
            return a, au, av
        w_, wu, wv = a[:, 3:4], au[:, 3:4], av[:, 3:4]
        return p, (au[:, :3] - p * wu) / w_, (av[:, :3] - p * wv) / w_

    return evaluate


def _array1(arr) -> np.ndarray:
    return np.array([arr.Value(i) for i in range(arr.Lower(), arr.Upper() + 1)], dtype=np.float64)
