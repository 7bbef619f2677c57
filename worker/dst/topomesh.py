"""The topology mesh: a coarse BRepMesh of one solid, merged into one closed indexed mesh.

It answers "which section loops exist at a plane and how do loops of consecutive planes connect"
and seeds Newton. Its node positions are exact surface points (BRepMesh evaluates the surfaces), but
no ring vertex of the DST mesh is taken from it without an exact solve.

Layout
------
xyz : (n, 3) float64, mm       global node positions (seam and pole copies merged)
tris : (m, 3) int64            global node ids, counter-clockwise seen from outside the solid
tri_face : (m,) int64          index into ``faces``
tri_uv : (m, 3, 2) float64     (u, v) of each corner in its own face (continuous inside a face)
edge_of : dict[(a, b), int]    fine edges lying on a B-rep edge (a < b) -> index into ``edges``
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from OCP.BRep import BRep_Tool
from OCP.BRepAdaptor import BRepAdaptor_Curve, BRepAdaptor_Surface
from OCP.BRepMesh import BRepMesh_IncrementalMesh
from OCP.BRepTools import BRepTools
from OCP.collections import IndexedMap_TopoDS_Shape_TopTools_ShapeMapHasher as ShapeIndexedMap
from OCP.TopAbs import TopAbs_EDGE, TopAbs_FACE, TopAbs_REVERSED
from OCP.TopExp import TopExp, TopExp_Explorer
from OCP.TopLoc import TopLoc_Location
from OCP.TopoDS import TopoDS, TopoDS_Shape
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from worker.dst.errors import TessellationError
from worker.dst.exact import EdgeEval, FaceEval
from worker.dst.meshops import edge_defects, signed_volume


@dataclass
class TopoMesh:
    xyz: np.ndarray
    tris: np.ndarray
    tri_face: np.ndarray
    tri_uv: np.ndarray
    faces: list[FaceEval]
    edges: list[EdgeEval]
    edge_of: dict[tuple[int, int], int]
    deflection: float

    @property
    def n_nodes(self) -> int:
        return int(self.xyz.shape[0])


def build_topomesh(solid: TopoDS_Shape, *, deflection: float, angular: float, merge_tol: float) -> TopoMesh:
    """Mesh ``solid`` with BRepMesh and merge it into one closed, outward-oriented indexed mesh.

    Raises TessellationError if a face cannot be meshed or the merged mesh is not closed.
    """
    BRepTools.Clean_s(solid)
    mesher = BRepMesh_IncrementalMesh(solid, deflection, False, angular, True)  # faces in parallel
    if not mesher.IsDone():
        raise TessellationError("OCCT's mesher failed on this solid")

    edge_map = ShapeIndexedMap()
    TopExp.MapShapes_s(solid, TopAbs_EDGE, edge_map)
    edges = [
        EdgeEval(BRepAdaptor_Curve(TopoDS.Edge(edge_map.FindKey(i)))) for i in range(1, edge_map.Extent() + 1)
    ]

    faces: list[FaceEval] = []
    xyz_parts, uv_parts, tri_parts, face_parts = [], [], [], []
    edge_local: list[tuple[int, np.ndarray]] = []  # (brep edge index, global-offset node ids)
    offset = 0
    exp = TopExp_Explorer(solid, TopAbs_FACE)
    while exp.More():
        face = TopoDS.Face(exp.Current())
        exp.Next()
        loc = TopLoc_Location()
        tri = BRep_Tool.Triangulation_s(face, loc)
        if tri is None or tri.NbTriangles() == 0:
            raise TessellationError(f"face {len(faces) + 1} could not be meshed (degenerate or invalid face)")
        trsf = loc.Transformation()
        n = tri.NbNodes()
        pts = np.array([tri.Node(i).Coord() for i in range(1, n + 1)], dtype=np.float64).reshape(-1, 3)
        if not loc.IsIdentity():
            pts = np.array([tri.Node(i).Transformed(trsf).Coord() for i in range(1, n + 1)]).reshape(-1, 3)
        uvs = np.array([tri.UVNode(i).Coord() for i in range(1, n + 1)], dtype=np.float64).reshape(-1, 2)
        t = np.array([tri.Triangle(i).Get() for i in range(1, tri.NbTriangles() + 1)], dtype=np.int64) - 1
        if face.Orientation() == TopAbs_REVERSED:
            t = t[:, ::-1]
        face_idx = len(faces)
        faces.append(FaceEval(BRepAdaptor_Surface(face)))
        xyz_parts.append(pts)
        uv_parts.append(uvs)
        tri_parts.append(t + offset)
        face_parts.append(np.full(len(t), face_idx, dtype=np.int64))
        eexp = TopExp_Explorer(face, TopAbs_EDGE)
        while eexp.More():
            edge = TopoDS.Edge(eexp.Current())
            eexp.Next()
            if BRep_Tool.Degenerated_s(edge):
                continue
            pot = BRep_Tool.PolygonOnTriangulation_s(edge, tri, loc)
            if pot is None:
                continue
            nodes = pot.Nodes()
            ids = np.array([nodes.Value(i) for i in range(nodes.Lower(), nodes.Upper() + 1)], dtype=np.int64)
            edge_local.append((edge_map.FindIndex(edge) - 1, ids - 1 + offset))
        offset += n

    local_xyz = np.concatenate(xyz_parts)
    local_uv = np.concatenate(uv_parts)
    local_tris = np.concatenate(tri_parts)
    tri_face = np.concatenate(face_parts)

    glob, xyz = _merge_nodes(local_xyz, merge_tol)
    tris = glob[local_tris]
    tri_uv = local_uv[local_tris]
    # Pole and seam copies merged into one node leave triangles with a repeated corner: drop them.
    keep = (tris[:, 0] != tris[:, 1]) & (tris[:, 1] != tris[:, 2]) & (tris[:, 2] != tris[:, 0])
    tris, tri_uv, tri_face = tris[keep], tri_uv[keep], tri_face[keep]

    edge_of: dict[tuple[int, int], int] = {}
    for brep_edge, ids in edge_local:
        g = glob[ids]
        for a, b in zip(g[:-1].tolist(), g[1:].tolist(), strict=True):
            if a != b:
                edge_of[(a, b) if a < b else (b, a)] = brep_edge

    _check_closed(tris)
    if signed_volume(xyz, tris) < 0:
        tris = tris[:, ::-1].copy()
        tri_uv = tri_uv[:, ::-1].copy()
    return TopoMesh(
        xyz=xyz,
        tris=tris,
        tri_face=tri_face,
        tri_uv=tri_uv,
        faces=faces,
        edges=edges,
        edge_of=edge_of,
        deflection=deflection,
    )


def _merge_nodes(xyz: np.ndarray, tol: float) -> tuple[np.ndarray, np.ndarray]:
    """Merge nodes closer than ``tol`` (copies of one node in several faces). Returns (map, unique xyz)."""
    pairs = cKDTree(xyz).query_pairs(tol, output_type="ndarray")
    n = len(xyz)
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    _, labels = connected_components(graph, directed=False)
    first = np.full(labels.max() + 1, -1, dtype=np.int64)
    order = np.arange(n)[::-1]
    first[labels[order]] = order  # smallest local index of each group represents it
    return labels.astype(np.int64), xyz[first]


def _check_closed(tris: np.ndarray) -> None:
    """Every directed edge once, and its reverse once: a closed, consistently oriented 2-manifold."""
    missing, dup = edge_defects(tris, int(tris.max()) + 1)
    if dup or missing:
        raise TessellationError(
            f"the solid's surface mesh is not closed ({missing} open and {dup} non-manifold edges): "
            "the B-rep has gaps, overlaps or badly trimmed faces"
        )
