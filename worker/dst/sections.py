"""Section topology: the topology mesh cut by every plane, vectorised.

Conventions (a symbolic perturbation that makes every degenerate case consistent): a node exactly on
a plane counts as *above* it. A topology-mesh edge from a lower node ``a`` to an upper node ``b``
crosses plane ``j`` when ``z_a < z_j <= z_b``; when ``z_j == z_b`` the crossing *is* node ``b``.

Slab ``k`` is the open layer between plane ``k - 1`` and plane ``k`` (slab 0 is below the first plane,
slab ``P`` above the last). A triangle spanning several slabs contributes one convex *piece* to each.
Pieces sharing an edge inside a slab are connected; a connected set of pieces is a *component*. Each
section loop at plane ``j`` bounds exactly one component of slab ``j`` (below) and one of slab
``j + 1`` (above). A component with one loop below, one above and Euler characteristic 0 is an annulus:
a strip of triangles between its two rings is topologically exact there ("zipper"). Every other
component (caps, branching, handles, closed pieces between two planes) keeps its topology-mesh pieces.

Loops are oriented with the material on their left seen from above (outer loops counter-clockwise).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from worker.dst import constants as C
from worker.dst.errors import ResourceLimitExceeded, TessellationError
from worker.dst.topomesh import TopoMesh

NOISE_MM = 1e-9  # a node this close to a plane is on it at least: numerical noise of the evaluators


@dataclass
class SectionTopology:
    """Everything the sampler and the tessellator need about the cut topology mesh.

    z : (n,) float64          node heights used for classification (snapped onto planes within tol)
    slab : (n,) int64         slab index of each node
    planes : (P,) float64     world plane heights
    edges : (E, 2) int64      undirected topology-mesh edges (a < b)
    edge_tris : (E, 2) int64  the two triangles of each edge
    tri_edges : (m, 3) int64  edge id of corner edge k -> k+1 of each triangle
    edge_lo, edge_hi          slab range of each edge (inclusive)
    cross_off : (E,) int64    first crossing id of each edge (crossings of edge e: planes lo..hi-1)
    cross_edge, cross_plane   per crossing
    cross_node : (N,) int64   the node a crossing coincides with, or -1
    succ : (N,) int64         next crossing along its loop
    seg_tri : (N,) int64      triangle holding the segment that starts at a crossing
    loops : list of (plane, crossing ids in order)
    loop_below, loop_above    component ids on both sides of each loop
    tri_smin, piece_off       piece id of (triangle T, slab k) = piece_off[T] + k - tri_smin[T]
    piece_comp : (Q,) int64   component of each piece
    comp_is_annulus : (C,) bool
    comp_euler : (C,) int64   Euler characteristic of each component (1: a disk)
    """

    z: np.ndarray
    slab: np.ndarray
    planes: np.ndarray
    edges: np.ndarray
    edge_tris: np.ndarray
    tri_edges: np.ndarray
    edge_lo: np.ndarray
    edge_hi: np.ndarray
    cross_off: np.ndarray
    cross_edge: np.ndarray
    cross_plane: np.ndarray
    cross_node: np.ndarray
    succ: np.ndarray
    seg_tri: np.ndarray
    loops: list[tuple[int, np.ndarray]]
    loop_below: np.ndarray
    loop_above: np.ndarray
    tri_smin: np.ndarray
    tri_smax: np.ndarray
    piece_off: np.ndarray
    piece_comp: np.ndarray
    comp_is_annulus: np.ndarray
    comp_euler: np.ndarray
    comp_bottom: list[list[int]]
    comp_top: list[list[int]]
    cross_xyz: np.ndarray
    cross_uv_start: np.ndarray
    cross_uv_end: np.ndarray
    cross_is_corner: np.ndarray
    flat_planes: list[int]
    node_plane: np.ndarray

    def crossing_id(self, edge: int, plane: int) -> int:
        return int(self.cross_off[edge] + plane - self.edge_lo[edge])

    def piece(self, tri: int, slab: int) -> int:
        return int(self.piece_off[tri] + slab - self.tri_smin[tri])


def section_pairs(mesh: TopoMesh, planes: np.ndarray) -> int:
    """How many (triangle, plane) pairs ``cut_topology`` cuts, within the few a node on a plane adds
    or takes away: each triangle's planes from its z range, ahead of the cut's memory."""
    lo, hi = _plane_ranges(mesh, planes)
    return int((hi - lo).sum())


def section_pairs_per_plane(mesh: TopoMesh, planes: np.ndarray) -> np.ndarray:
    """``section_pairs`` plane by plane: (P,) int64."""
    lo, hi = _plane_ranges(mesh, planes)
    steps = np.bincount(lo, minlength=len(planes) + 1) - np.bincount(hi, minlength=len(planes) + 1)
    return np.cumsum(steps)[: len(planes)]


def _plane_ranges(mesh: TopoMesh, planes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    # each triangle's planes lo .. hi - 1, from its z range
    tz = mesh.xyz[mesh.tris, 2]
    return np.searchsorted(planes, tz.min(axis=1), side="left"), np.searchsorted(
        planes, tz.max(axis=1), side="right"
    )


def cut_topology(
    mesh: TopoMesh, planes: np.ndarray, *, on_plane_tol: float, noise_tol: np.ndarray | None = None
) -> SectionTopology:
    """Cut ``mesh`` by the (ascending, world) ``planes`` and derive loops and slab components.

    ``noise_tol`` (per plane, mm): a node this close to a plane is on it whatever the geometry; pass the
    float32 resolution of the written heights, at which the STL puts such a node on the plane anyway.
    """
    pairs = section_pairs(mesh, planes)
    if pairs > C.MAX_SECTION_PAIRS:
        raise ResourceLimitExceeded(
            f"the part's {len(planes)} planes would cross its topology mesh's triangles about "
            f"{pairs / 1e6:.0f} million times (limit {C.MAX_SECTION_PAIRS / 1e6:.0f} million; the cut takes "
            "~400 bytes each): check the file's units, or use thicker layers"
        )
    tris = mesh.tris
    m = len(tris)
    n = len(mesh.xyz)

    # --- undirected edges and their two triangles --------------------------------------------------
    corner_a = np.concatenate([tris[:, 0], tris[:, 1], tris[:, 2]])
    corner_b = np.concatenate([tris[:, 1], tris[:, 2], tris[:, 0]])
    lo_id, hi_id = np.minimum(corner_a, corner_b), np.maximum(corner_a, corner_b)
    keys, inv = np.unique(lo_id * n + hi_id, return_inverse=True)
    n_edges = len(keys)
    edges = np.stack([keys // n, keys % n], axis=1)
    order = np.argsort(inv, kind="stable")
    if len(order) != 2 * n_edges:
        raise TessellationError("topology mesh is not a closed 2-manifold")
    edge_tris = (order.reshape(-1, 2) % m).astype(np.int64)
    tri_edges = inv.reshape(3, m).T.copy()

    if noise_tol is None:
        noise_tol = np.full(planes.size, NOISE_MM)
    z, flat_planes, snapped = snap_to_planes(
        mesh, planes, edges, keys, edge_tris, tol=on_plane_tol, noise_tol=np.maximum(noise_tol, NOISE_MM)
    )
    node_plane = _plane_of(z, planes)
    # A node on a plane counts as above it, except an isolated local maximum (a dome top or the top
    # line of a horizontal hole touching the plane): that counts as below, so the plane touching the
    # surface there does not invent a zero-width section.
    # The decision is made per connected set of on-plane nodes (joined by edges lying in the plane),
    # so a line of them is never split into above and below parts. A set whose in-plane edges are all
    # ridges (both neighbouring triangles below the plane: the surface touches it from below, like the
    # top line of a horizontal hole) counts as below; any other edge (a valley, or a surface passing
    # through the plane along it) or a flat face or horizontal edge makes it above. A lone node counts
    # as below when it is a local maximum (a dome top).
    on = node_plane >= 0
    a_, b_ = edges[:, 0], edges[:, 1]
    has_above = np.zeros(n, dtype=bool)
    np.logical_or.at(has_above, a_, z[b_] > z[a_])
    np.logical_or.at(has_above, b_, z[a_] > z[b_])
    in_plane = on[a_] & on[b_] & (node_plane[a_] == node_plane[b_])
    graph = coo_matrix((np.ones(int(in_plane.sum())), (a_[in_plane], b_[in_plane])), shape=(n, n))
    _, group = connected_components(graph, directed=False)
    n_groups = group.max() + 1
    ie = np.flatnonzero(in_plane)
    third = mesh.tris[edge_tris[ie]].sum(axis=2) - (a_[ie] + b_[ie])[:, None]  # (k, 2) third vertices
    side = np.sign(z[third] - z[a_[ie]][:, None])
    ridge = (side < 0).all(axis=1)
    g_edges = np.zeros(n_groups, dtype=bool)
    g_other = np.zeros(n_groups, dtype=bool)
    g_edges[group[a_[ie]]] = True
    np.logical_or.at(g_other, group[a_[ie]], ~ridge)
    g_above = np.zeros(n_groups, dtype=bool)
    np.logical_or.at(g_above, group[on], (snapped | has_above)[on])
    g_snapped = np.zeros(n_groups, dtype=bool)
    np.logical_or.at(g_snapped, group[on], snapped[on])
    g_below = ~g_snapped & np.where(g_edges, ~g_other, ~g_above)
    below = on & g_below[group]
    slab = (np.searchsorted(planes, z, side="right") - below).astype(np.int64)

    s_a, s_b = slab[edges[:, 0]], slab[edges[:, 1]]
    edge_lo, edge_hi = np.minimum(s_a, s_b), np.maximum(s_a, s_b)
    n_cross_e = edge_hi - edge_lo
    cross_off = np.concatenate([[0], np.cumsum(n_cross_e)[:-1]]).astype(np.int64)
    n_cross = int(n_cross_e.sum())
    cross_edge = np.repeat(np.arange(n_edges), n_cross_e)
    cross_plane = edge_lo[cross_edge] + (np.arange(n_cross) - cross_off[cross_edge])
    upper = np.where(s_a >= s_b, edges[:, 0], edges[:, 1])
    lower_e = np.where(s_a >= s_b, edges[:, 1], edges[:, 0])
    up_node = upper[cross_edge]
    lo_node = lower_e[cross_edge]
    if n_cross:
        zc_ = planes[cross_plane]
        cross_node = np.where(z[up_node] == zc_, up_node, np.where(z[lo_node] == zc_, lo_node, -1))
    else:
        cross_node = np.zeros(0, dtype=np.int64)

    # --- triangle segments: start on the edge going above->below, end on the edge going below->above
    smin, smax = slab[tris].min(axis=1), slab[tris].max(axis=1)
    n_seg_t = smax - smin
    seg_t = np.repeat(np.arange(m), n_seg_t)
    seg_off = np.concatenate([[0], np.cumsum(n_seg_t)[:-1]]).astype(np.int64)
    seg_j = smin[seg_t] + (np.arange(len(seg_t)) - seg_off[seg_t])
    above = slab[tris[seg_t]] > seg_j[:, None]
    nxt = np.roll(above, -1, axis=1)
    k_start = np.argmax(above & ~nxt, axis=1)
    k_end = np.argmax(~above & nxt, axis=1)
    e_start = tri_edges[seg_t, k_start]
    e_end = tri_edges[seg_t, k_end]
    c_start = cross_off[e_start] + seg_j - edge_lo[e_start]
    c_end = cross_off[e_end] + seg_j - edge_lo[e_end]
    succ = np.full(n_cross, -1, dtype=np.int64)
    succ[c_start] = c_end
    seg_tri = np.full(n_cross, -1, dtype=np.int64)
    seg_tri[c_start] = seg_t
    if n_cross and (succ < 0).any():
        raise TessellationError("section segments do not close into loops (non-manifold topology mesh)")

    loops = _walk_loops(succ, cross_plane)

    # --- slab pieces and components ------------------------------------------------------------------
    n_piece_t = smax - smin + 1
    piece_off = np.concatenate([[0], np.cumsum(n_piece_t)[:-1]]).astype(np.int64)
    n_pieces = int(n_piece_t.sum())
    n_eseg = edge_hi - edge_lo + 1
    e_rep = np.repeat(np.arange(n_edges), n_eseg)
    e_off = np.concatenate([[0], np.cumsum(n_eseg)[:-1]]).astype(np.int64)
    e_k = edge_lo[e_rep] + (np.arange(len(e_rep)) - e_off[e_rep])
    t1, t2 = edge_tris[e_rep, 0], edge_tris[e_rep, 1]
    p1 = piece_off[t1] + e_k - smin[t1]
    p2 = piece_off[t2] + e_k - smin[t2]
    graph = coo_matrix((np.ones(len(p1)), (p1, p2)), shape=(n_pieces, n_pieces))
    n_comp, piece_comp = connected_components(graph, directed=False)

    # Euler characteristic of each component: V - E + F of its open-slab cell complex (the loops'
    # vertices and edges cancel out: a closed loop has as many edges as vertices).
    faces_c = np.bincount(piece_comp, minlength=n_comp)
    edges_c = np.bincount(piece_comp[p1], minlength=n_comp)
    vt = np.empty(n, dtype=np.int64)
    vt[tris.ravel()] = np.repeat(np.arange(m), 3)
    verts_c = np.bincount(piece_comp[piece_off[vt] + slab - smin[vt]], minlength=n_comp)
    euler = verts_c - edges_c + faces_c

    loop_below = np.empty(len(loops), dtype=np.int64)
    loop_above = np.empty(len(loops), dtype=np.int64)
    comp_bottom: list[list[int]] = [[] for _ in range(n_comp)]
    comp_top: list[list[int]] = [[] for _ in range(n_comp)]
    for li, (j, cross) in enumerate(loops):
        t = int(seg_tri[cross[0]])
        below = int(piece_comp[piece_off[t] + j - smin[t]])
        above_c = int(piece_comp[piece_off[t] + j + 1 - smin[t]])
        loop_below[li], loop_above[li] = below, above_c
        comp_top[below].append(li)
        comp_bottom[above_c].append(li)
    n_bottom = np.array([len(b) for b in comp_bottom])
    n_top = np.array([len(t) for t in comp_top])
    comp_is_annulus = (n_bottom == 1) & (n_top == 1) & (euler == 0)

    # --- seeds: linear interpolation along each crossing's edge, in the segment triangle's (u, v) ------
    zc = planes[cross_plane] if n_cross else np.zeros(0)
    dz = z[up_node] - z[lo_node] if n_cross else np.zeros(0)
    # an edge joining two nodes of one plane (one counted below it, one above) crosses it at a node
    frac = np.divide(zc - z[lo_node], dz, out=np.ones_like(dz), where=dz != 0) if n_cross else np.zeros(0)
    cross_xyz = mesh.xyz[lo_node] + frac[:, None] * (mesh.xyz[up_node] - mesh.xyz[lo_node])
    cross_xyz[:, 2] = zc
    # the segment starting at crossing c lies in triangle seg_tri[c]; both of its ends are seeded there
    cross_uv_start = _uv_in_tri(mesh, seg_tri, lo_node, up_node, frac)
    cross_uv_end = _uv_in_tri(mesh, seg_tri, lo_node[succ], up_node[succ], frac[succ])
    brep_keys = np.array([a * n + b for a, b in mesh.edge_of], dtype=np.int64)
    edge_is_brep = np.isin(keys, brep_keys)
    cross_is_corner = edge_is_brep[cross_edge] | (cross_node >= 0)

    return SectionTopology(
        z=z,
        slab=slab,
        planes=planes,
        edges=edges,
        edge_tris=edge_tris,
        tri_edges=tri_edges,
        edge_lo=edge_lo,
        edge_hi=edge_hi,
        cross_off=cross_off,
        cross_edge=cross_edge,
        cross_plane=cross_plane,
        cross_node=cross_node,
        succ=succ,
        seg_tri=seg_tri,
        loops=loops,
        loop_below=loop_below,
        loop_above=loop_above,
        tri_smin=smin,
        tri_smax=smax,
        piece_off=piece_off,
        piece_comp=piece_comp,
        comp_is_annulus=comp_is_annulus,
        comp_euler=euler,
        comp_bottom=comp_bottom,
        comp_top=comp_top,
        cross_xyz=cross_xyz,
        cross_uv_start=cross_uv_start,
        cross_uv_end=cross_uv_end,
        cross_is_corner=cross_is_corner,
        flat_planes=flat_planes,
        node_plane=node_plane,
    )


def _plane_of(z: np.ndarray, planes: np.ndarray) -> np.ndarray:
    """Index of the plane each height is exactly on, or -1."""
    if not planes.size:
        return np.full(len(z), -1, dtype=np.int64)
    j = np.clip(np.searchsorted(planes, z), 0, planes.size - 1)
    return np.where(planes[j] == z, j, -1).astype(np.int64)


def _uv_in_tri(mesh: TopoMesh, t: np.ndarray, lower, upper, frac) -> np.ndarray:
    """(u, v) in triangle ``t[i]`` of the point at fraction ``frac[i]`` from node ``lower[i]`` to ``upper[i]``."""
    if len(t) == 0:
        return np.zeros((0, 2))
    tri_nodes = mesh.tris[t]
    k_lo = np.argmax(tri_nodes == lower[:, None], axis=1)
    k_up = np.argmax(tri_nodes == upper[:, None], axis=1)
    uv_lo = mesh.tri_uv[t, k_lo]
    uv_up = mesh.tri_uv[t, k_up]
    return uv_lo + frac[:, None] * (uv_up - uv_lo)


def snap_to_planes(
    mesh: TopoMesh, planes, edges, keys, edge_tris, *, tol: float, noise_tol: np.ndarray
) -> tuple[np.ndarray, list[int], np.ndarray]:
    """Node heights with horizontal B-rep geometry lying on a plane put exactly on it.

    Nodes within ``noise_tol`` of a plane (numerical noise, or the float32 resolution of the STL) are on
    it whatever the geometry; whether they count as above or below it is decided by the caller.

    Returns the heights, the indices of planes that hold a whole (flat) face, and the mask of nodes
    snapped as horizontal geometry.

    A flat face or a horizontal edge within ``tol`` of a plane is on it for a float32 slicer; left
    apart, its nodes and the ring just below would collapse into zero-area slivers in the STL. Only
    such geometry is snapped: the nodes of a horizontal face whose nodes all lie within ``tol`` of one
    plane, and of a B-rep edge likewise, unless the surface is tangent to the plane along that edge
    (both neighbouring triangles on the same side, as along the top line of a horizontal hole):
    there the plane misses the surface by its float32 rounding, and snapping would invent a
    degenerate, zero-width section.
    """
    z = mesh.xyz[:, 2].copy()
    none = np.zeros(len(z), dtype=bool)
    if not planes.size:
        return z, [], none
    j = np.clip(np.searchsorted(planes, z), 1, planes.size) - 1
    j = np.where(
        np.abs(z - planes[np.minimum(j + 1, planes.size - 1)]) < np.abs(z - planes[j]),
        np.minimum(j + 1, planes.size - 1),
        j,
    )
    noise = np.abs(z - planes[j]) <= noise_tol[j]
    z[noise] = planes[j[noise]]
    near = np.abs(z - planes[j]) <= tol
    if not near.any():
        return z, [], none
    snap = np.zeros(len(z), dtype=bool)
    tri_near = near[mesh.tris].all(axis=1) & (j[mesh.tris] == j[mesh.tris[:, :1]]).all(axis=1)
    face_all = np.ones(len(mesh.faces), dtype=bool)
    np.logical_and.at(face_all, mesh.tri_face, tri_near)
    _flat_within_tolerance(mesh, planes, j, near, tri_near, face_all, tol)
    snap[mesh.tris[face_all[mesh.tri_face]].ravel()] = True
    flat_planes = sorted(set(j[mesh.tris[face_all[mesh.tri_face], 0]].tolist()))

    n = len(z)
    by_edge: dict[int, list[int]] = {}
    for (a, b), ei in mesh.edge_of.items():
        if near[a] and near[b] and j[a] == j[b]:
            by_edge.setdefault(ei, []).append(int(np.searchsorted(keys, a * n + b)))
    all_count: dict[int, int] = {}
    for ei in mesh.edge_of.values():
        all_count[ei] = all_count.get(ei, 0) + 1
    for ei, fine in by_edge.items():
        if len(fine) != all_count[ei]:
            continue  # only part of the edge is near the plane: not a horizontal edge
        fine_arr = np.asarray(fine)
        a, b = edges[fine_arr, 0], edges[fine_arr, 1]
        zp = planes[j[a]]
        thirds = []
        for side in (0, 1):
            t = edge_tris[fine_arr, side]
            tn = mesh.tris[t]
            third = tn[(tn != a[:, None]) & (tn != b[:, None])]
            thirds.append(np.sign(np.where(near[third], 0.0, z[third] - zp)))
        tangent = (thirds[0] * thirds[1]) > 0
        if not tangent.any():
            snap[a] = True
            snap[b] = True
    z[snap] = planes[j[snap]]
    return z, flat_planes, snap


def _flat_within_tolerance(
    mesh: TopoMesh,
    planes: np.ndarray,
    j: np.ndarray,
    near: np.ndarray,
    tri_near: np.ndarray,
    face_all: np.ndarray,
    tol: float,
) -> None:
    """Mark as flat (in ``face_all``) the faces lying on a plane whose mesh has nodes off it by the
    file's tolerance: a B-rep vertex a few hundredths of a micrometre below a horizontal plane face
    still belongs to the face. Such a face counts as flat when its *surface* is within ``tol`` of the
    plane at every off node's (u, v) and the off nodes are within the mesh's deflection of it.
    (Left out, the face's triangles would reach below the plane and a plane moved just below the
    face would cut a flat face nowhere its surface is.)"""
    partly = np.zeros(len(face_all), dtype=bool)
    np.logical_or.at(partly, mesh.tri_face, tri_near)
    partly &= ~face_all
    for f in np.flatnonzero(partly).tolist():
        tris = np.flatnonzero(mesh.tri_face == f)
        jp = j[mesh.tris[tris[tri_near[tris]][0], 0]]
        zp = planes[jp]
        nodes, uv = mesh.tris[tris].ravel(), mesh.tri_uv[tris].reshape(-1, 2)
        off = ~(near[nodes] & (j[nodes] == jp))
        if (j[nodes[off]] != jp).any() or np.abs(mesh.xyz[nodes[off], 2] - zp).max() > mesh.deflection:
            continue
        face = mesh.faces[f]
        if all(abs(face.point(u, v)[2] - zp) <= tol for u, v in np.unique(uv[off], axis=0).tolist()):
            face_all[f] = True


def _walk_loops(succ: np.ndarray, cross_plane: np.ndarray) -> list[tuple[int, np.ndarray]]:
    """Split the permutation ``succ`` into its cycles (each a closed section loop)."""
    nxt = succ.tolist()
    seen = bytearray(len(nxt))
    loops = []
    for c0 in range(len(nxt)):
        if seen[c0]:
            continue
        cyc = []
        c = c0
        while not seen[c]:
            seen[c] = 1
            cyc.append(c)
            c = nxt[c]
        loops.append((int(cross_plane[c0]), np.asarray(cyc, dtype=np.int64)))
    return loops
