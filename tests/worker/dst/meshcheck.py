"""Independent checks of the DST guarantees on a finished mesh (test helpers, not product code)."""

from __future__ import annotations

import numpy as np
import trimesh

from worker.dst.meshops import unique_ints  # np.unique by a sort (numpy 2.3+ hashes: 10-30x slower here)


def assert_watertight(mesh) -> trimesh.Trimesh:
    tm = trimesh.Trimesh(mesh.vertices, mesh.triangles, process=False)
    assert tm.is_watertight, "mesh is not watertight"
    assert tm.is_winding_consistent, "mesh winding is inconsistent"
    assert tm.volume > 0, "mesh is inside out"
    area = tm.area_faces
    assert area.min() > 0, "zero-area triangle"
    return tm


def ring_edges(mesh) -> tuple[np.ndarray, np.ndarray]:
    """Undirected edges with both ends on the same plane, and that plane's index."""
    t = mesh.triangles
    e = np.sort(np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]]), axis=1)
    n = len(mesh.vertices)
    keys = unique_ints(e[:, 0] * n + e[:, 1])  # integer keys: far faster than unique rows
    e = np.stack([keys // n, keys % n], axis=1)
    vp = mesh.vertex_plane
    same = (vp[e[:, 0]] >= 0) & (vp[e[:, 0]] == vp[e[:, 1]])
    return e[same], vp[e[same, 0]]


def assert_slab_property(mesh, tol: float = 1e-9) -> None:
    """No triangle has vertices strictly on both sides of any plane, so a slicer's cut at each plane is
    made of mesh edges lying in it. Each such edge has one triangle above and one below (a ring edge),
    or both on one side (the surface touching the plane along it: slicers get a there-and-back pair of
    segments with no area), or a flat neighbour; and most are ring edges."""
    v, t, z = mesh.vertices, mesh.triangles, mesh.planes.section_z
    tz = v[t][:, :, 2]
    lo, hi = tz.min(axis=1), tz.max(axis=1)
    k_lo = np.searchsorted(z, lo + tol, side="left")  # first plane above lo
    k_hi = np.searchsorted(z, hi - tol, side="right")  # planes below hi
    straddle = k_hi > k_lo
    assert not straddle.any(), f"{int(straddle.sum())} triangles cross a plane"
    edges, planes = ring_edges(mesh)
    n = len(v)
    ring_key = edges[:, 0] * n + edges[:, 1]
    corners = [t[:, [0, 1, 2]], t[:, [1, 2, 0]], t[:, [2, 0, 1]]]
    a = np.concatenate([c[:, 0] for c in corners])
    b = np.concatenate([c[:, 1] for c in corners])
    third = np.concatenate([c[:, 2] for c in corners])
    key = np.minimum(a, b) * n + np.maximum(a, b)
    pos = np.searchsorted(ring_key, key)
    pos = np.minimum(pos, len(ring_key) - 1)
    hit = ring_key[pos] == key
    dz = v[third[hit], 2] - z[planes[pos[hit]]]
    above = np.bincount(pos[hit][dz > tol], minlength=len(edges))
    below = np.bincount(pos[hit][dz < -tol], minlength=len(edges))
    flat = (above + below) < 2
    ring = (above == 1) & (below == 1)
    contact = (above == 2) | (below == 2)
    assert (ring | contact | flat).all(), "an edge in a plane has more than two triangles"
    assert ring.sum() > 0.95 * len(edges), "most edges lying in a plane must be ring edges"


def occt_section_points(solid, z: float, step: float = 0.02) -> np.ndarray:
    """Points every ``step`` mm along OCCT's exact section (BRepAlgoAPI_Section, approximation on)
    of ``solid`` with the plane at world height ``z``: (k, 3)."""
    from OCP.BRepAdaptor import BRepAdaptor_Curve
    from OCP.BRepAlgoAPI import BRepAlgoAPI_Section
    from OCP.GCPnts import GCPnts_UniformAbscissa
    from OCP.GeomAbs import GeomAbs_Circle, GeomAbs_Line
    from OCP.gp import gp_Dir, gp_Pln, gp_Pnt
    from OCP.TopAbs import TopAbs_EDGE
    from OCP.TopExp import TopExp_Explorer
    from OCP.TopoDS import TopoDS

    sec = BRepAlgoAPI_Section(solid, gp_Pln(gp_Pnt(0, 0, z), gp_Dir(0, 0, 1)), False)
    sec.Approximation(True)
    sec.Build()
    pts = []
    exp = TopExp_Explorer(sec.Shape(), TopAbs_EDGE)
    while exp.More():
        curve = BRepAdaptor_Curve(TopoDS.Edge(exp.Current()))
        exp.Next()
        sampler = GCPnts_UniformAbscissa(curve, step)
        if not sampler.IsDone():
            continue
        u = np.array([sampler.Parameter(i) for i in range(1, sampler.NbPoints() + 1)])
        kind = curve.GetType()
        if kind in (GeomAbs_Line, GeomAbs_Circle):
            pts.append(_line_or_circle_points(curve, u, kind == GeomAbs_Line))
        else:
            pts.append(np.array([curve.Value(t).Coord() for t in u.tolist()]))
    return np.concatenate(pts).reshape(-1, 3) if pts else np.empty((0, 3))


def _line_or_circle_points(curve, u: np.ndarray, line: bool) -> np.ndarray:
    """The points of a line (``line``) or circle ``curve`` at parameters ``u``, computed together (a
    big part's sections hold millions of such points), checked against OCCT's own points at the ends
    and in the middle."""
    n = len(u)
    if line:
        lin = curve.Line()
        out = np.array(lin.Location().Coord()) + u[:, None] * np.array(lin.Direction().Coord())
    else:
        circle = curve.Circle()
        ax = circle.Position()
        x, y = np.array(ax.XDirection().Coord()), np.array(ax.YDirection().Coord())
        out = np.array(ax.Location().Coord()) + circle.Radius() * (
            np.cos(u)[:, None] * x + np.sin(u)[:, None] * y
        )
    for i in {0, n // 2, n - 1}:
        assert np.abs(out[i] - curve.Value(float(u[i])).Coord()).max() < 1e-9, "not OCCT's curve"
    return out


def distance_to_faces(points: np.ndarray, solids) -> np.ndarray:
    """Distance (mm) of each point to the nearest face of ``solids`` (their boundary: a point inside a
    solid is not at distance 0, as ``BRepExtrema_DistShapeShape`` with the solid itself can say)."""
    from OCP.BRep import BRep_Builder
    from OCP.BRepBuilderAPI import BRepBuilderAPI_MakeVertex
    from OCP.BRepExtrema import BRepExtrema_DistShapeShape
    from OCP.gp import gp_Pnt
    from OCP.TopAbs import TopAbs_FACE
    from OCP.TopExp import TopExp_Explorer
    from OCP.TopoDS import TopoDS_Compound

    faces = TopoDS_Compound()
    builder = BRep_Builder()
    builder.MakeCompound(faces)
    for solid in solids:
        exp = TopExp_Explorer(solid, TopAbs_FACE)
        while exp.More():
            builder.Add(faces, exp.Current())
            exp.Next()
    out = []
    for p in np.asarray(points, dtype=np.float64).reshape(-1, 3):
        vertex = BRepBuilderAPI_MakeVertex(gp_Pnt(*map(float, p))).Vertex()
        out.append(BRepExtrema_DistShapeShape(vertex, faces).Value())
    return np.array(out)
