# RibPull service image: the API (uvicorn app.main:app) and the worker (celery -A worker.celery_app)
# run from this one image with different commands (see docker-compose.yml).
#
#   docker build -t ribpull .                                  # CPU torch (default)
#   docker build -t ribpull:cuda \
#     --build-arg BASE_IMAGE=nvidia/cuda:12.8.1-cudnn-runtime-ubuntu24.04 \
#     --build-arg TORCH_INDEX_URL=https://download.pytorch.org/whl/cu128 .
ARG BASE_IMAGE=python:3.11-slim

# the web page's three.js: the exact versions of web/package-lock.json (npm ci checks their hashes)
FROM node:20-slim AS web
WORKDIR /web
COPY web/package.json web/package-lock.json ./
RUN npm ci --ignore-scripts --no-audit --no-fund

FROM ${BASE_IMAGE}

ARG TORCH_INDEX_URL=https://download.pytorch.org/whl/cpu
ARG TORCH_VERSION=2.13.0

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    VIRTUAL_ENV=/opt/venv \
    NUMBA_CACHE_DIR=/opt/numba-cache \
    PATH=/opt/venv/bin:$PATH \
    RIBPULL_STORAGE_DIR=/data \
    RIBPULL_HOST=0.0.0.0 \
    PORT=8000

# CUDA base images have no Python: install one (python:3.11-slim already has it)
RUN if ! command -v python3 >/dev/null 2>&1; then \
        apt-get update && apt-get install -y --no-install-recommends python3 python3-venv python3-pip \
        && rm -rf /var/lib/apt/lists/*; \
    fi \
    && python3 -m venv /opt/venv \
    && pip install --upgrade pip

WORKDIR /srv/ribpull
# torch first, from the index that matches the base image (CPU wheels by default)
RUN pip install --index-url ${TORCH_INDEX_URL} "torch==${TORCH_VERSION}"
COPY pyproject.toml README.md ./
COPY ribpull_core ./ribpull_core
COPY app ./app
COPY worker ./worker
COPY scripts ./scripts
COPY web ./web
# scripts/build_web.py copies the files the page loads into app/web/static/vendor/ (package data)
RUN --mount=type=bind,from=web,source=/web/node_modules,target=/tmp/node_modules \
    python3 scripts/build_web.py --node-modules /tmp/node_modules && python3 scripts/build_web.py --check
# the Postgres driver (psycopg2-binary) and alembic are main dependencies; `ribpull-db upgrade` migrates
RUN pip install . \
    && useradd --system --uid 10001 --home-dir /data ribpull \
    && mkdir -p /data && chown ribpull /data
# numba's kernels compiled into the image (NUMBA_CACHE_DIR), not in each container's first job; a
# machine whose CPU differs from the build machine's compiles its own on first use, beside these
RUN mkdir -p /opt/numba-cache && ribpull warmup && chown -R ribpull /opt/numba-cache

USER ribpull
VOLUME ["/data"]
EXPOSE 8000
HEALTHCHECK --interval=30s --timeout=5s --start-period=20s --retries=3 \
    CMD python -c "import os, urllib.request; urllib.request.urlopen('http://127.0.0.1:%s/healthz' % os.environ.get('PORT', '8000'), timeout=4)"
CMD ["sh", "-c", "exec uvicorn app.main:app --host 0.0.0.0 --port ${PORT:-8000} --proxy-headers --http app.httpserver:HardenedH11Protocol"]
