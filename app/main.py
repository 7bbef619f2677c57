"""The HTTP API of dst-service: uploads, jobs, streamed results. Never imports OCCT.

Jobs are queued to Celery workers (``worker.queue``); their state lives in the job store
(``worker.store``) and their files in the artifact store (``worker.storage``).
"""

from __future__ import annotations

import asyncio
import hashlib
import json
import os
import re
import tempfile
import time
from collections.abc import AsyncIterator, Mapping
from contextlib import asynccontextmanager
from datetime import UTC, datetime
from pathlib import Path
from typing import Annotated

from fastapi import Depends, FastAPI, File, Form, HTTPException, Query, Request, UploadFile
from fastapi import Path as PathParam
from fastapi.exceptions import RequestValidationError
from fastapi.responses import FileResponse, HTMLResponse, JSONResponse, Response, StreamingResponse
from starlette.concurrency import run_in_threadpool
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.routing import Match

from app import schemas as S
from app.page import INDEX_HTML
from worker.dst.baselines import BASELINES_PATTERN, parse_baselines
from worker.dst.errors import InvalidParameters
from worker.dst.params import ROTATION_FIELDS, SLICING_FIELDS, SliceParams
from worker.dst.report_schema import Report
from worker.dst.sniff import SNIFF_BYTES, sniff_step
from worker.settings import Settings, get_settings
from worker.storage import ARTIFACTS, ArtifactStore, make_artifact_store
from worker.store import Job, JobStore

API = "/v1"
INPUT_ERRORS = {"step_read_error", "empty_geometry", "not_a_solid", "invalid_parameters", "resource_limit"}

ERROR_RESPONSES = {
    404: {"model": S.ErrorResponse, "description": "Unknown job (code job_not_found)."},
    409: {"model": S.ErrorResponse, "description": "The artifact does not exist yet (code mesh_not_ready)."},
    413: {
        "model": S.ErrorResponse,
        "description": "Upload over the configured limit (code upload_too_large).",
    },
    422: {"model": S.ErrorResponse, "description": "Not a STEP file (not_step) or parameters out of range."},
    503: {"model": S.ErrorResponse, "description": "The queue is unreachable (code broker_unavailable)."},
}


class ApiError(HTTPException):
    def __init__(self, status: int, code: str, message: str, headers: dict[str, str] | None = None):
        super().__init__(status, detail=message, headers=headers)
        self.code = code


@asynccontextmanager
async def _lifespan(app: FastAPI) -> AsyncIterator[None]:
    settings = get_settings()
    settings.ensure_dirs()
    app.state.settings = settings
    app.state.store = JobStore(settings.effective_database_url)
    app.state.artifacts = make_artifact_store(settings)
    from worker import queue

    app.state.enqueue = queue.enqueue
    yield


app = FastAPI(
    title="dst-service",
    version="1.0.0",
    summary="Slicing-aware meshes of STEP parts: Direct Slicing Tessellation with a deviation report.",
    description="Upload a STEP part with the slicer's layer settings; a worker builds the DST mesh, whose "
    "vertex rings lie exactly on the slicer's planes, and a report comparing it and conventional meshes "
    'with the exact CAD geometry, layer by layer. Errors are JSON: {"error": {"code", "message"}}.',
    lifespan=_lifespan,
)


# --- errors -----------------------------------------------------------------------------------------
def _error(status: int, code: str, message: str, headers: Mapping[str, str] | None = None) -> JSONResponse:
    return JSONResponse({"error": {"code": code, "message": message}}, status_code=status, headers=headers)


@app.exception_handler(ApiError)
async def _api_error(_request: Request, exc: ApiError) -> JSONResponse:
    return _error(exc.status_code, exc.code, str(exc.detail), exc.headers)


# (Starlette's own: the router's 404 and 405 are not FastAPI's HTTPException, which subclasses it)
@app.exception_handler(StarletteHTTPException)
async def _http_error(request: Request, exc: StarletteHTTPException) -> JSONResponse:
    code = {404: "not_found", 405: "method_not_allowed"}.get(exc.status_code, "http_error")
    headers = getattr(exc, "headers", None)
    if exc.status_code == 405:  # the router names the methods of the first route of the path only
        headers = {**(headers or {}), "Allow": ", ".join(_allowed_methods(request))}
    return _error(exc.status_code, code, str(exc.detail), headers)


