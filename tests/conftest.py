"""Shared fixtures: STEP parts built by the tests themselves, and the shared corpus when present."""

from __future__ import annotations

import math
import os
from pathlib import Path

import pytest

CORPUS = Path(__file__).resolve().parents[1].parent / "shared" / "corpus"


def build_part(kind: str, **kw):
    """An analytic part as a build123d shape (mm). Kinds: hemisphere, torus, cone, tube, step_box,
    tangent_features, dome_below_top, tilted_boss, through_hole, lying_cylinder, half_torus,
    filleted_ridge, lens, cut_cap."""
    import build123d as bd

    if kind == "hemisphere":
        r = kw.get("radius", 20.0)
        return bd.Sphere(r) - bd.Box(
            3 * r, 3 * r, 3 * r, align=(bd.Align.CENTER, bd.Align.CENTER, bd.Align.MAX)
        )
    if kind == "filleted_ridge":
        # A 40 x 10 x 10 block whose top edge along x at y = +5 is rounded with radius ``radius``:
        # turned 45 degrees about x, that edge is a ridge whose crest is the fillet's middle line.
        block = bd.Box(40.0, 10.0, 10.0)
        edge = block.edges().filter_by(bd.Axis.X).filter_by(lambda e: e.center().Y > 0).sort_by(bd.Axis.Z)[-1]
        return bd.fillet(edge, kw.get("radius", 0.3))
    if kind == "lens":
        # A prism whose section is a lens: the overlap of two vertical cylinders of ``radius`` whose
        # axes are ``radius`` - ``sag`` either side of the y = 0 line (each arc sags ``sag`` from the
        # lens's chord along x), ``height`` tall.
        r, sag, h = kw.get("radius", 11.45), kw.get("sag", 0.4), kw.get("height", 2.0)
        return bd.Pos(0, r - sag, 0) * bd.Cylinder(r, h) & bd.Pos(0, sag - r, 0) * bd.Cylinder(r, h)
    if kind == "torus":
        return bd.Torus(kw.get("major", 15.0), kw.get("minor", 5.0))
    if kind == "cone":
        return bd.Cone(
            kw.get("radius", 10.0),
            0.0,
            kw.get("height", 20.0),
            align=(bd.Align.CENTER, bd.Align.CENTER, bd.Align.MIN),
        )
    if kind == "tube":
        outer = bd.Cylinder(kw.get("outer", 8.0), kw.get("length", 30.0))
        inner = bd.Cylinder(kw.get("inner", 4.0), kw.get("length", 30.0) + 2)
        return (outer - inner).rotate(bd.Axis.X, kw.get("tilt_deg", 30.0))
    if kind == "step_box":
        # A 20 x 20 x 4.1 block with a 10 x 10 x 3 block on it: the step's flat face at z = 4.1 lies
        # exactly on the middle-mode plane 0.1 + 0.2 * 20 for h = 0.2. ``overhang``: the blocks'
        # sizes swapped (the wide one on top, the flat face facing down).
        lower, upper = (10, 20) if kw.get("overhang") else (20, 10)
        align = (bd.Align.CENTER, bd.Align.CENTER, bd.Align.MIN)
        return bd.Box(lower, lower, 4.1, align=align) + bd.Pos(0, 0, 4.1) * bd.Box(
            upper, upper, 3, align=align
        )
    if kind == "tangent_features":
        # A block with a horizontal hole whose bottom (z = 0.1) and top (z = 4.1) lines lie on the
        # middle-mode planes for h = 0.2, and a sphere whose top (z = 8.1) touches plane 40.
        block = bd.Box(30, 10, 10, align=(bd.Align.CENTER, bd.Align.CENTER, bd.Align.MIN))
        hole = bd.Pos(0, 0, 2.1) * bd.Cylinder(2.0, 40, rotation=(0, 90, 0))
        dome = bd.Pos(8, 0, 6.1) * bd.Sphere(2.0)
        pocket = bd.Pos(8, 0, 9) * bd.Box(8, 8, 6)
        return (block - hole - pocket) + dome
    if kind == "dome_below_top":
        # A plate with a spherical dome (R 4, apex at z = 5.1005, 0.5 um above the middle-mode plane 5.1
        # for h = 0.2) and a taller post: the apex is a local, not the global, maximum. The sphere is
        # turned so that its apex is not a pole of the B-spline.
        plate = bd.Box(30, 20, 3, align=(bd.Align.CENTER, bd.Align.CENTER, bd.Align.MIN))
        post = bd.Pos(11, 0, 0) * bd.Box(4, 4, 10, align=(bd.Align.CENTER, bd.Align.CENTER, bd.Align.MIN))
        dome = bd.Pos(-5, 1, 5.1005 - 4.0) * bd.Sphere(4.0).rotate(bd.Axis.X, 37).rotate(bd.Axis.Z, 20)
        below = bd.Box(40, 40, 10, align=(bd.Align.CENTER, bd.Align.CENTER, bd.Align.MAX))
        return plate + post + (dome - below)
    if kind == "tilted_boss":
        # A plate with a cylinder (r 5, length 8) tilted 25 deg about x, whose circular top rim peaks
        # at z = 7.1005 (4 cos 25 + 5 sin 25 above the cylinder's centre), 0.5 um above the middle-mode
        # plane 7.1 for h = 0.2 (apex on a B-rep edge, not the part's top: a taller post stands beside it).
        t = math.radians(25.0)
        dz = 7.1005 - (4 * math.cos(t) + 5 * math.sin(t))
        plate = bd.Box(40, 30, 3, align=(bd.Align.CENTER, bd.Align.CENTER, bd.Align.MIN))
        post = bd.Pos(15, 0, 0) * bd.Box(4, 4, 15, align=(bd.Align.CENTER, bd.Align.CENTER, bd.Align.MIN))
        boss = bd.Pos(-6, 0, dz) * bd.Cylinder(5.0, 8.0).rotate(bd.Axis.X, 25)
        below = bd.Box(60, 60, 10, align=(bd.Align.CENTER, bd.Align.CENTER, bd.Align.MAX))
        return plate + post + (boss - below)
    if kind == "through_hole":
        # A 30 x 10 x 8 block with a horizontal hole (r 2, along x) whose top line lies ``clearance``
        # mm above the middle-mode plane 4.1 (h = 0.2): that plane cuts the block into two rectangles.
        top = 4.1 + kw["clearance"]
        block = bd.Box(30, 10, 8, align=(bd.Align.CENTER, bd.Align.CENTER, bd.Align.MIN))
        return block - bd.Pos(0, 0, top - 2.0) * bd.Cylinder(2.0, 40, rotation=(0, 90, 0))
    if kind == "lying_cylinder":
        # A cylinder (r 3, length 20, along x) lying on a plate, its top line ``clearance`` mm above
        # the middle-mode plane 4.1 (h = 0.2), and a taller 3 x 3 post beside it.
        top = 4.1 + kw["clearance"]
        plate = bd.Box(30, 10, 1, align=(bd.Align.CENTER, bd.Align.CENTER, bd.Align.MIN))
        post = bd.Pos(12, 0, 0) * bd.Box(3, 3, 8, align=(bd.Align.CENTER, bd.Align.CENTER, bd.Align.MIN))
        cyl = bd.Pos(-2, 0, top - 3.0) * bd.Cylinder(3.0, 20, rotation=(0, 90, 0))
        below = bd.Box(60, 60, 10, align=(bd.Align.CENTER, bd.Align.CENTER, bd.Align.MAX))
        return plate + post + (cyl - below)
    if kind == "flat_torus":
        # A torus (R 10, r 2, axis vertical) on a plate, the top circle of its tube ``clearance`` mm
        # above the middle-mode plane 4.1 (h = 0.2), and a taller 2 x 2 post in a corner.
        top = 4.1 + kw["clearance"]
        plate = bd.Box(30, 30, 1, align=(bd.Align.CENTER, bd.Align.CENTER, bd.Align.MIN))
        post = bd.Pos(13, 13, 0) * bd.Box(2, 2, 8, align=(bd.Align.CENTER, bd.Align.CENTER, bd.Align.MIN))
        return plate + post + bd.Pos(0, 0, top - 2.0) * bd.Torus(10.0, 2.0)
    if kind == "cut_cap":
        # The top of a sphere (R 20, axis along x: its top (0, 0, 20) is no pole) above z = 14, its
        # side beyond x = ``offset`` cut off by a 45 degree plane through the sphere's point
        # (offset, 0, sqrt(R^2 - offset^2)): the top lies inside the sphere's face, the edge with the
        # cut ``offset`` from it and at most R - sqrt(R^2 - offset^2) below it.
        r, off = 20.0, kw.get("offset", 0.3)
        ball = bd.Rot(0, 90, 0) * bd.Sphere(r)
        cap = ball & bd.Pos(0, 0, 14) * bd.Box(
            50, 50, 10, align=(bd.Align.CENTER, bd.Align.CENTER, bd.Align.MIN)
        )
        cut = bd.Plane(origin=(off, 0, math.sqrt(r * r - off * off)), z_dir=(1, 0, 1))
        return bd.split(cap, cut, keep=bd.Keep.BOTTOM)
    if kind == "half_torus":
        return _half_torus(kw.get("major", 4.0), kw.get("minor", 2.336), kw.get("seam", 0.1))
    raise ValueError(kind)


