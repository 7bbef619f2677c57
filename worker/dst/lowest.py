"""The part's exact lowest and highest points, and local apexes, made vertices of the topology meshes.

Slicers drop a mesh onto the bed by its lowest vertex, so the DST mesh's lowest vertex must be the
part's exact lowest point, and plane heights are measured from it. Likewise a plane just below the
part's top must see the small loop there. The topology mesh's nodes are exact surface points but
may miss the extreme (the bottom line of a horizontal cylinder, the top of a B-spline dome), so:

1. candidates are the faces and edges touching topology nodes within a few deflections of the
   lowest (highest) node;
2. the height is minimised exactly on each: on faces by bounded L-BFGS on z(u, v) from the lowest
   node's (u, v), kept only if the optimum is inside the trimmed face; on edges by bounded Brent
   around the lowest sample of the curve;
3. the node nearest to the winning point is moved onto it where it stays on every face around it
   (a node inside the face, or on the B-rep edge moved along it); otherwise the point becomes a new
   node, splitting the triangle of its face that holds it (or the mesh edge along its B-rep edge).
   Moving a node on a B-rep edge into one of its faces dragged the other face's triangles over the
   first (``trj7_b1-ec-214`` turned (32.9, 100.0, -141.2): the edge node below a dome's top moved
   onto it, and the top plane's ring bridged 0.05 mm inside the section).

Local apexes and dimples (``snap_local_extremes``) get the same treatment where a plane passes
between the node and the exact extreme: otherwise that plane's small loop would be missed.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import minimize

from worker.dst.meshops import unique_ints
from worker.dst.splits import curve_span, edge_extreme_between, split_edges, split_triangle
from worker.dst.topomesh import TopoMesh

_CURVE_SAMPLES = 64  # coarse scan of an edge before Brent: finds the basin of its lowest point
_BAND_DEFLECTIONS = 2.0  # an apex is at most one deflection beyond the node next to it; margin 2x
_SAME_POINT_MM = 1e-7  # a node closer than this to its exact point keeps its (u, v)
_AT_NODE_MM = 1e-6  # an extreme this close to a node is put on that node (no new node)
_ON_TRI_EDGE = 1e-6  # a barycentric coordinate at most this: the point is on the triangle's edge
_ON_FACE_MM = 1e-4  # an extreme this close to a face's surface (projected) lies on it


def snap_extremes(meshes: list[TopoMesh]) -> tuple[float, float]:
    """Make the exact lowest point a node of one mesh, and the highest: the node nearest to it moved
    onto it where it stays on its faces (``_stays_on_its_faces``), else a new node (``_make_node``).
    Returns (zmin, zmax)."""
    out = []
    for sign in (1.0, -1.0):
        mi, where, point, nearest = _extreme(meshes, sign=sign)
        mesh = meshes[mi]
        if where[0] == "node":
            pass  # (the extreme node itself)
        elif np.linalg.norm(mesh.xyz[nearest] - point) < _AT_NODE_MM or _stays_on_its_faces(
            mesh, nearest, point
        ):
            _move_node(mesh, nearest, point)
        else:
            point = _make_node(mesh, where, point, sign=sign)
        out.append(float(point[2]))
    return out[0], out[1]


def _stays_on_its_faces(mesh: TopoMesh, node: int, p: np.ndarray) -> bool:
    """Whether ``node`` moved onto ``p`` stays on every face around it: ``p`` projects onto each
    face's surface within ``_ON_FACE_MM``, inside its trim (a node inside a face, or one on a B-rep
    edge moved along it). A node on an edge moved into one of its faces would drag the other
    face's triangles over it."""
    tri, corner = np.nonzero(mesh.tris == node)
    seen: set[tuple[int, float, float]] = set()
    for t, c in zip(tri.tolist(), corner.tolist(), strict=True):
        key = (int(mesh.tri_face[t]), *mesh.tri_uv[t, c].tolist())
        if key in seen:
            continue
        seen.add(key)
        fe = mesh.faces[key[0]]
        u, v = fe.uv_near(tuple(p), key[1:])
        if np.linalg.norm(np.subtract(fe.point(u, v), p)) > _ON_FACE_MM or not fe.contains(u, v, 1e-7):
            return False
    return True


