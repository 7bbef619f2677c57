"""The topology mesh: BRepMesh's per-face meshes merged into one closed mesh, and its repairs where
BRepMesh leaves a hole in a face, folds a face over or meshes two faces on top of each other."""

from __future__ import annotations

import numpy as np
import pytest
from OCP.BRepBuilderAPI import BRepBuilderAPI_MakeVertex
from OCP.BRepExtrema import BRepExtrema_DistShapeShape
from OCP.gp import gp_Pnt

from tests.conftest import build_part
from worker.dst import topomesh as T
from worker.dst.errors import TessellationError
from worker.dst.meshops import edge_defects, signed_volume
from worker.dst.step_io import solid_volume

DEFLECTION = 0.01


def _solid(kind: str, **kw):
    from OCP.TopAbs import TopAbs_SOLID
    from OCP.TopExp import TopExp_Explorer
    from OCP.TopoDS import TopoDS

    exp = TopExp_Explorer(build_part(kind, **kw).wrapped, TopAbs_SOLID)
    return TopoDS.Solid(exp.Current())


def _distance_to_face(p, face) -> float:
    vertex = BRepBuilderAPI_MakeVertex(gp_Pnt(*map(float, p))).Vertex()
    return BRepExtrema_DistShapeShape(vertex, face).Value()


def _holed_face_mesh(monkeypatch, solid, radius: float):
    """Have BRepMesh's mesh of the solid's largest face lose its triangles whose centroids lie within
    ``radius`` of the face's middle node, as BRepMesh does where it cannot place part of a face.
    Returns the face's index."""
    mesh = T.build_topomesh(solid, deflection=DEFLECTION, angular=0.35, merge_tol=1e-7)
    counts = np.bincount(mesh.tri_face)
    target = int(counts.argmax())
    centre = mesh.xyz[mesh.tris[mesh.tri_face == target]].mean(axis=1)[counts[target] // 2]
    real = T.read_triangulations

    def holed(faces):
        meshes = real(faces)
        assert len(meshes) == len(counts), "every face of the solid is meshed"
        pts, uvs, t = meshes[target]
        meshes[target] = pts, uvs, t[np.linalg.norm(pts[t].mean(axis=1) - centre, axis=1) > radius]
        return meshes

    monkeypatch.setattr(T, "read_triangulations", holed)
    return target


def _assert_closed_topology_mesh(mesh) -> None:
    assert edge_defects(mesh.tris, mesh.n_nodes) == (0, 0)
    assert np.array_equal(np.unique(mesh.tris), np.arange(mesh.n_nodes)), "a node on no triangle"
    assert signed_volume(mesh.xyz, mesh.tris) > 0


def test_a_hole_left_in_a_flat_face_is_patched_on_that_face(monkeypatch):
    solid = _solid("step_box")
    target = _holed_face_mesh(monkeypatch, solid, radius=4.0)
    mesh = T.build_topomesh(solid, deflection=DEFLECTION, angular=0.35, merge_tol=1e-7)
    _assert_closed_topology_mesh(mesh)
    assert [f for f, _, _ in mesh.patched_faces] == [target]
    assert mesh.patched_faces[0][2] < 1e-9  # a plane: the patch lies on it
    face = mesh.faces[target].face
    patch = mesh.tri_face == target
    for c in mesh.xyz[mesh.tris[patch]].mean(axis=1):
        assert _distance_to_face(c, face) < 1e-9
    exact = solid_volume(solid)
    assert signed_volume(mesh.xyz, mesh.tris) == pytest.approx(exact, rel=1e-9)


def test_a_small_hole_in_a_curved_face_is_patched_within_the_deflection(monkeypatch):
    solid = _solid("hemisphere", radius=20.0)
    target = _holed_face_mesh(monkeypatch, solid, radius=0.2)  # a few small triangles missing
    mesh = T.build_topomesh(solid, deflection=DEFLECTION, angular=0.35, merge_tol=1e-7)
    _assert_closed_topology_mesh(mesh)
    ((face, n_tris, dist),) = mesh.patched_faces
    assert face == target and dist <= DEFLECTION
    c = mesh.xyz[mesh.tris[mesh.tri_face == target]].mean(axis=1)
    assert max(_distance_to_face(p, mesh.faces[target].face) for p in c[-n_tris:]) <= DEFLECTION


def test_a_hole_too_curved_for_a_flat_patch_is_refused(monkeypatch):
    # a hole about 6 mm across in a sphere of R 20: any patch on its rim is ~0.2 mm off the surface
    solid = _solid("hemisphere", radius=20.0)
    _holed_face_mesh(monkeypatch, solid, radius=3.0)
    with pytest.raises(TessellationError, match="not closed"):
        T.build_topomesh(solid, deflection=DEFLECTION, angular=0.35, merge_tol=1e-7)


def test_holes_touching_at_a_node_are_split_into_simple_loops():
    # a fan of 6 triangles round node 0 with two opposite triangles missing: two holes meeting at 0
    ring = [1, 2, 3, 4, 5, 6]
    fan = np.array([(0, ring[i], ring[(i + 1) % 6]) for i in range(6)])
    outer = np.array([(ring[(i + 1) % 6], ring[i], 7) for i in range(6)])  # a cap closing the rim
    tris = np.concatenate([fan[[0, 1, 3, 4]], outer])
    loops = T._hole_loops(tris, 8)
    assert sorted(sorted(loop) for loop in loops) == [[0, 1, 6], [0, 3, 4]]
    for loop in loops:  # each follows the direction the mesh holds its open edges
        held = {tuple(e) for t in tris.tolist() for e in ((t[0], t[1]), (t[1], t[2]), (t[2], t[0]))}
        assert all((a, b) in held for a, b in zip(loop, loop[1:] + loop[:1], strict=True))


def test_back_to_back_triangles_are_found():
    tris = np.array([[0, 1, 2], [1, 0, 2], [2, 3, 0], [3, 2, 1], [0, 2, 3]])
    # [1, 0, 2] is [0, 1, 2] turned over; [0, 2, 3] is [2, 3, 0] rotated (the same turn): not doubled
    assert T._doubled_triangles(tris).tolist() == [True, True, False, False, False]


def test_triangles_on_a_border_no_edge_bounds_are_stray():
    # a unit square as two triangles; the edge polygons cover three of its sides only
    pts = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], dtype=float)
    tris = np.array([[0, 1, 2], [0, 2, 3]])
    polygons = [np.array([0, 1, 2]), np.array([2, 3])]
    assert T._stray_triangles(pts, tris, polygons, 1e-9).tolist() == [False, True]
    assert not T._stray_triangles(pts, tris, polygons + [np.array([3, 0])], 1e-9).any()


