"""The Celery binding: the app, the one task, and the worker's own heartbeat and recovery thread.

Importing this module imports no OCCT (the API imports it to enqueue jobs).
"""

from __future__ import annotations

import logging
import threading

from celery import Celery
from celery.signals import worker_ready, worker_shutdown
from kombu.exceptions import KombuError
from sqlalchemy.exc import SQLAlchemyError

from worker.settings import get_settings
from worker.storage import ArtifactStore, make_artifact_store
from worker.store import JobStore, this_worker_name

log = logging.getLogger("dst.worker")
settings = get_settings()
# How often a worker looks for new jobs in the embedded SQLite broker (kombu's default, 1 s, kept a
# job up to a second in the queue). Set on the transport class: kombu's SQLAlchemy transport hands
# its transport options to ``create_engine``, which refuses a ``polling_interval``.
EMBEDDED_POLL_S = 0.1
if settings.effective_broker_url.startswith("sqla+"):
    from kombu.transport import sqlalchemy as _sqla_transport

    _sqla_transport.Transport.polling_interval = EMBEDDED_POLL_S

app = Celery("dst")
app.conf.update(
    broker_url=settings.effective_broker_url,
    broker_connection_retry_on_startup=True,
    task_default_queue=settings.queue,
    task_ignore_result=True,
    # Acknowledge on receipt: a job whose worker dies is re-run by recovery (bounded by max_attempts),
    # not redelivered by the broker again and again.
    task_acks_late=False,
    worker_prefetch_multiplier=1,
    worker_hijack_root_logger=False,
)

_store: JobStore | None = None
_artifacts: ArtifactStore | None = None


def store() -> JobStore:
    global _store
    if _store is None:
        _store = JobStore(settings.effective_database_url)
    return _store


def artifacts() -> ArtifactStore:
    global _artifacts
    if _artifacts is None:
        _artifacts = make_artifact_store(settings)
    return _artifacts


@app.task(name="dst.run_job")
def run_job(job_id: str) -> str:
    from worker.sandbox import run_sandboxed

    status = run_sandboxed(job_id, store(), artifacts(), settings)
    log.info("job %s: %s", job_id, status)
    return status


def enqueue(job_id: str) -> None:
    run_job.apply_async(args=[job_id], queue=settings.queue)


_stop = threading.Event()


def _housekeeping(concurrency: int) -> None:
    from worker.recovery import recover

    name = this_worker_name()
    while not _stop.is_set():
        try:
            store().worker_seen(name, concurrency)
            for job_id, action in recover(store(), settings, enqueue):
                log.warning("job %s: worker lost, %s", job_id, action)
        except (SQLAlchemyError, OSError, KombuError):  # store or broker briefly away: next round
            log.exception("housekeeping failed")
        _stop.wait(min(5.0, settings.heartbeat_s * 2))


@worker_ready.connect
def _on_ready(sender=None, **_kw) -> None:
    from worker.sandbox import warm_up

    warm_up()  # the jobs' fork server imports OCCT while the worker waits for its first job
    concurrency = getattr(getattr(sender, "controller", None), "concurrency", None) or 1
    threading.Thread(
        target=_housekeeping, args=(int(concurrency),), name="dst-housekeeping", daemon=True
    ).start()


@worker_shutdown.connect
def _on_shutdown(**_kw) -> None:
    _stop.set()
    try:
        store().worker_gone(this_worker_name())
    except SQLAlchemyError:
        log.exception("could not deregister the worker")
