import pytest

from worker.dst.errors import EmptyGeometryError, NotASolidError, StepReadError
from worker.dst.step_io import read_step, sniff_step, solid_volume


def test_sniff_accepts_part21_and_refuses_others():
    assert sniff_step(b"ISO-10303-21;\nHEADER;")
    assert sniff_step(b"\xef\xbb\xbf  iso-10303-21;")
    assert not sniff_step(b"solid stl")
    assert not sniff_step(b"")


def test_inch_file_is_read_in_millimetres(make_step):
    path = make_step("cone", radius=1.0, height=2.0, nurbs=False, unit="INCH")
    part = read_step(path)
    assert any("INCH" in w.upper() for w in part.warnings)
    # build123d built it in mm; the writer declared inches and scaled, the reader scales back
    assert solid_volume(part.solids[0]) == pytest.approx(3.14159265 * 1.0 * 2.0 / 3.0, rel=1e-6)


def test_open_shell_is_not_a_solid(tmp_path):
    import build123d as bd

    from tests.conftest import write_step

    face = bd.Face.make_rect(10, 10)
    path = write_step(face, tmp_path / "face.step", nurbs=False)
    with pytest.raises(NotASolidError):
        read_step(path)


def test_truncated_file_is_a_read_error(make_step, tmp_path):
    good = make_step("cone", radius=2, height=2).read_bytes()
    bad = tmp_path / "cut.step"
    bad.write_bytes(good[: len(good) // 2])
    with pytest.raises((StepReadError, EmptyGeometryError, NotASolidError)):
        read_step(bad)


def _strip_with_joined_corners(tol: float = 1.001):
    """A B-spline box 40 x 1 x 10 mm whose corners one vertex joins across the 1 mm width, as a file
    written with a 1 mm tolerance has them (every vertex moved to y = 0, its tolerance covering y = 1)."""
    from OCP.BRep import BRep_Builder, BRep_Tool
    from OCP.BRepBuilderAPI import BRepBuilderAPI_NurbsConvert
    from OCP.BRepPrimAPI import BRepPrimAPI_MakeBox
    from OCP.BRepTools import BRepTools_ReShape
    from OCP.gp import gp_Pnt
    from OCP.TopAbs import TopAbs_EDGE, TopAbs_FORWARD, TopAbs_REVERSED
    from OCP.TopExp import TopExp, TopExp_Explorer
    from OCP.TopoDS import TopoDS, TopoDS_Vertex

    box = BRepBuilderAPI_NurbsConvert(BRepPrimAPI_MakeBox(40.0, 1.0, 10.0).Shape(), True).Shape()
    builder, joined, reshape, seen = BRep_Builder(), {}, BRepTools_ReShape(), []
    exp = TopExp_Explorer(box, TopAbs_EDGE)
    while exp.More():
        edge = TopoDS.Edge(exp.Current().Oriented(TopAbs_FORWARD))
        exp.Next()
        if any(edge.IsSame(e) for e in seen):
            continue
        seen.append(edge)
        copy = TopoDS.Edge(edge.EmptyCopied())
        first, last = BRep_Tool.Range_s(edge)
        for v, param, orientation in (
            (TopExp.FirstVertex_s(edge), first, TopAbs_FORWARD),
            (TopExp.LastVertex_s(edge), last, TopAbs_REVERSED),
        ):
            x, _, z = BRep_Tool.Pnt_s(v).Coord()
            key = (round(x, 6), round(z, 6))
            if key not in joined:
                joined[key] = TopoDS_Vertex()
                builder.MakeVertex(joined[key], gp_Pnt(x, 0.0, z), tol)
            builder.Add(copy, joined[key].Oriented(orientation))
            builder.UpdateVertex(joined[key], param, copy, tol)
        reshape.Replace(edge, copy)
    return reshape.Apply(box)


def test_corners_joined_by_a_coarse_tolerance_are_split(tmp_path, monkeypatch):
    import numpy as np

    import worker.dst.step_io as step_io
    from tests.conftest import write_step
    from tests.worker.dst.meshcheck import assert_watertight, ring_edges
    from worker.dst.errors import TessellationError
    from worker.dst.params import SliceParams
    from worker.dst.pipeline import slice_part
    from worker.dst.topomesh import max_tolerance

    path = write_step(_strip_with_joined_corners(), tmp_path / "joined.step", nurbs=False)
    params = SliceParams(layer_height=0.2)

    # Read as the file has it, one node stands for two corners and the mesh folds there.
    with monkeypatch.context() as m:
        m.setattr(step_io, "split_loose_vertices", lambda solid: None)
        joined = read_step(path)
        assert max_tolerance(joined.solids[0]) > 1.0
        with pytest.raises(TessellationError):
            slice_part(joined, params)

    part = read_step(path)
    assert any("4 vertex(es)" in w and "up to 1 mm apart" in w for w in part.warnings)
    assert max_tolerance(part.solids[0]) < 1e-3
    assert solid_volume(part.solids[0]) == pytest.approx(400.0, rel=1e-9)
    mesh = slice_part(part, params)
    assert_watertight(mesh)
    # every ring is the exact 40 x 1 rectangle: its vertices on the sides, its perimeter 82 mm
    v = mesh.vertices
    ring = mesh.vertex_plane >= 0
    x, y = v[ring, 0], v[ring, 1]
    off_side = np.minimum.reduce([np.abs(x), np.abs(x - 40), np.abs(y), np.abs(y - 1)])
    assert off_side.max() < 1e-6
    assert np.all((x > -1e-6) & (x < 40 + 1e-6) & (y > -1e-6) & (y < 1 + 1e-6))
    edges, plane = ring_edges(mesh)
    lengths = np.linalg.norm(v[edges[:, 0]] - v[edges[:, 1]], axis=1)
    perimeter = np.bincount(plane, weights=lengths, minlength=len(mesh.planes.section_z))
    np.testing.assert_allclose(perimeter, 82.0, rtol=1e-9)


def _shortest_edge(solid) -> float:
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


def _notched_box():
    """A 10 mm cube with a groove 2 um deep and 4 um wide across one side: edges of 2 and 4 um."""
    import build123d as bd
    from OCP.TopAbs import TopAbs_SOLID
    from OCP.TopExp import TopExp_Explorer
    from OCP.TopoDS import TopoDS

    shape = bd.Box(10, 10, 10) - bd.Pos(5, 0, 0) * bd.Box(0.004, 20, 0.004)
    return TopoDS.Solid(TopExp_Explorer(shape.wrapped, TopAbs_SOLID).Current())


def test_wire_repair_drops_edges_under_its_precision_and_keeps_the_volume():
    import build123d as bd

    from worker.dst.step_io import heal_wires

    cube = bd.Box(10, 10, 10).solids()[0].wrapped
    assert heal_wires(cube, 0.01) is None  # nothing to repair

    notched = _notched_box()
    assert _shortest_edge(notched) == pytest.approx(0.002, rel=1e-6)
    healed, change = heal_wires(notched, 0.01)
    assert _shortest_edge(healed) > 0.01
    assert solid_volume(healed) == pytest.approx(solid_volume(notched), rel=1e-6)
    assert change < 1e-6


def test_a_face_the_mesher_cannot_mesh_is_retried_after_the_wire_repair(monkeypatch, tmp_path):
    import worker.dst.pipeline as pipeline
    from tests.worker.dst.meshcheck import assert_watertight
    from worker.dst.errors import UnmeshedFaceError
    from worker.dst.params import SliceParams
    from worker.dst.step_io import LoadedPart

    # a mesher that, like BRepMesh on trj7_b1-ec-214's face 354, gives up on a face whose wire has
    # edges too short for it
    real = pipeline.build_topomesh

    def picky(solid, **kw):
        if _shortest_edge(solid) < kw["deflection"]:
            raise UnmeshedFaceError("face 3 could not be meshed (degenerate or invalid face)")
        return real(solid, **kw)

    monkeypatch.setattr(pipeline, "build_topomesh", picky)
    part = LoadedPart(solids=[_notched_box()], source_units=["MM"])
    mesh = pipeline.slice_part(part, SliceParams(layer_height=0.2))
    assert_watertight(mesh)
    assert _shortest_edge(mesh.part.solids[0]) > 0.003  # the 2 um edges are gone from the part itself
    assert any("face 3 could not be meshed" in w and "repaired" in w for w in mesh.warnings)

    monkeypatch.setattr(pipeline, "heal_wires", lambda solid, precision: None)
    with pytest.raises(UnmeshedFaceError):
        pipeline.slice_part(
            LoadedPart(solids=[_notched_box()], source_units=["MM"]), SliceParams(layer_height=0.2)
        )
