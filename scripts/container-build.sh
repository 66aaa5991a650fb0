#!/usr/bin/env bash
# Build the Dockerfile for real with podman, run the image, and drive it over HTTP; the same for
# the Ray images (the API on a Ray head, one Ray worker node). Not part of `make test`: minutes.
#
#   bash scripts/container-build.sh [base|plain|ray|all]      (default: all)
#
# Needs Debian's podman, runc, debootstrap and python3-yaml (apt-get install podman runc debootstrap
# python3-yaml) and root.
# No Docker daemon and no Docker Hub here, so:
#   * storage driver vfs and runtime runc (podman --storage-driver vfs --runtime runc), with a
#     containers.conf that sets no default ulimits (CONTAINERS_CONF);
#   * the base image is Debian bookworm minbase with python3 and python3-venv, made with
#     debootstrap and imported with `podman import` (BASE_IMAGE build argument);
#   * torch comes from a folder of wheels when TORCH_WHEELS names one (default /opt/wheels when
#     it holds a torch wheel; its 2.13.0+cpu sorts above PyPI's CUDA 2.13.0), else from
#     PyTorch's CPU index (TORCH_PIP_ARGS build argument);
#   * pip in the build reaches PyPI with this host's CA bundle (/etc/ssl/certs, mounted).
# The plain image's container uses the host's network and binds 127.0.0.1; the Ray check runs
# in a pod that has no network but loopback (check_ray says why).
# Prints the build times, image sizes and each end-to-end check; exits non-zero on a failure.
set -euo pipefail

