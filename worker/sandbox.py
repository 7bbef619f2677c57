"""Run one job in a killable child process, with a wall-clock and a memory limit.

OCCT holds the GIL and cannot be interrupted by a signal or a thread: the only reliable stop is to
kill the process it runs in. The supervisor (a thread of the Celery worker) claims the job, starts a
child for it, relays its progress to the job store, beats the job's heartbeat, and kills the child on
timeout or cancellation. A child that dies (segfault, OOM kill) fails the job with
``worker_crashed``; the worker carries on. The job's report may fork helpers of its own
(``worker.dst.forked``); they die with the job's process.

On Linux each child is forked from a fork server (``multiprocessing``'s ``forkserver``) that has
imported what a job needs (``PRELOAD``: OCCT, scipy, matplotlib) and done nothing else: a job starts
in ~0.02 s instead of the 3-4 s a fresh interpreter spends on those imports, and every job still
starts from the same untouched state, never a fork of a process that ran OCCT (whose thread pool
does not survive a fork). The server costs its worker ~400 MB of memory while it lives; it exits
with the worker, and the jobs' processes with it. Elsewhere each child is a fresh *spawned*
interpreter.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import resource
import signal
import sys
import time
import traceback
from pathlib import Path
from typing import Any

from worker.dst.forked import die_with_parent
from worker.settings import Settings
from worker.storage import ARTIFACTS, ArtifactStore
from worker.store import JobStore, this_worker_name

_PROGRESS_EVERY_S = 0.25
# Imported once by the fork server, before any job: every module a job imports (matplotlib's
# backends are imported when a figure is first saved), this one (the child's entry point: its job
# store imports SQLAlchemy) and the `dst` command's (a child runs its parent's main script again).
PRELOAD = (
    "worker.cli",
    "worker.sandbox",
    "worker.job",
    "worker.dst.pipeline",
    "worker.dst.report",
    "worker.dst.render",
    "matplotlib.backends.backend_agg",
    "matplotlib.backends.backend_svg",
)


def _context():
    """Where jobs' processes come from: the preloaded fork server on Linux, else fresh interpreters."""
    if not sys.platform.startswith("linux"):
        return mp.get_context("spawn")
    ctx = mp.get_context("forkserver")
    ctx.set_forkserver_preload(list(PRELOAD))
    return ctx


def warm_up() -> None:
    """Start the fork server now (its imports take seconds), not when the first job comes."""
    if _context().get_start_method() == "forkserver":
        from multiprocessing import forkserver

        forkserver.ensure_running()


