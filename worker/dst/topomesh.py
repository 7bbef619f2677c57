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

import io
from dataclasses import dataclass

import numpy as np
from OCP.BinTools import BinTools_ShapeSet
from OCP.Bnd import Bnd_Box
from OCP.BRep import BRep_Builder, BRep_Tool
from OCP.BRepAdaptor import BRepAdaptor_Curve, BRepAdaptor_Surface
from OCP.BRepBndLib import BRepBndLib
from OCP.BRepGProp import BRepGProp
from OCP.BRepMesh import BRepMesh_IncrementalMesh
from OCP.BRepTools import BRepTools
from OCP.collections import IndexedMap_TopoDS_Shape_TopTools_ShapeMapHasher as ShapeIndexedMap
from OCP.gp import gp_Identity, gp_Pnt, gp_PntMirror, gp_Scale, gp_Translation
from OCP.GProp import GProp_GProps
from OCP.Poly import Poly_Triangulation
from OCP.ShapeAnalysis import ShapeAnalysis_Surface
from OCP.TopAbs import TopAbs_EDGE, TopAbs_FACE, TopAbs_REVERSED, TopAbs_VERTEX
from OCP.TopExp import TopExp, TopExp_Explorer
from OCP.TopLoc import TopLoc_Location
from OCP.TopoDS import TopoDS, TopoDS_Face, TopoDS_Shape
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from worker.dst.errors import TessellationError, UnmeshedFaceError
from worker.dst.exact import EdgeEval, FaceEval
from worker.dst.meshops import edge_defects, open_edges, repeated_corner, signed_volume, unique_ints

# BRepMesh leaves a face without triangles: closed from its neighbours' nodes if its box diagonal
# is within this many deflections (any triangle across it is then within the mesh's tolerance).
TINY_FACE_DEFLECTIONS = 1.0
# Holes BRepMesh leaves inside a face are patched only up to this many border nodes, and only where
# at most this many of its triangles (and a tenth of them) must be dropped.
HOLE_MAX_NODES = 200


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
    # holes BRepMesh left inside a face, closed with triangles within the deflection of its surface:
    # (face index, triangles added, largest distance of the patch from the surface, mm)
    patched_faces: tuple[tuple[int, int, float], ...] = ()
    dropped_triangles: int = 0  # BRepMesh triangles dropped where a face folded over or was doubled

    @property
    def n_nodes(self) -> int:
        return int(self.xyz.shape[0])


