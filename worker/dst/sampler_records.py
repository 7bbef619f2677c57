"""The records a ring sampler keeps: the pool its exact vertices live in (with the plane, face and
(u, v) each was solved on), its statistics, and the result of a share of its loops sampled
elsewhere (``RingSampler.sample_share``)."""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np


class VertexPool:
    """Output vertices in world millimetres; ``plane`` is the plane index of ring vertices, else -1.

    A growable numpy buffer: ``xyz`` and ``plane`` are views of the vertices added so far. A vertex
    solved on a face keeps that face and its (u, v) there (``uv_on``), where it was given.
    """

    def __init__(self, capacity: int = 4096):
        self._xyz = np.empty((capacity, 3), dtype=np.float64)
        self._plane = np.empty(capacity, dtype=np.int64)
        self._face = np.empty(capacity, dtype=np.int64)
        self._uv = np.empty((capacity, 2), dtype=np.float64)
        self.n = 0

    @property
    def xyz(self) -> np.ndarray:
        return self._xyz[: self.n]

    @property
    def plane(self) -> np.ndarray:
        return self._plane[: self.n]

    def __len__(self) -> int:
        return self.n

    def _reserve(self, extra: int) -> None:
        need = self.n + extra
        if need > len(self._plane):
            cap = max(need, 2 * len(self._plane))
            self._xyz = np.concatenate([self._xyz[: self.n], np.empty((cap - self.n, 3))])
            self._plane = np.concatenate([self._plane[: self.n], np.empty(cap - self.n, dtype=np.int64)])
            self._face = np.concatenate([self._face[: self.n], np.empty(cap - self.n, dtype=np.int64)])
            self._uv = np.concatenate([self._uv[: self.n], np.empty((cap - self.n, 2))])

    def add(
        self, p: tuple[float, float, float], plane: int, on: tuple[int, float, float] | None = None
    ) -> int:
        """Add a vertex; ``on``: the face it was solved on and its (u, v) there, where known."""
        self._reserve(1)
        self._xyz[self.n] = p
        self._plane[self.n] = plane
        self._face[self.n] = -1 if on is None else on[0]
        if on is not None:
            self._uv[self.n] = on[1:]
        self.n += 1
        return self.n - 1

    def extend(
        self,
        xy: np.ndarray,
        z: np.ndarray,
        plane: np.ndarray,
        face: np.ndarray | None = None,
        uv: np.ndarray | None = None,
    ) -> np.ndarray:
        """Add ring vertices (x, y) at heights ``z`` on planes ``plane``; returns their ids. ``face``
        and ``uv``: the face each was solved on and its (u, v) there (face -1 or (u, v) NaN: not
        known)."""
        k = len(xy)
        self._reserve(k)
        n0 = self.n
        self._xyz[n0 : n0 + k, :2] = xy
        self._xyz[n0 : n0 + k, 2] = z
        self._plane[n0 : n0 + k] = plane
        if face is None or uv is None:
            self._face[n0 : n0 + k] = -1
        else:
            self._face[n0 : n0 + k] = np.where(np.isnan(uv).any(axis=1), -1, face)
            self._uv[n0 : n0 + k] = uv
        self.n += k
        return np.arange(n0, self.n, dtype=np.int64)

    @property
    def faces(self) -> np.ndarray:
        """(n,): the face each vertex was solved on, -1 where none is known."""
        return self._face[: self.n]

    @property
    def uvs(self) -> np.ndarray:
        """(n, 2): each vertex's (u, v) on ``faces`` (meaningless where that is -1)."""
        return self._uv[: self.n]

    def uv_on(self, face: int, v: int) -> tuple[float, float] | None:
        """Vertex ``v``'s (u, v) on ``face``, where it was solved there (else None)."""
        if v >= self.n or self._face[v] != face:
            return None
        return float(self._uv[v, 0]), float(self._uv[v, 1])


