# dst-service: `dst serve` on the embedded default (SQLite broker and job store, artifacts in /data).
FROM python:3.11-slim-bookworm

# libGL/libX11 bits OCCT's wheel links against; curl for the health check
RUN apt-get update \
 && apt-get install -y --no-install-recommends libgl1 libglib2.0-0 libxrender1 libxext6 libsm6 curl \
 && rm -rf /var/lib/apt/lists/*

WORKDIR /app
COPY pyproject.toml README.md ./
COPY app ./app
COPY worker ./worker
COPY openapi ./openapi
RUN pip install --no-cache-dir . && useradd --create-home --uid 10001 dst && mkdir /data && chown dst /data

USER dst
ENV DST_DATA_DIR=/data MPLCONFIGDIR=/tmp/matplotlib
VOLUME ["/data"]
EXPOSE 8000
HEALTHCHECK --interval=30s --timeout=5s --start-period=60s --retries=3 \
  CMD curl -fsS http://127.0.0.1:8000/health || exit 1
CMD ["dst", "serve", "--host", "0.0.0.0", "--port", "8000"]