def build_topomesh(
    solid: TopoDS_Shape, *, deflection: float, angular: float, merge_tol: float, parallel: bool = True
) -> TopoMesh:
    """Mesh ``solid`` with BRepMesh and merge it into one closed, outward-oriented indexed mesh.
    ``parallel``: faces on OCCT's thread pool (never in a forked process: see ``forked``).

    Raises TessellationError if a face cannot be meshed or the merged mesh is not closed.
    """
    BRepTools.Clean_s(solid)
    mesher = BRepMesh_IncrementalMesh(solid, deflection, False, angular, parallel)
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
    edge_faces: dict[int, set[int]] = {}  # brep edge index -> faces bounded by it
    stray: list[np.ndarray] = []  # per face: its triangles on a border that no edge polygon bounds
    offset = 0
    unmeshed: list[tuple[int, TopoDS_Face, np.ndarray, np.ndarray]] = []  # index, face, box
    listed: list[tuple[TopoDS_Face, TopLoc_Location, Poly_Triangulation | None]] = []
    exp = TopExp_Explorer(solid, TopAbs_FACE)
    while exp.More():
        face = TopoDS.Face(exp.Current())
        exp.Next()
        loc = TopLoc_Location()
        tri = BRep_Tool.Triangulation_s(face, loc)
        listed.append((face, loc, None if tri is None or tri.NbTriangles() == 0 else tri))
    read = iter(read_triangulations([(face, loc, tri) for face, loc, tri in listed if tri is not None]))
    for face, loc, tri in listed:
        if tri is None:
            lo, hi = _face_box(face)
            if np.linalg.norm(hi - lo) > TINY_FACE_DEFLECTIONS * deflection:
                raise UnmeshedFaceError(
                    f"face {len(faces) + 1} could not be meshed (degenerate or invalid face)"
                )
            # A sliver smaller than the mesh's own tolerance (BRepMesh skips those): closed below
            # from the nodes its neighbours put on its edges.
            unmeshed.append((len(faces), face, lo, hi))
            faces.append(FaceEval(BRepAdaptor_Surface(face)))
            continue
        pts, uvs, t = next(read)
        n = len(pts)
        face_idx = len(faces)
        faces.append(FaceEval(BRepAdaptor_Surface(face)))
        xyz_parts.append(pts)
        uv_parts.append(uvs)
        tri_parts.append(t + offset)
        face_parts.append(np.full(len(t), face_idx, dtype=np.int64))
        polygons = []
        eexp = TopExp_Explorer(face, TopAbs_EDGE)
        while eexp.More():
            edge = TopoDS.Edge(eexp.Current())
            eexp.Next()
            if BRep_Tool.Degenerated_s(edge):
                continue
            edge_faces.setdefault(edge_map.FindIndex(edge) - 1, set()).add(face_idx)
            pot = BRep_Tool.PolygonOnTriangulation_s(edge, tri, loc)
            if pot is None:
                continue
            nodes = pot.Nodes()
            ids = np.array([nodes.Value(i) for i in range(nodes.Lower(), nodes.Upper() + 1)], dtype=np.int64)
            edge_local.append((edge_map.FindIndex(edge) - 1, ids - 1 + offset))
            polygons.append(ids - 1)
        stray.append(_stray_triangles(pts, t, polygons, merge_tol))
        offset += n

    local_xyz = np.concatenate(xyz_parts)
    local_uv = np.concatenate(uv_parts)
    local_tris = np.concatenate(tri_parts)
    tri_face = np.concatenate(face_parts)
    stray_mask = np.concatenate(stray)

    glob, xyz = _merge_nodes(local_xyz, merge_tol)
    # Pole and seam copies merged into one node leave triangles with a repeated corner: dropped.
    tris, tri_uv, tri_face, stray_mask = _drop_degenerate(
        glob[local_tris], local_uv[local_tris], tri_face, stray_mask
    )

    if unmeshed:  # first, so that a sliver keeps its shape where its nodes are far enough apart
        n_before = len(tris)
        tris, tri_uv, tri_face = _fill_tiny_faces(xyz, tris, tri_uv, tri_face, unmeshed, merge_tol)
        stray_mask = np.concatenate([stray_mask, np.zeros(len(tris) - n_before, dtype=bool)])

    merged_open = 0
    holes = open_edges(tris, len(xyz))
    if len(holes):
        # Open edges: copies of a node that lie farther apart than the merge tolerance but within
        # the B-rep's own vertex tolerance (a sloppy corner in the file). Merge those, there only.
        remap = _merge_open_nodes(xyz, holes, min(max_tolerance(solid), deflection))
        if remap is not None:
            glob = remap[glob]
            tris, tri_uv, tri_face, stray_mask = _drop_degenerate(remap[tris], tri_uv, tri_face, stray_mask)
            n_before = len(xyz)
            xyz, tris, glob = _drop_unused_nodes(xyz, tris, glob)
            merged_open = n_before - len(xyz)

    edge_of = _edges_on_brep(edge_local, glob)
    patched: list[tuple[int, int, float]] = []
    dropped = 0
    if any(edge_defects(tris, len(xyz))):
        # BRepMesh left part of a face out, folded it over (a sliver a few micrometres wide
        # between two nearly coincident edges) or meshed two faces on top of each other.
        tris, tri_uv, tri_face, patched, dropped = _patch_holes(
            xyz, tris, tri_uv, tri_face, stray_mask, faces, edge_faces, edge_of, deflection
        )
        if dropped or patched:
            xyz, tris, glob = _drop_unused_nodes(xyz, tris, glob)
            edge_of = _edges_on_brep(edge_local, glob)

    _check_closed(tris)
    if signed_volume(xyz, tris) < 0:
        tris = tris[:, ::-1].copy()
        tri_uv = tri_uv[:, ::-1].copy()
    _wedge_poles(tri_uv, tri_face, faces)
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
        patched_faces=tuple(patched),
        dropped_triangles=dropped,
    )


