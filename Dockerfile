# voxfusion web application, CPU build.
#   docker build -t voxfusion .
#   docker run -p 8000:8000 -v voxfusion-data:/data -e VOXFUSION_TOKEN=change-me voxfusion
# then open http://localhost:8000/?token=change-me (the 3D viewer is relayed through port 8000;
# 8080 is viser's own port, which admits only that token-checked relay: no need to publish it).
#
# Build arguments:
#   BASE_IMAGE      any Debian-like image with python3 (>= 3.10) and its venv module
#                   (default python:3.11-slim; scripts/container-build.sh uses a debootstrap base)
#   TORCH_PIP_ARGS  where pip takes torch from (default PyTorch's CPU index; a bare PyPI resolve
#                   would pull several GB of CUDA wheels)
#   EXTRAS          optional extras of the package, e.g. "ray" for the Ray cluster image
#                   (deploy/compose.ray.yml: the API server, the Ray head and the Ray workers)
ARG BASE_IMAGE=python:3.11-slim
FROM ${BASE_IMAGE}

ARG TORCH_VERSION=2.13.0
ARG TORCH_PIP_ARGS="--index-url https://download.pytorch.org/whl/cpu"
ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    VOXFUSION_DATA_DIR=/data \
    VOXFUSION_VIEWER_PORT=8080 \
    PATH=/opt/venv/bin:$PATH

# libglib2.0-0 and libgomp1: shared libraries opencv-python-headless and torch load at import.
RUN apt-get update \
    && apt-get install -y --no-install-recommends libglib2.0-0 libgomp1 \
    && rm -rf /var/lib/apt/lists/*

# A virtual environment: Debian's own python3 refuses pip installs into the system (PEP 668),
# and the same layout works on python:3.11-slim.
RUN python3 -m venv /opt/venv && pip install --upgrade pip

# The CPU build of torch first: a plain resolve of the package's "torch" requirement would
# pull several GB of CUDA wheels.
RUN pip install ${TORCH_PIP_ARGS} "torch==${TORCH_VERSION}"

WORKDIR /app
# Declared here, not above: the layers before (system libraries, torch) are shared by the plain
# and the Ray image.
ARG EXTRAS=""
# Dependencies in their own layer, so that code changes do not reinstall them.
COPY pyproject.toml README.md ./
RUN mkdir -p slam ar server client \
    && touch slam/__init__.py ar/__init__.py server/__init__.py client/__init__.py \
    && pip install ".${EXTRAS:+[$EXTRAS]}" && pip uninstall -y voxfusion
COPY slam ./slam
COPY ar ./ar
COPY server ./server
# The stream client: `voxfusion`'s parser includes its `stream` subcommand.
COPY client ./client
COPY static ./static
# Editable: the page's files in /app/static are served from where they are.
RUN pip install --no-deps -e .

RUN useradd --create-home --uid 1000 voxfusion \
    && mkdir -p /data && chown voxfusion:voxfusion /data
USER voxfusion
VOLUME ["/data"]
EXPOSE 8000 8080

HEALTHCHECK --interval=30s --timeout=5s --start-period=60s \
    CMD python -c "import urllib.request; urllib.request.urlopen('http://127.0.0.1:8000/openapi.json', timeout=4)"

# viser binds loopback inside the container by default; the page reaches it through the API.
CMD ["voxfusion", "serve", "--host", "0.0.0.0", "--port", "8000"]
