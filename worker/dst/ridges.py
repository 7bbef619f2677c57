"""Topology-mesh nodes where a plane grazes a face: rows along horizontal ridges and valleys, and
splits of edges the B-rep between whose ends passes a plane.

The top line of a cylinder lying on its side (a horizontal hole, a round bar) is a line of maxima of
z inside its face: a ridge, all of it at one height. BRepMesh puts node rows along such a face at
steps that need not include the top, so the highest row can lie up to a deflection below the ridge.
A plane in that band cuts a thin sliver along the ridge (two lines 2 sqrt(2 r d) apart, d below the
top) that the topology mesh does not cross at all: the section would lose it (a hole's top printed
closed). ``snap_local_extremes`` cannot help: a node of a row along the ridge is not higher than its
neighbours in the row (or, moved onto the ridge, gets a loop around itself only).

Where a plane lies within the band of a face's highest point (lowest: a hole's bottom line, a bar's
underside), the face's extreme is found exactly (bounded L-BFGS from its highest node, as for
apexes); if the surface keeps that height along the iso-parameter line through it (u or v fixed:
the generatrix of a cylinder or an extrusion, the top circle of a torus or of a surface of revolution
about a vertical axis, analytic or B-spline), the face's triangles are split along that line: a node
wherever it crosses a mesh edge, each an exact point of the B-rep (on the line inside the face; on a
boundary edge, the edge's own height extreme there: where an edge on the surface crosses the ridge,
its height is stationary). Every triangle using a split edge is split too (on both faces of a
boundary edge), so the mesh stays closed and consistently oriented.

A ridge that is not its face's extreme, or not an iso-parameter line, gets no row; where a plane
grazes it (or a saddle, or a tilted crest), the topology edges across it whose B-rep passes the plane
between their ends are split there instead (``split_grazed_edges``): a node per edge, not a row.
"""

from __future__ import annotations

import numpy as np
from OCP.GeomAbs import GeomAbs_Line, GeomAbs_Plane

from worker.dst.chords import point_segment_offset
from worker.dst.constants import ON_PLANE_TOL_MM
from worker.dst.lowest import face_optimum_from_nodes, snap_local_extremes
from worker.dst.splits import curve_span, edge_extreme_between, split_edges
from worker.dst.topomesh import TopoMesh

# a plane this many topology deflections beside a face's highest (lowest) node may miss its sliver
BAND_DEFLECTIONS = 2.0
_LINE_SAMPLES = 9  # points along a candidate line checked for constant height
_LINE_TOL_MM = 1e-9  # ... within this of the extreme's height: a horizontal line
# a node this close to the line, relative to its edge's extent in the line's parameter, is on it
_ON_LINE_REL = 1e-6
_GRAZE_ROUNDS = 3  # edges made by grazed splits checked again, at most this many times
_NOISE_MM = 1e-9  # a grazed edge's extreme must pass its plane by more than this (evaluator noise)
_END_MARGIN = 1e-3  # an extreme this close (a fraction of the edge) to an end is at the end
_CLOSE_REL = 0.25  # a grazed edge's split point may lie this far (times its length) off the edge
_UV_GAP_MM = 1e-6  # a corner whose (u, v) gives a point farther than this from its node is projected


def prepare_extremes(
    mesh: TopoMesh, planes: np.ndarray, depth: np.ndarray | None = None
) -> tuple[int, int, int]:
    """What the planes need of a topology mesh's local extremes, in place, in order: apexes and
    dimples near a plane snapped onto their exact point (``lowest.snap_local_extremes``), node rows
    along ridges and valleys near a plane (``add_ridge_rows``), then edges split where the B-rep
    between their ends passes a plane they do not cross (``split_grazed_edges``, with ``depth``).
    Returns (snapped, ridge, grazed) nodes."""
    return (
        snap_local_extremes(mesh, planes),
        add_ridge_rows(mesh, planes),
        split_grazed_edges(mesh, planes, depth),
    )


