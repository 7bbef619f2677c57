"""Exact ring vertices: every section loop sampled under the segment-length and chord-error budget.

Two kinds of loops (see ``sections``):

- *free* loops (an annulus component on both sides) are re-sampled from scratch: corners of the
  section (where it crosses a B-rep edge, or meets a mesh node lying on the plane) are kept; between
  two corners the section runs inside one face, and points are placed at equal arc length along the
  topology-mesh path, then moved onto the exact level set ``z(u, v) = plane`` by Newton in that face's
  parameter space;
- *pinned* loops (a topology-mesh cap or branching component on a side) keep every crossing of a
  topology-mesh edge, each solved exactly (Brent along the edge), because the kept pieces are built
  on them.

In both, each segment is then checked against the exact curve: the curve point halfway along the
segment (Newton again) must lie within ``chord_error`` of the chord, and the chord must be no longer
than ``segment_length``; otherwise the segment is split and both halves are checked again. The
chord test at the middle is exact for circles and, for other smooth curves, measures the sagitta
to second order in the segment length.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from worker.dst.constants import MAX_SUBDIVISION, MIN_LOOP_VERTICES, SEGMENT_FILL
from worker.dst.errors import TessellationError
from worker.dst.exact import ExactFailure
from worker.dst.sections import SectionTopology
from worker.dst.topomesh import TopoMesh

MAX_REFINE_DEPTH = 24  # halving a segment 24 times takes 1 m down to 60 nm: a curve still failing is broken


@dataclass
class VertexPool:
    """Output vertices in world millimetres; ``plane`` is the plane index of ring vertices, else -1."""

    xyz: list[tuple[float, float, float]] = field(default_factory=list)
    plane: list[int] = field(default_factory=list)

    def add(self, p: tuple[float, float, float], plane: int) -> int:
        self.xyz.append(p)
        self.plane.append(plane)
        return len(self.xyz) - 1


@dataclass
class SamplingStats:
    newton_solves: int = 0
    edge_roots: int = 0
    fallbacks: int = 0  # corner points that had to be solved on a face because the curve root failed


class RingSampler:
    """Computes and caches exact ring vertices for one solid."""

    def __init__(
        self,
        mesh: TopoMesh,
        topo: SectionTopology,
        pool: VertexPool,
        *,
        segment_length: float,
        chord_error: float,
    ):
        self.mesh, self.topo, self.pool = mesh, topo, pool
        self.seg_len = segment_length
        self.chord = chord_error
        self.stats = SamplingStats()
        self.node_vid: dict[int, int] = {}
        self.cross_vid: dict[int, int] = {}
        self.subdiv: dict[int, list[int]] = {}  # start crossing of a pinned segment -> inner vertex ids
        self._edge_param: dict[tuple[int, int], float] = {}
        # (u, v) scale of each triangle: Newton's trust region and the size of a "local" step
        uv = mesh.tri_uv
        self.tri_uv_scale = np.max(np.linalg.norm(uv - np.roll(uv, 1, axis=1), axis=2), axis=1) + 1e-12
        self.tri_corner_edge = {}

    # --- vertices shared with the kept topology-mesh pieces -------------------------------------------
    def node(self, n: int) -> int:
        vid = self.node_vid.get(n)
        if vid is None:
            p = self.mesh.xyz[n]
            z = float(self.topo.z[n])
            plane = int(self.topo.slab[n]) - 1
            on_plane = plane >= 0 and self.topo.planes[plane] == z
            vid = self.pool.add((float(p[0]), float(p[1]), z), plane if on_plane else -1)
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
            vid = self.pool.add(self._solve_crossing(c, float(topo.planes[j])), j)
        self.cross_vid[c] = vid
        return vid

    def _solve_crossing(self, c: int, zc: float) -> tuple[float, float, float]:
        topo, mesh = self.topo, self.mesh
        e = int(topo.cross_edge[c])
        a, b = (int(x) for x in topo.edges[e])
        brep_edge = mesh.edge_of.get((a, b))
        if brep_edge is not None:
            try:
                self.stats.edge_roots += 1
                return self._root_on_brep_edge(brep_edge, a, b, zc)
            except ExactFailure:
                self.stats.fallbacks += 1
        t = int(topo.edge_tris[e, 0])
        ka, kb = self._corners(t, a, b)
        ua, va = mesh.tri_uv[t, ka]
        ub, vb = mesh.tri_uv[t, kb]
        x, y, z, _, _ = mesh.faces[int(mesh.tri_face[t])].root_on_uv_segment(ua, va, ub, vb, zc)
        return x, y, zc

    def _root_on_brep_edge(self, ei: int, a: int, b: int, zc: float) -> tuple[float, float, float]:
        ev = self.mesh.edges[ei]
        sa, sb = self._param(ei, a), self._param(ei, b)
        span = ev.s1 - ev.s0
        if abs(sa - sb) > 0.5 * span:
            # A node at the closing vertex of a closed curve projects to either end: take the end
            # on the side of the other node.
            if abs(sa - ev.s0) < abs(sa - ev.s1):
                sa = ev.s1 if sb > 0.5 * (ev.s0 + ev.s1) else sa
            if abs(sb - ev.s0) < abs(sb - ev.s1):
                sb = ev.s1 if sa > 0.5 * (ev.s0 + ev.s1) else sb
        x, y, _ = ev.root(min(sa, sb), max(sa, sb), zc)
        return x, y, zc

    def _param(self, ei: int, node: int) -> float:
        key = (ei, node)
        s = self._edge_param.get(key)
        if s is None:
            s = self.mesh.edges[ei].parameter_of(tuple(self.mesh.xyz[node]))
            self._edge_param[key] = s
        return s

    def _corners(self, t: int, a: int, b: int) -> tuple[int, int]:
        row = self.mesh.tris[t].tolist()
        return row.index(a), row.index(b)

    # --- approximate geometry of a crossing inside one triangle ---------------------------------------
    def _approx(self, c: int, t: int) -> tuple[np.ndarray, np.ndarray]:
        """(xyz, uv) of crossing ``c`` by linear interpolation along its edge inside triangle ``t``."""
        topo, mesh = self.topo, self.mesh
        e = int(topo.cross_edge[c])
        a, b = (int(x) for x in topo.edges[e])
        if topo.z[a] > topo.z[b]:
            a, b = b, a
        zc = topo.planes[int(topo.cross_plane[c])]
        za, zb = topo.z[a], topo.z[b]
        s = (zc - za) / (zb - za)
        ka, kb = self._corners(t, a, b)
        xyz = mesh.xyz[a] + s * (mesh.xyz[b] - mesh.xyz[a])
        uv = mesh.tri_uv[t, ka] + s * (mesh.tri_uv[t, kb] - mesh.tri_uv[t, ka])
        return xyz, uv

    def _is_corner(self, c: int) -> bool:
        topo = self.topo
        if topo.cross_node[c] >= 0:
            return True
        a, b = (int(x) for x in topo.edges[int(topo.cross_edge[c])])
        return (a, b) in self.mesh.edge_of

    # --- free loops: resample between corners -----------------------------------------------------------
    def free_loop(self, li: int) -> list[int]:
        j, cross = self.topo.loops[li]
        zc = float(self.topo.planes[j])
        cl = cross.tolist()
        n = len(cl)
        tris_ = [int(self.topo.seg_tri[c]) for c in cl]
        faces_ = [int(self.mesh.tri_face[t]) for t in tris_]
        corner = [self._is_corner(cl[i]) or faces_[i] != faces_[i - 1] for i in range(n)]
        starts = [i for i in range(n) if corner[i]] or [0]
        out: list[int] = []
        for r, i0 in enumerate(starts):
            i1 = starts[(r + 1) % len(starts)]
            count = (i1 - i0) % n or n
            out.extend(self._sample_run(cl, tris_, i0, count, j, zc, faces_[i0]))
        if len(out) < MIN_LOOP_VERTICES:
            # A tiny loop (a dome just below its top): sample it as a whole with three points.
            out = self._sample_run(cl, tris_, starts[0], n, j, zc, faces_[starts[0]], min_segments=3)
        return _dedupe_cyclic(out, self.pool)

    def _sample_run(
        self, cl, tris_, i0: int, count: int, j: int, zc: float, face: int, min_segments: int = 1
    ) -> list[int]:
        """Vertices of the run from crossing ``cl[i0]`` over ``count`` segments (start included, end not)."""
        n = len(cl)
        pts = np.empty((count + 1, 3))
        uvs = np.empty((count + 1, 2))
        scale = 0.0
        for k in range(count):
            i = (i0 + k) % n
            t = tris_[i]
            pts[k], uvs[k] = self._approx(cl[i], t)
            if k == count - 1:
                pts[k + 1], uvs[k + 1] = self._approx(cl[(i + 1) % n], t)
            scale = max(scale, float(self.tri_uv_scale[t]))
        start_vid = self.crossing(cl[i0])
        end_vid = self.crossing(cl[(i0 + count) % n])
        pts[0] = self.pool.xyz[start_vid]
        pts[-1] = self.pool.xyz[end_vid]
        s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))])
        run = _Run(self, face, zc, j, s, uvs, 2.0 * scale)
        n_seg = max(min_segments, math.ceil(s[-1] / (self.seg_len * SEGMENT_FILL)))
        seeds = [(0.0, start_vid)]
        for k in range(1, n_seg):
            sk = s[-1] * k / n_seg
            seeds.append((sk, run.solve(sk)))
        seeds.append((float(s[-1]), end_vid))
        refined = run.refine(seeds)
        return [vid for _, vid in refined[:-1]]

    # --- pinned loops: every crossing, plus points where a segment breaks the budget -----------------
    def pinned_loop(self, li: int) -> list[int]:
        j, cross = self.topo.loops[li]
        zc = float(self.topo.planes[j])
        cl = cross.tolist()
        out: list[int] = []
        for i, c in enumerate(cl):
            out.append(self.crossing(c))
            out.extend(self.pinned_segment(c, cl[(i + 1) % len(cl)], j, zc))
        return out

    def pinned_segment(self, c: int, c_next: int, j: int, zc: float) -> list[int]:
        """Inner vertices of the segment from crossing ``c`` to ``c_next`` (cached by ``c``)."""
        got = self.subdiv.get(c)
        if got is not None:
            return got
        t = int(self.topo.seg_tri[c])
        va, vb = self.crossing(c), self.crossing(c_next)
        inner: list[int] = []
        if va != vb:
            _, uva = self._approx(c, t) if self.topo.cross_node[c] < 0 else self._node_uv(c, t)
            _, uvb = self._approx(c_next, t) if self.topo.cross_node[c_next] < 0 else self._node_uv(c_next, t)
            pa, pb = np.array(self.pool.xyz[va]), np.array(self.pool.xyz[vb])
            d = float(np.linalg.norm(pb - pa))
            run = _Run(
                self,
                int(self.mesh.tri_face[t]),
                zc,
                j,
                np.array([0.0, d]),
                np.stack([uva, uvb]),
                2.0 * float(self.tri_uv_scale[t]),
            )
            refined = run.refine([(0.0, va), (d, vb)])
            inner = [vid for _, vid in refined[1:-1]]
        self.subdiv[c] = inner
        return inner

    def _node_uv(self, c: int, t: int) -> tuple[np.ndarray, np.ndarray]:
        node = int(self.topo.cross_node[c])
        k = self.mesh.tris[t].tolist().index(node)
        return self.mesh.xyz[node], self.mesh.tri_uv[t, k]


class _Run:
    """A piece of a section curve inside one face, parametrised by arc length ``s`` along a seed path."""

    def __init__(self, sampler: RingSampler, face: int, zc: float, plane: int, s, uvs, max_step: float):
        self.sp = sampler
        self.face = sampler.mesh.faces[face]
        self.zc, self.plane = zc, plane
        self.s, self.uvs = s, uvs
        self.max_step = max_step

    def _solve_xyz(self, sk: float) -> tuple[float, float, float]:
        u = float(np.interp(sk, self.s, self.uvs[:, 0]))
        v = float(np.interp(sk, self.s, self.uvs[:, 1]))
        self.sp.stats.newton_solves += 1
        try:
            x, y, _, _, _ = self.face.level_point(u, v, self.zc, self.max_step)
        except ExactFailure as exc:
            raise TessellationError(f"no exact section point near z={self.zc:.4f} mm: {exc}") from None
        return x, y, self.zc

    def solve(self, sk: float) -> int:
        return self.sp.pool.add(self._solve_xyz(sk), self.plane)

    def refine(self, pts: list[tuple[float, int]]) -> list[tuple[float, int]]:
        """Split segments until each is within the length and chord budgets (checked at midpoints)."""
        pool = self.sp.pool
        L, e = self.sp.seg_len, self.sp.chord
        out = [pts[0]]
        stack = [(pts[i], pts[i + 1], 0) for i in range(len(pts) - 2, -1, -1)]
        while stack:
            (sa, va), (sb, vb), depth = stack.pop()
            a, b = np.array(pool.xyz[va]), np.array(pool.xyz[vb])
            length = float(np.linalg.norm(b - a))
            mid = np.array(self._solve_xyz(0.5 * (sa + sb)))
            sag = _point_segment_distance(mid, a, b)
            if (length <= L and sag <= e) or length < 1e-9:
                out.append((sb, vb))
                continue
            if depth >= MAX_REFINE_DEPTH:
                raise TessellationError(
                    f"section curve at z={self.zc:.4f} mm cannot meet the chord budget (sag {sag:.3g} mm)"
                )
            m = max(2, math.ceil(length / (L * SEGMENT_FILL)), math.ceil(math.sqrt(sag / e) * 1.05))
            m = min(m, MAX_SUBDIVISION)
            new = [(sa, va)] + [(sa + (sb - sa) * i / m, self.solve(sa + (sb - sa) * i / m)) for i in range(1, m)]
            new.append((sb, vb))
            for i in range(len(new) - 2, -1, -1):
                stack.append((new[i], new[i + 1], depth + 1))
        return out


def _point_segment_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    ab = b - a
    denom = float(ab @ ab)
    t = 0.0 if denom == 0.0 else min(1.0, max(0.0, float((p - a) @ ab) / denom))
    return float(np.linalg.norm(p - (a + t * ab)))


def _dedupe_cyclic(vids: list[int], pool: VertexPool) -> list[int]:
    """Drop consecutive repeats (ids, or points closer than 1 nm) in a closed ring."""
    out: list[int] = []
    for v in vids:
        if out and (v == out[-1] or _close(pool.xyz[v], pool.xyz[out[-1]])):
            continue
        out.append(v)
    while len(out) > 1 and (out[0] == out[-1] or _close(pool.xyz[out[0]], pool.xyz[out[-1]])):
        out.pop()
    return out


def _close(p, q) -> bool:
    return abs(p[0] - q[0]) < 1e-9 and abs(p[1] - q[1]) < 1e-9 and abs(p[2] - q[2]) < 1e-9