def _allowed_methods(request: Request) -> list[str]:
    """Every method the routes of the request's path answer."""
    methods: set[str] = set()
    for route in request.app.router.routes:
        if route.matches(request.scope)[0] != Match.NONE:
            methods |= getattr(route, "methods", None) or set()
    return sorted(methods)


@app.exception_handler(RequestValidationError)
async def _validation_error(_request: Request, exc: RequestValidationError) -> JSONResponse:
    parts = []
    for err in exc.errors():
        loc = ".".join(str(p) for p in err["loc"] if p not in ("body", "query", "path"))
        parts.append(f"{loc}: {err['msg']}")
    code = "missing_file" if any(e["loc"][-1] == "file" for e in exc.errors()) else "invalid_parameters"
    return _error(422, code, "; ".join(parts))


@app.middleware("http")
async def _upload_limit(request: Request, call_next):
    """Refuse an oversized upload from its Content-Length, before reading it."""
    if request.method == "POST" and request.url.path in (f"{API}/jobs", f"{API}/slice"):
        length = request.headers.get("content-length")
        limit = get_settings().max_upload_mb * 1e6
        if length and length.isdigit() and int(length) > limit + 1_000_000:  # form overhead allowed
            return _error(
                413,
                "upload_too_large",
                f"the upload is {int(length) / 1e6:.1f} MB; the limit is {limit / 1e6:g} MB",
            )
    return await call_next(request)


# --- helpers ----------------------------------------------------------------------------------------
def _store(request: Request) -> JobStore:
    return request.app.state.store


def _artifacts(request: Request) -> ArtifactStore:
    return request.app.state.artifacts


def _settings(request: Request) -> Settings:
    return request.app.state.settings


def _ts(t: float | None) -> datetime | None:
    return None if t is None else datetime.fromtimestamp(t, tz=UTC)


def job_out(job: Job, *, reused: bool = False) -> S.JobOut:
    base = f"{API}/jobs/{job.id}"
    done = job.status == "succeeded"
    have = job.artifacts if done else {}
    links = S.JobLinks(
        self=base,
        events=f"{base}/events",
        mesh=f"{base}/mesh" if "mesh" in have else None,
        report=f"{base}/report" if "report" in have else None,
        report_html=f"{base}/report.html" if "report_html" in have else None,
        plot_svg=f"{base}/plot.svg" if "plot_svg" in have else None,
        plot_png=f"{base}/plot.png" if "plot_png" in have else None,
    )
    error = S.ErrorInfo(code=job.error_code, message=job.error_message or "") if job.error_code else None
    result = S.JobResult(**job.result) if done and job.result else None
    return S.JobOut(
        id=job.id,
        status=job.status,
        progress=max(0.0, min(1.0, job.progress)),
        stage=job.stage[:200],
        created_at=_ts(job.created_at),
        started_at=_ts(job.started_at),
        finished_at=_ts(job.finished_at),
        file_name=job.file_name,
        file_size=job.file_size,
        file_sha256=job.file_sha256,
        params=S.JobParams(**job.params),
        attempts=job.attempts,
        reused=reused,
        error=error,
        result=result,
        links=links,
    )


def _get_job(request: Request, job_id: JobId) -> Job:
    job = _store(request).get(job_id) if re.fullmatch(r"[0-9a-f]{32}", job_id) else None
    if job is None:
        raise ApiError(404, "job_not_found", f"no job {job_id}")
    return job


def sanitise_name(name: str | None) -> str:
    base = os.path.basename((name or "").replace("\\", "/"))
    base = re.sub(r"[^A-Za-z0-9._-]+", "_", base).strip("._") or "part.step"
    return base[:120]