@dataclass
class SamplingStats:
    newton_solves: int = 0
    edge_roots: int = 0
    fallbacks: int = 0  # corner points solved on a face because the curve root failed
    tolerance_gaps: int = 0  # segments kept over budget because the B-rep is inconsistent there
    tangent_segments: int = 0  # segments kept over budget where the plane is tangent to the surface
    newton_failures: int = 0  # seeds with no exact point (dropped; see tangent_segments)
    outside_face_points: int = 0  # points beyond a face's trim (a nearly tangent edge), dropped
    pole_points: int = 0  # points Newton put past a pole of their face, solved on it (``_through_poles``)
    excursions: int = 0  # segments re-sampled along an excursion of the curve they skipped
    excursion_failures: int = 0  # segments suspected of skipping one that could not be traced
    corner_handovers: int = 0  # bridges to a corner sampled on the face beyond it (_corner_handovers)
    corner_handover_failures: int = 0  # ... that could not be sampled there (the bridge kept)
    spur_vertices: int = 0  # ring vertices dropped as tips of spurs onto a face's extension
    reordered_crossings: int = 0  # crossings put at the section point nearest them (see _solve_crossing)
    kink_corners: int = 0  # corners placed where a section crosses a C0 line inside a face
    deep_bends: int = 0  # segments split for turning through more than ~67 degrees (DEEP_BEND_REL)
    quarter_checks: int = 0  # segments also checked at their quarter points (see _quarter_sags)
    quarter_resolves: int = 0  # quarter points the seed path put past their segment, solved from its chord
    gap_samples: int = 0  # segments whose samples left much of their chord unseen, sampled in the gap
    halved_segments: int = 0  # segments kept as their two halves (see RingSampler._halves)
    inflection_checks: int = 0  # segments checked again for an inflection inside (inflected_segments)
    end_bend_checks: int = 0  # run end segments checked again for a bend at their corner (END_BEND_FACTOR)
    gap_ends: int = 0  # points added next to run ends off their face's curve (GAP_END_REL)
    trim_entry_points: int = 0  # points put where a section leaves or enters its face (_into_trims)
    unchecked_segments: int = 0  # segments whose midpoint could not be placed (see _midpoints_off_the_path)
    unresolved_segments: int = 0  # segments still over budget after every round (``keep_unresolved``)
    off_trim_crossings: int = 0  # crossings whose root lay beyond their face's trim (see _drop_off_trim)
    off_trim_end_points: int = 0  # points next to a corner beyond their face's trim, dropped
    merged_crossings: int = 0  # crossings at the same point as their loop neighbour (_merge_coincident)
    repeat_samples: int = 0  # a run's samples at the same point as the one before or its end (dropped)
    max_gap_mm: float = 0.0  # the longest segment kept over budget (tolerance_gaps) ...
    max_gap_plane: int = -1  # ... its plane
    max_gap_at: str = ""  # ... its face and ends (x, y)

    def add(self, other: SamplingStats) -> None:
        """Accumulate another sampler's counts (the largest gap, with its place, is kept)."""
        for f in fields(self):
            if f.name == "max_gap_mm":
                if other.max_gap_mm > self.max_gap_mm:
                    self.max_gap_mm, self.max_gap_plane, self.max_gap_at = (
                        other.max_gap_mm,
                        other.max_gap_plane,
                        other.max_gap_at,
                    )
            elif f.name not in ("max_gap_plane", "max_gap_at"):
                setattr(self, f.name, getattr(self, f.name) + getattr(other, f.name))


def unresolved_summary(unresolved: list[tuple[int, float]]) -> tuple[list[int], int, float]:
    """Of segments kept over budget after the refinement's last round (``RingSampler.unresolved``:
    (plane, length) each, not empty): their planes in order, and the plane and length of the
    longest."""
    j, longest = max(unresolved, key=lambda s: s[1])
    return sorted({p for p, _ in unresolved}), j, longest


@dataclass
class SampledShare:
    """Free loops sampled by a sampler of their own (``RingSampler.sample_share``), as another
    sampler of the same solid takes them in (``RingSampler.adopt``): its vertices, its rings as ids
    into them, and what the sampler keeps of them for the rings and checks that come after."""

    rings: dict[int, list[int]]
    xyz: np.ndarray  # (n, 3) every vertex the share's sampler added, in order
    plane: np.ndarray  # (n,)
    face: np.ndarray  # (n,) the face each was solved on (-1: none known), and its (u, v) there
    uv: np.ndarray  # (n, 2)
    stats: SamplingStats
    gaps: list[tuple]
    unresolved: list[tuple[int, float]]
    corner_vids: set[int]
    gap_vids: set[int]
    node_vid: dict[int, int]
    cross_vid: dict[int, int]
