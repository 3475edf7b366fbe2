# syntax=docker/dockerfile:1
# aefabmap runtime image: `aefabmap run|replay|eval|demo|publish` with the runtime set only
# (numpy, OpenCV headless, onnxruntime, zenoh, mcap; no torch, no onnx, no scipy).
#
#   docker buildx build --platform linux/arm64,linux/amd64 -t aefabmap:0.2.0 .
#   docker run --rm aefabmap:0.2.0 demo          # smoke test: publish -> run -> loops -> MCAP -> replay check
#   docker run --rm --network host -v /var/log/aefabmap:/var/log/aefabmap aefabmap:0.2.0 \
#       run --model /bundle --key robot/camera/image --connect tcp/127.0.0.1:7447 \
#           --mcap /var/log/aefabmap/lcd.mcap --image-every 30     # (+ -v /path/to/bundle:/bundle:ro)
#
# One lock for both architectures: deploy/requirements-board.txt is resolved for aarch64 but
# carries the hashes of every wheel of each pinned release, and deploy/lock.sh refuses to write it
# unless the x86-64 resolution is the same package set, so amd64 installs the same versions,
# hash-checked. Base: Python 3.11 on Debian 12 (glibc 2.36 >= the 2.28 the wheels need); pin it
# by digest for production (`docker buildx imagetools inspect python:3.11-slim-bookworm`).
ARG PYTHON_IMAGE=python:3.11-slim-bookworm

FROM ${PYTHON_IMAGE} AS build
ENV PIP_DISABLE_PIP_VERSION_CHECK=1 PIP_NO_CACHE_DIR=1
# Dependencies first (their layer survives source edits): exact versions, hash-checked, wheels only.
COPY deploy/requirements-board.txt /tmp/requirements-board.txt
RUN python -m venv /opt/aefabmap \
 && /opt/aefabmap/bin/pip install --require-hashes --only-binary=:all: --no-deps -r /tmp/requirements-board.txt
# Then the project itself, as a wheel with its compiled kernels (the build backend and the C
# compiler stay in this stage).
RUN apt-get update && apt-get install -y --no-install-recommends gcc libc6-dev && rm -rf /var/lib/apt/lists/*
COPY . /src
RUN pip wheel --no-deps -w /tmp/dist /src \
 && /opt/aefabmap/bin/pip install --no-deps /tmp/dist/aefabmap-*.whl \
 && /opt/aefabmap/bin/pip check \
 && /opt/aefabmap/bin/python -c "from aefabmap_runtime.core.kernels import native; assert native.available(), native.unavailable_reason()" \
 && ! /opt/aefabmap/bin/python -c "import torch" 2>/dev/null

FROM ${PYTHON_IMAGE}
LABEL org.opencontainers.image.title="aefabmap runtime" \
      org.opencontainers.image.licenses="BSD-3-Clause"
COPY --from=build /opt/aefabmap /opt/aefabmap
# A fixed non-root uid (orchestrators check runAsNonRoot numerically); its home is the work dir.
RUN useradd --system --uid 10001 --user-group --create-home --home-dir /var/lib/aefabmap aefabmap \
 && install -d -o aefabmap -g aefabmap -m 0750 /var/log/aefabmap
USER 10001:10001
WORKDIR /var/lib/aefabmap
# OMP_NUM_THREADS=1: one core for the detector, as in deploy/aefabmap.service.
ENV PATH=/opt/aefabmap/bin:$PATH \
    OMP_NUM_THREADS=1 \
    PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1
# No HEALTHCHECK: `aefabmap run` has no probe endpoint; its liveness is the stats it publishes on
# <key>/lcd/stats, and `docker run IMAGE demo` is the smoke test (exit 0 = the whole chain works).
HEALTHCHECK NONE
ENTRYPOINT ["aefabmap"]
CMD ["--help"]