def _parse_params(values: dict, baselines: str | None) -> dict:
    try:
        p = SliceParams.parse(**values)
        names = parse_baselines(baselines)
    except InvalidParameters as exc:
        raise ApiError(422, "invalid_parameters", str(exc)) from None
    out = p.model_dump()
    out["baselines"] = list(names)
    return out


async def _receive_upload(request: Request, file: UploadFile) -> tuple[Path, int, str]:
    """Copy the upload to a temporary file while hashing it; refuse it if too large or not STEP."""
    settings = _settings(request)
    limit = int(settings.max_upload_mb * 1e6)
    tmp_dir = settings.data_dir / "uploads"
    tmp_dir.mkdir(parents=True, exist_ok=True)
    fd, name = tempfile.mkstemp(dir=tmp_dir, suffix=".step")
    path = Path(name)
    h = hashlib.sha256()
    size = 0
    head = b""
    try:
        with os.fdopen(fd, "wb") as out:
            while chunk := await file.read(1 << 20):
                size += len(chunk)
                if size > limit:
                    raise ApiError(
                        413, "upload_too_large", f"the upload is over the {limit / 1e6:g} MB limit"
                    )
                if len(head) < SNIFF_BYTES:
                    head += chunk[: SNIFF_BYTES - len(head)]
                h.update(chunk)
                out.write(chunk)
        if size == 0:
            raise ApiError(422, "not_step", "the uploaded file is empty")
        if not sniff_step(head):
            raise ApiError(422, "not_step", "not a STEP file: it does not start with the ISO-10303-21 header")
    except BaseException:
        path.unlink(missing_ok=True)
        raise
    return path, size, h.hexdigest()


def _submit(
    request: Request, tmp: Path, size: int, sha: str, file_name: str, params: dict
) -> tuple[Job, bool]:
    """Create the job (or reuse one with the same inputs) and queue it. Returns (job, reused)."""
    store, artifacts = _store(request), _artifacts(request)
    # (an unturned part's key leaves the turn out, as the keys of jobs from before it existed do)
    keyed = {k: v for k, v in params.items() if not (k in ROTATION_FIELDS and v == 0)}
    key = hashlib.sha256((sha + json.dumps(keyed, sort_keys=True)).encode()).hexdigest()
    try:
        old = store.find_reusable(key)
        if old is not None and (
            old.status != "succeeded"
            or all(artifacts.exists(old.id, a["file"]) for a in old.artifacts.values())
        ):
            return old, True
        job = store.create(
            file_name=file_name, file_size=size, file_sha256=sha, dedupe_key=key, params=params
        )
        artifacts.save_input(job.id, tmp)
    finally:
        tmp.unlink(missing_ok=True)
    try:
        request.app.state.enqueue(job.id)
    except Exception as exc:  # any broker failure: the job must not stay queued with no message
        store.update(
            job.id,
            status="failed",
            stage="failed",
            error_code="broker_unavailable",
            error_message=f"could not queue the job: {exc}",
            finished_at=time.time(),
        )
        raise ApiError(503, "broker_unavailable", f"the job queue is unreachable: {exc}") from None
    # the job as submitted, not read back: a worker may already have claimed it (a race)
    return job, False


JobId = Annotated[str, PathParam(max_length=64, description="Job id (32 hex digits).")]

# --- form fields shared by the two upload endpoints -------------------------------------------------
FileField = Annotated[UploadFile, File(description="The STEP part (AP203/AP214/AP242, ISO 10303-21).")]
LayerField = Annotated[float | None, Form(ge=0.01, le=2.0, description="Layer height h, mm (default 0.2).")]
FirstField = Annotated[
    float | None, Form(ge=0.01, le=2.0, description="First-layer height h0, mm (default h).")
]
ModeField = Annotated[
    str | None,
    Form(
        pattern="^(middle|inclusive|exclusive)$",
        description="Plane placement: middle (default), inclusive, exclusive.",
    ),
]
SegField = Annotated[
    float | None, Form(ge=0.01, le=50.0, description="Longest ring segment, mm (default 0.8).")
]
ChordField = Annotated[
    float | None, Form(ge=0.0001, le=1.0, description="Largest chord error, mm (default 0.025).")
]
SlicerField = Annotated[
    str | None, Form(pattern="^(cura|prusa)$", description="Ring heights as cura or prusa computes planes.")
]
RotateField = Annotated[
    float | None,
    Form(
        ge=-360.0,
        le=360.0,
        description="Degrees to turn the part about this axis before slicing (default 0): the orientation "
        "it is printed in. Turns apply about x, then y, then z (fixed axes, right-handed).",
    ),
]
BaselinesField = Annotated[
    str | None,
    Form(
        max_length=200,
        description="Comma-separated report baselines or 'none' (default occt_fast,occt_high_quality,prusaslicer).",
        # documented, checked by the app itself (a message naming the unknown baseline and the choices)
        json_schema_extra={"pattern": BASELINES_PATTERN},
    ),
]