FaceMesh = tuple[np.ndarray, np.ndarray, np.ndarray]  # (n, 3) xyz, (n, 2) uv, (m, 3) triangles


def _wedge_poles(tri_uv: np.ndarray, tri_face: np.ndarray, faces: list[FaceEval]) -> None:
    """Give each triangle's corner at a pole of its face's parametrisation (a side of the face's
    (u, v) box whose iso-line is one point: the apex of a cap of revolution) the mean of the
    triangle's other two corners in the parameter that is arbitrary there (in place). BRepMesh gives
    a pole node one fixed value for all its triangles (u = 0 or 2 pi at an apex), so a point
    interpolated along a fan triangle's edge from the apex, a crossing's root or a seed, lay at the
    wrong angle round the apex: bug27453_165-174_piattello turned (-171.8, -177.1, -119.4) at z =
    27.1, a plane 0.01 mm below the apex of a cap, had the 21 crossings of the fan round it on a
    12-degree arc of the section's 0.036 mm circle, and the ring a sliver along that arc."""
    for f in unique_ints(tri_face).tolist():
        fe = faces[f]
        box = (fe.u0, fe.u1, fe.v0, fe.v1)
        sel = None
        for axis in (0, 1):
            lo, hi = box[2 * axis], box[2 * axis + 1]
            if not (np.isfinite(lo) and np.isfinite(hi)):
                continue
            tol = 1e-9 * max(hi - lo, 1.0)
            for bound in (lo, hi):
                if not fe.is_pole(axis, bound):
                    continue
                if sel is None:
                    sel = np.flatnonzero(tri_face == f)
                at = np.abs(tri_uv[sel, :, axis] - bound) <= tol  # (k, 3) corners on the pole
                one = np.flatnonzero(at.sum(axis=1) == 1)
                if not len(one):
                    continue
                t, c = sel[one], np.argmax(at[one], axis=1)
                other = tri_uv[t, :, 1 - axis].sum(axis=1) - tri_uv[t, c, 1 - axis]
                tri_uv[t, c, 1 - axis] = 0.5 * other


def read_triangulations(
    faces: list[tuple[TopoDS_Face, TopLoc_Location, Poly_Triangulation]],
) -> list[FaceMesh]:
    """Each face's BRepMesh triangulation: node positions (n, 3) with the face's location applied,
    their (u, v) (n, 2) and the triangles (m, 3) as 0-based node ids, counter-clockwise seen from
    outside the solid (reversed for a reversed face).

    Read in one pass: OCCT's binary shape writer copies every node, (u, v) and triangle of the
    triangulations into one buffer (``_written``), ~20x faster than node by node through OCP (the
    hemisphere's 22,000 nodes: 0.2 s against 0.01 s). Node by node (``_face_mesh``) where that buffer
    does not hold exactly these triangulations, in this order."""
    written = _written([tri for _, _, tri in faces]) if faces else []
    if written is None:
        return [_face_mesh(face, tri, loc) for face, loc, tri in faces]
    out = []
    for (face, loc, _), (xyz, uv, t) in zip(faces, written, strict=True):
        out.append((_located(xyz, loc), uv, t[:, ::-1] if face.Orientation() == TopAbs_REVERSED else t))
    return out


def _written(tris: list[Poly_Triangulation]) -> list[FaceMesh] | None:
    """The triangulations as ``BinTools_ShapeSet.WriteTriangulation`` writes them (local node
    positions, triangles not reversed), or None if the buffer is not the one expected: each
    triangulation once, in order, with (u, v) and the counts OCP gives."""
    shapes = BinTools_ShapeSet()
    shapes.SetWithTriangles(True)
    shapes.SetWithNormals(False)
    builder = BRep_Builder()
    for tri in tris:  # a face of its triangulation only: no edges bringing their other faces' ones
        carrier = TopoDS_Face()
        builder.MakeFace(carrier, tri)
        shapes.Add(carrier)
    stream = io.BytesIO()
    shapes.WriteTriangulation(stream)
    return _parse_triangulations(stream.getvalue(), shapes.FormatNb() >= 4, tris)


