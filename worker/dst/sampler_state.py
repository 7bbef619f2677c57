"""What ``RingSampler``'s mixins share: the sampler's state, as ``RingSampler.__init__`` sets it
(declared here for the type checker and the reader: these annotations assign nothing), and the
methods one mixin calls on another (declared only for the type checker; ``RingSampler``'s method
resolution never reaches this class for them)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from scipy.spatial import cKDTree

    from worker.dst.runs import Run
    from worker.dst.sampler_records import SamplingStats, VertexPool
    from worker.dst.sections import SectionTopology
    from worker.dst.topomesh import TopoMesh


class SamplerState:
    """The state of a ``RingSampler`` (see its ``__init__`` for each field's meaning)."""

    mesh: TopoMesh
    topo: SectionTopology
    pool: VertexPool
    seg_len: float
    chord: float
    halving: bool
    gap_ends: bool
    exact_trim: bool
    keep_unresolved: bool
    unresolved: list[tuple[int, float]]
    trace_reach: float
    keep_crossings: bool
    stats: SamplingStats
    node_vid: dict[int, int]
    cross_vid: dict[int, int]
    off_trim: set[int]
    subdiv: dict[int, list[int]]
    edge_subdiv: dict[tuple[int, int], list[int]]
    corner_vids: set[int]
    gap_vids: set[int]
    bridge_vids: set[int]
    tri_uv_scale: np.ndarray
    _on_brep_edge: np.ndarray
    _edge_param: dict[tuple[int, int], float]
    _pred: np.ndarray | None
    _solving: set[int]
    _gaps: list[tuple]
    _gap_keys: tuple
    _kinks: dict[int, tuple[np.ndarray, np.ndarray]]
    _ads: list[Any]  # each face's OCCT surface adaptor
    _evals: list[Any]  # each face's vectorised evaluator (``FaceEval.batch``), or None
    _analytic: np.ndarray
    _uv_box: np.ndarray
    _box_checked: np.ndarray
    _period: np.ndarray
    _surface_box: np.ndarray
    _face_nodes: dict[int, tuple[cKDTree, np.ndarray] | None]
    _trim_memo: dict[tuple[int, int], bool]
    _chord_end_uv: dict[tuple[int, bytes], tuple[float, float]]

    if TYPE_CHECKING:

        def crossing(self, c: int) -> int: ...

        def _sample_runs(self, runs: list[Run]) -> list[list[int]]: ...

        def _into_trims(
            self, jobs: Sequence[tuple[int, float, float, np.ndarray, np.ndarray, np.ndarray, np.ndarray]]
        ) -> list[tuple[np.ndarray, np.ndarray] | None]: ...

        def _d1(
            self, fa: np.ndarray, ua: np.ndarray, va: np.ndarray, ads, p, du, dv, derivatives: bool = True
        ) -> np.ndarray: ...

        def _newton(
            self, fidx: np.ndarray, u: np.ndarray, v: np.ndarray, zc, max_step: np.ndarray
        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]: ...