class UploadForm:
    """The multipart fields shared by the two upload endpoints."""

    def __init__(
        self,
        file: FileField,
        layer_height: LayerField = None,
        first_layer_height: FirstField = None,
        mode: ModeField = None,
        segment_length: SegField = None,
        chord_error: ChordField = None,
        target_slicer: SlicerField = None,
        rotate_x: RotateField = None,
        rotate_y: RotateField = None,
        rotate_z: RotateField = None,
        baselines: BaselinesField = None,
    ):
        fields = locals()  # one form field per slicing field (FastAPI needs them in the signature)
        self.file = file
        self.values = {name: fields[name] for name in SLICING_FIELDS}
        self.baselines = baselines

    def params(self, *, default_baselines: str | None = None) -> dict:
        baselines = self.baselines if self.baselines is not None else default_baselines
        return _parse_params(self.values, baselines)


Upload = Annotated[UploadForm, Depends()]


# --- routes -----------------------------------------------------------------------------------------
@app.get("/", response_class=HTMLResponse, include_in_schema=False)
def index() -> str:
    return INDEX_HTML


@app.get("/health", response_model=S.Health, operation_id="health", tags=["service"])
def health() -> S.Health:
    """Liveness: the API process answers."""
    return S.Health()


@app.get(
    "/ready",
    response_model=S.Readiness,
    operation_id="readiness",
    tags=["service"],
    responses={503: {"model": S.Readiness, "description": "Not ready."}},
)
def ready(request: Request) -> JSONResponse:
    """Readiness: the job store and the broker answer and at least one worker reported recently."""
    detail = []
    store_ok = broker_ok = False
    n_workers = 0
    try:
        _store(request).ping()
        store_ok = True
        n_workers = len(_store(request).live_workers(within_s=15.0))
    except Exception as exc:  # any database failure means not ready; say which
        detail.append(f"job store: {exc}")
    try:
        from kombu import Connection

        with Connection(_settings(request).effective_broker_url, connect_timeout=2) as conn:
            conn.ensure_connection(max_retries=1)
        broker_ok = True
    except Exception as exc:  # any broker failure means not ready; say which
        detail.append(f"broker: {exc}")
    if not n_workers:
        detail.append("no worker has reported in the last 15 s")
    body = S.Readiness(
        ready=store_ok and broker_ok and n_workers > 0,
        store=store_ok,
        broker=broker_ok,
        workers=n_workers,
        detail=detail,
    )
    return JSONResponse(body.model_dump(), status_code=200 if body.ready else 503)


@app.post(
    f"{API}/jobs",
    status_code=201,
    response_model=S.JobOut,
    operation_id="create_job",
    tags=["jobs"],
    responses={
        200: {"model": S.JobOut, "description": "An earlier job with the same file and parameters."},
        **{k: ERROR_RESPONSES[k] for k in (413, 422, 503)},
    },
)
async def create_job(
    request: Request,
    form: Upload,
) -> JSONResponse:
    """Upload a STEP part and queue its DST job. The same file with the same parameters reuses the
    earlier job (200) instead of creating one (201)."""
    params = form.params()
    tmp, size, sha = await _receive_upload(request, form.file)
    job, reused = await run_in_threadpool(
        _submit, request, tmp, size, sha, sanitise_name(form.file.filename), params
    )
    body = job_out(job, reused=reused).model_dump(mode="json")
    return JSONResponse(
        body, status_code=200 if reused else 201, headers={"Location": f"{API}/jobs/{job.id}"}
    )