def _parse_triangulations(
    buf: bytes, normals_flag: bool, tris: list[Poly_Triangulation]
) -> list[FaceMesh] | None:
    """``BinTools_ShapeSet::WriteTriangulation``'s format (little-endian on every platform): a text
    line "Triangulations N", then per triangulation int32 nodes, int32 triangles, a byte "has (u, v)",
    [a byte "has normals" from format 4], float64 deflection, float64 (x, y, z) per node, float64
    (u, v) per node, int32 1-based node ids per triangle, float32 normals if any."""
    line = buf.find(b"\n")
    head = buf[:line].split()
    if len(head) != 2 or head[0] != b"Triangulations" or int(head[1]) != len(tris):
        return None
    pos, out = line + 1, []
    head_size = 17 + normals_flag  # the counts, the flags and the deflection
    for tri in tris:
        if pos + head_size > len(buf):
            return None
        n_nodes, n_tris = (int(x) for x in np.frombuffer(buf, "<i4", 2, pos))
        has_uv = buf[pos + 8]
        has_normals = buf[pos + 9] if normals_flag else 0
        pos += head_size
        size = 24 * n_nodes + 16 * n_nodes + 12 * n_tris + (12 * n_nodes if has_normals else 0)
        if (n_nodes, n_tris) != (tri.NbNodes(), tri.NbTriangles()) or not has_uv or pos + size > len(buf):
            return None
        xyz = np.frombuffer(buf, "<f8", 3 * n_nodes, pos).reshape(-1, 3)
        uv = np.frombuffer(buf, "<f8", 2 * n_nodes, pos + 24 * n_nodes).reshape(-1, 2)
        t = np.frombuffer(buf, "<i4", 3 * n_tris, pos + 40 * n_nodes).reshape(-1, 3).astype(np.int64) - 1
        out.append((xyz.copy(), uv.copy(), t))
        pos += size
    return out if pos == len(buf) else None


def _located(xyz: np.ndarray, loc: TopLoc_Location) -> np.ndarray:
    """Node positions moved by the face's location, rounded as ``gp_Pnt.Transformed`` rounds them:
    the same operations in the same order (``gp_Pnt::Transform``, ``gp_Trsf::Transforms``)."""
    if loc.IsIdentity():
        return xyz
    trsf = loc.Transformation()
    form = trsf.Form()
    t = np.array(trsf.TranslationPart().Coord())
    if form == gp_Identity:
        return xyz
    if form == gp_Translation:
        return xyz + t
    if form == gp_Scale:
        return xyz * trsf.ScaleFactor() + t
    if form == gp_PntMirror:
        return -xyz + t
    m = trsf.HVectorialPart()
    x, y, z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    out = np.column_stack([m.Value(r, 1) * x + m.Value(r, 2) * y + m.Value(r, 3) * z for r in (1, 2, 3)])
    if trsf.ScaleFactor() != 1.0:
        out *= trsf.ScaleFactor()
    return out + t


def _face_mesh(face: TopoDS_Face, tri, loc: TopLoc_Location) -> FaceMesh:
    """One face's triangulation as ``read_triangulations`` gives it, node by node through OCP."""
    n = tri.NbNodes()
    uvs = np.array([tri.UVNode(i).Coord() for i in range(1, n + 1)], dtype=np.float64).reshape(-1, 2)
    if loc.IsIdentity():
        xyz = np.array([tri.Node(i).Coord() for i in range(1, n + 1)], dtype=np.float64)
    else:
        trsf = loc.Transformation()
        xyz = np.array([tri.Node(i).Transformed(trsf).Coord() for i in range(1, n + 1)], dtype=np.float64)
    t = np.array([tri.Triangle(i).Get() for i in range(1, tri.NbTriangles() + 1)], dtype=np.int64) - 1
    t = t.reshape(-1, 3)
    return xyz.reshape(-1, 3), uvs, t[:, ::-1] if face.Orientation() == TopAbs_REVERSED else t


