"""The jobs' processes: forked from a server that imported what a job needs, and nothing else."""

from __future__ import annotations

import os
import sys

import pytest

from worker import sandbox


def _probe(conn) -> None:
    conn.send(([m for m in sandbox.PRELOAD if m in sys.modules], os.getppid()))
    conn.close()


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="the fork server is Linux-only")
def test_a_jobs_process_starts_with_a_jobs_imports_done_by_the_fork_server():
    ctx = sandbox._context()
    assert ctx.get_start_method() == "forkserver"
    sandbox.warm_up()
    for _ in range(2):  # every job from the same untouched server
        parent, child = ctx.Pipe(duplex=False)
        proc = ctx.Process(target=_probe, args=(child,))
        proc.start()
        child.close()
        loaded, ppid = parent.recv()
        proc.join(30)
        assert proc.exitcode == 0
        assert loaded == list(sandbox.PRELOAD)  # OCCT, scipy, matplotlib: imported before the job
        assert ppid not in (os.getpid(), 1)  # forked by the server, not by this (the worker's) process


def _report_fails_with_resource_limit(*args, **kwargs):
    from worker.dst.errors import ResourceLimitExceeded

    raise ResourceLimitExceeded("the report's reference would cut 12,000,000 (triangle, plane) pairs")


def _report_crashes(*args, **kwargs):
    import signal

    os.kill(os.getpid(), signal.SIGSEGV)  # what a crash inside OCCT looks like from outside


def _report_hangs(*args, **kwargs):
    import time

    time.sleep(600)


def _build_fails(*args, **kwargs):
    from worker.dst.errors import TessellationError

    raise TessellationError("OCCT's mesher failed on this solid")


_REPORTS = {"fails": _report_fails_with_resource_limit, "crashes": _report_crashes, "hangs": _report_hangs}
_REAL_CHILD = sandbox._child


def _child_with_report(conn, job_dir, input_path, params, file_name, *rest) -> None:
    """The job's process with the report's work after the build replaced by ``_REPORTS[stem]`` of the
    job's file name (or, for "no_mesh", the build by one that fails). Runs in a process from the fork
    server (which imports this module by name): a process forked from the test's own would inherit
    OCCT's thread pool in a state it cannot use."""
    from worker.dst import report as report_module

    stem = file_name.split(".")[0]
    if stem == "no_mesh":
        report_module.slice_part = _build_fails
    else:
        report_module._build_report = _REPORTS[stem]
    _REAL_CHILD(conn, job_dir, input_path, params, file_name, *rest)


def _run_with_report(tmp_path, monkeypatch, make_step, report: str, timeout_s: float = 300.0):
    """One job through ``run_sandboxed``, whose report after the build is ``_REPORTS[report]``.
    Returns (job, artifact store)."""
    import hashlib

    from worker.settings import Settings
    from worker.storage import ArtifactStore
    from worker.store import JobStore

    monkeypatch.setattr(sandbox, "_child", _child_with_report)
    step = make_step("tube", tilt_deg=0.0, length=20.0)  # 20 mm tall: 40 planes at 0.5 mm layers
    settings = Settings(data_dir=tmp_path, job_timeout_s=timeout_s)
    store = JobStore(f"sqlite:///{tmp_path / 'jobs.sqlite'}")
    artifacts = ArtifactStore(tmp_path / "artifacts")
    job = store.create(
        file_name=f"{report}.step",
        file_size=step.stat().st_size,
        file_sha256=hashlib.sha256(step.read_bytes()).hexdigest(),
        dedupe_key="k",
        params={"layer_height": 0.5, "baselines": "none"},
    )
    artifacts.save_input(job.id, step)
    sandbox.run_sandboxed(job.id, store, artifacts, settings)
    return store.get(job.id), artifacts


@pytest.mark.parametrize(
    ("report", "timeout_s", "code", "says"),
    [
        ("fails", 300.0, "resource_limit", "12,000,000"),
        ("crashes", 300.0, "worker_crashed", "SIGSEGV"),
        ("hangs", 20.0, "timeout", "20 s limit"),
    ],
)
def test_a_report_that_fails_after_the_mesh_keeps_the_mesh(
    tmp_path, monkeypatch, make_step, report, timeout_s, code, says
):
    """The mesh is written whole before the report starts: a report that raises, crashes or outlives
    the job's time limit leaves a succeeded job with the mesh and why there is no report, not a
    failed job whose mesh is lost."""
    from worker.dst.stl_io import binary_stl_corners
    from worker.storage import ARTIFACTS

    job, artifacts = _run_with_report(tmp_path, monkeypatch, make_step, report, timeout_s)
    assert job.status == "succeeded" and job.error_code is None
    assert set(job.artifacts) == {"mesh"}
    assert job.result["report_error"]["code"] == code and says in job.result["report_error"]["message"]
    assert job.result["triangles"] > 0 and job.result["planes"] == 40
    data = artifacts.path(job.id, "mesh.stl").read_bytes()
    assert len(binary_stl_corners(data)) == 3 * job.result["triangles"]
    assert job.artifacts["mesh"]["size"] == len(data)
    for name, (file, _) in ARTIFACTS.items():
        assert name == "mesh" or not artifacts.exists(job.id, file)


def test_a_job_that_fails_before_its_mesh_is_failed(tmp_path, monkeypatch, make_step):
    """Without a mesh there is nothing to keep: a job that ends before its mesh is written fails."""
    job, artifacts = _run_with_report(tmp_path, monkeypatch, make_step, "no_mesh")
    assert job.status == "failed" and job.error_code == "tessellation_error"
    assert job.result in (None, {}) and "mesher failed" in job.error_message
    assert job.artifacts == {} and not artifacts.exists(job.id, "mesh.stl")