def add_ridge_rows(mesh: TopoMesh, planes: np.ndarray) -> int:
    """Split ``mesh`` (in place) along every face's ridge (valley) line with a plane strictly within
    the band below (above) it. Returns the nodes added."""
    planes = np.sort(np.asarray(planes, dtype=np.float64))
    if not len(planes) or not len(mesh.tris):
        return 0
    band = BAND_DEFLECTIONS * mesh.deflection
    n_faces = len(mesh.faces)
    zc = mesh.xyz[mesh.tris, 2]  # (m, 3)
    top = np.full(n_faces, -np.inf)
    bottom = np.full(n_faces, np.inf)
    np.maximum.at(top, mesh.tri_face, zc.max(axis=1))
    np.minimum.at(bottom, mesh.tri_face, zc.min(axis=1))
    added = 0
    for sign, level in ((-1.0, top), (1.0, bottom)):
        # faces whose highest (lowest) node has a plane within the band on either side
        k = np.searchsorted(planes, level - band, side="left")
        near = (k < len(planes)) & (planes[np.minimum(k, len(planes) - 1)] <= level + band)
        for f in np.flatnonzero(near).tolist():
            if mesh.faces[f].ad.GetType() == GeomAbs_Plane:
                continue  # flat faces on planes are the cut's business
            line = _extreme_line(mesh, f, sign)
            if line is None:
                continue
            axis, value, height = line
            lo, hi = (height - band, height) if sign < 0 else (height, height + band)
            j = np.searchsorted(planes, lo, side="left")
            # strictly beside the line: a plane through it meets the surface along the line only
            if j < len(planes) and planes[j] <= hi and planes[j] != height:
                added += _split_along(mesh, f, axis, value, sign)
    return added


def split_grazed_edges(mesh: TopoMesh, planes: np.ndarray, depth: np.ndarray | None = None) -> int:
    """Split (in place) every mesh edge whose two ends lie on one side of a plane while the exact
    B-rep between them crosses it, at the exact point farthest beyond. Returns the nodes added.

    A plane grazing a face a little off a critical point of its height (a tilted crest, a saddle)
    cuts the surface into pieces the topology mesh's chords need not show: the ends of an edge lie
    up to a deflection below a crest that rises above the plane between them. The mesh's section
    then joins what the exact section keeps apart, or parts what it joins (a crest's tongue cut off
    from its tip; two loops touching at a saddle made one). Each edge with an end within the band of
    the nearest plane beyond its ends (whether or not it crosses planes between them) is checked at
    its middle (the surface along the edge's (u, v) segment, or the B-rep edge's own curve); where
    the parabola through its ends and middle comes near the plane (and for an edge inside a face, a
    parabola through its quarter points too), the exact extreme along the edge is found (bounded
    Brent), and if it lies beyond the plane by more than ``depth`` (per plane, mm: what a float32
    slicer cannot tell from the plane; default ``_NOISE_MM``) and belongs to the edge
    (``_along_edge``) the edge is split there. Edges made by the splits are checked again (at most
    ``_GRAZE_ROUNDS`` times).

    Edges inside a flat face are straight (never checked); the planes an edge crosses are the cut's
    business, even where the surface crosses one three times.
    """
    planes = np.asarray(planes, dtype=np.float64)
    order = np.argsort(planes)
    planes = planes[order]
    if not len(planes) or not len(mesh.tris):
        return 0
    depth = np.maximum(0.0 if depth is None else np.asarray(depth, dtype=np.float64)[order], _NOISE_MM)
    depth = np.broadcast_to(depth, planes.shape)
    added, since = 0, 0
    for _ in range(_GRAZE_ROUNDS):
        n0 = mesh.n_nodes
        points = _grazed_edges(mesh, planes, depth, since)
        if not points:
            break
        added += split_edges(mesh, points)
        since = n0  # the next round: only the edges of the new nodes
    return added


