"""Assemble the DST mesh of one solid from its rings and slab components.

- An annulus component (one ring below, one above, Euler characteristic 0) becomes a *zipper*: a
  strip of triangles each with two vertices on one ring and one on the other, advancing along both
  rings by normalised arc length from their nearest pair. Two triangles per ring vertex.
- Every other component keeps its topology-mesh pieces: each triangle clipped to the slab, its cut
  edges replaced by the exact ring vertices (crossings and the points that keep them within budget).
  A piece is triangulated as a fan from a node strictly inside the slab, or, when it has none, as a
  zipper between its lower and upper chain, so no triangle joins two vertices of one plane except
  along a ring edge.

Every vertex is an exact surface point (ring vertices exact on their plane), every triangle lies
between two consecutive planes, and the cut of the mesh by plane ``j`` is exactly its rings.
"""

from __future__ import annotations

import math

import numpy as np

from worker.dst.chords import distances_to_segments
from worker.dst.cuts import segment_pairs_near, side
from worker.dst.forked import TaskDied, TaskGroup, idle_cores
from worker.dst.meshops import repeated_corner, unique_ints
from worker.dst.sampler_records import VertexPool
from worker.dst.sampling import RingSampler
from worker.dst.sections import SectionTopology

# Free loops with fewer topology crossings than this are sampled in one share: ~20 ms of sampling
# or less each side, about what a helper's fork costs.
FREE_SPLIT_CROSSINGS = 4000


def tessellate_solid(sampler: RingSampler, *, helper: bool = True) -> tuple[np.ndarray, dict]:
    """(F, 3) triangles (vertex ids into ``sampler.pool``) of one solid, and counts for the report.
    ``helper``: half the free loops may be sampled in a forked helper (``free_rings``)."""
    topo: SectionTopology = sampler.topo
    annulus = topo.comp_is_annulus
    free = annulus[topo.loop_below] & annulus[topo.loop_above]
    rings = free_rings(sampler, np.flatnonzero(free), helper=helper)
    for li in np.flatnonzero(~free).tolist():
        rings[li] = sampler.pinned_loop(li)
    fans: dict[int, list[tuple[int, int, int]]] = {}  # cap component -> its fan
    for li in np.flatnonzero(~free).tolist():
        if fanned := _fanned_cap(sampler, li, rings[li]):
            rings[li], comp, fans[comp] = fanned

    strips = [np.empty((0, 3), dtype=np.int64)]
    for comp in np.flatnonzero(annulus).tolist():
        (lb,), (lt,) = topo.comp_bottom[comp], topo.comp_top[comp]
        strips.append(zipper(rings[lb], rings[lt], sampler.pool))
    out: list[tuple[int, int, int]] = []

    kept = ~annulus[topo.piece_comp] & ~np.isin(topo.piece_comp, list(fans))
    pieces = np.flatnonzero(kept)
    n_kept_pieces = len(pieces)
    if n_kept_pieces:
        tri_of = np.searchsorted(topo.piece_off, pieces, side="right") - 1
        slab_of = pieces - topo.piece_off[tri_of] + topo.tri_smin[tri_of]
        whole = topo.tri_smin[tri_of] == topo.tri_smax[tri_of]
        es = sampler.edge_subdiv
        for t in tri_of[whole].tolist():
            na, nb, nc = (int(n) for n in sampler.mesh.tris[t])
            if es and any((min(p, q), max(p, q)) in es for p, q in ((na, nb), (nb, nc), (nc, na))):
                out.extend(_piece_triangles(sampler, t, int(topo.tri_smin[t])))
                continue
            out.append((sampler.node(na), sampler.node(nb), sampler.node(nc)))
        for t, k in zip(tri_of[~whole].tolist(), slab_of[~whole].tolist(), strict=True):
            out.extend(_piece_triangles(sampler, t, k))
    for fan in fans.values():
        out.extend(fan)
    # A ring that degenerates to one point (a dome top exactly on a plane) makes zipper triangles with
    # a repeated corner. Such a triangle adds the edges a->b and b->a, which cancel: dropping it keeps
    # the mesh closed.
    sampler.settle_gaps(rings.values())
    tris = np.concatenate([*strips, np.asarray(out, dtype=np.int64).reshape(-1, 3)])
    tris = tris[~repeated_corner(tris)]
    stats = {
        "loops": len(topo.loops),
        "free_loops": int(free.sum()),
        "annulus_components": int(annulus.sum()),
        "kept_components": int((~annulus).sum()),
        "kept_pieces": n_kept_pieces,
        "fanned_caps": len(fans),
    }
    return tris, stats


