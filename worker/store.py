"""The job store: one row per job, shared by the API and every worker (SQLAlchemy; SQLite by default).

The API writes a job when it is submitted; the worker that runs it writes its progress, heartbeat
and outcome. Nothing here imports OCCT.
"""

from __future__ import annotations

import builtins
import json
import os
import socket
import time
import uuid
from dataclasses import dataclass
from typing import Any

import sqlalchemy as sa
from sqlalchemy.engine import Engine

TERMINAL = ("succeeded", "failed", "cancelled")
STATUSES = ("queued", "running", *TERMINAL)

metadata = sa.MetaData()

jobs = sa.Table(
    "jobs",
    metadata,
    sa.Column("id", sa.String(32), primary_key=True),
    sa.Column("seq", sa.Integer, nullable=False, index=True),  # creation order, for newest-first pages
    sa.Column("created_at", sa.Float, nullable=False),
    sa.Column("updated_at", sa.Float, nullable=False),
    sa.Column("started_at", sa.Float),
    sa.Column("finished_at", sa.Float),
    sa.Column("status", sa.String(16), nullable=False, index=True),
    sa.Column("progress", sa.Float, nullable=False, default=0.0),
    sa.Column("stage", sa.String(200), nullable=False, default=""),
    sa.Column("file_name", sa.String(255), nullable=False),
    sa.Column("file_size", sa.Integer, nullable=False),
    sa.Column("file_sha256", sa.String(64), nullable=False),
    sa.Column("dedupe_key", sa.String(64), nullable=False, index=True),
    sa.Column("params", sa.Text, nullable=False),  # JSON
    sa.Column("error_code", sa.String(64)),
    sa.Column("error_message", sa.Text),
    sa.Column("attempts", sa.Integer, nullable=False, default=0),
    sa.Column("worker", sa.String(255)),
    sa.Column("sandbox_pid", sa.Integer),
    sa.Column("heartbeat_at", sa.Float),
    sa.Column("cancel_requested", sa.Boolean, nullable=False, default=False),
    sa.Column("artifacts", sa.Text, nullable=False, default="{}"),  # JSON name -> {size, sha256}
    sa.Column("result", sa.Text, nullable=False, default="{}"),  # JSON: summary numbers, warnings
)

workers = sa.Table(
    "workers",
    metadata,
    sa.Column("name", sa.String(255), primary_key=True),
    sa.Column("hostname", sa.String(255), nullable=False),
    sa.Column("pid", sa.Integer, nullable=False),
    sa.Column("started_at", sa.Float, nullable=False),
    sa.Column("last_seen", sa.Float, nullable=False),
    sa.Column("concurrency", sa.Integer, nullable=False),
)


@dataclass
class Job:
    id: str
    seq: int
    created_at: float
    updated_at: float
    started_at: float | None
    finished_at: float | None
    status: str
    progress: float
    stage: str
    file_name: str
    file_size: int
    file_sha256: str
    dedupe_key: str
    params: dict[str, Any]
    error_code: str | None
    error_message: str | None
    attempts: int
    worker: str | None
    sandbox_pid: int | None
    heartbeat_at: float | None
    cancel_requested: bool
    artifacts: dict[str, dict[str, Any]]
    result: dict[str, Any]

    @classmethod
    def from_row(cls, row: Any) -> Job:
        d = dict(row._mapping)
        d["params"] = json.loads(d["params"])
        d["artifacts"] = json.loads(d["artifacts"] or "{}")
        d["result"] = json.loads(d["result"] or "{}")
        d["cancel_requested"] = bool(d["cancel_requested"])
        return cls(**d)

    @property
    def terminal(self) -> bool:
        return self.status in TERMINAL


def this_worker_name() -> str:
    return f"{socket.gethostname()}:{os.getpid()}"


