import numpy as np
import pytest

from tests.conftest import notched_box, shortest_edge
from worker.dst.errors import EmptyGeometryError, NotASolidError, StepReadError
from worker.dst.step_io import LoadedPart, orient, read_step, rotation_matrix, sniff_step, solid_volume


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


def test_wire_repair_drops_edges_under_its_precision_and_keeps_the_volume():
    import build123d as bd

    from worker.dst.step_io import heal_wires

    cube = bd.Box(10, 10, 10).solids()[0].wrapped
    assert heal_wires(cube, 0.01) is None  # nothing to repair

    notched = notched_box()
    assert shortest_edge(notched) == pytest.approx(0.002, rel=1e-6)
    healed, change = heal_wires(notched, 0.01)
    assert shortest_edge(healed) > 0.01
    assert solid_volume(healed) == pytest.approx(solid_volume(notched), rel=1e-6)
    assert change < 1e-6


def test_a_face_the_mesher_cannot_mesh_is_retried_after_the_wire_repair(monkeypatch, tmp_path):
    import worker.dst.pipeline as pipeline
    from tests.worker.dst.meshcheck import assert_watertight
    from worker.dst.errors import UnmeshedFaceError
    from worker.dst.params import SliceParams
    from worker.dst.step_io import LoadedPart

    # a mesher that, like BRepMesh on trj7_b1-ec-214's face 354, gives up on a face whose wire has
    # edges too short for it (the notch's 2 um), at any deflection: meshing finer does not help
    real = pipeline.build_topomesh

    def picky(solid, **kw):
        if shortest_edge(solid) < 0.0025:
            raise UnmeshedFaceError("face 3 could not be meshed (degenerate or invalid face)")
        return real(solid, **kw)

    monkeypatch.setattr(pipeline, "build_topomesh", picky)
    part = LoadedPart(solids=[notched_box()], source_units=["MM"])
    mesh = pipeline.slice_part(part, SliceParams(layer_height=0.2))
    assert_watertight(mesh)
    assert shortest_edge(mesh.part.solids[0]) > 0.003  # the 2 um edges are gone from the part itself
    assert any("face 3 could not be meshed" in w and "repaired" in w for w in mesh.warnings)

    monkeypatch.setattr(pipeline, "heal_wires", lambda solid, precision: None)
    with pytest.raises(UnmeshedFaceError):
        pipeline.slice_part(
            LoadedPart(solids=[notched_box()], source_units=["MM"]), SliceParams(layer_height=0.2)
        )


def _vertices(solid) -> np.ndarray:
    from OCP.BRep import BRep_Tool
    from OCP.TopAbs import TopAbs_VERTEX
    from OCP.TopExp import TopExp_Explorer
    from OCP.TopoDS import TopoDS

    pts = []
    exp = TopExp_Explorer(solid, TopAbs_VERTEX)
    while exp.More():
        pts.append(BRep_Tool.Pnt_s(TopoDS.Vertex(exp.Current())).Coord())
        exp.Next()
    return np.unique(np.array(pts), axis=0)


@pytest.mark.parametrize("angles", [(90, 0, 0), (0, -90, 180), (30, 0, 0), (12.5, -70, 200), (-360, 360, 45)])
def test_rotation_matrix_is_the_turn_about_x_then_y_then_z(angles):
    from scipy.spatial.transform import Rotation

    m = rotation_matrix(angles)
    # scipy's lower-case 'xyz': extrinsic turns about the fixed axes, x first
    assert np.allclose(m, Rotation.from_euler("xyz", angles, degrees=True).as_matrix(), atol=1e-15)
    assert np.allclose(m @ m.T, np.eye(3), atol=1e-15) and np.linalg.det(m) == pytest.approx(1.0)
    if all(a % 90 == 0 for a in angles):  # exactly: a face turned horizontal is exactly horizontal
        assert set(np.unique(m)) <= {-1.0, 0.0, 1.0}


def test_orient_turns_the_solids_and_leaves_the_read_part_alone(tmp_path):
    import build123d as bd

    from tests.conftest import write_step

    box = bd.Box(10, 20, 30, align=(bd.Align.MIN, bd.Align.MIN, bd.Align.MIN))
    part = read_step(write_step(box, tmp_path / "box.step", nurbs=False))
    corners = _vertices(part.solids[0])
    up = orient(part, (90, 0, 0))  # y -> z, z -> -y
    turned = _vertices(up.solids[0])
    assert turned.min(axis=0).tolist() == [0.0, -30.0, 0.0]
    assert turned.max(axis=0).tolist() == [10.0, 0.0, 20.0]
    assert np.array_equal(_vertices(part.solids[0]), corners)  # a copy was turned
    assert up.rotation == (90.0, 0.0, 0.0) and part.rotation == (0.0, 0.0, 0.0)
    assert up.volume_mm3 == pytest.approx(6000.0, rel=1e-9)
    assert orient(up, (90, 0, 0)) is up and orient(part, (0, 0, 0)) is part
    with pytest.raises(ValueError, match="already turned"):
        orient(up, (0, 90, 0))
    odd = orient(part, (12.5, -70, 200))
    expect = np.unique(corners @ rotation_matrix((12.5, -70, 200)).T, axis=0)
    assert np.allclose(_vertices(odd.solids[0]), expect, atol=1e-12)


def test_orient_turns_a_placed_solid_with_its_placement(tmp_path):
    """An assembly's instances come with a placement (a TopLoc_Location) on their shapes: the turn
    applies to where the solid is, not to its geometry before placement."""
    import build123d as bd

    placed = bd.Pos(100, 0, 0) * bd.Box(2, 2, 2).solid()
    assert not placed.wrapped.Location().IsIdentity()
    part = LoadedPart(solids=[placed.wrapped], source_units=["MM"])
    turned = _vertices(orient(part, (0, 0, 90)).solids[0])  # x -> y
    assert np.allclose(turned.min(axis=0), [-1, 99, -1]) and np.allclose(turned.max(axis=0), [1, 101, 1])