def _drop_unused_nodes(xyz: np.ndarray, tris: np.ndarray, glob: np.ndarray):
    """Renumber the nodes still on a triangle (every node of a topology mesh must be); nodes of the
    per-face meshes that lost theirs map to -1. Returns (xyz, tris, glob)."""
    used = unique_ints(tris)
    new_id = np.full(len(xyz), -1, dtype=np.int64)
    new_id[used] = np.arange(len(used))
    return xyz[used], new_id[tris], np.where(glob >= 0, new_id[np.maximum(glob, 0)], -1)


def _edges_on_brep(edge_local: list[tuple[int, np.ndarray]], glob: np.ndarray) -> dict[tuple[int, int], int]:
    """Mesh edges (a < b) lying on a B-rep edge -> that edge's index, from the faces' edge polygons."""
    edge_of: dict[tuple[int, int], int] = {}
    for brep_edge, ids in edge_local:
        g = glob[ids]
        for a, b in zip(g[:-1].tolist(), g[1:].tolist(), strict=True):
            if a != b and a >= 0 and b >= 0:
                edge_of[(a, b) if a < b else (b, a)] = brep_edge
    return edge_of


def max_tolerance(shape: TopoDS_Shape, kind=TopAbs_VERTEX) -> float:
    """The largest tolerance of the shape's vertices (``kind`` TopAbs_VERTEX) or edges (TopAbs_EDGE)."""
    cast = TopoDS.Vertex if kind == TopAbs_VERTEX else TopoDS.Edge
    tol = 0.0
    exp = TopExp_Explorer(shape, kind)
    while exp.More():
        tol = max(tol, BRep_Tool.Tolerance_s(cast(exp.Current())))
        exp.Next()
    return tol


def _merge_open_nodes(xyz: np.ndarray, holes: np.ndarray, tol: float) -> np.ndarray | None:
    """A node map merging the nodes of the open edges ``holes`` that lie within ``tol`` of each other
    (into the lowest id of each group), or None if there are none."""
    nodes = unique_ints(holes)
    labels, _ = _merge_nodes(xyz[nodes], tol)
    if labels.max() + 1 == len(nodes):
        return None
    first = np.full(labels.max() + 1, len(xyz), dtype=np.int64)
    np.minimum.at(first, labels, nodes)
    remap = np.arange(len(xyz))
    remap[nodes] = first[labels]
    return remap


def _drop_degenerate(tris: np.ndarray, *per_triangle: np.ndarray):
    """The triangles that do not repeat a corner, with the same rows of each per-triangle array."""
    keep = ~repeated_corner(tris)
    return (tris[keep], *(a[keep] for a in per_triangle))


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


def _stray_triangles(pts: np.ndarray, tris: np.ndarray, polygons: list[np.ndarray], tol: float) -> np.ndarray:
    """Mask of one face's triangles that have an edge on the border of the face's triangulation but
    on none of its edges' polygons (BRepMesh folded the face over, or cut off a sliver of it).
    Border edges shorter than ``tol`` (the copies of a pole) do not count."""
    border = open_edges(tris, len(pts))
    if not len(border):
        return np.zeros(len(tris), dtype=bool)
    n = len(pts)
    bounded = [np.minimum(ids[:-1], ids[1:]) * n + np.maximum(ids[:-1], ids[1:]) for ids in polygons]
    border_key = border.min(axis=1) * n + border.max(axis=1)  # undirected
    loose = ~np.isin(border_key, np.concatenate(bounded)) if bounded else np.ones(len(border), dtype=bool)
    loose &= np.linalg.norm(pts[border[:, 0]] - pts[border[:, 1]], axis=1) > tol
    if not loose.any():
        return np.zeros(len(tris), dtype=bool)
    e = np.sort(np.stack([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]], axis=1), axis=2)
    return np.asarray(np.isin(e[..., 0] * n + e[..., 1], border_key[loose]).any(axis=1))


