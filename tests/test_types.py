"""The code type-checks: mypy, as ``pyproject.toml`` configures it (``[tool.mypy]``: the pydantic
plugin, untyped functions' bodies checked too), finds no error in ``app`` and ``worker``."""

from pathlib import Path

from mypy import api

ROOT = Path(__file__).resolve().parents[1]


def test_the_service_and_its_geometry_core_type_check(tmp_path):
    out, err, status = api.run(
        [
            "--config-file",
            str(ROOT / "pyproject.toml"),
            "--cache-dir",
            str(tmp_path / "mypy-cache"),
            str(ROOT / "app"),
            str(ROOT / "worker"),
        ]
    )
    assert status == 0, out + err
    assert out.startswith("Success: no issues found"), out
