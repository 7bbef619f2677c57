"""Python client of dst-service (httpx). Imports nothing else of the project.

from app.client import DstClient
with DstClient("http://127.0.0.1:8000") as c:
    job = c.submit("part.step", layer_height=0.2, target_slicer="prusa")
    job = c.wait(job["id"])
    c.download_mesh(job["id"], "part.stl")
    report = c.report(job["id"])
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Iterator
from typing import Any

import httpx


class DstError(Exception):
    """An error answer of the service: ``status`` (HTTP), ``code`` (machine-readable), message."""

    def __init__(self, status: int, code: str, message: str):
        super().__init__(f"{code}: {message}")
        self.status, self.code, self.message = status, code, message


class JobFailed(DstError):
    """The job ended as failed or cancelled."""


class DstClient:
    def __init__(self, base_url: str = "http://127.0.0.1:8000", *, timeout: float = 60.0):
        self.http = httpx.Client(base_url=base_url.rstrip("/"), timeout=timeout)

    def __enter__(self) -> DstClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        self.http.close()

    # --- calls ---------------------------------------------------------------------------------------
    def submit(self, path: str | os.PathLike[str], **params: Any) -> dict[str, Any]:
        """Upload a STEP file; returns the job (an earlier identical job is reused: ``job['reused']``)."""
        data = {k: _form(v) for k, v in params.items() if v is not None}
        with open(path, "rb") as fh:
            r = self.http.post(
                "/v1/jobs", files={"file": (os.path.basename(path), fh, "application/step")}, data=data
            )
        return _json(r)

    def job(self, job_id: str) -> dict[str, Any]:
        return _json(self.http.get(f"/v1/jobs/{job_id}"))

    def jobs(self, *, limit: int = 20, offset: int = 0, status: str | None = None) -> dict[str, Any]:
        params: dict[str, Any] = {"limit": limit, "offset": offset}
        if status:
            params["status"] = status
        return _json(self.http.get("/v1/jobs", params=params))

    def events(self, job_id: str) -> Iterator[tuple[str, dict[str, Any]]]:
        """Server-sent events of the job: (event, job) until it ends."""
        with self.http.stream("GET", f"/v1/jobs/{job_id}/events", timeout=None) as r:
            if r.status_code != 200:
                r.read()
                _json(r)
            event = "message"
            for line in r.iter_lines():
                if line.startswith("event:"):
                    event = line[6:].strip()
                elif line.startswith("data:"):
                    yield event, json.loads(line[5:])
                    if event == "end":
                        return

    def wait(self, job_id: str, *, timeout: float = 3600.0, poll: float = 0.5) -> dict[str, Any]:
        """Poll until the job ends; raise JobFailed if it did not succeed."""
        deadline = time.monotonic() + timeout
        while True:
            job = self.job(job_id)
            if job["status"] in ("succeeded", "failed", "cancelled"):
                break
            if time.monotonic() > deadline:
                raise TimeoutError(f"job {job_id} still {job['status']} after {timeout} s")
            time.sleep(poll)
        if job["status"] != "succeeded":
            err = job.get("error") or {"code": job["status"], "message": f"the job was {job['status']}"}
            raise JobFailed(200, err["code"], err["message"])
        return job

    def download_mesh(
        self, job_id: str, path: str | os.PathLike[str], *, ascii: bool = False, format: str | None = None
    ) -> int:
        """Stream the DST mesh to ``path``; returns bytes written. ``format``: "stl" (binary),
        "ascii" or "3mf"; by default 3MF for a path ending in .3mf, else binary STL (ASCII with
        ``ascii``)."""
        if format is None:
            format = "3mf" if os.fspath(path).lower().endswith(".3mf") else "ascii" if ascii else "stl"
        return self._download(f"/v1/jobs/{job_id}/mesh", path, params={"format": format})

    def report(self, job_id: str) -> dict[str, Any]:
        return _json(self.http.get(f"/v1/jobs/{job_id}/report"))

    def download(self, job_id: str, artifact: str, path: str | os.PathLike[str]) -> int:
        """``artifact``: report, report.html, plot.svg or plot.png."""
        return self._download(f"/v1/jobs/{job_id}/{artifact}", path)

    def delete(self, job_id: str) -> None:
        r = self.http.delete(f"/v1/jobs/{job_id}")
        if r.status_code != 204:
            _json(r)

    def slice(
        self, path: str | os.PathLike[str], out: str | os.PathLike[str], **params: Any
    ) -> dict[str, Any]:
        """Submit, wait, download: the DST mesh of ``path`` in ``out``; returns the finished job."""
        job = self.submit(path, **params)
        job = self.wait(job["id"])
        self.download_mesh(job["id"], out)
        return job

    def _download(self, url: str, path: str | os.PathLike[str], params: dict[str, Any] | None = None) -> int:
        tmp = f"{os.fspath(path)}.part"
        n = 0
        with self.http.stream("GET", url, params=params, timeout=None) as r:
            if r.status_code != 200:
                r.read()
                _json(r)
            with open(tmp, "wb") as fh:
                for chunk in r.iter_bytes(1 << 20):
                    fh.write(chunk)
                    n += len(chunk)
        os.replace(tmp, path)
        return n


def _form(v: Any) -> str:
    if isinstance(v, list | tuple):
        return ",".join(map(str, v))
    return str(v)


def _json(r: httpx.Response) -> dict[str, Any]:
    try:
        body = r.json()
    except ValueError:
        body = None
    if r.status_code >= 400:
        err = (body or {}).get("error") if isinstance(body, dict) else None
        if err:
            raise DstError(r.status_code, err.get("code", "error"), err.get("message", ""))
        raise DstError(r.status_code, "http_error", r.text[:500])
    return body