def test_least_area_patch_of_a_planar_polygon_covers_it_once():
    angles = np.linspace(0, 2 * np.pi, 9)[:-1]
    pts = np.c_[np.cos(angles), np.sin(angles), np.zeros(8)]
    pts[2] = 0.5 * (pts[1] + pts[3])  # a point on the segment between its neighbours
    tri = T._min_area_triangulation(pts)
    assert len(tri) == 6
    areas = [0.5 * np.linalg.norm(np.cross(pts[j] - pts[i], pts[k] - pts[i])) for i, j, k in tri]
    assert min(areas) > 1e-6  # no triangle on the three collinear points
    x, y = pts[:, 0], pts[:, 1]
    polygon_area = 0.5 * abs(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))
    assert sum(areas) == pytest.approx(polygon_area, rel=1e-12)


def _meshed_faces(shape, deflection: float = 0.05):
    """(face, location, triangulation) of every face of ``shape`` after BRepMesh, in explorer order."""
    from OCP.BRep import BRep_Tool
    from OCP.BRepMesh import BRepMesh_IncrementalMesh
    from OCP.TopAbs import TopAbs_FACE
    from OCP.TopExp import TopExp_Explorer
    from OCP.TopLoc import TopLoc_Location
    from OCP.TopoDS import TopoDS

    BRepMesh_IncrementalMesh(shape, deflection, False, 0.35, False)
    out = []
    exp = TopExp_Explorer(shape, TopAbs_FACE)
    while exp.More():
        face = TopoDS.Face(exp.Current())
        exp.Next()
        loc = TopLoc_Location()
        out.append((face, loc, BRep_Tool.Triangulation_s(face, loc)))
    return out


