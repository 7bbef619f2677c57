"""Jobs left running by a lost worker are re-run once, then failed; live ones are left alone."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time

from worker.recovery import recover
from worker.settings import Settings
from worker.store import JobStore, this_worker_name


def dead_pid() -> int:
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


def running_job(store: JobStore, worker: str, attempts: int, beat_age: float = 0.0) -> str:
    job = store.create(
        file_name="p.step", file_size=1, file_sha256="0" * 64, dedupe_key=os.urandom(8).hex(), params={}
    )
    store.update(
        job.id, status="running", worker=worker, attempts=attempts, heartbeat_at=time.time() - beat_age
    )
    return job.id


def test_recover(tmp_path):
    settings = Settings(data_dir=tmp_path, stale_after_s=30, max_attempts=2)
    store = JobStore(f"sqlite:///{tmp_path / 'jobs.sqlite'}")
    me = this_worker_name()
    store.worker_seen(me, 1)
    host = socket.gethostname()
    crashed_once = running_job(store, f"{host}:{dead_pid()}", attempts=1)
    crashed_twice = running_job(store, f"{host}:{dead_pid()}", attempts=2)
    alive = running_job(store, me, attempts=1)
    silent_elsewhere = running_job(store, "other-machine:123", attempts=1, beat_age=120)
    unregistered_elsewhere = running_job(store, "other-machine:456", attempts=1, beat_age=0)

    queued: list[str] = []
    done = dict(recover(store, settings, queued.append))

    assert done == {
        crashed_once: "requeued",
        crashed_twice: "failed",
        silent_elsewhere: "requeued",
        unregistered_elsewhere: "requeued",
    }
    assert sorted(queued) == sorted([crashed_once, silent_elsewhere, unregistered_elsewhere])
    assert store.get(crashed_once).status == "queued"
    failed = store.get(crashed_twice)
    assert failed.status == "failed" and failed.error_code == "worker_crashed"
    assert store.get(alive).status == "running"
    assert recover(store, settings, queued.append) == []  # nothing left to do: no repeated requeues