def free_rings(sampler: RingSampler, ids: np.ndarray, *, helper: bool = True) -> dict[int, list[int]]:
    """Rings of the free loops ``ids``: most of the build's sampling. With enough of them
    (``FREE_SPLIT_CROSSINGS``), in two shares of alternate planes, each sampled by a sampler of its
    own; the second in a forked helper where ``helper`` and a core is idle, at the same time as this
    process samples the first, else here after it. The rings are the same either way (the shares,
    and the order in which this sampler takes them in, do not depend on where they ran). A helper
    that dies (killed, crashed) has its share sampled here, as a build without it would."""
    topo = sampler.topo
    if sum(len(topo.loops[li][1]) for li in ids.tolist()) < FREE_SPLIT_CROSSINGS:
        return sampler.free_loops(ids.tolist())
    plane = np.array([topo.loops[li][0] for li in ids.tolist()], dtype=np.int64)
    first, second = ids[plane % 2 == 0].tolist(), ids[plane % 2 == 1].tolist()
    with TaskGroup(forked=helper and idle_cores() > 0, limit=1) as tasks:
        later = tasks.submit(sampler.sample_share, second)
        rings = sampler.free_loops(first)
        try:
            share = later.result()
        except TaskDied:
            share = sampler.sample_share(second)
    rings.update(sampler.adopt(share))
    return rings


def _fanned_cap(
    sampler: RingSampler, li: int, ring: list[int]
) -> tuple[list[int], int, list[tuple[int, int, int]]] | None:
    """Where pinned loop ``li``'s ring crosses itself and the component it pins is a disk cap
    bounded by that loop alone (the other side a zipper): the loop traced on the exact curve
    (``RingSampler.traced_loop``) and the cap as a fan to it from its node farthest from the plane.
    Returns (ring, cap component, fan triangles), or None where any of that does not hold or the
    fan would fold (its apex not seeing the whole ring from inside).

    A cap this small against the topology mesh has crossings far inside the exact curve, whose
    exact points can come out of order: trj6_k1-al-214 turned (114.0, 17.7, 173.1) at z = 16.1,
    a 0.58 mm bowl whose crossings lay up to 0.25 mm inside it, had a ring folded onto half the
    curve (0.37 mm off the other half)."""
    topo = sampler.topo
    below, above = int(topo.loop_below[li]), int(topo.loop_above[li])
    if topo.comp_is_annulus[below] == topo.comp_is_annulus[above]:
        return None
    cap_below = not topo.comp_is_annulus[below]
    cap = below if cap_below else above
    if topo.comp_bottom[cap] + topo.comp_top[cap] != [li] or topo.comp_euler[cap] != 1:
        return None
    pool = sampler.pool
    if not _crosses_itself(pool.xyz[ring, :2]):
        return None
    traced = sampler.traced_loop(li)
    if traced is None or len(traced) < 3 or _crosses_itself(pool.xyz[traced, :2]):
        return None
    j, cross = topo.loops[li]
    # oriented as the topology loop (material on the left), as the zipper on the other side takes it
    if np.sign(_signed_area(pool.xyz[traced, :2])) != np.sign(_signed_area(topo.cross_xyz[cross, :2])):
        return None
    pieces = np.flatnonzero(topo.piece_comp == cap)
    tri_of = np.searchsorted(topo.piece_off, pieces, side="right") - 1
    nodes = unique_ints(sampler.mesh.tris[tri_of])
    slab = j if cap_below else j + 1
    nodes = nodes[topo.slab[nodes] == slab]
    zc = float(topo.planes[j])
    height = (zc - topo.z[nodes]) if cap_below else (topo.z[nodes] - zc)
    nodes, height = nodes[height > 0], height[height > 0]
    # the cap's nodes off the plane are exact surface points on its side of it: inside its loop, or
    # (lying all but on it) within the budget of the ring (a trace that went round another loop of
    # the face would not hold them)
    if not len(nodes):
        return None
    q, p = sampler.mesh.xyz[nodes, :2], pool.xyz[traced, :2]
    out = ~_inside(q, p)
    if (
        out.any()
        and distances_to_segments(q[out], np.stack([p, np.roll(p, -1, axis=0)], axis=1)).max() > sampler.chord
    ):
        return None
    apex = sampler.node(int(nodes[np.argmax(height)]))
    r = np.asarray(traced)
    # the zipper takes the ring above a cap forward (below one, backward): the fan the other way
    a, b = (np.roll(r, -1), r) if cap_below else (r, np.roll(r, -1))
    fan = np.column_stack([np.full(len(r), apex), a, b])
    corners = pool.xyz[fan][..., :2]
    e1, e2 = corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]
    area = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    if not ((area > 0).all() or (area < 0).all()):
        return None
    return traced, cap, [tuple(t) for t in fan.tolist()]


