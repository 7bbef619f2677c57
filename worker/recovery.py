"""Jobs whose worker died: re-run them (up to ``max_attempts`` runs in all) or fail them. Never left
``running`` forever, never redelivered endlessly."""

from __future__ import annotations

import os
import socket
import time
from collections.abc import Callable

from worker.settings import Settings
from worker.store import Job, JobStore


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def is_orphaned(job: Job, settings: Settings, live_workers: set[str]) -> bool:
    """A running job whose worker is gone: a dead process on this machine, a worker that no longer
    reports, or silence longer than ``stale_after_s``."""
    if job.status != "running":
        return False
    if job.worker:
        host, _, pid = job.worker.rpartition(":")
        if host == socket.gethostname() and pid.isdigit() and not _pid_alive(int(pid)):
            return True
        if job.worker not in live_workers:  # its worker has not reported for stale_after_s
            return True
    beat = job.heartbeat_at or job.started_at or job.updated_at
    return time.time() - beat > settings.stale_after_s


def recover(store: JobStore, settings: Settings, enqueue: Callable[[str], None]) -> list[tuple[str, str]]:
    """Handle every orphaned running job; returns (job id, what was done)."""
    done = []
    live = {w["name"] for w in store.live_workers(within_s=settings.stale_after_s)}
    for job in store.running():
        if not is_orphaned(job, settings, live):
            continue
        if job.attempts < settings.max_attempts:
            if store.update(
                job.id,
                only_if_status=("running",),
                status="queued",
                stage=f"re-queued: its worker stopped during attempt {job.attempts}",
                progress=0.0,
                worker=None,
                sandbox_pid=None,
            ):
                enqueue(job.id)
                done.append((job.id, "requeued"))
        elif store.update(
            job.id,
            only_if_status=("running",),
            status="failed",
            stage="failed",
            finished_at=time.time(),
            error_code="worker_crashed",
            error_message=f"the worker running this job stopped {job.attempts} time(s); not retried again",
        ):
            done.append((job.id, "failed"))
    return done