def _hole_loops(tris: np.ndarray, n_nodes: int) -> list[list[int]] | None:
    """The holes of a mesh as simple node loops, each following its open edges (in the direction its
    triangles hold them). Holes that touch at a node are split there into loops. None if the open
    edges do not form closed loops."""
    succ: dict[int, list[int]] = {}
    for a, b in open_edges(tris, n_nodes).tolist():
        succ.setdefault(a, []).append(b)
    loops = []
    while succ:
        path = [next(iter(succ))]
        at = {path[0]: 0}
        while True:
            nxt = succ.get(path[-1])
            if not nxt:
                return None  # an open edge ends where no open edge starts
            b = nxt.pop()
            if not nxt:
                del succ[path[-1]]
            if b in at:  # a loop closes: cut it off the path, keep walking from b
                i = at[b]
                loop = path[i:]
                loops.append(loop)
                for node in loop[1:]:
                    del at[node]
                path = path[: i + 1]
                if not succ.get(b):
                    break
            else:
                at[b] = len(path)
                path.append(b)
        if len(path) > 1:
            return None
    return loops


def _doubled_triangles(tris: np.ndarray) -> np.ndarray:
    """Mask of the triangles whose reverse (the same three nodes, turned the other way) is also in
    the mesh: two faces meshed on top of each other, back to back, enclosing nothing."""
    first = np.argmin(tris, axis=1)
    rows = np.arange(len(tris))[:, None]
    canon = tris[rows, (first[:, None] + np.arange(3)) % 3]  # smallest node first, same turn
    # rows matched whole (three node ids packed into one integer overflow beyond ~2 million nodes)
    _, inv = np.unique(np.concatenate([canon, canon[:, [0, 2, 1]]]), axis=0, return_inverse=True)
    inv = inv.ravel()
    return np.isin(inv[: len(tris)], inv[len(tris) :])


def _repeated_edge_triangles(tris: np.ndarray, n_nodes: int, keep: np.ndarray) -> np.ndarray:
    """Mask of the kept triangles holding a directed edge that another kept triangle also holds."""
    e = np.stack([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]], axis=1)
    key = e[..., 0] * n_nodes + e[..., 1]  # (m, 3)
    uniq, counts = np.unique(key[keep], return_counts=True)
    return keep & np.isin(key, uniq[counts > 1]).any(axis=1)


def _min_area_triangulation(pts: np.ndarray) -> list[tuple[int, int, int]] | None:
    """Triangles (i, j, k), i < j < k, over the closed polygon ``pts`` (k, 3) with the least total
    area and no degenerate triangle (dynamic programming over its diagonals, O(k^3)); None if
    there is none."""
    k = len(pts)
    if k < 3:
        return None
    scale = max(float(np.ptp(pts, axis=0).max()), 1e-300)
    min_area = 1e-12 * scale * scale
    cost = np.full((k, k), np.inf)
    best = np.full((k, k), -1, dtype=np.int64)
    for a in range(k - 1):
        cost[a, a + 1] = 0.0
    for span in range(2, k):
        for a in range(k - span):
            b = a + span
            mids = np.arange(a + 1, b)
            area = 0.5 * np.linalg.norm(np.cross(pts[mids] - pts[a], pts[b] - pts[a]), axis=1)
            c = cost[a, mids] + cost[mids, b] + np.where(area > min_area, area, np.inf)
            m = int(np.argmin(c))
            cost[a, b], best[a, b] = c[m], mids[m]
    if not np.isfinite(cost[0, k - 1]):
        return None
    out, stack = [], [(0, k - 1)]
    while stack:
        a, b = stack.pop()
        if b - a < 2:
            continue
        m = int(best[a, b])
        out.append((a, m, b))
        stack += [(a, m), (m, b)]
    return out


