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
from OCP.Bnd import Bnd_Box
from OCP.BRep import BRep_Tool
from OCP.BRepAdaptor import BRepAdaptor_Curve, BRepAdaptor_Surface
from OCP.BRepBndLib import BRepBndLib
from OCP.BRepGProp import BRepGProp
from OCP.BRepMesh import BRepMesh_IncrementalMesh
from OCP.BRepTools import BRepTools
from OCP.collections import IndexedMap_TopoDS_Shape_TopTools_ShapeMapHasher as ShapeIndexedMap
from OCP.gp import gp_Pnt
from OCP.GProp import GProp_GProps
from OCP.ShapeAnalysis import ShapeAnalysis_Surface
from OCP.TopAbs import TopAbs_EDGE, TopAbs_FACE, TopAbs_REVERSED, TopAbs_VERTEX
from OCP.TopExp import TopExp, TopExp_Explorer
from OCP.TopLoc import TopLoc_Location
from OCP.TopoDS import TopoDS, TopoDS_Face, TopoDS_Shape
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from worker.dst.errors import TessellationError
from worker.dst.exact import EdgeEval, FaceEval
from worker.dst.meshops import edge_defects, open_edges, signed_volume

# BRepMesh leaves a face without triangles: closed from its neighbours' nodes if its box diagonal
# is within this many deflections (any triangle across it is then within the mesh's tolerance).
TINY_FACE_DEFLECTIONS = 1.0


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
    # faces BRepMesh left without triangles, small enough to be closed from their neighbours'
    # boundary nodes: (face index, area mm^2)
    filled_faces: tuple[tuple[int, float], ...] = ()
    merged_open_nodes: int = 0  # node copies merged within the B-rep's vertex tolerance to close cracks

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
    unmeshed: list[tuple[int, TopoDS_Face, np.ndarray, np.ndarray]] = []  # index, face, box
    exp = TopExp_Explorer(solid, TopAbs_FACE)
    while exp.More():
        face = TopoDS.Face(exp.Current())
        exp.Next()
        loc = TopLoc_Location()
        tri = BRep_Tool.Triangulation_s(face, loc)
        if tri is None or tri.NbTriangles() == 0:
            lo, hi = _face_box(face)
            if np.linalg.norm(hi - lo) > TINY_FACE_DEFLECTIONS * deflection:
                raise TessellationError(
                    f"face {len(faces) + 1} could not be meshed (degenerate or invalid face)"
                )
            # A sliver smaller than the mesh's own tolerance (BRepMesh skips those): closed below
            # from the nodes its neighbours put on its edges.
            unmeshed.append((len(faces), face, lo, hi))
            faces.append(FaceEval(BRepAdaptor_Surface(face)))
            continue
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
    # Pole and seam copies merged into one node leave triangles with a repeated corner: dropped.
    tris, tri_uv, tri_face = _drop_degenerate(glob[local_tris], local_uv[local_tris], tri_face)

    if unmeshed:  # first, so that a sliver keeps its shape where its nodes are far enough apart
        tris, tri_uv, tri_face = _fill_tiny_faces(xyz, tris, tri_uv, tri_face, unmeshed, merge_tol)

    merged_open = 0
    holes = open_edges(tris, len(xyz))
    if len(holes):
        # Open edges: copies of a node that lie farther apart than the merge tolerance but within
        # the B-rep's own vertex tolerance (a sloppy corner in the file). Merge those, there only.
        remap = _merge_open_nodes(xyz, holes, min(_max_vertex_tolerance(solid), deflection))
        if remap is not None:
            glob = remap[glob]
            tris, tri_uv, tri_face = _drop_degenerate(remap[tris], tri_uv, tri_face)
            # renumber the nodes still in use (every node of a topology mesh is on a triangle)
            used = np.unique(tris)
            new_id = np.full(len(xyz), -1, dtype=np.int64)
            new_id[used] = np.arange(len(used))
            merged_open = len(xyz) - len(used)
            xyz, tris, glob = xyz[used], new_id[tris], new_id[glob]

    edge_of: dict[tuple[int, int], int] = {}
    for brep_edge, ids in edge_local:
        g = glob[ids]
        for a, b in zip(g[:-1].tolist(), g[1:].tolist(), strict=True):
            if a != b and a >= 0 and b >= 0:
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
        filled_faces=tuple((fi, _face_area(face)) for fi, face, _, _ in unmeshed),
        merged_open_nodes=merged_open,
    )


def _max_vertex_tolerance(solid: TopoDS_Shape) -> float:
    tol = 0.0
    exp = TopExp_Explorer(solid, TopAbs_VERTEX)
    while exp.More():
        tol = max(tol, BRep_Tool.Tolerance_s(TopoDS.Vertex(exp.Current())))
        exp.Next()
    return tol