# where an extreme lies: ("node", node), ("face", face, (u, v)) or ("edge", edge, curve parameter)
Where = tuple


def _extreme(meshes: list[TopoMesh], *, sign: float) -> tuple[int, Where, np.ndarray, int]:
    """(mesh index, where, exact point, the node nearest to it of those near the extreme height) of
    the lowest (sign=+1) or highest (sign=-1) point."""
    best_h = np.inf
    best: tuple[int, Where, np.ndarray, int] | None = None
    node_h = [sign * m.xyz[:, 2] for m in meshes]
    global_node = min(float(h.min()) for h in node_h)
    for mi, mesh in enumerate(meshes):
        h = node_h[mi]
        window = global_node + 4.0 * mesh.deflection
        if h.min() > window:
            continue
        low_nodes = np.flatnonzero(h <= window)
        low_set = set(low_nodes.tolist())
        # Start from the node itself: already exact, so the result never gets worse.
        n0 = int(low_nodes[np.argmin(h[low_nodes])])
        candidates: list[tuple[float, Where, np.ndarray]] = [
            (float(h[n0]), ("node", n0), mesh.xyz[n0].copy())
        ]
        tri_mask = np.asarray(np.isin(mesh.tris, low_nodes).any(axis=1))
        for f in unique_ints(mesh.tri_face[tri_mask]).tolist():
            candidates.extend(_face_extreme(mesh, f, tri_mask, sign))
        edge_ids = {ei for (a, b), ei in mesh.edge_of.items() if a in low_set or b in low_set}
        for ei in sorted(edge_ids):
            candidates.append(_edge_extreme(mesh, ei, sign))
        hval, where, point = min(candidates, key=lambda c: c[0])
        if hval < best_h:
            nearest = int(low_nodes[np.argmin(np.linalg.norm(mesh.xyz[low_nodes] - point, axis=1))])
            best_h, best = hval, (mi, where, point, nearest)
    assert best is not None
    return best


def _face_extreme(
    mesh: TopoMesh, f: int, tri_mask: np.ndarray, sign: float
) -> list[tuple[float, Where, np.ndarray]]:
    fe = mesh.faces[f]
    u, v = face_optimum_from_nodes(mesh, f, np.flatnonzero(tri_mask & (mesh.tri_face == f)), sign)
    if not fe.contains(u, v):
        return []
    p = np.array(fe.point(u, v))
    return [(sign * p[2], ("face", f, (u, v)), p)]


def face_optimum_from_nodes(mesh: TopoMesh, f: int, sel: np.ndarray, sign: float) -> tuple[float, float]:
    """``_face_optimum`` of face ``f`` from the lowest (sign=+1) or highest (sign=-1) corner of its
    triangles ``sel``, at that corner's (u, v) in its triangle."""
    z = mesh.xyz[mesh.tris[sel].ravel(), 2]
    return _face_optimum(mesh.faces[f], mesh.tri_uv[sel].reshape(-1, 2)[int(np.argmin(sign * z))], sign)


def _face_optimum(fe, uv0: np.ndarray, sign: float) -> tuple[float, float]:
    """(u, v) of the face's lowest (sign=+1) or highest (sign=-1) point reached from ``uv0`` by bounded
    L-BFGS on the untrimmed surface (the caller checks the trim). A periodic direction is not bounded
    by its seam, only to a period either side of ``uv0`` (``_window``): the surface goes on past the
    seam (a torus turned to an odd angle has its lowest point just across the seam from its lowest
    node: bounded there, the search stopped on the seam 2.2 um higher). The search is evaluated, and
    its result given, on the period nearest ``uv0``: a line search can try a step of many periods,
    which OCCT refuses to evaluate (bug24595_281390 turned (-47.0, -178.7, 118.8):
    "Geom_BSplineSurface::PeriodicNormalization: Vparameter is too great number")."""
    start = (float(uv0[0]), float(uv0[1]))

    def fun(x: np.ndarray) -> tuple[float, np.ndarray]:
        z, zu, zv = fe.z_and_grad(*fe.same_branch((float(x[0]), float(x[1])), start))
        return sign * z, sign * np.array([zu, zv])

    res = minimize(
        fun,
        np.asarray(uv0, dtype=np.float64),
        jac=True,
        method="L-BFGS-B",
        bounds=[
            _window(start[0], fe.period(0)) if fe.period(0) else (fe.u0, fe.u1),
            _window(start[1], fe.period(1)) if fe.period(1) else (fe.v0, fe.v1),
        ],
        options={"ftol": 1e-15, "gtol": 1e-12},
    )
    return fe.same_branch((float(res.x[0]), float(res.x[1])), start)