def _inside(q: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Whether each point of ``q`` (m, 2) lies inside the closed polyline ``p`` (k, 2) (even-odd
    rule: crossings of a ray towards +x)."""
    a, b = p[None, :, :], np.roll(p, -1, axis=0)[None, :, :]
    x, y = q[:, None, 0], q[:, None, 1]
    spans = (a[..., 1] > y) != (b[..., 1] > y)
    with np.errstate(divide="ignore", invalid="ignore"):
        at = a[..., 0] + (y - a[..., 1]) * (b[..., 0] - a[..., 0]) / (b[..., 1] - a[..., 1])
    return (spans & (x < at)).sum(axis=1) % 2 == 1


def _signed_area(p: np.ndarray) -> float:
    q = np.roll(p, -1, axis=0)
    return 0.5 * float((p[:, 0] * q[:, 1] - q[:, 0] * p[:, 1]).sum())


def _crosses_itself(p: np.ndarray) -> bool:
    """Whether the closed polyline ``p`` (k, 2) has two non-adjacent segments that cross or touch
    (collinear ones overlapping): of the pairs ``cuts.segment_pairs_near`` finds (every pair
    that meets is among them), unlike ``cuts.self_crossings`` touching ones too."""
    k = len(p)
    if k < 4:
        return False
    a, b = p, np.roll(p, -1, axis=0)
    i, m = segment_pairs_near(a, b, np.zeros(k, dtype=np.int64))
    keep = (m - i > 1) & ~((i == 0) & (m == k - 1))  # not neighbours (the closing segment and the first)
    i, m = i[keep], m[keep]
    d1, d2 = side(a[i], b[i], a[m]), side(a[i], b[i], b[m])
    d3, d4 = side(a[m], b[m], a[i]), side(a[m], b[m], b[i])
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    boxes = ((lo[i] <= hi[m]) & (lo[m] <= hi[i])).all(axis=1)  # (collinear ones must overlap)
    return bool(((d1 * d2 <= 0) & (d3 * d4 <= 0) & boxes).any())


def zipper(bottom: list[int], top: list[int], pool: VertexPool) -> np.ndarray:
    """Triangulate the strip between two closed rings oriented alike (material on the left)."""
    pb = pool.xyz[bottom]
    pt = pool.xyz[top]
    j0 = int(np.argmin(np.sum((pt[:, :2] - pb[0, :2]) ** 2, axis=1)))
    top = top[j0:] + top[:j0]
    pt = np.roll(pt, -j0, axis=0)
    ub = _closed_arclength(pb)
    ut = _closed_arclength(pt)
    m, n = len(bottom), len(top)
    # Advance on the ring whose next vertex comes first by normalised arc length (the bottom one on
    # a tie): a stable merge of both rings' arc lengths.
    is_top = np.concatenate([np.zeros(m, dtype=bool), np.ones(n, dtype=bool)])
    order = np.argsort(np.concatenate([ub[1:], ut[1:]]), kind="stable")
    step_top = is_top[order]
    i = np.cumsum(~step_top) - ~step_top  # bottom steps taken before each step
    j = np.cumsum(step_top) - step_top  # top steps taken before each step
    b, t = np.asarray(bottom), np.asarray(top)
    tris = np.where(
        step_top[:, None],
        np.stack([b[i % m], t[(j + 1) % n], t[j % n]], axis=1),
        np.stack([b[i % m], b[(i + 1) % m], t[j % n]], axis=1),
    )
    return tris


def _closed_arclength(p: np.ndarray) -> np.ndarray:
    """(k + 1,) normalised cumulative length around a closed polyline of k points."""
    d = np.linalg.norm(np.diff(np.vstack([p, p[:1]]), axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(d)])
    return s / s[-1] if s[-1] > 0 else np.linspace(0.0, 1.0, len(s))


def _piece_triangles(sampler: RingSampler, t: int, k: int) -> list[tuple[int, int, int]]:
    """The part of topology triangle ``t`` inside slab ``k``, with exact ring vertices on its cuts."""
    topo, mesh = sampler.topo, sampler.mesh
    tri = mesh.tris[t].tolist()
    s = [int(topo.slab[n]) for n in tri]
    poly: list[tuple[int, str]] = []  # (vertex id, kind) with kind 'in' (node inside slab) or 'p<j>'
    cross_seq: list[int] = []  # crossing id at each poly position, or -1
    es = sampler.edge_subdiv
    for i in range(3):
        a, b = tri[i], tri[(i + 1) % 3]
        if s[i] == k:
            vid = sampler.node(a)
            on = int(sampler.pool.plane[vid])
            poly.append((vid, "in" if on < 0 else f"p{on}"))
            cross_seq.append(-1)
        sa, sb = s[i], s[(i + 1) % 3]
        if sa == sb:
            if s[i] == k and (min(a, b), max(a, b)) in es:
                # an edge lying in a plane, subdivided on its ring: the same points here
                inner = es[(min(a, b), max(a, b))]
                kind = poly[-1][1]
                for v in inner if a < b else inner[::-1]:
                    poly.append((v, kind))
                    cross_seq.append(-1)
            continue
        e = int(topo.tri_edges[t, i])
        if sa < sb:
            planes = [j for j in (k - 1, k) if sa <= j < sb]
        else:
            planes = [j for j in (k, k - 1) if sb <= j < sa]
        for j in planes:
            c = topo.crossing_id(e, j)
            poly.append((sampler.crossing(c), f"p{j}"))
            cross_seq.append(c)
    # Insert the exact points that subdivide each cut segment of this triangle.
    full: list[tuple[int, str]] = []
    n = len(poly)
    for i in range(n):
        full.append(poly[i])
        c0, c1 = cross_seq[i], cross_seq[(i + 1) % n]
        if c0 < 0 or c1 < 0 or topo.cross_plane[c0] != topo.cross_plane[c1]:
            continue
        j = int(topo.cross_plane[c0])
        if topo.succ[c0] == c1 and topo.seg_tri[c0] == t:
            inner = sampler.pinned_segment(c0)
        elif topo.succ[c1] == c0 and topo.seg_tri[c1] == t:
            inner = sampler.pinned_segment(c1)[::-1]
        else:
            continue
        full.extend((v, f"p{j}") for v in inner)
    # Drop repeated vertices (a crossing that is a node on the plane appears twice).
    ring: list[tuple[int, str]] = []
    for item in full:
        if not ring or ring[-1][0] != item[0]:
            ring.append(item)
    while len(ring) > 1 and ring[0][0] == ring[-1][0]:
        ring.pop()
    if len(ring) < 3:
        return []
    ids = [v for v, _ in ring]
    kinds = [kd for _, kd in ring]
    if _collapsed(sampler.pool, ids):
        # The piece has collapsed onto a path walked there and back (a triangle touching a plane
        # along an edge): its boundary edges cancel, so it contributes nothing.
        return []
    if "in" in kinds:
        apex = kinds.index("in")
        m = len(ids)
        return [(ids[apex], ids[(apex + q) % m], ids[(apex + q + 1) % m]) for q in range(1, m - 1)]
    if len(set(kinds)) == 1:
        return _centroid_fan(sampler.pool, ids, int(kinds[0][1:]))
    return _two_chain_zipper(ids, kinds)


def _centroid_fan(pool: VertexPool, ids: list[int], plane: int) -> list[tuple[int, int, int]]:
    """Triangulate a convex polygon lying in one plane (a piece of a flat face on that plane).

    Its edges may carry collinear subdivision points, so a fan from one of its vertices could make
    zero-area triangles; the centroid is strictly inside and, the face being planar, on the face.
    """
    if len(ids) == 3:
        return [(ids[0], ids[1], ids[2])]
    c = pool.xyz[ids].mean(axis=0)
    cv = pool.add((float(c[0]), float(c[1]), float(c[2])), plane)
    return [(cv, ids[q], ids[(q + 1) % len(ids)]) for q in range(len(ids))]


def _collapsed(pool: VertexPool, ids: list[int]) -> bool:
    """True if the closed polygon has no area relative to its perimeter (a path walked there and back)."""
    # a handful of vertices: plain floats are several times faster than numpy here
    p = pool.xyz[ids].tolist()
    cx = cy = cz = perimeter = 0.0
    for (x0, y0, z0), (x1, y1, z1) in zip(p, p[1:] + p[:1], strict=True):
        cx += y0 * z1 - z0 * y1
        cy += z0 * x1 - x0 * z1
        cz += x0 * y1 - y0 * x1
        perimeter += math.sqrt((x1 - x0) ** 2 + (y1 - y0) ** 2 + (z1 - z0) ** 2)
    area = 0.5 * math.sqrt(cx * cx + cy * cy + cz * cz)
    return area <= 1e-12 * perimeter**2


def _two_chain_zipper(ids: list[int], kinds: list[str]) -> list[tuple[int, int, int]]:
    """Triangulate a polygon whose vertices lie on two planes without in-plane diagonals."""
    m = len(ids)
    # Rotate so the polygon starts where the first chain starts.
    start = next(q for q in range(m) if kinds[q] != kinds[q - 1])
    ids = ids[start:] + ids[:start]
    kinds = kinds[start:] + kinds[:start]
    split = next(q for q in range(m) if kinds[q] != kinds[0])
    chain_a = ids[:split]  # walked forward
    chain_b = ids[split:][::-1]  # walked backwards, so both run the same way
    tris = []
    i = j = 0
    na, nb = len(chain_a) - 1, len(chain_b) - 1
    while i < na or j < nb:
        if i < na and (j >= nb or (i + 1) / max(na, 1) <= (j + 1) / max(nb, 1)):
            tris.append((chain_a[i], chain_a[i + 1], chain_b[j]))
            i += 1
        else:
            tris.append((chain_a[i], chain_b[j + 1], chain_b[j]))
            j += 1
    return tris
