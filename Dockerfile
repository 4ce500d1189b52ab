# CPU image by default. For CUDA: --build-arg BASE_IMAGE=nvidia/cuda:12.8.0-cudnn-runtime-ubuntu24.04
# (bases without Python get it from apt below).
ARG BASE_IMAGE=python:3.11-slim
FROM ${BASE_IMAGE}

ENV PYTHONUNBUFFERED=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    PIP_NO_CACHE_DIR=1 \
    MPLBACKEND=Agg \
    WANDB_MODE=offline \
    DEBIAN_FRONTEND=noninteractive

RUN if ! command -v python3 >/dev/null 2>&1 || ! python3 -c "import venv, ensurepip" >/dev/null 2>&1; then \
        apt-get update && apt-get install -y --no-install-recommends python3 python3-venv python3-pip \
        && rm -rf /var/lib/apt/lists/*; \
    fi

WORKDIR /opt/vitfly
COPY . .
# The README's install, into a venv that is first on PATH.
RUN python3 -m venv .venv && .venv/bin/pip install -e ".[dev]"
ENV PATH=/opt/vitfly/.venv/bin:$PATH

# The main job; `docker run IMAGE pytest -q` runs the tests.
CMD ["vitfly", "pipeline", "--config", "configs/quickstart.yaml"]
