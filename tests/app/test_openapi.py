"""The committed OpenAPI spec is the app's: regenerate it with ``python -m app.openapi`` after a change."""

from __future__ import annotations

import json
import subprocess
import sys

from app.openapi import SPEC, spec_text


def test_committed_spec_matches_the_app():
    assert SPEC.is_file(), "openapi/openapi.json is missing: run python -m app.openapi"
    assert json.loads(SPEC.read_text()) == json.loads(spec_text()), (
        "openapi/openapi.json differs from the app: run python -m app.openapi and commit it"
    )


def test_operation_ids_are_stable_and_fields_described():
    spec = json.loads(spec_text())
    ids = [op["operationId"] for path in spec["paths"].values() for op in path.values()]
    assert len(ids) == len(set(ids))
    assert {
        "create_job",
        "get_job",
        "list_jobs",
        "job_events",
        "get_mesh",
        "get_report",
        "delete_job",
        "slice",
        "health",
        "readiness",
    } <= set(ids)
    for name, schema in spec["components"]["schemas"].items():
        for field, prop in schema.get("properties", {}).items():
            if name.startswith(("Body_", "HTTPValidationError", "ValidationError")):
                continue
            assert "description" in prop, f"{name}.{field} has no description"


def test_the_api_never_imports_occt():
    code = "import sys, app.main, app.client; sys.exit(any(m == 'OCP' or m.startswith('OCP.') for m in sys.modules))"
    assert subprocess.run([sys.executable, "-c", code]).returncode == 0


def test_the_report_schema_is_published_with_the_report_endpoint():
    """A web front end can type the deviation report from the spec: GET .../report is documented with
    the report's own model (worker.dst.report_schema, loaded without the geometry kernel)."""
    spec = json.loads(spec_text())
    ok = spec["paths"]["/v1/jobs/{job_id}/report"]["get"]["responses"]["200"]
    assert ok["content"]["application/json"]["schema"] == {"$ref": "#/components/schemas/Report"}
    schemas = spec["components"]["schemas"]
    assert {"input", "params", "planes", "reference", "meshes", "warnings"} <= set(
        schemas["Report"]["required"]
    )
    mesh = schemas["MeshReport"]["properties"]
    assert {"name", "triangles", "stl_bytes", "watertight", "seconds", "summary", "layers"} <= set(mesh)
    layer = schemas["Layer"]["properties"]
    assert {"z", "vertex_dev", "chord_dev", "perimeter_err", "loops", "loops_exact"} <= set(layer)