def _half_torus(major: float, minor: float, seam: float):
    """The upper half of a torus standing on its rim (axis along x, top at z = major + minor), closed
    by its two end disks on z = 0, its one toroidal face parametrised past v = 2 pi: the tube's seam
    at v = ``seam`` rad (``seam`` x minor mm along the tube from the top), the top at v = 2 pi."""
    import build123d as bd
    from OCP.BRep import BRep_Tool
    from OCP.BRepAdaptor import BRepAdaptor_Curve
    from OCP.BRepBuilderAPI import (
        BRepBuilderAPI_MakeFace,
        BRepBuilderAPI_MakeSolid,
        BRepBuilderAPI_MakeWire,
        BRepBuilderAPI_Sewing,
    )
    from OCP.Geom import Geom_ToroidalSurface
    from OCP.gp import gp_Ax3, gp_Dir, gp_Pnt
    from OCP.ShapeFix import ShapeFix_Solid
    from OCP.TopAbs import TopAbs_EDGE, TopAbs_SHELL
    from OCP.TopExp import TopExp_Explorer
    from OCP.TopoDS import TopoDS

    surface = Geom_ToroidalSurface(gp_Ax3(gp_Pnt(0, 0, 0), gp_Dir(1, 0, 0), gp_Dir(0, 0, 1)), major, minor)
    face = BRepBuilderAPI_MakeFace(surface, -math.pi / 2, math.pi / 2, seam, seam + 2 * math.pi, 1e-7).Face()
    sewing = BRepBuilderAPI_Sewing(1e-6)
    sewing.Add(face)
    exp = TopExp_Explorer(face, TopAbs_EDGE)
    while exp.More():  # the two end circles on z = 0 get a disk each
        edge = TopoDS.Edge(exp.Current())
        curve = BRepAdaptor_Curve(edge)
        mid = curve.Value(0.5 * (curve.FirstParameter() + curve.LastParameter()))
        if not BRep_Tool.IsClosed_s(edge, face) and abs(mid.Z()) < 1e-9:
            sewing.Add(BRepBuilderAPI_MakeFace(BRepBuilderAPI_MakeWire(edge).Wire()).Face())
        exp.Next()
    sewing.Perform()
    shell = TopoDS.Shell(TopExp_Explorer(sewing.SewedShape(), TopAbs_SHELL).Current())
    fix = ShapeFix_Solid(BRepBuilderAPI_MakeSolid(shell).Solid())
    fix.Perform()
    return bd.Solid(fix.Solid())