def _patch_holes(xyz, tris, tri_uv, tri_face, stray_mask, faces, edge_faces, edge_of, deflection):
    """Repair BRepMesh's mesh where it folded a face over, doubled it or left part of it out.

    Dropped: the stray triangles, pairs of back-to-back triangles (two faces meshed on top of each
    other), and the triangles of a folded face on an edge then held twice in one direction. Each
    hole left is closed with its least-area triangulation on the face that owns it (the face across
    the hole's B-rep edges, or the face around it); every patch must lie within ``deflection`` of
    that face's surface (checked at its corners, edge midpoints and centroids). If any step fails the
    mesh is returned as it came, for the closedness check to refuse.

    Returns (tris, tri_uv, tri_face, [(face, triangles added, distance mm)], triangles dropped).
    """
    no_patches: list[tuple[int, int, float]] = []
    unpatched = tris, tri_uv, tri_face, no_patches, 0
    keep = ~stray_mask & ~_doubled_triangles(tris)
    folded = np.isin(tri_face, unique_ints(tri_face[stray_mask]))
    keep &= ~(_repeated_edge_triangles(tris, len(xyz), keep) & folded)
    if np.count_nonzero(~keep) > min(HOLE_MAX_NODES, 0.1 * len(tris)):
        return unpatched  # not a local defect
    t2, uv2, f2 = tris[keep], tri_uv[keep], tri_face[keep]
    loops = _hole_loops(t2, len(xyz))
    if loops is None or edge_defects(t2, len(xyz))[1]:
        return unpatched
    # directed open edge -> face of the triangle holding it
    n = len(xyz)
    key = np.stack([t2[:, [0, 1]], t2[:, [1, 2]], t2[:, [2, 0]]], axis=1) @ np.array([n, 1])  # (m, 3)
    is_open = np.isin(
        key, [a * n + b for loop in loops for a, b in zip(loop, loop[1:] + loop[:1], strict=True)]
    )
    holder = dict(
        zip(key[is_open].tolist(), np.broadcast_to(f2[:, None], key.shape)[is_open].tolist(), strict=True)
    )
    new_t, new_uv, new_f, patched = [], [], [], []
    for loop in loops:
        votes: dict[int, int] = {}
        for a, b in zip(loop, loop[1:] + loop[:1], strict=True):
            brep_edge = edge_of.get((a, b) if a < b else (b, a))
            inside = holder[a * n + b]
            if brep_edge is None:  # an edge inside a face: the hole is in that face
                candidates = {inside}
            else:  # on a B-rep edge: the hole is in the face across it
                candidates = edge_faces.get(brep_edge, set()) - {inside}
            for f in candidates:
                votes[f] = votes.get(f, 0) + 1
        if not votes or len(loop) > HOLE_MAX_NODES:
            return unpatched
        owner = max(votes, key=lambda f: votes[f])
        pts = xyz[loop]
        tri = _min_area_triangulation(pts)
        if tri is None:
            return unpatched
        ids = np.asarray(loop)
        sas = ShapeAnalysis_Surface(BRep_Tool.Surface_s(faces[owner].face))
        corners = np.array([(i, k, j) for i, j, k in tri])  # against the hole's direction
        samples = np.concatenate([pts, np.einsum("wc,tcx->twx", _PATCH_WEIGHTS, pts[corners]).reshape(-1, 3)])
        dist = 0.0
        for q in samples.tolist():
            sas.ValueOfUV(gp_Pnt(*q), 0.01 * deflection)
            dist = max(dist, sas.Gap())
        if dist > deflection:
            return unpatched
        uv = np.array([sas.ValueOfUV(gp_Pnt(*q), 0.01 * deflection).Coord() for q in pts.tolist()])
        new_t.append(ids[corners])
        new_uv.append(uv[corners])
        new_f.append(np.full(len(corners), owner, dtype=np.int64))
        patched.append((owner, len(corners), dist))
    return (
        np.vstack([t2, *new_t]),
        np.concatenate([uv2, *new_uv]),
        np.concatenate([f2, *new_f]),
        patched,
        int(np.count_nonzero(~keep)),
    )


# points of a triangle where a patch is checked against its surface: edge midpoints and centroid
_PATCH_WEIGHTS = np.array([[0.5, 0.5, 0.0], [0.0, 0.5, 0.5], [0.5, 0.0, 0.5], [1 / 3, 1 / 3, 1 / 3]])


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