@app.get(f"{API}/jobs", response_model=S.JobList, operation_id="list_jobs", tags=["jobs"])
def list_jobs(
    request: Request,
    limit: Annotated[int, Query(ge=1, le=100, description="Jobs per page.")] = 20,
    offset: Annotated[int, Query(ge=0, le=1_000_000, description="Jobs to skip.")] = 0,
    status: Annotated[S.JobStatus | None, Query(description="Only jobs in this state.")] = None,
) -> S.JobList:
    """Jobs, newest first."""
    jobs, total = _store(request).list(limit=limit, offset=offset, status=status)
    nxt = None
    if offset + len(jobs) < total:
        nxt = f"{API}/jobs?limit={limit}&offset={offset + limit}" + (f"&status={status}" if status else "")
    return S.JobList(jobs=[job_out(j) for j in jobs], total=total, limit=limit, offset=offset, next=nxt)


@app.get(
    f"{API}/jobs/{{job_id}}",
    response_model=S.JobOut,
    operation_id="get_job",
    tags=["jobs"],
    responses={404: ERROR_RESPONSES[404]},
)
def get_job(request: Request, job_id: JobId) -> S.JobOut:
    """The job's status, progress, parameters, error and artifact links."""
    return job_out(_get_job(request, job_id))


@app.get(
    f"{API}/jobs/{{job_id}}/events",
    operation_id="job_events",
    tags=["jobs"],
    responses={
        200: {"content": {"text/event-stream": {}}, "description": "Server-sent events."},
        404: ERROR_RESPONSES[404],
    },
)
async def job_events(request: Request, job_id: JobId) -> StreamingResponse:
    """Progress as server-sent events (`event: progress`, data = the job JSON) until the job ends
    (`event: end`)."""
    job = await run_in_threadpool(_get_job, request, job_id)

    async def stream() -> AsyncIterator[bytes]:
        last = None
        quiet = 0.0
        current: Job | None = job
        while True:
            if current is None:
                yield b'event: end\ndata: {"status": "deleted"}\n\n'
                return
            state = (current.status, round(current.progress, 3), current.stage)
            if state != last:
                last = state
                data = job_out(current).model_dump_json()
                kind = "end" if current.terminal else "progress"
                yield f"event: {kind}\ndata: {data}\n\n".encode()
                if current.terminal:
                    return
                quiet = 0.0
            elif quiet > 15.0:
                yield b": keep-alive\n\n"
                quiet = 0.0
            if await request.is_disconnected():
                return
            await asyncio.sleep(0.25)
            quiet += 0.25
            current = await run_in_threadpool(_store(request).get, job_id)

    return StreamingResponse(stream(), media_type="text/event-stream", headers={"Cache-Control": "no-cache"})


def _artifact_response(
    request: Request, job_id: str, name: str, download_name: str | None = None
) -> Response:
    job = _get_job(request, job_id)
    if job.status != "succeeded":
        detail = f"the job is {job.status}"
        if job.error_code:
            detail += f" ({job.error_code}: {job.error_message})"
        raise ApiError(409, "mesh_not_ready" if name == "mesh" else "artifact_not_ready", detail)
    meta = job.artifacts.get(name)
    failed = (job.result or {}).get("report_error")
    if name != "mesh" and meta is None and failed:
        raise ApiError(
            404,
            "report_failed",
            f"the deviation report could not be made ({failed['code']}: {failed['message']}); "
            f"the mesh is at {API}/jobs/{job.id}/mesh",
        )
    store = _artifacts(request)
    file = ARTIFACTS[name][0]
    if meta is None or not store.exists(job.id, file):
        raise ApiError(404, "artifact_missing", f"the job has no {name} (removed from storage?)")
    etag = f'"{meta["sha256"]}"'
    headers = {"ETag": etag, "Cache-Control": "private, max-age=0, must-revalidate"}
    if request.headers.get("if-none-match") == etag:
        return Response(status_code=304, headers={"ETag": etag})
    if not store.remote:
        return FileResponse(
            store.path(job.id, file),
            media_type=meta["media_type"],
            filename=download_name,
            content_disposition_type="attachment" if download_name else "inline",
            headers=headers,
        )
    return _ranged_stream(request, store, job.id, file, meta, download_name, headers)