def _window(start: float, period: float) -> tuple[float, float]:
    """Bounds one period either side of ``start`` in a periodic direction: every extreme of the
    surface has a copy within half a period of it, so none is lost, and the search cannot wander
    off by many periods (bug24595_281390 turned (122.2, -174.3, -59.3): a line search ran 23
    periods out along a closed B-spline's v and L-BFGS-B's next point was NaN)."""
    return start - period, start + period


def _edge_extreme(mesh: TopoMesh, ei: int, sign: float) -> tuple[float, Where, np.ndarray]:
    ev = mesh.edges[ei]
    s = np.linspace(ev.s0, ev.s1, _CURVE_SAMPLES + 1)
    h = np.array([sign * ev.ad.Value(float(x)).Z() for x in s])
    i = int(np.argmin(h))
    lo, hi = s[max(i - 1, 0)], s[min(i + 1, len(s) - 1)]
    x = ev.height_extreme(lo, hi, sign)
    if sign * ev.point(x)[2] > h[i]:
        x = float(s[i])
    pt = np.array(ev.point(x))
    return sign * pt[2], ("edge", ei, x), pt


def _make_node(mesh: TopoMesh, where: Where, p: np.ndarray, *, sign: float) -> np.ndarray:
    """Make the exact extreme ``p`` (found at ``where``, farther than ``_AT_NODE_MM`` from every node
    near it: ``snap_extremes`` puts such a node on it) a node of ``mesh``, in place, and return the
    node's point: ``p``, or, where ``p`` lies on the border of its face's triangles, the extreme of
    the B-rep edge there (within the mesh's resolution of ``p``).

    A new node splits the mesh edge of ``p``'s B-rep edge between the two nodes either side of it,
    or the triangle of ``p``'s face
    that holds its (u, v) (at a point on one of that triangle's edges: that edge, on both its
    triangles; a point of the face's border can lie inside a triangle in (u, v), where the border
    curves away from its chord: that triangle is split, its new node exact on the face). No other
    node moves, so no face's triangles are dragged over another face."""
    if where[0] == "edge":
        return _node_on_edge(mesh, where[1], where[2], p)
    _, f, uv = where
    t, bary, quv = _triangle_at(mesh, f, uv)
    corners = mesh.tris[t]
    if bary.min() > _ON_TRI_EDGE:
        split_triangle(mesh, t, p, quv)
        return p
    # on (or, where BRepMesh's border chords cut the trim, just past) the edge opposite the corner
    # with the smallest barycentric coordinate
    k = int(np.argmin(bary))
    a, b = int(corners[(k + 1) % 3]), int(corners[(k + 2) % 3])
    key = (min(a, b), max(a, b))
    ei = mesh.edge_of.get(key)
    if ei is not None:  # the face's border: the point goes onto its B-rep edge
        q = edge_extreme_between(mesh, ei, a, b, sign)
        if q is None:  # the edge's extreme between the two is one of them
            lower = a if sign * mesh.xyz[a, 2] <= sign * mesh.xyz[b, 2] else b
            return mesh.xyz[lower]
        split_edges(mesh, {key: q})
        return q
    split_edges(mesh, {key: p})
    return p


