"""Write the service's OpenAPI spec: ``python -m app.openapi [openapi/openapi.json]``.

The committed ``openapi/openapi.json`` is checked against the app by ``tests/app/test_openapi.py``.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

SPEC = Path(__file__).resolve().parents[1] / "openapi" / "openapi.json"


def spec_text() -> str:
    from app.main import app

    return json.dumps(app.openapi(), indent=2, sort_keys=True) + "\n"


if __name__ == "__main__":
    out = Path(sys.argv[1]) if len(sys.argv) > 1 else SPEC
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(spec_text())
    print(f"wrote {out}")
