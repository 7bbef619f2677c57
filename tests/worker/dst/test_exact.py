"""Exact evaluation on faces: a point's own (u, v) on its face (``FaceEval.uv_near``)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from OCP.BRepAdaptor import BRepAdaptor_Surface
from OCP.BRepBuilderAPI import BRepBuilderAPI_NurbsConvert
from OCP.GeomAbs import GeomAbs_BSplineSurface, GeomAbs_Cone, GeomAbs_Sphere, GeomAbs_Torus
from OCP.TopAbs import TopAbs_FACE
from OCP.TopExp import TopExp_Explorer
from OCP.TopoDS import TopoDS

from worker.dst.exact import FaceEval


def _faces(shape) -> list[FaceEval]:
    out = []
    exp = TopExp_Explorer(shape, TopAbs_FACE)
    while exp.More():
        out.append(FaceEval(BRepAdaptor_Surface(TopoDS.Face(exp.Current()))))
        exp.Next()
    return out


def _curved(kind: str) -> FaceEval:
    import build123d as bd

    solid = bd.Torus(15.0, 5.0) if kind == "torus" else bd.Sphere(20.0)
    shape = solid.wrapped
    if kind == "bspline":
        shape = BRepBuilderAPI_NurbsConvert(shape, True).Shape()
    want = {"sphere": GeomAbs_Sphere, "torus": GeomAbs_Torus, "bspline": GeomAbs_BSplineSurface}[kind]
    (ev,) = [f for f in _faces(shape) if f.ad.GetType() == want]
    return ev


@pytest.mark.parametrize("kind", ["sphere", "torus", "bspline"])
def test_a_point_on_its_face_gets_its_own_parameters_from_a_nearby_seed(kind):
    """Points on the surface, seeded a little off their (u, v) as the sampler seeds them (from a
    topology-mesh node): found by Newton (not the slow projection), at their own parameters."""
    ev = _curved(kind)
    rng = np.random.default_rng(7)
    # away from a sphere's poles, where u is not defined
    u = rng.uniform(ev.u0, ev.u1, 50)
    v = rng.uniform(ev.v0 + 0.1 * (ev.v1 - ev.v0), ev.v1 - 0.1 * (ev.v1 - ev.v0), 50)
    for ui, vi in zip(u.tolist(), v.tolist(), strict=True):
        xyz = ev.point(ui, vi)
        seed = (ui + 0.01 * (ev.u1 - ev.u0), vi - 0.01 * (ev.v1 - ev.v0))
        assert ev._newton_uv(xyz, seed) is not None
        got = ev.uv_near(xyz, seed)
        assert got == pytest.approx((ui, vi), abs=1e-9)
        assert ev.point(*got) == pytest.approx(xyz, abs=1e-10)


def test_a_periodic_surfaces_parameters_come_on_the_seeds_branch():
    """A torus's point seeded one period on (both directions wrap) comes back on the seed's period."""
    ev = _curved("torus")
    xyz = ev.point(1.0, 2.0)
    tau = 2.0 * math.pi
    got = ev.uv_near(xyz, (1.0 + tau + 0.01, 2.0 - tau - 0.01))
    assert got == pytest.approx((1.0 + tau, 2.0 - tau), abs=1e-9)


def test_newton_never_answers_with_a_parameter_the_face_does_not_hold():
    """Seeded past a sphere's pole, Newton would land on the same point at v beyond the pole (the
    sphere's other parametrisation of it), which the face's trim does not hold: the fast path
    declines, and the answer is the point's parameters within the face's range."""
    ev = _curved("sphere")
    u, v = 0.5, 0.5 * math.pi - 0.05  # near the north pole
    xyz = ev.point(u, v)
    seed = (u + math.pi, 0.5 * math.pi + 0.06)  # the same point's mirror image past the pole, nearby
    assert ev._newton_uv(xyz, seed) is None
    got = ev.uv_near(xyz, seed)
    assert ev.v0 <= got[1] <= ev.v1
    assert ev.point(*got) == pytest.approx(xyz, abs=1e-9)


def test_a_point_off_the_surface_gets_its_foot_point():
    """A point off the surface (an edge's vertex within its tolerance of a face) is no Newton root:
    it gets OCCT's projection, the nearest point of the surface."""
    ev = _curved("bspline")
    u, v = 1.0, 0.3
    p = np.array(ev.point(u, v))
    ev.ad.D1(u, v, ev._p, ev._du, ev._dv)
    n = np.cross(ev._du.Coord(), ev._dv.Coord())
    off = p + 1e-4 * n / np.linalg.norm(n)
    assert ev._newton_uv(tuple(off), (u + 0.01, v)) is None
    got = ev.uv_near(tuple(off), (u + 0.01, v))
    assert got == pytest.approx((u, v), abs=1e-7)
    assert np.linalg.norm(np.array(ev.point(*got)) - off) == pytest.approx(1e-4, rel=1e-6)


def test_a_walk_along_a_section_arrives_unless_it_passes_a_point_to_avoid():
    """On the sphere (R 20) at z = 10 the section is the circle of radius sqrt(300): a walk from
    longitude 0 towards the point at 60 degrees ends there, on the circle. Told to avoid a point of
    the section it passes (30 degrees), it fails; points it does not pass (-30 degrees on the
    circle, or 30 degrees but 0.5 mm outside it) do not stop it."""
    from worker.dst.exact import ExactFailure

    ev = _curved("sphere")
    c, r = 10.0, math.sqrt(300.0)

    def at(deg: float, radius: float = r) -> tuple[float, float]:
        return radius * math.cos(math.radians(deg)), radius * math.sin(math.radians(deg))

    u0, v0 = ev.uv_near((*at(0.0), c), (0.0, 0.5))
    assert ev.point(u0, v0) == pytest.approx((*at(0.0), c), abs=1e-9)
    kw = {"step": 0.5, "max_steps": 200}
    for avoid in ((), (at(-30.0),), (at(30.0, r + 0.5),)):
        x, y, u, v = ev.walk_level(u0, v0, c, at(60.0), avoid=avoid, **kw)
        assert (x, y) == pytest.approx(at(60.0), abs=1e-6)
        assert ev.point(u, v)[2] == pytest.approx(c, abs=1e-9)
    with pytest.raises(ExactFailure, match="passed a point to avoid"):
        ev.walk_level(u0, v0, c, at(60.0), avoid=[at(30.0)], **kw)


@pytest.mark.parametrize(
    ("kind", "poles"),
    [
        ("sphere", {(1, -0.5 * math.pi), (1, 0.5 * math.pi)}),
        ("bspline", {(1, -0.5 * math.pi), (1, 0.5 * math.pi)}),
        ("torus", set()),
        ("cone", {"apex"}),
        ("frustum", set()),
    ],
)
def test_a_side_of_the_parameter_box_is_a_pole_only_where_its_iso_line_is_one_point(kind, poles):
    """The sides of a face's (u, v) box that are poles: a sphere's (exact or B-spline) two ends in v,
    a cone's apex (the side where its iso-circle's radius is zero); none on a torus, nor on a frustum
    whose top circle is only 0.2 um across (an iso-line 0.6 um long is not one point)."""
    import build123d as bd

    if kind in ("cone", "frustum"):
        (ev,) = [
            f
            for f in _faces(bd.Cone(10.0, 0.0 if kind == "cone" else 1e-4, 20.0).wrapped)
            if f.ad.GetType() == GeomAbs_Cone
        ]
    else:
        ev = _curved(kind)
    sides = [(0, ev.u0), (0, ev.u1), (1, ev.v0), (1, ev.v1)]
    if poles == {"apex"}:  # the side of the box whose point at u = 0 lies on the cone's axis
        poles = {s for s in sides if s[0] == 1 and math.hypot(*ev.point(0.0, s[1])[:2]) < 1e-9}
        assert len(poles) == 1
    got = [side for side in sides if ev.is_pole(*side)]
    assert sorted((a, round(b, 9)) for a, b in got) == sorted((a, round(b, 9)) for a, b in poles)
    assert [side for side in sides if ev.is_pole(*side)] == got  # the same answer, kept


def test_a_point_holds_on_its_face_with_or_without_its_parameters_alike():
    """``FaceEval.holds`` given a point's (u, v) skips BRepExtrema's distance where the surface's
    point there is IN its face: the answer must be BRepExtrema's. A sphere (as B-splines) with a
    5 mm hole through it: points on the surface at 5 mm +- 1e-7 to 1e-5 mm from the axis (the
    trim's edge), inside and inside out, at tolerance 1e-6; some moved off the surface by twice
    the tolerance, which no longer hold. Both answers occur, and the skipped distance does."""
    import build123d as bd

    holed = bd.Sphere(20.0) - bd.Cylinder(5.0, 60.0)
    shape = BRepBuilderAPI_NurbsConvert(holed.wrapped, True).Shape()
    (ev,) = [
        f
        for f in _faces(shape)
        if np.linalg.norm(f.point(0.5 * (f.u0 + f.u1), 0.5 * (f.v0 + f.v1))) == pytest.approx(20.0)
    ]
    tol = 1e-6
    rng = np.random.default_rng(3)
    answers, skipped = [], 0
    for r in (5.0 - 1e-5, 5.0 - 1e-6, 5.0 - 2e-7, 5.0 + 2e-7, 5.0 + 1e-6, 5.0 + 1e-5, 8.0, 12.0):
        for a in rng.uniform(0.0, 2.0 * math.pi, 6).tolist():
            z = math.sqrt(400.0 - r * r) * (1.0 if a < math.pi else -1.0)
            xyz = (r * math.cos(a), r * math.sin(a), z)
            uv = ev.uv_near(xyz, ev.uv_near(xyz, (0.0, 0.0)))
            p = ev.point(*uv)
            for off in (0.0, 2.0 * tol):
                q = tuple(np.array(p) * (1.0 + off / 20.0))  # along the sphere's normal
                fast = ev.holds(q, tol, uv)
                assert fast == ev.holds(q, tol), (r, a, off)
                answers.append(fast)
                skipped += ev._surface_point_in_face(q, uv, tol)
    assert any(answers) and not all(answers)
    assert skipped > 0


class _CountingD1:
    """A surface adaptor that counts its D1 evaluations (for ``FaceEval._newton_uv``)."""

    def __init__(self, ad):
        self.ad, self.calls = ad, 0

    def D1(self, *args):
        self.calls += 1
        return self.ad.D1(*args)

    def __getattr__(self, name):
        return getattr(self.ad, name)


def test_newton_gives_up_once_it_settles_at_the_foot_of_a_point_off_the_surface():
    """A point 0.01 mm off the B-spline surface (a chord's point, which ``refine`` projects): Newton
    settles at its foot in a few steps and stops there, not after all ``UV_NEAR_MAX_ITER`` (the
    projection then comes from ``uv_near``'s fallback, at the foot). A point on the surface from the
    same seed, and one 1e-10 mm off (within the tolerance), are still found."""
    from worker.dst.exact import UV_NEAR_MAX_ITER

    ev = _curved("bspline")
    u, v = 1.0, 0.3
    p = np.array(ev.point(u, v))
    ev.ad.D1(u, v, ev._p, ev._du, ev._dv)
    n = np.cross(ev._du.Coord(), ev._dv.Coord())
    n /= np.linalg.norm(n)
    seed = (u + 0.02, v - 0.02)
    counting = _CountingD1(ev.ad)
    ev.ad = counting
    try:
        assert ev._newton_uv(tuple(p + 0.01 * n), seed) is None
        assert counting.calls < UV_NEAR_MAX_ITER
        for off in (0.0, 1e-10):
            assert ev._newton_uv(tuple(p + off * n), seed) == pytest.approx((u, v), abs=1e-9)
    finally:
        ev.ad = counting.ad
    got = ev.uv_near(tuple(p + 0.01 * n), seed)
    assert got == pytest.approx((u, v), abs=1e-7)


def test_a_seed_for_a_point_off_the_surface_is_its_foot_without_occts_projection():
    """``uv_near(..., foot=True)`` (a seed for solving a chord's point onto a section): for points
    0.001-0.05 mm off a B-spline surface, over it and under it, Newton's settled foot, within a few
    steps and without ``ShapeAnalysis_Surface``: the surface point there is the point's foot (it
    was offset along the normal) to 1e-5 of the gap, where OCCT's projection is to 1e-9 mm. A
    point whose foot lies past the parameter box (beyond an edge of the surface) still gets
    OCCT's projection."""
    from worker.dst.exact import UV_NEAR_MAX_ITER

    ev = _curved("bspline")
    rng = np.random.default_rng(11)
    for _ in range(12):
        u = float(rng.uniform(ev.u0 + 0.2 * (ev.u1 - ev.u0), ev.u1 - 0.2 * (ev.u1 - ev.u0)))
        v = float(rng.uniform(ev.v0 + 0.2 * (ev.v1 - ev.v0), ev.v1 - 0.2 * (ev.v1 - ev.v0)))
        p = np.array(ev.point(u, v))
        ev.ad.D1(u, v, ev._p, ev._du, ev._dv)
        n = np.cross(ev._du.Coord(), ev._dv.Coord())
        n /= np.linalg.norm(n)
        seed = (u + 0.01 * (ev.u1 - ev.u0), v - 0.01 * (ev.v1 - ev.v0))
        for gap in (1e-3, -0.01, 0.05):
            q = tuple(p + gap * n)
            ev._sas = None
            counting = _CountingD1(ev.ad)
            ev.ad = counting
            try:
                got = ev.uv_near(q, seed, foot=True)
            finally:
                ev.ad = counting.ad
            assert ev._sas is None  # OCCT's projection was not needed
            assert counting.calls < UV_NEAR_MAX_ITER
            assert np.linalg.norm(np.array(ev.point(*got)) - p) < 1e-5 * abs(gap)
            assert np.linalg.norm(np.array(ev.point(*ev.uv_near(q, seed))) - p) < 1e-9
    # past the box: a point beyond the top edge of a cylinder (as B-splines), whose foot on the
    # surface's extension is off the face
    import build123d as bd

    shape = BRepBuilderAPI_NurbsConvert(bd.Cylinder(10.0, 20.0).wrapped, True).Shape()
    (side,) = [f for f in _faces(shape) if f.ad.IsUPeriodic() or f.ad.IsVPeriodic()]
    axis = 1 if side.ad.IsUPeriodic() else 0
    u, v = (0.5 * (side.u0 + side.u1), side.v1) if axis == 1 else (side.u1, 0.5 * (side.v0 + side.v1))
    side.ad.D1(u, v, side._p, side._du, side._dv)
    along = np.array((side._dv if axis == 1 else side._du).Coord())
    n = np.cross(side._du.Coord(), side._dv.Coord())
    out = np.array(side.point(u, v)) + 0.5 * along / np.linalg.norm(along) + 0.01 * n / np.linalg.norm(n)
    seed = (u, v - 0.05 * (side.v1 - side.v0)) if axis == 1 else (u - 0.05 * (side.u1 - side.u0), v)
    assert side._newton_uv(tuple(out), seed, foot=True) is None
    assert side.uv_near(tuple(out), seed, foot=True) == side.uv_near(tuple(out), seed)
    assert side._sas is not None
