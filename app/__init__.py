"""dst-service HTTP API (FastAPI). Imports no OCCT: the geometry runs in the workers."""