def _node_by_node(face, loc, tri):
    """A face's triangulation read through OCP one node and triangle at a time, as OCCT's own
    ``gp_Pnt::Transformed`` places the nodes."""
    from OCP.TopAbs import TopAbs_REVERSED

    trsf = loc.Transformation()
    xyz = np.array([tri.Node(i).Transformed(trsf).Coord() for i in range(1, tri.NbNodes() + 1)])
    uv = np.array([tri.UVNode(i).Coord() for i in range(1, tri.NbNodes() + 1)])
    t = np.array([tri.Triangle(i).Get() for i in range(1, tri.NbTriangles() + 1)]) - 1
    return xyz, uv, t[:, ::-1] if face.Orientation() == TopAbs_REVERSED else t


def _moved(shape, kind: str):
    from OCP.gp import gp_Ax1, gp_Ax2, gp_Dir, gp_Trsf, gp_Vec
    from OCP.TopLoc import TopLoc_Location

    trsf = gp_Trsf()
    if kind == "translated":
        trsf.SetTranslation(gp_Vec(1.5, -20.25, 3.125))
    elif kind == "turned":  # a rotation about a tilted axis, then a translation
        trsf.SetRotation(gp_Ax1(gp_Pnt(1, 2, 3), gp_Dir(0.3, -0.5, 0.8)), 0.7)
        trsf.SetTranslationPart(gp_Vec(-7.0, 0.3, 11.0))
    elif kind == "mirrored":  # a plane mirror: OCCT keeps it as a matrix and a scale of -1
        trsf.SetMirror(gp_Ax2(gp_Pnt(0.5, 0, 0), gp_Dir(1, 1, 0.2)))
    return shape if kind == "in place" else shape.Moved(TopLoc_Location(trsf))


@pytest.mark.parametrize("kind", ["in place", "translated", "turned", "mirrored"])
def test_triangulations_read_in_one_pass_are_the_ones_read_node_by_node(kind):
    """The bulk reader (OCCT's binary writer parsed with numpy) gives every node, (u, v) and triangle
    bit for bit as reading them one by one through OCP does, with the face's location applied as
    OCCT applies it and reversed faces' triangles turned."""
    from OCP.TopAbs import TopAbs_REVERSED

    faces = _meshed_faces(_moved(build_part("tube").wrapped, kind))
    assert any(face.Orientation() == TopAbs_REVERSED for face, _, _ in faces)
    assert T._written([tri for _, _, tri in faces]) is not None, "the one-pass read was not taken"
    for got, want in zip(T.read_triangulations(faces), (_node_by_node(*f) for f in faces), strict=True):
        for a, b in zip(got, want, strict=True):
            assert a.shape == b.shape and np.array_equal(a, b)


def test_triangulations_the_one_pass_cannot_tell_apart_are_read_node_by_node():
    """Two faces sharing one triangulation: OCCT's writer writes it once, so the buffer no longer
    lines up with the faces and each face is read node by node instead."""
    faces = _meshed_faces(build_part("cone").wrapped)
    doubled = faces + faces[:1]
    assert T._written([tri for _, _, tri in doubled]) is None
    got = T.read_triangulations(doubled)
    assert len(got) == len(doubled)
    for mesh, face in zip(got, doubled, strict=True):
        for a, b in zip(mesh, _node_by_node(*face), strict=True):
            assert np.array_equal(a, b)


def test_a_triangulation_buffer_cut_short_is_not_taken_for_one():
    """A buffer that ends anywhere inside a triangulation's header or data is refused (None: the
    faces are then read node by node), not misread or an IndexError."""
    import io

    from OCP.BinTools import BinTools_ShapeSet
    from OCP.BRep import BRep_Builder
    from OCP.TopoDS import TopoDS_Face

    tris = [tri for _, _, tri in _meshed_faces(build_part("tube").wrapped)]
    shapes, builder = BinTools_ShapeSet(), BRep_Builder()
    shapes.SetWithTriangles(True)
    for tri in tris:
        carrier = TopoDS_Face()
        builder.MakeFace(carrier, tri)
        shapes.Add(carrier)
    stream = io.BytesIO()
    shapes.WriteTriangulation(stream)
    buf, flag = stream.getvalue(), shapes.FormatNb() >= 4
    assert T._parse_triangulations(buf, flag, tris) is not None
    first = buf.find(b"\n") + 1
    second = first + 17 + flag + 40 * tris[0].NbNodes() + 12 * tris[0].NbTriangles()
    for end in [*range(first, first + 19), first + 100, *range(second, second + 19), len(buf) - 1]:
        assert T._parse_triangulations(buf[:end], flag, tris) is None, end
