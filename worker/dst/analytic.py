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

# (u, v) -> (P, Pu, Pv), each (n, 3)
Evaluator = Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray, np.ndarray]]


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

        def plane(u, v):
            n = len(u)
            return o + u[:, None] * x + v[:, None] * y, np.tile(x, (n, 1)), np.tile(y, (n, 1))

        return plane
    if kind == GeomAbs_Cylinder:
        cyl = ad.Cylinder()
        o, x, y, z = _frame(cyl.Position())
        r = cyl.Radius()

        def cylinder(u, v):
            c, s = np.cos(u)[:, None], np.sin(u)[:, None]
            radial = c * x + s * y
            return o + r * radial + v[:, None] * z, r * (-s * x + c * y), np.tile(z, (len(u), 1))

        return cylinder
    if kind == GeomAbs_Cone:
        cone = ad.Cone()
        o, x, y, z = _frame(cone.Position())
        r, a = cone.RefRadius(), cone.SemiAngle()
        sa, ca = np.sin(a), np.cos(a)

        def cone_(u, v):
            c, s = np.cos(u)[:, None], np.sin(u)[:, None]
            radial = c * x + s * y
            rr = (r + v * sa)[:, None]
            return o + rr * radial + (v * ca)[:, None] * z, rr * (-s * x + c * y), sa * radial + ca * z

        return cone_
    if kind == GeomAbs_Sphere:
        sph = ad.Sphere()
        o, x, y, z = _frame(sph.Position())
        r = sph.Radius()

        def sphere(u, v):
            c, s = np.cos(u)[:, None], np.sin(u)[:, None]
            cv, sv = np.cos(v)[:, None], np.sin(v)[:, None]
            radial = c * x + s * y
            return o + r * cv * radial + r * sv * z, r * cv * (-s * x + c * y), -r * sv * radial + r * cv * z

        return sphere
    if kind == GeomAbs_Torus:
        tor = ad.Torus()
        o, x, y, z = _frame(tor.Position())
        big, small = tor.MajorRadius(), tor.MinorRadius()

        def torus(u, v):
            c, s = np.cos(u)[:, None], np.sin(u)[:, None]
            cv, sv = np.cos(v)[:, None], np.sin(v)[:, None]
            radial = c * x + s * y
            rr = big + small * cv
            return o + rr * radial + small * sv * z, rr * (-s * x + c * y), -small * sv * radial + small * cv * z

        return torus
    if kind == GeomAbs_BSplineSurface:
        return _bspline(ad)
    return None


def _bspline(ad: BRepAdaptor_Surface) -> Evaluator:
    bs = ad.BSpline()  # a copy with the face location applied
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

    def evaluate(u, v):
        xi = np.stack([u, v], axis=1)
        a, au, av = spline(xi), spline(xi, nu=(1, 0)), spline(xi, nu=(0, 1))
        if not rational:
            return a, au, av
        w_, wu, wv = a[:, 3:4], au[:, 3:4], av[:, 3:4]
        p = a[:, :3] / w_
        return p, (au[:, :3] - p * wu) / w_, (av[:, :3] - p * wv) / w_

    return evaluate


def _array1(arr) -> np.ndarray:
    return np.array([arr.Value(i) for i in range(arr.Lower(), arr.Upper() + 1)], dtype=np.float64)