REPO=$(cd "$(dirname "$0")/.." && pwd)
WORK=${VOXFUSION_CONTAINER_WORK:-/var/tmp/voxfusion-container}
MIRROR=${DEBIAN_MIRROR:-http://deb.debian.org/debian}
BASE=localhost/voxfusion-base:bookworm
TORCH_WHEELS=${TORCH_WHEELS:-/opt/wheels}
STEP=${1:-all}
mkdir -p "$WORK"
export CONTAINERS_CONF="$WORK/containers.conf"
printf '[containers]\ndefault_ulimits = []\n' > "$CONTAINERS_CONF"
PODMAN=(podman --storage-driver vfs --runtime runc)
NAMES=()
PODS=()

cleanup() {
    for name in "${NAMES[@]}"; do "${PODMAN[@]}" rm -f "$name" >/dev/null 2>&1 || true; done
    for pod in "${PODS[@]}"; do "${PODMAN[@]}" pod rm -f "$pod" >/dev/null 2>&1 || true; done
}
trap cleanup EXIT

log() { printf '[container-build %s] %s\n' "$(date -u +%H:%M:%S)" "$*"; }

build_base() {
    if "${PODMAN[@]}" image exists "$BASE"; then log "base image $BASE exists"; return; fi
    local rootfs="$WORK/rootfs" start=$SECONDS
    rm -rf "$rootfs"
    debootstrap --variant=minbase --include=python3,python3-venv bookworm "$rootfs" "$MIRROR"
    rm -rf "$rootfs/var/cache/apt/archives/"*.deb
    tar -C "$rootfs" -c . | "${PODMAN[@]}" import - "$BASE"
    rm -rf "$rootfs"
    log "base image $BASE made in $((SECONDS - start)) s"
}

build_image() {  # build_image TAG EXTRAS
    local tag=$1 extras=$2 start=$SECONDS
    local args=(--build-arg "BASE_IMAGE=$BASE" --build-arg "EXTRAS=$extras" --network host
                --volume /etc/ssl/certs:/etc/ssl/certs:ro --env PIP_CERT=/etc/ssl/certs/ca-certificates.crt)
    if compgen -G "$TORCH_WHEELS/torch-*.whl" >/dev/null; then
        args+=(--volume "$TORCH_WHEELS:/wheels:ro" --build-arg "TORCH_PIP_ARGS=--find-links /wheels")
    fi
    "${PODMAN[@]}" build "${args[@]}" -t "$tag" "$REPO"
    local size
    size=$("${PODMAN[@]}" image inspect "$tag" --format '{{.Size}}')
    log "image $tag built in $((SECONDS - start)) s, $((size / 1024 / 1024)) MiB"
}

free_port() {
    python3 -c 'import socket; s = socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])'
}

run_container() {  # run_container NAME IMAGE [podman run args...] -- COMMAND...
    local name=$1 image=$2
    shift 2
    local opts=()
    while [[ $1 != -- ]]; do opts+=("$1"); shift; done
    shift
    NAMES+=("$name")
    "${PODMAN[@]}" run -d --name "$name" --network host --shm-size 1g "${opts[@]}" "$image" "$@" >/dev/null
}

drive() {  # drive PORT LABEL [--ray]: the page, a synthetic session to the end, a render
    python3 "$REPO/scripts/container-drive.py" --port "$1" --label "$2" "${@:3}"
}

check_plain() {
    local port name=voxfusion-check
    port=$(free_port)
    run_container "$name" localhost/voxfusion -e VOXFUSION_VIEWER_PORT=-1 -- \
        voxfusion serve --host 127.0.0.1 --port "$port"
    drive "$port" "plain image" || { "${PODMAN[@]}" logs "$name" | tail -30; return 1; }
}

compose_service() {  # compose_service SERVICE: its shell command, then its environment as NAME=VALUE lines
    python3 - "$REPO/deploy/compose.ray.yml" "$1" <<'PY'
import sys

import yaml  # Debian: python3-yaml

service = yaml.safe_load(open(sys.argv[1]))["services"][sys.argv[2]]
command = service["command"]
assert command[:2] == ["sh", "-c"], f"{sys.argv[2]}: expected sh -c COMMAND, got {command}"
print(command[2].replace("$$", "$"))  # compose's escape for a literal $
for name, value in (service.get("environment") or {}).items():
    print(f"{name}={value}")
PY
}

check_ray() {
    # The compose file's own commands (deploy/compose.ray.yml: the API on the Ray head, one
    # worker node), each in its own container, in a pod whose network namespace holds only the
    # loopback interface (--network none). There `ray start` keeps 127.0.0.1: it swaps a loopback
    # --node-ip-address for the address of the route to the internet, and without an interface
    # there is none (on the host's network it took the machine's interface address, where only
    # loopback may be used here). Adapted to the shared namespace: the hosts file names `api`
    # (compose's service name) and the pod's host name 127.0.0.1, the worker's dashboard agent
    # takes a port of its own, and the drive script runs inside the pod.
    local pod=voxfusion-ray-pod head=voxfusion-ray-head worker=voxfusion-ray-worker token=container-check
    local head_command worker_command agent=52400
    head_command=$(compose_service api | head -1)
    worker_command=$(compose_service ray-worker | head -1)
    worker_command=${worker_command/ --block/ --dashboard-agent-listen-port=$agent --block}
    local head_env=()
    while IFS= read -r line; do
        [[ $line == VOXFUSION_TOKEN=* ]] && line="VOXFUSION_TOKEN=$token"
        head_env+=(-e "$line")
    done < <(compose_service api | tail -n +2)
    printf '127.0.0.1 localhost api voxfusion-ray\n' > "$WORK/hosts"
    "${PODMAN[@]}" pod rm -f "$pod" >/dev/null 2>&1 || true
    "${PODMAN[@]}" pod create --name "$pod" --network none --hostname voxfusion-ray >/dev/null
    PODS+=("$pod")
    local mounts=(-v "$WORK/hosts:/etc/hosts:ro" -v "$REPO/scripts:/drive:ro" --shm-size 1g)
    "${PODMAN[@]}" run -d --pod "$pod" --name "$head" "${mounts[@]}" "${head_env[@]}" -e VOXFUSION_VIEWER_PORT=-1 \
        localhost/voxfusion-ray sh -c "$head_command" >/dev/null
    "${PODMAN[@]}" run -d --pod "$pod" --name "$worker" "${mounts[@]}" -e RAY_WORKER_CPUS=2 \
        localhost/voxfusion-ray sh -c "sleep 10; $worker_command" >/dev/null
    "${PODMAN[@]}" exec "$head" python /drive/container-drive.py --port 8000 --token "$token" --ray \
        --label "ray images, compose commands (API on the head, one worker node, loopback-only pod)" \
        || { "${PODMAN[@]}" logs "$head" | tail -30; "${PODMAN[@]}" logs "$worker" | tail -30; return 1; }
    # Nothing in the pod could listen on the machine's interfaces: it has none but loopback.
    "${PODMAN[@]}" exec "$head" python -c "import socket; print('pod interfaces:', [n for _, n in socket.if_nameindex()])"
}

case $STEP in
    base) build_base ;;
    plain) build_base; build_image localhost/voxfusion ""; check_plain ;;
    ray) build_base; build_image localhost/voxfusion-ray ray; check_ray ;;
    all) build_base; build_image localhost/voxfusion ""; check_plain
         build_image localhost/voxfusion-ray ray; check_ray ;;
    *) echo "usage: $0 [base|plain|ray|all]" >&2; exit 2 ;;
esac
log "done: $STEP"
