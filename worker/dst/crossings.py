"""Single exact vertices of the section: a topology-mesh node lying on the plane, and where the
section crosses a topology edge, solved exactly on the B-rep edge it lies on (Brent) or on its face
(Newton from the crossing), in the order the loop passes them (``Crossings``, a mixin of
``RingSampler``: the topology, faces, vertex pool and statistics are the sampler's).
"""

from __future__ import annotations

import math

import numpy as np

from worker.dst.chords import distances_to_segments
from worker.dst.errors import TessellationError
from worker.dst.exact import ExactFailure, FaceEval, WalkPassed
from worker.dst.face_limits import TRIM_TOL_MM
from worker.dst.runs import SUSPECT_DEFLECTIONS
from worker.dst.sampler_state import SamplerState

# steps (in topology deflections) of a walk along a section curve: short enough that the pull back
# onto the plane cannot reach another branch of the section
WALK_STEP_DEFLECTIONS = 5.0


class Crossings(SamplerState):
    """``RingSampler``'s exact vertices at topology nodes and crossings (a mixin)."""

    # --- single exact vertices ---------------------------------------------------------------------
    def node(self, n: int) -> int:
        vid = self.node_vid.get(n)
        if vid is None:
            p = self.mesh.xyz[n]
            vid = self.pool.add(
                (float(p[0]), float(p[1]), float(self.topo.z[n])), int(self.topo.node_plane[n])
            )
            self.node_vid[n] = vid
        return vid

    def crossing(self, c: int) -> int:
        """Vertex id of crossing ``c``, solved exactly on first use."""
        vid = self.cross_vid.get(c)
        if vid is not None:
            return vid
        topo = self.topo
        node = int(topo.cross_node[c])
        if node >= 0:
            vid = self.node(node)
        else:
            j = int(topo.cross_plane[c])
            xyz, on = self._solve_crossing(c, float(topo.planes[j]))
            vid = self.pool.add(xyz, j, on)
        self.cross_vid[c] = vid
        return vid

    def _solve_crossing(
        self, c: int, zc: float
    ) -> tuple[tuple[float, float, float], tuple[int, float, float] | None]:
        """The exact point of crossing ``c`` at height ``zc``, and where it is the root found on a
        face: (that face, its (u, v) there), else None (a root on a B-rep edge, a walked or a
        fallback point)."""
        topo, mesh = self.topo, self.mesh
        e = int(topo.cross_edge[c])
        a, b = (int(x) for x in topo.edges[e])
        brep_edge = mesh.edge_of.get((a, b))
        if brep_edge is not None:
            try:
                self.stats.edge_roots += 1
                return self._root_on_brep_edge(brep_edge, a, b, zc), None
            except ExactFailure:
                self.stats.fallbacks += 1
        t = int(topo.edge_tris[e, 0])
        row = mesh.tris[t].tolist()
        ua, va = mesh.tri_uv[t, row.index(a)]
        ub, vb = mesh.tri_uv[t, row.index(b)]
        face = int(mesh.tri_face[t])
        try:
            x, y, _, ur, vr = self._root_on_face(face, a, b, (ua, va), (ub, vb), zc)
            # Between nodes on the face's boundary, the root can lie beyond the trim, where the
            # face is narrower than its topology triangle (a sliver's tip): not on the B-rep.
            if (self._on_brep_edge[a] or self._on_brep_edge[b]) and not mesh.faces[face].contains(
                ur, vr, tol=TRIM_TOL_MM
            ):
                self.off_trim.add(c)
            near = topo.cross_xyz[c]
            d_root = math.hypot(x - near[0], y - near[1])
            if d_root > SUSPECT_DEFLECTIONS * mesh.deflection:
                # Along an edge that runs nearly level over the surface (a long triangle across a
                # ridge or a valley just off the plane), the surface's root can lie far from the
                # edge's crossing, out of order with its neighbours along the section (a ring that
                # doubles back). The point of the root's own section curve nearest the crossing keeps
                # the order: walked to along that curve, since Newton from the crossing can land on
                # the other side of a ridge a few micrometres above the plane (a gap narrower than
                # the crossing's distance from either side).
                walked = self._reordered(c, face, ur, vr, zc, near, d_root)
                if walked is not None:
                    x, y = walked
                    self.off_trim.discard(c)
                    self.stats.reordered_crossings += 1
                    return (x, y, zc), None
            return (x, y, zc), (face, ur, vr)
        except ExactFailure:
            # The surface at a node's (u, v) can differ from the node (an edge point) by the file's
            # tolerance, so a plane that close to a node is not bracketed: Newton from the seed.
            self.stats.fallbacks += 1
            p = self._newton_from_crossing(t, a, b, (ua, va), (ub, vb), zc)
            if p is None:
                raise TessellationError(
                    f"no exact point of face {face + 1} at z={zc:.4f} mm near a topology edge"
                ) from None
            x, y, _ = p
        return (x, y, zc), None

    def _reordered(
        self, c: int, face: int, ur: float, vr: float, zc: float, near: np.ndarray, d_root: float
    ) -> tuple[float, float] | None:
        """Where crossing ``c`` goes instead of its root at (``ur``, ``vr``) on ``face``, far from the
        crossing's own point ``near``: the point of the root's section curve nearest ``near``
        (walked to), or None to keep the root (no such point inside the face's trim, or none
        nearer). A walk that passes a neighbouring crossing's point along the loop is taken only if
        the root does not lie on the curve between those neighbours (``_between_neighbours``): the
        root can be in order and ``near`` not (r103ec turned (35.3, -158.7, -40.5) at z = 52.5: the
        root at a tongue's tip, between its neighbours on either side of the tongue; the crossing
        inside the tongue, whose nearest point down one side lies past the next crossing: the ring
        crossed the tongue four times), or the root out of order beyond a neighbour (a long edge
        along a level ridge line: ec_soapbox-A turned (0, 35, 0), where the walk back passes it)."""
        ev = self.mesh.faces[face]
        step = WALK_STEP_DEFLECTIONS * self.mesh.deflection
        target = (float(near[0]), float(near[1]))
        max_steps = int(d_root / step) + 100
        pred, succ = self._neighbour_points(c)
        try:
            try:
                px, py, pu, pv = ev.walk_level(
                    ur, vr, zc, target, step=step, max_steps=max_steps, avoid=[q for q in (pred, succ) if q]
                )
            except WalkPassed:
                # (with a neighbour unknown, the order cannot be told: walked as before)
                if pred and succ and self._between_neighbours(ev, ur, vr, zc, pred, succ, step, d_root):
                    return None
                px, py, pu, pv = ev.walk_level(ur, vr, zc, target, step=step, max_steps=max_steps)
        except ExactFailure:
            return None
        if math.hypot(px - target[0], py - target[1]) < d_root and ev.contains(pu, pv, tol=TRIM_TOL_MM):
            return px, py
        return None

    def _between_neighbours(
        self,
        ev: FaceEval,
        ur: float,
        vr: float,
        zc: float,
        pred: tuple[float, float],
        succ: tuple[float, float],
        step: float,
        reach: float = 0.0,
    ) -> bool:
        """Whether the section point at (``ur``, ``vr``) of face ``ev`` lies on the section curve
        from ``pred`` to ``succ`` (x, y): a trace along it from one (in the loops' direction) to
        the other passes within a tenth of a step of it. False where the trace fails, or runs
        farther than 4 times the neighbours' distance and ``reach`` (the point's distance from its
        crossing) without arriving."""
        x, y = ev.point(ur, vr)[:2]
        try:
            u0, v0 = ev.uv_near((*pred, zc), (ur, vr))
            direction = ev.section_direction(*ev.uv_near((*succ, zc), (ur, vr)))
            if direction is None:
                return False
            longest = 4.0 * (math.hypot(succ[0] - pred[0], succ[1] - pred[1]) + reach) + step
            trace = ev.trace_level(u0, v0, zc, succ, direction, step=step, max_length=longest)
        except ExactFailure:
            return False
        path = np.array([pred, *(t[:2] for t in trace), succ], dtype=np.float64)
        seg = np.stack([path[:-1], path[1:]], axis=1)
        return bool(distances_to_segments(np.array([[x, y]]), seg).min() <= 0.1 * step)

    def _neighbour_points(self, c: int) -> tuple[tuple[float, float] | None, tuple[float, float] | None]:
        """The exact (x, y) of crossing ``c``'s neighbours along its loop (before it, after it), solved
        here if they are not yet (not while another crossing's neighbours are being solved: no
        chains along the loop); None for one without an exact point."""
        if self._pred is None:
            self._pred = np.empty_like(self.topo.succ)
            self._pred[self.topo.succ] = np.arange(len(self.topo.succ))
        nested = bool(self._solving)
        self._solving.add(c)
        try:
            out: list[tuple[float, float] | None] = []
            for q in (int(self._pred[c]), int(self.topo.succ[c])):
                vid = self.cross_vid.get(q)
                if vid is None and not nested and q != c:
                    try:
                        vid = self.crossing(q)
                    except TessellationError:
                        vid = None
                out.append(
                    None if vid is None else (float(self.pool.xyz[vid, 0]), float(self.pool.xyz[vid, 1]))
                )
            return out[0], out[1]
        finally:
            self._solving.discard(c)

    def _root_on_face(self, face: int, a: int, b: int, uva, uvb, zc: float) -> tuple[float, ...]:
        """``FaceEval.root_on_uv_segment`` of face ``face`` between nodes ``a`` and ``b`` at (u, v)
        ``uva`` and ``uvb``, or where those do not bracket the plane, between the (u, v) of the
        nodes' own positions: a node on a B-rep edge has the (u, v) of the edge's curve on the face,
        which can lie farther from the node (the edge's 3D curve) than the file's tolerance admits
        (``trj3_s1-al-214`` turned (78.4, 32.6, -18.9): 0.37 mm at an edge of tolerance 0.003 mm,
        the node 0.17 mm above the plane and the surface at its (u, v) 0.16 mm below it).
        Raises ExactFailure if neither brackets it."""
        fe = self.mesh.faces[face]
        try:
            return fe.root_on_uv_segment(uva[0], uva[1], uvb[0], uvb[1], zc)
        except ExactFailure:
            if not (self._on_brep_edge[a] or self._on_brep_edge[b]):
                raise
        own = [
            fe.uv_near(tuple(self.mesh.xyz[n]), tuple(uv)) if self._on_brep_edge[n] else tuple(uv)
            for n, uv in ((a, uva), (b, uvb))
        ]
        return fe.root_on_uv_segment(own[0][0], own[0][1], own[1][0], own[1][1], zc)

    def _newton_from_crossing(self, t: int, a: int, b: int, uva, uvb, zc: float) -> np.ndarray | None:
        """Newton (the smallest 3D move onto ``z = zc``) from where edge a-b of triangle ``t``
        crosses the plane, interpolated in (u, v): the point, or None if it fails."""
        mesh = self.mesh
        za, zb = mesh.xyz[a, 2], mesh.xyz[b, 2]
        frac = min(1.0, max(0.0, (zc - za) / (zb - za))) if zb != za else 0.5
        seed = np.asarray(uva, dtype=np.float64) + frac * np.subtract(uvb, uva)
        pts, ok, _ = self._newton(
            np.array([int(mesh.tri_face[t])]),
            seed[:1],
            seed[1:],
            zc,
            np.array([2.0 * self.tri_uv_scale[t]]),
        )
        return pts[0] if ok[0] else None

    def _root_on_brep_edge(self, ei: int, a: int, b: int, zc: float) -> tuple[float, float, float]:
        ev = self.mesh.edges[ei]
        sa, sb = self._param(ei, a), self._param(ei, b)
        if ev.closed and abs(sa - sb) > 0.5 * (ev.s1 - ev.s0):
            # A node at the closing vertex of a closed curve projects to either end: use the end on
            # the other node's side.
            mid = 0.5 * (ev.s0 + ev.s1)
            if min(abs(sa - ev.s0), abs(sa - ev.s1)) < min(abs(sb - ev.s0), abs(sb - ev.s1)):
                sa = ev.s1 if sb > mid else ev.s0
            else:
                sb = ev.s1 if sa > mid else ev.s0
        x, y, _ = ev.root(min(sa, sb), max(sa, sb), zc)
        return x, y, zc

    def _param(self, ei: int, node: int) -> float:
        key = (ei, node)
        s = self._edge_param.get(key)
        if s is None:
            s = self.mesh.edges[ei].parameter_of(tuple(self.mesh.xyz[node]))
            self._edge_param[key] = s
        return s