def _node_on_edge(mesh: TopoMesh, ei: int, s: float, p: np.ndarray) -> np.ndarray:
    """Make ``p``, at parameter ``s`` of B-rep edge ``ei``, a node: a new one splitting the mesh edge
    along ``ei`` whose span holds ``s``; at a node's parameter (the curve's end, where a loose file's
    vertex lies off it within its tolerance), the node of that edge nearest to ``p``, put on it."""
    ev = mesh.edges[ei]
    for (a, b), e in mesh.edge_of.items():
        if e != ei:
            continue
        span = curve_span(ev, ev.parameter_of(tuple(mesh.xyz[a])), ev.parameter_of(tuple(mesh.xyz[b])))
        margin = 0.0 if span is None else 1e-9 * (span[1] - span[0])
        if span is not None and span[0] + margin < s < span[1] - margin:
            split_edges(mesh, {(a, b): p})
            return p
    nodes = {n for key, e in mesh.edge_of.items() if e == ei for n in key}
    _move_node(mesh, min(nodes, key=lambda n: float(np.linalg.norm(mesh.xyz[n] - p))), p)
    return p


def _triangle_at(mesh: TopoMesh, f: int, uv: tuple[float, float]) -> tuple[int, np.ndarray, np.ndarray]:
    """The triangle of face ``f`` that holds ``uv`` (the one it lies deepest inside: on the border,
    nearest to it), its barycentric coordinates there, and ``uv`` on the triangle's branch of a
    periodic surface."""
    fe = mesh.faces[f]
    sel = np.flatnonzero(mesh.tri_face == f)
    tuv = mesh.tri_uv[sel]  # (k, 3, 2)
    q = np.tile(np.asarray(uv, dtype=np.float64), (len(sel), 1))
    for axis in (0, 1):
        period = fe.period(axis)
        if period:
            q[:, axis] += np.round((tuv[:, 0, axis] - q[:, axis]) / period) * period
    e1, e2, w = tuv[:, 1] - tuv[:, 0], tuv[:, 2] - tuv[:, 0], q - tuv[:, 0]
    den = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    ok = np.abs(den) > 0.0
    den = np.where(ok, den, 1.0)
    l1 = (w[:, 0] * e2[:, 1] - w[:, 1] * e2[:, 0]) / den
    l2 = (e1[:, 0] * w[:, 1] - e1[:, 1] * w[:, 0]) / den
    bary = np.column_stack([1.0 - l1 - l2, l1, l2])
    depth = np.where(ok, bary.min(axis=1), -np.inf)
    i = int(np.argmax(depth))
    return int(sel[i]), bary[i], q[i]


def snap_local_extremes(mesh: TopoMesh, planes: np.ndarray) -> int:
    """Move nodes that are local height extremes of the topology mesh onto the exact extreme of
    their face, where a plane passes between the two. Returns how many nodes moved.

    A dome or dimple whose apex is not a node tops out up to one deflection above (below) its
    highest (lowest) node: a plane in that band cuts a small loop the topology mesh does not see. A
    node higher than all its neighbours that lies inside one face is moved onto the face's local
    maximum found from its (u, v) (likewise for minima), if that lies inside the trimmed face and
    within the node's fan; a node on a B-rep edge is moved onto the edge's extreme between its two
    neighbours along it (the top of a tilted circular rim). Ridges (a line of maxima inside a face)
    get a row of nodes from ``ridges.add_ridge_rows``, called after this.
    """
    planes = np.sort(np.asarray(planes, dtype=np.float64))
    if not len(planes):
        return 0
    z = mesh.xyz[:, 2]
    e = np.concatenate([mesh.tris[:, [0, 1]], mesh.tris[:, [1, 2]], mesh.tris[:, [2, 0]]])
    n = mesh.n_nodes
    nb_max = np.full(n, -np.inf)
    nb_min = np.full(n, np.inf)
    np.maximum.at(nb_max, e[:, 0], z[e[:, 1]])
    np.minimum.at(nb_min, e[:, 0], z[e[:, 1]])
    band = _BAND_DEFLECTIONS * mesh.deflection
    moved = 0
    for sign, extreme in ((-1.0, z > nb_max), (1.0, z < nb_min)):
        cand = np.flatnonzero(extreme)
        if not len(cand):
            continue
        # a plane strictly beyond the node, within the band (above a maximum, below a minimum)
        if sign < 0:
            k = np.searchsorted(planes, z[cand], side="right")
            hit = (k < len(planes)) & (planes[np.minimum(k, len(planes) - 1)] <= z[cand] + band)
        else:
            k = np.searchsorted(planes, z[cand], side="left") - 1
            hit = (k >= 0) & (planes[np.maximum(k, 0)] >= z[cand] - band)
        for node in cand[hit].tolist():
            moved += _snap_node(mesh, node, sign)
    return moved


