"""Closed-form, vectorised evaluation of OCCT's elementary surfaces (plane, cylinder, cone, sphere, torus).

Same parametrisations as OCCT's ``ElSLib`` (and hence ``BRepAdaptor_Surface.D1`` on such faces, face
location included), so a batch of Newton iterates on these faces costs a few numpy operations instead
of one Python-level OCCT call per point. Checked against ``D1`` in ``tests/worker/dst/test_analytic.py``.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from OCP.BRepAdaptor import BRepAdaptor_Surface
from OCP.GeomAbs import GeomAbs_Cone, GeomAbs_Cylinder, GeomAbs_Plane, GeomAbs_Sphere, GeomAbs_Torus

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
    return None