def _merge_open_nodes(xyz: np.ndarray, holes: np.ndarray, tol: float) -> np.ndarray | None:
    """A node map merging the nodes of the open edges ``holes`` that lie within ``tol`` of each other
    (into the lowest id of each group), or None if there are none."""
    nodes = np.unique(holes)
    labels, _ = _merge_nodes(xyz[nodes], tol)
    if labels.max() + 1 == len(nodes):
        return None
    first = np.full(labels.max() + 1, len(xyz), dtype=np.int64)
    np.minimum.at(first, labels, nodes)
    remap = np.arange(len(xyz))
    remap[nodes] = first[labels]
    return remap


def _drop_degenerate(tris: np.ndarray, tri_uv: np.ndarray, tri_face: np.ndarray):
    """The triangles (with their (u, v) and faces) that do not repeat a corner."""
    keep = (tris[:, 0] != tris[:, 1]) & (tris[:, 1] != tris[:, 2]) & (tris[:, 2] != tris[:, 0])
    return tris[keep], tri_uv[keep], tri_face[keep]


def _face_area(face: TopoDS_Face) -> float:
    props = GProp_GProps()
    BRepGProp.SurfaceProperties_s(face, props)
    return float(props.Mass())


def _face_box(face: TopoDS_Face) -> tuple[np.ndarray, np.ndarray]:
    """Corners of the face's bounding box, mm."""
    box = Bnd_Box()
    BRepBndLib.Add_s(face, box, False)
    return np.array(box.CornerMin().Coord()), np.array(box.CornerMax().Coord())


def _fill_tiny_faces(xyz, tris, tri_uv, tri_face, unmeshed, merge_tol):
    """Close the holes left by tiny unmeshed faces: each hole of the merged mesh (a loop of edges
    used once) that fits in one such face's box is fanned from the corner that gives the
    best-shaped triangles, oriented against the hole's edges, with (u, v) projected on the face.
    Holes that fit no tiny face are left for the closedness check to refuse."""
    succ: dict[int, int] = {}
    for a, b in open_edges(tris, len(xyz)).tolist():
        if a in succ:  # a node on two holes (or a non-manifold spot): not a simple hole
            return tris, tri_uv, tri_face
        succ[a] = b
    pad = 2.0 * merge_tol
    boxes = [(fi, face, lo - pad, hi + pad) for fi, face, lo, hi in unmeshed]
    new_t, new_uv, new_f = [], [], []
    seen: set[int] = set()
    for start in list(succ):
        if start in seen:
            continue
        loop = [start]
        while succ.get(loop[-1], start) != start and len(loop) <= len(succ):
            loop.append(succ[loop[-1]])
        seen.update(loop)
        if succ.get(loop[-1]) != start or len(loop) < 3:
            continue
        pts = xyz[loop]
        owner = next((b for b in boxes if (pts >= b[2]).all() and (pts <= b[3]).all()), None)
        if owner is None:
            continue
        fi, face, _, _ = owner
        fan = _best_fan(pts)
        if fan is None:
            continue
        surf = ShapeAnalysis_Surface(BRep_Tool.Surface_s(face))
        uv = np.array([surf.ValueOfUV(gp_Pnt(*p), merge_tol).Coord() for p in pts.tolist()])
        ids = np.asarray(loop)
        # the hole's edges run a -> b; the filling triangles must hold b -> a
        for i, j, k in fan:
            new_t.append(ids[[i, k, j]])
            new_uv.append(uv[[i, k, j]])
            new_f.append(fi)
    if not new_t:
        return tris, tri_uv, tri_face
    return (
        np.vstack([tris, np.array(new_t, dtype=np.int64)]),
        np.concatenate([tri_uv, np.array(new_uv)]),
        np.concatenate([tri_face, np.array(new_f, dtype=np.int64)]),
    )


def _best_fan(pts: np.ndarray) -> list[tuple[int, int, int]] | None:
    """Fan triangles (apex, i, i + 1) over a small closed polygon from the apex whose smallest
    triangle is largest; None if every fan has a degenerate triangle."""
    k = len(pts)
    best, best_area = None, 0.0
    for apex in range(k):
        order = [(apex + d) % k for d in range(k)]
        fan = [(order[0], order[i], order[i + 1]) for i in range(1, k - 1)]
        area = min(float(np.linalg.norm(np.cross(pts[j] - pts[i], pts[m] - pts[i]))) for i, j, m in fan)
        if area > best_area:
            best, best_area = fan, area
    return best if best_area > 1e-18 else None


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
