"""The geometry core type-checks: mypy, as ``pyproject.toml`` configures it (``[tool.mypy]``: the
pydantic plugin, untyped functions' bodies checked too), finds no error in ``worker/dst``."""

from pathlib import Path

from mypy import api

ROOT = Path(__file__).resolve().parents[3]


def test_the_geometry_core_type_checks(tmp_path):
    out, err, status = api.run(
        [
            "--config-file",
            str(ROOT / "pyproject.toml"),
            "--cache-dir",
            str(tmp_path / "mypy-cache"),
            str(ROOT / "worker" / "dst"),
        ]
    )
    assert status == 0, out + err
    assert out.startswith("Success: no issues found"), out
