"""The free loops sampled in two shares (``tessellate.free_rings``): the same mesh whether the second
share runs in a forked helper or here, the same points as one sampler's, and a dead helper's share
sampled again here."""

from __future__ import annotations

import os
import signal

import numpy as np
import pytest
from scipy.spatial import cKDTree

import worker.dst.tessellate as T
from tests.worker.dst.meshcheck import assert_watertight
from worker.dst.forked import fork_available
from worker.dst.params import SliceParams
from worker.dst.pipeline import slice_step
from worker.dst.sampler_records import SampledShare, SamplingStats, VertexPool
from worker.dst.sampling import RingSampler

needs_fork = pytest.mark.skipif(not fork_available(), reason="fork is used on Linux only")


@pytest.fixture(scope="module")
def hemisphere_step(tmp_path_factory):
    from tests.conftest import build_part, write_step

    return write_step(build_part("hemisphere", radius=20.0), tmp_path_factory.mktemp("t") / "hemi.step")


@pytest.fixture
def sampled_in(monkeypatch) -> list[int]:
    """The process each share taken in by ``adopt`` was sampled in (its pid travels with it)."""
    pids: list[int] = []
    sample, adopt = RingSampler.sample_share, RingSampler.adopt

    def noting(self, loop_ids):
        share = sample(self, loop_ids)
        share.pid = os.getpid()
        return share

    def adopting(self, share):
        pids.append(share.pid)
        return adopt(self, share)

    monkeypatch.setattr(RingSampler, "sample_share", noting)
    monkeypatch.setattr(RingSampler, "adopt", adopting)
    return pids


def _build(path, monkeypatch, *, idle: int, split: int = T.FREE_SPLIT_CROSSINGS):
    monkeypatch.setattr(T, "idle_cores", lambda: idle)
    monkeypatch.setattr(T, "FREE_SPLIT_CROSSINGS", split)
    return slice_step(path, SliceParams())


@needs_fork
def test_the_mesh_is_the_same_whether_the_second_share_ran_in_a_helper_or_here(
    hemisphere_step, monkeypatch, sampled_in
):
    forked = _build(hemisphere_step, monkeypatch, idle=1)
    assert len(sampled_in) == 1 and sampled_in[0] != os.getpid()  # split, the share sampled in a child
    sampled_in.clear()
    here = _build(hemisphere_step, monkeypatch, idle=0)
    assert sampled_in == [os.getpid()]
    np.testing.assert_array_equal(forked.vertices, here.vertices)
    np.testing.assert_array_equal(forked.triangles, here.triangles)
    assert {k: v for k, v in forked.stats.items() if k != "timings_s"} == {
        k: v for k, v in here.stats.items() if k != "timings_s"
    }


def test_two_shares_place_the_points_one_sampler_places(hemisphere_step, monkeypatch):
    """Sampled in shares, each point is the one a single sampler solves (to rounding: a batch's size
    changes the last bits of its arithmetic); the mesh has the same triangles and is closed."""
    split = _build(hemisphere_step, monkeypatch, idle=0)
    whole = _build(hemisphere_step, monkeypatch, idle=0, split=10**12)
    assert len(split.vertices) == len(whole.vertices) and len(split.triangles) == len(whole.triangles)
    d, _ = cKDTree(whole.vertices).query(split.vertices)
    assert d.max() < 1e-9
    assert split.stats["newton_solves"] == whole.stats["newton_solves"]
    assert_watertight(split)


@needs_fork
def test_a_helper_that_dies_has_its_share_sampled_here(hemisphere_step, monkeypatch):
    parent = os.getpid()
    original = RingSampler.sample_share
    here_calls = []

    def dying(self, loop_ids):
        if os.getpid() != parent:
            os.kill(os.getpid(), signal.SIGKILL)
        here_calls.append(len(loop_ids))
        return original(self, loop_ids)

    monkeypatch.setattr(RingSampler, "sample_share", dying)
    survived = _build(hemisphere_step, monkeypatch, idle=1)
    assert len(here_calls) == 1 and here_calls[0] > 0  # the dead helper's share, sampled here
    monkeypatch.setattr(RingSampler, "sample_share", original)
    here = _build(hemisphere_step, monkeypatch, idle=0)
    np.testing.assert_array_equal(survived.vertices, here.vertices)
    np.testing.assert_array_equal(survived.triangles, here.triangles)


def test_adopt_keeps_this_samplers_vertex_of_a_node_both_placed(hemisphere_step, monkeypatch):
    """A share's node vertex that this sampler has already is not added again (the mesh stays joined
    there); every other vertex is appended, with its crossings, marks, gaps and counts, and the face
    and (u, v) it was solved at."""
    captured = []
    original = T.free_rings

    def capture(sampler, ids, *, helper=True):
        captured.append(sampler)
        return original(sampler, ids, helper=helper)

    monkeypatch.setattr(T, "free_rings", capture)
    slice_step(hemisphere_step, SliceParams())
    (built,) = captured
    mesh, topo = built.mesh, built.topo
    main = RingSampler(mesh, topo, VertexPool(), segment_length=0.8, chord_error=0.025)
    node = 0
    own = main.node(node)
    before = len(main.pool)
    gap = (0.5, 1.0, 0, [1.0, 2.0, 3.0], [1.5, 2.0, 3.0])
    share = SampledShare(
        rings={7: [0, 1, 2]},
        xyz=np.array([[*mesh.xyz[node][:2], topo.z[node]], [1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]),
        plane=np.array([topo.node_plane[node], 5, 5]),
        face=np.array([-1, 3, -1]),
        uv=np.array([[0.0, 0.0], [0.25, 0.5], [9.0, 9.0]]),
        stats=SamplingStats(newton_solves=3),
        gaps=[gap],
        unresolved=[(5, 0.003)],
        corner_vids={1},
        gap_vids={2},
        node_vid={node: 0},
        cross_vid={11: 1, 12: 2},
    )
    rings = main.adopt(share)
    assert rings == {7: [own, before, before + 1]}
    assert len(main.pool) == before + 2
    np.testing.assert_array_equal(main.pool.xyz[before:], share.xyz[1:])
    np.testing.assert_array_equal(main.pool.plane[before:], [5, 5])
    # the face and (u, v) a vertex was solved at come along; none where the share had none
    assert main.pool.uv_on(3, before) == (0.25, 0.5) and main.pool.uv_on(3, before + 1) is None
    assert main.cross_vid[11] == before and main.cross_vid[12] == before + 1
    assert main.node_vid[node] == own
    assert before in main.corner_vids and before + 1 in main.gap_vids
    assert main._gaps == [gap] and main.stats.newton_solves == 3
    assert main.unresolved == [(5, 0.003)]


def test_a_job_asked_to_run_in_one_process_samples_both_shares_here(hemisphere_step, monkeypatch, sampled_in):
    """``slice_and_report(processes=1)`` forks nothing: not for its report, nor for the build's
    second share, even with a core idle."""
    from worker.dst.report import slice_and_report

    monkeypatch.setattr(T, "idle_cores", lambda: 1)
    slice_and_report(hemisphere_step, SliceParams(), baselines=(), processes=1)
    assert sampled_in == [os.getpid()]