def _grazed_edges(
    mesh: TopoMesh, planes: np.ndarray, depth: np.ndarray, since: int
) -> dict[tuple[int, int], np.ndarray]:
    """{(a, b): exact point} of the edges ``split_grazed_edges`` splits (planes sorted), of those with
    a node numbered ``since`` or above."""
    n = mesh.n_nodes
    a_all = mesh.tris.ravel()
    b_all = np.roll(mesh.tris, -1, axis=1).ravel()
    keys, first = np.unique(np.minimum(a_all, b_all) * n + np.maximum(a_all, b_all), return_index=True)
    if since:
        new = (a_all[first] >= since) | (b_all[first] >= since)
        keys, first = keys[new], first[new]
    a, b = a_all[first], b_all[first]
    z = mesh.xyz[:, 2]
    za, zb = z[a], z[b]
    lo, hi = np.minimum(za, zb), np.maximum(za, zb)
    # the planes next beyond the ends: the first above the higher end, the last below the lower
    # (an edge may cross planes between its ends and still graze the next one: trj7_b1-ec-214's
    # long triangles over a ridge 0.1 mm above its top plane, their edges from 0.47 mm below it
    # to 0.005 mm below, the ridge between: the mesh's cut joined the ridge's two sides)
    lo_at = np.searchsorted(planes, lo, side="left")  # the first plane at or above the lower end
    k_up = np.searchsorted(planes, hi, side="right")
    k_down = lo_at - 1
    last = len(planes) - 1
    up = np.where(k_up <= last, planes[np.minimum(k_up, last)], np.inf)
    down = np.where(k_down >= 0, planes[np.maximum(k_down, 0)], -np.inf)
    band = BAND_DEFLECTIONS * mesh.deflection
    # a plane beyond an end within the band (none through an end: the edge touches it there)
    through = lo_at < np.searchsorted(planes, lo, side="right")
    through |= np.searchsorted(planes, hi, side="left") < k_up
    cand = np.flatnonzero(~through & ((up - hi <= band) | (lo - down <= band)))
    if not len(cand):
        return {}
    t, i = np.divmod(first[cand], 3)
    face = mesh.tri_face[t]
    brep_keys = np.fromiter((ka * n + kb for ka, kb in mesh.edge_of), dtype=np.int64, count=len(mesh.edge_of))
    on_brep = np.isin(keys[cand], brep_keys)
    flat = np.array([fe.ad.GetType() == GeomAbs_Plane for fe in mesh.faces], dtype=bool)
    inner = ~on_brep & ~flat[face]  # edges inside a flat face are straight
    uva, uvb = mesh.tri_uv[t, i].copy(), mesh.tri_uv[t, (i + 1) % 3].copy()
    # the profile's ends: the nodes' heights (inner edges: the surface's at their (u, v), below)
    za, zb = za[cand], zb[cand]
    zm = np.full(len(cand), np.nan)
    # the surface at each inner edge's ends and middle (u, v), a batch per face. A node on a B-rep
    # edge carries the (u, v) of the edge's curve on the face, which a sloppy file puts off the node
    # (boxed_sphere: up to 0.06 mm): the profile is then taken from the node's own (u, v), projected.
    sel = np.flatnonzero(inner)
    sel = sel[np.argsort(face[sel], kind="stable")]
    groups = np.split(sel, np.flatnonzero(np.diff(face[sel])) + 1) if len(sel) else []
    ends = (a[cand], b[cand])
    for g in groups:
        fe = mesh.faces[int(face[g[0]])]
        for uv, node in ((uva, ends[0]), (uvb, ends[1])):
            gap = np.linalg.norm(_surface(fe, uv[g]) - mesh.xyz[node[g]], axis=1)
            for c in g[gap > _UV_GAP_MM].tolist():
                uv[c] = fe.uv_near(tuple(mesh.xyz[node[c]]), tuple(uv[c]))
        pts = _surface(fe, np.concatenate([uva[g], uvb[g], 0.5 * (uva[g] + uvb[g])]))[:, 2]
        za[g], zb[g], zm[g] = np.split(pts, 3)
    # a B-rep edge's own curve at the middle parameter between its nodes
    param: dict[tuple[int, int], float] = {}  # (B-rep edge, node) -> curve parameter

    def s_of(ei: int, node: int) -> float:
        s = param.get((ei, node))
        if s is None:
            s = param[(ei, node)] = mesh.edges[ei].parameter_of(tuple(mesh.xyz[node]))
        return s

    span: dict[int, tuple[int, float, float]] = {}  # candidate -> (B-rep edge, its parameter span)
    for c in np.flatnonzero(on_brep).tolist():
        na, nb = int(a[cand[c]]), int(b[cand[c]])
        ei = mesh.edge_of[(min(na, nb), max(na, nb))]
        ev = mesh.edges[ei]
        if ev.ad.GetType() == GeomAbs_Line:
            continue  # straight
        lo_hi = curve_span(ev, s_of(ei, na), s_of(ei, nb))
        if lo_hi is None:
            continue
        span[c] = (ei, *lo_hi)
        zm[c] = ev.point(0.5 * sum(lo_hi))[2]
    sag = zm - 0.5 * (za + zb)  # NaN: not checked
    sign = np.where(sag > 0.0, -1.0, 1.0)  # -1: the edge bulges up, towards the plane above
    plane_j = np.where(sag > 0.0, k_up[cand], k_down[cand])
    ok = np.isfinite(sag) & (sag != 0.0) & (plane_j >= 0) & (plane_j <= last)
    plane = planes[np.clip(plane_j, 0, last)]
    # the extreme of the parabola through the ends and the middle, beyond the plane or short of it
    # by less than a quarter of the sag (a profile not quite a parabola: an edge turns ~20 deg at most)
    reach, _ = _farthest(za, zm, zb, sign)
    # an end within the on-plane tolerance is on the plane for a float32 slicer (and for the cut):
    # the edge touches it there (a face undulating about a plane within micrometres is left alone)
    gap = np.minimum(np.abs(z[a[cand]] - plane), np.abs(z[b[cand]] - plane))
    near = np.flatnonzero(ok & (gap > ON_PLANE_TOL_MM) & (reach + sign * plane >= -0.25 * np.abs(sag)))
    # an inner edge's profile looked at again at its quarter points (one batch per face) before its
    # exact extreme is sought: kept if the parabola of either half reaches as near the plane (an
    # edge crossing planes is long: of the soap box's ~220 edges its parabola keeps, 85 go on to the
    # search and 12 are split)
    looked = near[inner[near]]
    looked = looked[np.argsort(face[looked], kind="stable")]
    for g in np.split(looked, np.flatnonzero(np.diff(face[looked])) + 1) if len(looked) else []:
        fe = mesh.faces[int(face[g[0]])]
        quarters = np.concatenate([0.75 * uva[g] + 0.25 * uvb[g], 0.25 * uva[g] + 0.75 * uvb[g]])
        q1, q3 = np.split(_surface(fe, quarters)[:, 2], 2)
        keep = np.zeros(len(g), dtype=bool)
        for z0, zq, z1 in ((za[g], q1, zm[g]), (zm[g], q3, zb[g])):
            half_reach, half_sag = _farthest(z0, zq, z1, sign[g])
            keep |= half_reach + sign[g] * plane[g] >= -0.25 * half_sag
        ok[g[~keep]] = False
    near = near[ok[near]]
    found: list[tuple[int, np.ndarray, np.ndarray]] = []  # (candidate, exact point, unit normal)
    for c in near.tolist():
        sg = float(sign[c])
        if on_brep[c]:
            ei, lo_s, hi_s = span[c]
            ev = mesh.edges[ei]
            s_x = ev.height_extreme(lo_s, hi_s, sg)
            x = (s_x - lo_s) / (hi_s - lo_s) if hi_s > lo_s else 0.0
            p, normal = np.array(ev.point(s_x)), np.full(3, np.nan)
        else:
            fe = mesh.faces[int(face[c])]
            (ua, va), (du, dv) = uva[c].tolist(), (uvb[c] - uva[c]).tolist()
            x = fe.height_extreme_on_uv_segment(ua, va, ua + du, va + dv, sg)
            p, normal = fe.point_and_normal(ua + x * du, va + x * dv)
        # strictly inside (else the profile is monotone: a projected end beyond the plane, an edge
        # off its face) and beyond the plane
        if _END_MARGIN < x < 1.0 - _END_MARGIN and -sg * (p[2] - plane[c]) > depth[plane_j[c]]:
            found.append((c, p, normal))
    if not found:
        return {}
    c = np.array([c for c, _, _ in found])
    pts = np.array([p for _, p, _ in found])
    normals = np.array([n for _, _, n in found])
    na, nb = a[cand[c]], b[cand[c]]
    close = _along_edge(pts, normals, mesh.xyz[na], mesh.xyz[nb], band)
    return {
        (int(min(i, j)), int(max(i, j))): p
        for i, j, p, ok in zip(na.tolist(), nb.tolist(), pts, close.tolist(), strict=True)
        if ok
    }