def _snap_node(mesh: TopoMesh, node: int, sign: float) -> int:
    tri, corner = np.nonzero(mesh.tris == node)
    faces = unique_ints(mesh.tri_face[tri])
    old = mesh.xyz[node]
    fan = mesh.xyz[unique_ints(mesh.tris[tri])]
    reach = float(np.linalg.norm(fan - old, axis=1).max())
    if len(faces) > 1:  # on a B-rep edge: its extreme along the edge
        p = _edge_node_optimum(mesh, node, sign)
        if p is None or sign * p[2] >= sign * old[2] or np.linalg.norm(p - old) > reach:
            return 0
        _move_node(mesh, node, p)
        return 1
    fe = mesh.faces[int(faces[0])]
    u, v = _face_optimum(fe, mesh.tri_uv[tri[0], corner[0]], sign)
    p = np.array(fe.point(u, v))
    if sign * p[2] >= sign * old[2] or np.linalg.norm(p - old) > reach or not fe.contains(u, v):
        return 0
    _move_node(mesh, node, p, uv=(u, v))
    return 1


def _move_node(mesh: TopoMesh, node: int, p: np.ndarray, uv: tuple[float, float] | None = None) -> None:
    """Put ``node`` at the exact surface point ``p``, with its (u, v) in every face around it (the
    crossings next to it are solved along (u, v) segments from there). ``uv``: known, one face."""
    moved = np.linalg.norm(p - mesh.xyz[node]) >= _SAME_POINT_MM
    mesh.xyz[node] = p
    if not moved:
        return  # (u, v) as it was (a pole keeps its per-triangle (u, v))
    tri, corner = np.nonzero(mesh.tris == node)
    # per face and old (u, v): a node on a seam has one (u, v) on each side of it
    uv_of: dict[tuple[int, float, float], tuple[float, float]] = {}
    for t, c in zip(tri.tolist(), corner.tolist(), strict=True):
        key = (int(mesh.tri_face[t]), *mesh.tri_uv[t, c].tolist())
        if key not in uv_of:
            fe = mesh.faces[key[0]]
            # on the old (u, v)'s branch of a periodic surface: a seam node keeps one (u, v) per side
            new = fe.same_branch(uv, key[1:]) if uv is not None else fe.uv_near(tuple(p), key[1:])
            # keep the old (u, v) where the projection does not give the point back (a singular spot)
            ok = np.linalg.norm(np.subtract(fe.point(*new), p)) < _SAME_POINT_MM
            uv_of[key] = new if ok else key[1:]
        mesh.tri_uv[t, c] = uv_of[key]


def _edge_node_optimum(mesh: TopoMesh, node: int, sign: float) -> np.ndarray | None:
    """The most extreme point of the B-rep edges through ``node`` between its two neighbours on each
    (bounded Brent in the curve parameter), or None if there is none to search."""
    along: dict[int, list[int]] = {}
    for (a, b), ei in mesh.edge_of.items():
        if a == node or b == node:
            along.setdefault(ei, []).append(b if a == node else a)
    best: np.ndarray | None = None
    for ei, nbrs in along.items():
        if len(nbrs) != 2:
            continue  # the node ends this edge (a B-rep vertex)
        ev = mesh.edges[ei]
        s_n = ev.parameter_of(tuple(mesh.xyz[node]))
        lo, hi = sorted(ev.parameter_of(tuple(mesh.xyz[n])) for n in nbrs)
        if lo < s_n < hi:
            spans = [(lo, hi)]
        elif ev.closed:
            # the node is a closed edge's seam vertex, its neighbours either side of it: the spans
            # from each neighbour to the seam (the lowest point of a tilted circle can lie next to
            # its vertex: eight_cyl turned (-147.4, -67.2, -169.1), a solid's lowest point 7 um
            # below that node, and the plane between them lost its sliver of the section)
            spans = [(ev.s0, lo), (hi, ev.s1)]
        else:
            continue
        for sa, sb in spans:
            pt = np.array(ev.point(ev.height_extreme(sa, sb, sign)))
            if best is None or sign * pt[2] < sign * best[2]:
                best = pt
    return best