def parse_range(header: str | None, size: int) -> tuple[int, int] | None:
    """(start, end inclusive) of a single-range ``bytes=`` header; None for the whole file.

    Raises ApiError 416 for a range outside the file."""
    if not header or not header.startswith("bytes=") or "," in header:
        return None
    first, _, last = header[6:].strip().partition("-")
    try:
        if first == "":
            n = int(last)
            start, end = max(0, size - n), size - 1
        else:
            start = int(first)
            end = min(int(last), size - 1) if last else size - 1
    except ValueError:
        return None
    if start > end or start >= size:
        raise ApiError(
            416,
            "range_not_satisfiable",
            f"bytes {header[6:]} of a {size}-byte file",
            headers={"Content-Range": f"bytes */{size}"},
        )
    return start, end


def _ranged_stream(request, store, job_id, file, meta, download_name, headers) -> Response:
    """An artifact from a remote store, streamed in chunks, with single-range support."""
    size = int(meta["size"])
    rng = parse_range(request.headers.get("range"), size)
    start, end = rng if rng else (0, size - 1)
    headers = {**headers, "Accept-Ranges": "bytes", "Content-Length": str(end - start + 1)}
    if download_name:
        headers["Content-Disposition"] = f'attachment; filename="{download_name}"'
    if rng:
        headers["Content-Range"] = f"bytes {start}-{end}/{size}"

    def chunks():
        with store.open(job_id, file) as fh:
            fh.seek(start)
            left = end - start + 1
            while left > 0:
                block = fh.read(min(1 << 20, left))
                if not block:
                    break
                left -= len(block)
                yield block

    return StreamingResponse(
        chunks(), status_code=206 if rng else 200, media_type=meta["media_type"], headers=headers
    )


def _stl_name(job: Job) -> str:
    return f"{Path(job.file_name).stem or 'part'}.stl"


@app.get(
    f"{API}/jobs/{{job_id}}/mesh",
    operation_id="get_mesh",
    tags=["artifacts"],
    responses={
        200: {
            "content": {"model/stl": {}, "model/3mf": {}},
            "description": "Binary STL (ranges supported), ASCII STL, or 3MF.",
        },
        404: ERROR_RESPONSES[404],
        409: ERROR_RESPONSES[409],
    },
)
async def get_mesh(
    request: Request,
    job_id: JobId,
    format: Annotated[
        str,
        Query(
            pattern="^(stl|ascii|3mf)$",
            description="stl (binary, default), ascii, or 3mf (the same float32 vertices, indexed).",
        ),
    ] = "stl",
) -> Response:
    """The DST mesh, streamed from storage with Content-Length, ETag and range requests."""
    job = await run_in_threadpool(_get_job, request, job_id)
    if format in {"ascii", "3mf"} and job.status == "succeeded":
        path = await run_in_threadpool(_converted_copy, request, job, format)
        stem = Path(_stl_name(job)).stem
        if format == "3mf":
            return FileResponse(path, media_type="model/3mf", filename=f"{stem}.3mf")
        return FileResponse(path, media_type="model/stl", filename=f"{stem}_ascii.stl")
    return await run_in_threadpool(_artifact_response, request, job_id, "mesh", _stl_name(job))


def _converted_copy(request: Request, job: Job, format: str) -> Path:
    """The ASCII STL or the 3MF, made once from the binary STL and kept beside it."""
    from worker.dst.stl_io import binary_stl_corners, merge_equal_vertices, write_3mf, write_stl

    art = _artifacts(request)
    out = art.path(job.id, "mesh.3mf" if format == "3mf" else "mesh_ascii.stl")
    if not out.is_file():
        out.parent.mkdir(parents=True, exist_ok=True)
        with art.open(job.id, "mesh.stl") as fh:
            uniq, inv = merge_equal_vertices(binary_stl_corners(fh.read()))
        name = Path(job.file_name).stem or "dst"
        if format == "3mf":
            write_3mf(out, uniq, inv.reshape(-1, 3), name=name)
        else:
            write_stl(out, uniq, inv.reshape(-1, 3), ascii=True, name=name)
    return out