def _farthest(
    z0: np.ndarray, zm: np.ndarray, z1: np.ndarray, sign: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The largest ``-sign * z`` of the parabola through heights ``z0``, ``zm``, ``z1`` at 0, 1/2 and
    1 over [0, 1], and the size of its sag (``zm`` off the chord)."""
    sag = zm - 0.5 * (z0 + z1)
    with np.errstate(divide="ignore", invalid="ignore"):
        tp = np.clip(0.5 + (z1 - z0) / (8.0 * sag), 0.0, 1.0)
    vertex = z0 + (z1 - z0) * tp + 4.0 * sag * tp * (1.0 - tp)
    ends = np.maximum(-sign * z0, -sign * z1)
    return np.where(-sign * sag > 0.0, -sign * vertex, ends), np.abs(sag)


def _along_edge(
    pts: np.ndarray, normals: np.ndarray, a: np.ndarray, b: np.ndarray, band: float
) -> np.ndarray:
    """Which split points ``pts`` belong to the edges a-b they were found along (else the profile
    was not along the edge). A point on a B-rep edge's curve (normal NaN): within ``band`` of the
    edge, as BRepMesh's polygon follows the curve. A point inside a face: within ``band`` of the
    edge in the surface's tangent plane (the profile of a (u, v) segment runs along the mesh edge
    only where the parametrisation is even: on trj3_s1-al-214's flat B-spline wall, a long edge's
    profile bowed 0.15 mm up within the wall, a point above its plane where the wall's section is
    the mesh's own), and no farther than ``_CLOSE_REL`` times the edge's length in all, the sag of
    a 90-degree arc (BRepMesh's triangles can stray far past its deflection: trj7_b1-ec-214's over
    a ridge, 0.24 mm below it along an 8.5 mm edge at a deflection of 0.02 mm)."""
    off = point_segment_offset(pts, a, b)
    dist = np.linalg.norm(off, axis=1)
    inner = np.isfinite(normals).all(axis=1)
    out_of_surface = np.abs((off * np.where(inner[:, None], normals, 0.0)).sum(axis=1))
    in_surface = np.sqrt(np.maximum(dist**2 - out_of_surface**2, 0.0))
    sag = np.maximum(band, _CLOSE_REL * np.linalg.norm(b - a, axis=1))
    return np.where(inner, (in_surface <= band) & (dist <= sag), dist <= band)


def _surface(fe, uv: np.ndarray) -> np.ndarray:
    """The face's surface at (k, 2) parameters: (k, 3)."""
    if fe.batch is not None:
        return fe.batch(uv[:, 0], uv[:, 1], False)[0]
    return np.array([fe.point(float(u), float(v)) for u, v in uv]).reshape(-1, 3)


def _extreme_line(mesh: TopoMesh, f: int, sign: float) -> tuple[int, float, float] | None:
    """(parameter axis: 0 for an iso-u line, 1 for iso-v; its parameter; its height) of the
    horizontal iso-parameter line through face ``f``'s highest (sign -1) or lowest (+1) point, or
    None if the extreme is not on such a line (a point: an apex) or lies on the face's border."""
    fe = mesh.faces[f]
    sel = np.flatnonzero(mesh.tri_face == f)
    uvs = mesh.tri_uv[sel].reshape(-1, 2)
    u, v = face_optimum_from_nodes(mesh, f, sel, sign)
    height = fe.point(u, v)[2]
    lo, hi = uvs.min(axis=0), uvs.max(axis=0)
    for axis, value in ((0, u), (1, v)):
        period = fe.period(axis)
        if period:  # onto the branch of the face's (u, v) in its triangles
            value = lo[axis] + (value - lo[axis]) % period
        span = hi[axis] - lo[axis]
        if not lo[axis] + 1e-9 * span < value < hi[axis] - 1e-9 * span:
            continue  # on the face's border: its edge's nodes are on it already
        other = 1 - axis
        along = np.linspace(lo[other], hi[other], _LINE_SAMPLES)
        uv = np.empty((_LINE_SAMPLES, 2))
        uv[:, axis], uv[:, other] = value, along
        if all(abs(fe.point(float(a), float(b))[2] - height) <= _LINE_TOL_MM for a, b in uv):
            return axis, value, height
    return None


def _split_along(mesh: TopoMesh, f: int, axis: int, value: float, sign: float) -> int:
    """Split the triangles of face ``f`` along the line ``uv[axis] = value`` (and the triangles of
    other faces that share a split boundary edge). Returns the nodes added."""
    fe = mesh.faces[f]
    period = fe.period(axis)
    sel = np.flatnonzero(mesh.tri_face == f)
    if not len(sel):
        return 0
    c = mesh.tri_uv[sel, :, axis]
    # the line's parameter on each triangle's branch of a periodic surface
    w = np.full(len(sel), value)
    if period:
        w = value + np.ceil((c.min(axis=1) - value) / period) * period
    d = c - w[:, None]
    scale = np.abs(np.roll(c, -1, axis=1) - c)  # each edge's extent in the line's parameter
    on = np.abs(d) <= _ON_LINE_REL * np.maximum(scale, np.roll(scale, 1, axis=1))
    d = np.where(on, 0.0, d)
    d_next = np.roll(d, -1, axis=1)
    crossed = d * d_next < 0  # edge i (corner i -> i + 1) strictly crossed
    rows, cols = np.nonzero(crossed)
    if not len(rows):
        return 0
    # one new node per crossed edge, keyed by its global nodes
    points: dict[tuple[int, int], np.ndarray] = {}
    for r, i in zip(rows.tolist(), cols.tolist(), strict=True):
        t = int(sel[r])
        a, b = int(mesh.tris[t, i]), int(mesh.tris[t, (i + 1) % 3])
        key = (min(a, b), max(a, b))
        if key in points:
            continue
        ei = mesh.edge_of.get(key)
        p = None if ei is None else edge_extreme_between(mesh, ei, a, b, sign)
        if p is None:
            # inside the face; or on a boundary edge whose extreme is not between the two nodes:
            # the surface on the line, on the edge's pcurve
            # where that is an iso-line itself (a seam), within the chord's sag of it otherwise
            s = d[r, i] / (d[r, i] - d_next[r, i])
            uv = mesh.tri_uv[t, i] + s * (mesh.tri_uv[t, (i + 1) % 3] - mesh.tri_uv[t, i])
            p = np.array(fe.point(float(uv[0]), float(uv[1])))
        points[key] = p
    return split_edges(mesh, points)
