"""New topology-mesh nodes at exact B-rep points, the mesh kept closed and consistently oriented:
mesh edges split (``split_edges``: on both faces of a boundary edge) and triangles split at a point
inside them (``split_triangle``)."""

from __future__ import annotations

import numpy as np

from worker.dst.topomesh import TopoMesh

_SEAM_REL = 1e-9  # a node this close (a fraction of a closed edge's range) to its ends is at its seam


def split_edges(mesh: TopoMesh, points: dict[tuple[int, int], np.ndarray]) -> int:
    """Split each mesh edge ``(a, b)`` (a < b) of ``points`` at its exact B-rep point, in place:
    a new node there, each triangle using a split edge cut into triangles (corner order kept, so the
    mesh stays closed and consistently oriented), each new node's (u, v) in every face around it
    projected from the point, and a split edge lying on a B-rep edge replaced by its two pieces in
    ``edge_of``. Returns the nodes added."""
    if not points:
        return 0
    new_of = {key: mesh.n_nodes + k for k, key in enumerate(points)}
    xyz = np.vstack([mesh.xyz, np.asarray(list(points.values()))])
    # every triangle (any face) with a split edge
    e = np.stack([mesh.tris, np.roll(mesh.tris, -1, axis=1)], axis=2)  # (m, 3, 2)
    lo_hi = np.sort(e, axis=2)
    keys = np.array(list(new_of), dtype=np.int64)
    n = max(xyz.shape[0], 1)
    hit = np.isin(lo_hi[..., 0] * n + lo_hi[..., 1], keys[:, 0] * n + keys[:, 1])
    touched = np.flatnonzero(hit.any(axis=1))
    new_tris, new_uv, new_face = [], [], []
    for t in touched.tolist():
        face = int(mesh.tri_face[t])
        fe_t = mesh.faces[face]
        corners = mesh.tris[t].tolist()
        uvs = mesh.tri_uv[t]
        poly: list[tuple[int, np.ndarray, bool]] = []
        for i in range(3):
            a, b = corners[i], corners[(i + 1) % 3]
            poly.append((a, uvs[i], False))
            m = new_of.get((min(a, b), max(a, b)))
            if m is None:
                continue
            p = xyz[m]
            # (u, v) of the new node in this triangle's face, on this triangle's branch
            seed = _uv_on_segment(uvs[i], uvs[(i + 1) % 3], mesh.xyz[a], mesh.xyz[b], p)
            poly.append((m, np.asarray(fe_t.uv_near(tuple(p), tuple(seed))), True))
        for tri in _triangulate(poly, xyz):
            new_tris.append([v for v, _ in tri])
            new_uv.append([uv for _, uv in tri])
            new_face.append(face)
    keep = np.ones(len(mesh.tris), dtype=bool)
    keep[touched] = False
    mesh.xyz = xyz
    mesh.tris = np.concatenate([mesh.tris[keep], np.asarray(new_tris, dtype=np.int64)])
    mesh.tri_uv = np.concatenate([mesh.tri_uv[keep], np.asarray(new_uv, dtype=np.float64)])
    mesh.tri_face = np.concatenate([mesh.tri_face[keep], np.asarray(new_face, dtype=mesh.tri_face.dtype)])
    for (a, b), m in new_of.items():
        ei = mesh.edge_of.pop((a, b), None)
        if ei is not None:
            mesh.edge_of[(min(a, m), max(a, m))] = ei
            mesh.edge_of[(min(m, b), max(m, b))] = ei
    return len(points)


def _uv_on_segment(uva, uvb, pa, pb, p) -> np.ndarray:
    """(u, v) interpolated along a triangle edge at the fraction where ``p`` projects on it."""
    ab = pb - pa
    s = float(np.clip(np.dot(p - pa, ab) / max(float(np.dot(ab, ab)), 1e-300), 0.0, 1.0))
    return np.asarray(uva) + s * (np.asarray(uvb) - np.asarray(uva))