for _name, _suffix, _summary in (
    ("report", "report", "The deviation report (JSON, versioned)."),
    ("report_html", "report.html", "The deviation report as a self-contained web page."),
    ("plot_svg", "plot.svg", "chord_dev and perimeter_err along z for DST and the baselines, SVG."),
    ("plot_png", "plot.png", "The same plot, PNG."),
):

    def _make(name: str):
        def endpoint(request: Request, job_id: JobId) -> Response:
            return _artifact_response(request, job_id, name)

        return endpoint

    app.add_api_route(
        f"{API}/jobs/{{job_id}}/{_suffix}",
        _make(_name),
        methods=["GET"],
        operation_id=f"get_{_name}",
        tags=["artifacts"],
        summary=_summary,
        responses={
            200: {
                "content": {ARTIFACTS[_name][1].split(";")[0]: {}},
                **({"model": Report} if _name == "report" else {}),
            },
            404: ERROR_RESPONSES[404],
            409: ERROR_RESPONSES[409],
        },
    )


@app.delete(
    f"{API}/jobs/{{job_id}}",
    status_code=204,
    operation_id="delete_job",
    tags=["jobs"],
    responses={404: ERROR_RESPONSES[404]},
)
def delete_job(request: Request, job_id: JobId) -> Response:
    """Cancel the job if it is queued or running (its process is killed) and remove it and its files."""
    job = _get_job(request, job_id)
    store = _store(request)
    if not job.terminal:
        store.update(
            job.id, cancel_requested=True, status="cancelled", stage="cancelled", finished_at=time.time()
        )
    store.delete(job.id)
    _artifacts(request).remove(job.id)
    return Response(status_code=204)


@app.post(
    f"{API}/slice",
    operation_id="slice",
    tags=["jobs"],
    responses={
        200: {"content": {"model/stl": {}}, "description": "The DST mesh (binary STL)."},
        504: {"model": S.ErrorResponse, "description": "The job did not finish in time (code wait_timeout)."},
        **{k: ERROR_RESPONSES[k] for k in (413, 422, 503)},
    },
)
async def slice_now(
    request: Request,
    form: Upload,
) -> Response:
    """One call for curl: upload, wait for the job, and get the STL streamed back. The job id is in
    the X-DST-Job header (its report stays available under /v1/jobs/{id}/report)."""
    params = form.params(default_baselines="none")
    tmp, size, sha = await _receive_upload(request, form.file)
    job, _ = await run_in_threadpool(
        _submit, request, tmp, size, sha, sanitise_name(form.file.filename), params
    )
    deadline = time.monotonic() + _settings(request).slice_wait_s
    while not job.terminal:
        if time.monotonic() > deadline:
            raise ApiError(
                504,
                "wait_timeout",
                f"job {job.id} is still {job.status}; poll {API}/jobs/{job.id}",
                headers={"X-DST-Job": job.id, "Location": f"{API}/jobs/{job.id}"},
            )
        await asyncio.sleep(0.2)
        current = await run_in_threadpool(_store(request).get, job.id)
        if current is None:
            raise ApiError(409, "job_deleted", f"job {job.id} was deleted while waiting")
        job = current
    if job.status != "succeeded":
        code = job.error_code or job.status
        status = 422 if code in INPUT_ERRORS else 504 if code == "timeout" else 500
        raise ApiError(
            status, code, job.error_message or f"the job was {job.status}", headers={"X-DST-Job": job.id}
        )
    response = await run_in_threadpool(_artifact_response, request, job.id, "mesh", _stl_name(job))
    response.headers["X-DST-Job"] = job.id
    response.headers["Location"] = f"{API}/jobs/{job.id}"
    return response