def _child(
    conn,
    job_dir: str,
    input_path: str,
    params: dict,
    file_name: str,
    memory_mb: int,
    report_processes: int | None,
) -> None:
    """The sandboxed process: limits, quiet OCCT, the job, one final message."""
    die_with_parent()
    resource.setrlimit(resource.RLIMIT_AS, (memory_mb << 20, memory_mb << 20))
    log = os.open(os.path.join(job_dir, "occt.log"), os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
    os.dup2(log, 1)  # OCCT prints banners on the C++ stdout/stderr
    os.dup2(log, 2)
    try:
        from worker.dst.errors import DstError
        from worker.job import run_job

        def progress(stage: str, frac: float) -> None:
            conn.send(("progress", stage, float(frac)))

        def mesh_written(summary: dict) -> None:
            conn.send(("mesh", summary))

        result = run_job(
            Path(job_dir),
            Path(input_path),
            params,
            file_name,
            progress,
            report_processes=report_processes,
            on_mesh=mesh_written,
        )
        conn.send(("done", result))
    except DstError as exc:
        conn.send(("error", exc.code, str(exc)))
    except MemoryError:
        conn.send(("error", "resource_limit", f"the job needed more than its {memory_mb} MB memory limit"))
    except Exception as exc:  # a bug in the core: report it, with the traceback in occt.log
        traceback.print_exc()
        conn.send(("error", "internal_error", f"{type(exc).__name__}: {exc}"))
    finally:
        conn.close()


def run_sandboxed(job_id: str, store: JobStore, artifacts: ArtifactStore, settings: Settings) -> str:
    """Run the job if it is still queued; return its final status (or 'skipped')."""
    job = store.get(job_id)
    if job is None or job.status != "queued" or job.cancel_requested:
        return "skipped"
    now = time.time()
    claimed = store.update(
        job_id,
        only_if_status=("queued",),
        status="running",
        stage="starting",
        started_at=now,
        heartbeat_at=now,
        attempts=job.attempts + 1,
        worker=this_worker_name(),
    )
    if not claimed:
        return "skipped"  # another worker took it, or it was cancelled meanwhile
    job_dir = artifacts.job_dir(job_id)
    try:
        input_path = artifacts.fetch_input(job_id)
    except OSError as exc:
        return _finish(
            store, artifacts, job_id, "failed", "input_missing", f"the uploaded file is gone: {exc}"
        )
    ctx = _context()
    parent, child = ctx.Pipe(duplex=False)
    proc = ctx.Process(
        target=_child,
        args=(
            child,
            str(job_dir),
            str(input_path),
            job.params,
            job.file_name,
            settings.job_memory_mb,
            settings.report_processes,
        ),
        name=f"dst-job-{job_id[:8]}",
        daemon=True,
    )
    proc.start()
    child.close()
    store.update(job_id, sandbox_pid=proc.pid)
    deadline = time.monotonic() + settings.job_timeout_s
    last_beat = last_progress = last_cancel_check = 0.0
    pending: tuple[str, float] | None = None
    outcome: tuple | None = None
    mesh: dict | None = None  # the mesh's summary, once the job has written it whole
    try:
        while True:
            if parent.poll(0.2):
                try:
                    msg = parent.recv()
                except EOFError:
                    msg = None
                if msg is None:
                    proc.join(5)
                    break
                if msg[0] == "progress":
                    pending = (msg[1], msg[2])
                elif msg[0] == "mesh":
                    mesh = msg[1]
                else:
                    outcome = msg
                    break
            elif not proc.is_alive():
                break
            t = time.monotonic()
            if pending and t - last_progress >= _PROGRESS_EVERY_S:
                store.update(
                    job_id,
                    only_if_status=("running",),
                    stage=pending[0][:200],
                    progress=pending[1],
                    heartbeat_at=time.time(),
                )
                pending, last_progress, last_beat = None, t, t
            if t - last_beat >= settings.heartbeat_s:
                store.update(job_id, heartbeat_at=time.time())
                last_beat = t
            if t - last_cancel_check >= 0.5:
                last_cancel_check = t
                current = store.get(job_id)
                if current is None or current.cancel_requested or current.status != "running":
                    _kill(proc)
                    return "cancelled"
            if t > deadline:
                _kill(proc)
                limit = f"the job ran longer than its {settings.job_timeout_s:g} s limit and was stopped"
                outcome = ("error", "timeout", limit)
                break
    finally:
        parent.close()
    proc.join(10)
    if outcome is None:
        code = proc.exitcode
        if code is not None and code < 0:
            name = signal.Signals(-code).name
            reason = "was killed by the system (out of memory?)" if name == "SIGKILL" else f"crashed ({name})"
        else:
            reason = f"exited unexpectedly (status {code})"
        outcome = ("error", "worker_crashed", f"the job's process {reason}")
    if outcome[0] == "error" and mesh is None:
        return _finish(store, artifacts, job_id, "failed", outcome[1], outcome[2])
    result = outcome[1]
    if outcome[0] == "error":
        assert mesh is not None  # (failed above otherwise)
        # The mesh was written whole before the report failed, crashed or ran out of time: the job
        # succeeds with the mesh alone and says why there is no report (nothing of it is kept).
        for name, (file, _) in ARTIFACTS.items():
            if name != "mesh":
                (artifacts.job_dir(job_id) / file).unlink(missing_ok=True)
        result = mesh | {"report_error": {"code": outcome[1], "message": outcome[2]}}
    try:
        manifest = artifacts.publish(job_id)
    except OSError as exc:
        return _finish(
            store, artifacts, job_id, "failed", "storage_error", f"could not store the results: {exc}"
        )
    return _finish(store, artifacts, job_id, "succeeded", None, None, result=result, manifest=manifest)


def _finish(
    store: JobStore,
    artifacts: ArtifactStore,
    job_id: str,
    status: str,
    code: str | None,
    message: str | None,
    *,
    result: dict[str, Any] | None = None,
    manifest: dict[str, Any] | None = None,
) -> str:
    values: dict[str, Any] = {
        "status": status,
        "finished_at": time.time(),
        "error_code": code,
        "error_message": message,
        "sandbox_pid": None,
    }
    if status == "succeeded":
        values.update(progress=1.0, stage="done", result=result or {}, artifacts=manifest or {})
    else:
        values.update(stage=status)
    store.update(job_id, only_if_status=("running",), **values)
    final = store.get(job_id)
    return final.status if final else "deleted"


def _kill(proc) -> None:
    if proc.is_alive():
        proc.kill()
    proc.join(10)