def kinked_prism(corners, height: float):
    """A prism whose whole side wall is ONE face: the extrusion of a closed degree-1 B-spline through
    ``corners`` (C0 at each), so that the section's corners lie inside that face, not on its edges."""
    from OCP.BRepBuilderAPI import BRepBuilderAPI_MakeEdge, BRepBuilderAPI_MakeFace, BRepBuilderAPI_MakeWire
    from OCP.BRepPrimAPI import BRepPrimAPI_MakePrism
    from OCP.collections import Array1_double, Array1_gp_Pnt, Array1_int
    from OCP.Geom import Geom_BSplineCurve
    from OCP.gp import gp_Pnt, gp_Vec

    pts = [*corners, corners[0]]
    poles, knots, mults = Array1_gp_Pnt(1, len(pts)), Array1_double(1, len(pts)), Array1_int(1, len(pts))
    for i, (x, y) in enumerate(pts, 1):
        poles.SetValue(i, gp_Pnt(x, y, 0.0))
        knots.SetValue(i, float(i - 1))
        mults.SetValue(i, 2 if i in (1, len(pts)) else 1)
    wire = BRepBuilderAPI_MakeWire(BRepBuilderAPI_MakeEdge(Geom_BSplineCurve(poles, knots, mults, 1)).Edge())
    face = BRepBuilderAPI_MakeFace(wire.Wire(), True).Face()
    return BRepPrimAPI_MakePrism(face, gp_Vec(0, 0, height)).Shape()