def _triangulate(
    poly: list[tuple[int, np.ndarray, bool]], xyz: np.ndarray
) -> list[list[tuple[int, np.ndarray]]]:
    """Triangles (corner order kept) of a triangle whose edges got new nodes, given as the polygon of
    its corners and new nodes in order, each as (node, (u, v), is new). One new node: the fan from
    it (the other diagonal would join the ends of its own edge: a zero-area triangle). More: each
    corner between two new nodes is cut off, and what is left (the new nodes' triangle, or a
    quadrilateral split along its shorter diagonal) filled."""
    k = len(poly)
    if k == 4:
        j = next(i for i, (_, _, new) in enumerate(poly) if new)
        q = [(v, uv) for v, uv, _ in poly[j:] + poly[:j]]
        return [[q[0], q[1], q[2]], [q[0], q[2], q[3]]]
    cut = [i for i in range(k) if not poly[i][2] and poly[i - 1][2] and poly[(i + 1) % k][2]]
    out = [[poly[(i + d) % k][:2] for d in (-1, 0, 1)] for i in cut]
    left = [poly[i][:2] for i in range(k) if i not in cut]
    if len(left) == 3:
        out.append(left)
    elif len(left) == 4:
        p = [xyz[v] for v, _ in left]
        if np.linalg.norm(p[0] - p[2]) <= np.linalg.norm(p[1] - p[3]):
            out += [[left[0], left[1], left[2]], [left[0], left[2], left[3]]]
        else:
            out += [[left[0], left[1], left[3]], [left[1], left[2], left[3]]]
    else:
        raise AssertionError(f"a triangle split into a {len(left)}-gon")
    return out


def split_triangle(mesh: TopoMesh, t: int, p: np.ndarray, uv: np.ndarray) -> int:
    """Split triangle ``t`` at the exact point ``p`` of its face strictly inside it, ``uv`` its
    (u, v) on the triangle's branch: a new node, and the three triangles from it to the corners in
    place of ``t`` (corner order kept). Returns the new node."""
    m = mesh.n_nodes
    a, b, c = mesh.tris[t].tolist()
    ua, ub, uc = mesh.tri_uv[t]
    uv = np.asarray(uv, dtype=np.float64)
    keep = np.ones(len(mesh.tris), dtype=bool)
    keep[t] = False
    mesh.xyz = np.vstack([mesh.xyz, np.asarray(p, dtype=np.float64)[None, :]])
    mesh.tris = np.concatenate([mesh.tris[keep], np.array([[a, b, m], [b, c, m], [c, a, m]], dtype=np.int64)])
    mesh.tri_uv = np.concatenate([mesh.tri_uv[keep], np.array([[ua, ub, uv], [ub, uc, uv], [uc, ua, uv]])])
    mesh.tri_face = np.concatenate(
        [mesh.tri_face[keep], np.full(3, mesh.tri_face[t], dtype=mesh.tri_face.dtype)]
    )
    return m


def curve_span(ev, sa: float, sb: float) -> tuple[float, float] | None:
    """(lo, hi): the curve parameters of the span between two neighbouring nodes on a B-rep edge, in
    order. On a closed edge the node at its seam vertex has two parameters, and ``parameter_of``
    gives either: two nodes more than half the edge apart are that vertex and its neighbour across
    the seam, whose span runs from the neighbour to the seam's other end (the highest point of a
    tilted circle can lie there, next to its vertex). None where neither node is at the seam."""
    lo, hi = min(sa, sb), max(sa, sb)
    if ev.closed and hi - lo > 0.5 * (ev.s1 - ev.s0):
        at_seam = _SEAM_REL * (ev.s1 - ev.s0)
        if lo - ev.s0 <= at_seam:
            return hi, ev.s1
        if ev.s1 - hi <= at_seam:
            return ev.s0, lo
        return None
    return lo, hi


def edge_extreme_between(mesh: TopoMesh, ei: int, a: int, b: int, sign: float) -> np.ndarray | None:
    """The B-rep edge's highest (sign -1) or lowest (+1) point strictly between nodes ``a`` and
    ``b`` (bounded Brent in the curve parameter), or None if it is at either node."""
    ev = mesh.edges[ei]
    lo_hi = curve_span(ev, ev.parameter_of(tuple(mesh.xyz[a])), ev.parameter_of(tuple(mesh.xyz[b])))
    if lo_hi is None:
        return None
    lo, hi = lo_hi
    s = ev.height_extreme(lo, hi, sign)
    margin = 1e-9 * (hi - lo)
    if not lo + margin < s < hi - margin:
        return None
    return np.array(ev.point(s))