class JobStore:
    def __init__(self, url: str):
        kwargs: dict[str, Any] = {}
        if url.startswith("sqlite"):
            kwargs["connect_args"] = {"timeout": 30, "check_same_thread": False}
        self.engine: Engine = sa.create_engine(url, future=True, pool_pre_ping=True, **kwargs)
        if url.startswith("sqlite"):

            @sa.event.listens_for(self.engine, "connect")
            def _pragmas(dbapi_conn, _record):  # WAL: readers never wait for the writer
                cur = dbapi_conn.cursor()
                cur.execute("PRAGMA journal_mode=WAL")
                cur.execute("PRAGMA synchronous=NORMAL")
                cur.close()

        metadata.create_all(self.engine)

    # --- jobs ------------------------------------------------------------------------------------------
    def create(
        self, *, file_name: str, file_size: int, file_sha256: str, dedupe_key: str, params: dict[str, Any]
    ) -> Job:
        now = time.time()
        job_id = uuid.uuid4().hex
        with self.engine.begin() as c:
            seq = c.execute(sa.select(sa.func.coalesce(sa.func.max(jobs.c.seq), 0))).scalar_one() + 1
            c.execute(
                jobs.insert().values(
                    id=job_id,
                    seq=seq,
                    created_at=now,
                    updated_at=now,
                    status="queued",
                    progress=0.0,
                    stage="queued",
                    file_name=file_name,
                    file_size=file_size,
                    file_sha256=file_sha256,
                    dedupe_key=dedupe_key,
                    params=json.dumps(params, sort_keys=True),
                    attempts=0,
                    cancel_requested=False,
                    artifacts="{}",
                    result="{}",
                )
            )
        job = self.get(job_id)
        assert job is not None
        return job

    def get(self, job_id: str) -> Job | None:
        with self.engine.connect() as c:
            row = c.execute(jobs.select().where(jobs.c.id == job_id)).first()
        return Job.from_row(row) if row else None

    def find_reusable(self, dedupe_key: str) -> Job | None:
        """The newest job with these inputs that succeeded or is still on its way."""
        with self.engine.connect() as c:
            row = c.execute(
                jobs.select()
                .where(jobs.c.dedupe_key == dedupe_key, jobs.c.status.in_(("queued", "running", "succeeded")))
                .order_by(jobs.c.seq.desc())
                .limit(1)
            ).first()
        return Job.from_row(row) if row else None

    def list(self, *, limit: int, offset: int, status: str | None = None) -> tuple[list[Job], int]:
        q = jobs.select()
        count = sa.select(sa.func.count()).select_from(jobs)
        if status:
            q = q.where(jobs.c.status == status)
            count = count.where(jobs.c.status == status)
        with self.engine.connect() as c:
            rows = c.execute(q.order_by(jobs.c.seq.desc()).limit(limit).offset(offset)).all()
            total = c.execute(count).scalar_one()
        return [Job.from_row(r) for r in rows], int(total)

    def update(self, job_id: str, *, only_if_status: tuple[str, ...] | None = None, **values: Any) -> bool:
        """Update fields; with ``only_if_status`` only while the job is in one of those states."""
        for key in ("params", "artifacts", "result"):
            if key in values and not isinstance(values[key], str):
                values[key] = json.dumps(values[key], sort_keys=True)
        values["updated_at"] = time.time()
        q = jobs.update().where(jobs.c.id == job_id)
        if only_if_status:
            q = q.where(jobs.c.status.in_(only_if_status))
        with self.engine.begin() as c:
            return c.execute(q.values(**values)).rowcount > 0

    def delete(self, job_id: str) -> None:
        with self.engine.begin() as c:
            c.execute(jobs.delete().where(jobs.c.id == job_id))

    def running(self) -> builtins.list[Job]:
        with self.engine.connect() as c:
            rows = c.execute(jobs.select().where(jobs.c.status == "running")).all()
        return [Job.from_row(r) for r in rows]

    # --- workers ---------------------------------------------------------------------------------------
    def worker_seen(self, name: str, concurrency: int) -> None:
        now = time.time()
        host, _, pid = name.rpartition(":")
        with self.engine.begin() as c:
            done = c.execute(workers.update().where(workers.c.name == name).values(last_seen=now)).rowcount
            if not done:
                c.execute(
                    workers.insert().values(
                        name=name,
                        hostname=host,
                        pid=int(pid),
                        started_at=now,
                        last_seen=now,
                        concurrency=concurrency,
                    )
                )

    def live_workers(self, within_s: float) -> builtins.list[dict[str, Any]]:
        with self.engine.connect() as c:
            rows = c.execute(workers.select().where(workers.c.last_seen >= time.time() - within_s)).all()
        return [dict(r._mapping) for r in rows]

    def worker_gone(self, name: str) -> None:
        with self.engine.begin() as c:
            c.execute(workers.delete().where(workers.c.name == name))

    def ping(self) -> None:
        with self.engine.connect() as c:
            c.execute(sa.text("SELECT 1"))
