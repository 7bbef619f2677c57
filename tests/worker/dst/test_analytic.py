"""The closed-form evaluators agree with OCCT's D1 on every elementary surface kind, placed anywhere."""

import numpy as np
import pytest
from OCP.BRepAdaptor import BRepAdaptor_Surface
from OCP.gp import gp_Pnt, gp_Vec
from OCP.TopAbs import TopAbs_FACE
from OCP.TopExp import TopExp_Explorer
from OCP.TopoDS import TopoDS

from worker.dst.analytic import evaluator


def _faces(kind):
    import build123d as bd
    from OCP.BRepBuilderAPI import BRepBuilderAPI_NurbsConvert

    if kind == "periodic-bspline":
        # a torus as a B-spline periodic in both directions (NurbsConvert gives clamped ones)
        from OCP.BRepBuilderAPI import BRepBuilderAPI_MakeFace
        from OCP.Geom import Geom_ToroidalSurface
        from OCP.GeomConvert import GeomConvert
        from OCP.gp import gp_Ax3, gp_Dir

        torus = Geom_ToroidalSurface(gp_Ax3(gp_Pnt(1, 2, 3), gp_Dir(0.2, 0.3, 0.9)), 8.0, 2.0)
        bs = GeomConvert.SurfaceToBSplineSurface_s(torus)
        assert bs.IsUPeriodic() and bs.IsVPeriodic()
        yield BRepBuilderAPI_MakeFace(bs, 1e-7).Face()
        return
    if kind.startswith("nurbs-"):
        base = {"nurbs-sphere": bd.Sphere(5), "nurbs-torus": bd.Torus(8, 2), "nurbs-box": bd.Box(3, 4, 5)}[
            kind
        ]
        base = base.rotate(bd.Axis((1, 2, 3), (0.3, -0.5, 0.8)), 37).translate((5, -7, 11))
        converted = BRepBuilderAPI_NurbsConvert(base.wrapped, True).Shape()
        exp = TopExp_Explorer(converted, TopAbs_FACE)
        while exp.More():
            yield TopoDS.Face(exp.Current())
            exp.Next()
        return
    shape = {
        "plane": bd.Box(3, 4, 5),
        "cylinder": bd.Cylinder(3, 7),
        "cone": bd.Cone(4, 1.5, 6),
        "sphere": bd.Sphere(5),
        "torus": bd.Torus(8, 2),
    }[kind]
    shape = shape.rotate(bd.Axis((1, 2, 3), (0.3, -0.5, 0.8)), 37).translate((5, -7, 11))
    exp = TopExp_Explorer(shape.wrapped, TopAbs_FACE)
    while exp.More():
        yield TopoDS.Face(exp.Current())
        exp.Next()


@pytest.mark.parametrize(
    "kind",
    [
        "plane",
        "cylinder",
        "cone",
        "sphere",
        "torus",
        "nurbs-sphere",
        "nurbs-torus",
        "nurbs-box",
        "periodic-bspline",
    ],
)
def test_closed_form_matches_occt(kind):
    rng = np.random.default_rng(7)
    checked = 0
    for face in _faces(kind):
        ad = BRepAdaptor_Surface(face)
        ev = evaluator(ad)
        assert ev is not None
        u = rng.uniform(ad.FirstUParameter(), ad.LastUParameter(), 50)
        v = rng.uniform(max(ad.FirstVParameter(), -50), min(ad.LastVParameter(), 50), 50)
        if kind == "periodic-bspline":  # Newton may step past the seam: parameters wrap, not extrapolate
            u += 2 * np.pi * rng.integers(-2, 3, 50)
            v += 2 * np.pi * rng.integers(-2, 3, 50)
        P, Pu, Pv = ev(u, v)
        np.testing.assert_array_equal(ev(u, v, False)[0], P)  # the value-only evaluation
        p, du, dv = gp_Pnt(), gp_Vec(), gp_Vec()
        for i in range(50):
            ad.D1(u[i], v[i], p, du, dv)
            np.testing.assert_allclose(P[i], p.Coord(), atol=1e-10, rtol=1e-10)
            np.testing.assert_allclose(Pu[i], du.Coord(), atol=1e-9, rtol=1e-9)
            np.testing.assert_allclose(Pv[i], dv.Coord(), atol=1e-9, rtol=1e-9)
        checked += 1
    assert checked
