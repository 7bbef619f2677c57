"""The API's JSON shapes (the OpenAPI spec is generated from them). Every field bounded and described."""

from __future__ import annotations

from datetime import datetime
from typing import Literal

from pydantic import BaseModel, Field

from worker.dst.params import SlicingMode, TargetSlicer

JobStatus = Literal["queued", "running", "succeeded", "failed", "cancelled"]


class ErrorInfo(BaseModel):
    code: str = Field(
        max_length=64,
        description="Stable machine-readable code, e.g. not_step, invalid_parameters, upload_too_large, "
        "job_not_found, mesh_not_ready, report_failed, step_read_error, not_a_solid, timeout, resource_limit, "
        "worker_crashed.",
    )
    message: str = Field(max_length=4000, description="What went wrong, for people.")


class ErrorResponse(BaseModel):
    error: ErrorInfo = Field(description="The error.")


class JobParams(BaseModel):
    layer_height: float = Field(ge=0.01, le=2.0, description="Layer height h, mm.")
    first_layer_height: float | None = Field(None, ge=0.01, le=2.0, description="First-layer height h0, mm.")
    mode: SlicingMode = Field(description="Slicing tolerance (plane placement).")
    segment_length: float = Field(ge=0.01, le=50.0, description="Longest ring segment, mm.")
    chord_error: float = Field(ge=0.0001, le=1.0, description="Largest chord error, mm.")
    target_slicer: TargetSlicer | None = Field(
        None, description="Ring heights as this slicer computes planes."
    )
    rotate_x: float = Field(
        0.0, ge=-360.0, le=360.0, description="Degrees the part is turned about x (first)."
    )
    rotate_y: float = Field(0.0, ge=-360.0, le=360.0, description="Then about y, degrees.")
    rotate_z: float = Field(0.0, ge=-360.0, le=360.0, description="Then about z, degrees.")
    baselines: list[str] = Field(max_length=6, description="Conventional meshes the report compares with.")


class JobResult(BaseModel):
    triangles: int | None = Field(None, ge=0, description="Triangles of the DST mesh.")
    vertices: int | None = Field(None, ge=0, description="Vertices of the DST mesh.")
    planes: int | None = Field(None, ge=0, description="Slicing planes (layers).")
    height_mm: float | None = Field(None, ge=0, description="Part height, mm.")
    max_vertex_dev: float | None = Field(
        None, ge=0, description="DST: largest ring vertex distance from the exact section, mm."
    )
    max_chord_dev: float | None = Field(
        None, ge=0, description="DST: largest contour distance from the exact section, mm."
    )
    warnings: list[str] = Field(
        default_factory=list, max_length=10_000, description="Warnings a user must see."
    )
    report_error: ErrorInfo | None = Field(
        None,
        description="Why the deviation report could not be made (it failed, crashed or ran out of time "
        "after the mesh was written): the job succeeded with the mesh alone.",
    )


class JobLinks(BaseModel):
    self: str = Field(max_length=200, description="This job.")
    events: str = Field(max_length=200, description="Progress as server-sent events.")
    mesh: str | None = Field(None, max_length=200, description="The DST STL (once succeeded).")
    report: str | None = Field(None, max_length=200, description="The deviation report, JSON.")
    report_html: str | None = Field(None, max_length=200, description="The deviation report as a web page.")
    plot_svg: str | None = Field(None, max_length=200, description="Per-layer deviation plot, SVG.")
    plot_png: str | None = Field(None, max_length=200, description="Per-layer deviation plot, PNG.")


class JobOut(BaseModel):
    id: str = Field(max_length=32, description="Job id.")
    status: JobStatus = Field(description="queued, running, succeeded, failed or cancelled.")
    progress: float = Field(ge=0.0, le=1.0, description="Fraction done.")
    stage: str = Field(max_length=200, description="What the job is doing now.")
    created_at: datetime = Field(description="When the job was submitted (UTC).")
    started_at: datetime | None = Field(None, description="When its current run started (UTC).")
    finished_at: datetime | None = Field(None, description="When it ended (UTC).")
    file_name: str = Field(max_length=255, description="The upload's sanitised file name.")
    file_size: int = Field(ge=0, description="Upload size, bytes.")
    file_sha256: str = Field(max_length=64, description="SHA-256 of the upload.")
    params: JobParams = Field(description="The job's slicing parameters and report baselines.")
    attempts: int = Field(
        ge=0, le=10, description="Runs started (a run interrupted by a lost worker is retried)."
    )
    reused: bool = Field(
        False, description="True when this response reuses an earlier job with the same inputs."
    )
    error: ErrorInfo | None = Field(None, description="Why the job failed.")
    result: JobResult | None = Field(None, description="Summary of the finished job.")
    links: JobLinks = Field(description="Where to find the job and its artifacts.")


class JobList(BaseModel):
    jobs: list[JobOut] = Field(max_length=100, description="This page's jobs, newest first.")
    total: int = Field(ge=0, description="Jobs matching the filter.")
    limit: int = Field(ge=1, le=100, description="Page size asked for.")
    offset: int = Field(ge=0, description="Jobs skipped.")
    next: str | None = Field(None, max_length=300, description="URL of the next page, if any.")


class Health(BaseModel):
    status: Literal["ok"] = Field("ok", description="Always ok when the API answers.")


class Readiness(BaseModel):
    ready: bool = Field(description="True when jobs can be accepted and run.")
    store: bool = Field(description="The job store answers.")
    broker: bool = Field(description="The broker accepts connections.")
    workers: int = Field(ge=0, description="Workers seen recently.")
    detail: list[str] = Field(default_factory=list, max_length=20, description="What is not ready.")