def shortest_edge(solid) -> float:
    from OCP.BRepGProp import BRepGProp
    from OCP.GProp import GProp_GProps
    from OCP.TopAbs import TopAbs_EDGE
    from OCP.TopExp import TopExp_Explorer

    shortest = float("inf")
    exp = TopExp_Explorer(solid, TopAbs_EDGE)
    while exp.More():
        props = GProp_GProps()
        BRepGProp.LinearProperties_s(exp.Current(), props)
        shortest = min(shortest, props.Mass())
        exp.Next()
    return shortest


def notched_box():
    """A 10 mm cube with a groove 2 um deep and 4 um wide across one side: edges of 2 and 4 um."""
    import build123d as bd
    from OCP.TopAbs import TopAbs_SOLID
    from OCP.TopExp import TopExp_Explorer
    from OCP.TopoDS import TopoDS

    shape = bd.Box(10, 10, 10) - bd.Pos(5, 0, 0) * bd.Box(0.004, 20, 0.004)
    return TopoDS.Solid(TopExp_Explorer(shape.wrapped, TopAbs_SOLID).Current())


def write_step(shape, path: Path, *, nurbs: bool = True, unit: str | None = None) -> Path:
    """Write ``shape`` to STEP, converted to B-splines (``BRepBuilderAPI_NurbsConvert``) by default."""
    from OCP.BRepBuilderAPI import BRepBuilderAPI_NurbsConvert
    from OCP.Interface import Interface_Static
    from OCP.STEPControl import STEPControl_AsIs, STEPControl_Writer

    occ = shape.wrapped if hasattr(shape, "wrapped") else shape
    if nurbs:
        occ = BRepBuilderAPI_NurbsConvert(occ, True).Shape()
    writer = STEPControl_Writer()
    if unit:
        Interface_Static.SetCVal_s("write.step.unit", unit)
    try:
        writer.Transfer(occ, STEPControl_AsIs)
        assert writer.Write(str(path)) == 1
    finally:
        if unit:
            Interface_Static.SetCVal_s("write.step.unit", "MM")
    return path


@pytest.fixture
def make_step(tmp_path):
    """Factory: ``make_step("hemisphere", radius=20)`` -> path of a B-spline STEP file under tmp_path."""
    counter = [0]

    def factory(kind: str, *, nurbs: bool = True, unit: str | None = None, **kw) -> Path:
        counter[0] += 1
        return write_step(
            build_part(kind, **kw), tmp_path / f"{kind}_{counter[0]}.step", nurbs=nurbs, unit=unit
        )

    return factory


@pytest.fixture(scope="session")
def corpus() -> Path:
    if not CORPUS.is_dir():
        pytest.skip(f"the shared STEP corpus is not beside this checkout ({CORPUS})")
    return CORPUS


def circle_sag(radius, length):
    """Sagitta (mm) of a chord of ``length`` in a circle of ``radius``."""
    return radius - math.sqrt(max(radius * radius - 0.25 * length * length, 0.0))


os.environ.setdefault("OMP_NUM_THREADS", "1")


def process_dead(pid: int) -> bool:
    """The process is gone or a zombie (Linux /proc)."""
    try:
        with open(f"/proc/{pid}/status") as f:
            return any(line.startswith("State:") and "Z" in line.split()[1] for line in f)
    except FileNotFoundError:
        return True
