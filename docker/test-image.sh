#!/usr/bin/env bash
# Builds the container image from docker/Dockerfile on this machine and runs it: the
# image's HEALTHCHECK must report healthy, the viewer must be served with its security
# headers, and cut-bot (from the same image) must pass an example script against the
# containerized server. Part of the test command (scripts/test-all.sh).
#
# No registry is reachable here, so the two base images the Dockerfile names are made
# locally first (docker/base-images.sh: debootstrap, and this machine's Rust toolchain).
# With no Docker engine running, one is installed (Debian's docker.io, as root) and
# started privately for the run (its own data root, no bridge, no iptables rules), then
# stopped. $CUTSIM_DOCKER_WORK keeps its images between runs (default target/docker).
set -euo pipefail
cd "$(dirname "$0")/.."
root=$(pwd)
work="${CUTSIM_DOCKER_WORK:-$root/target/docker}"
mkdir -p "$work"
image=cutsim:test
operator="container-test-operator-$(date +%s%N)"
data_dir="${CUTSIM_DATA_DIR:-$root/../shared/data}"

started_engine=""
container=""
cleanup() {
    [ -n "$container" ] && docker rm -f "$container" >/dev/null 2>&1 || true
    if [ -n "$started_engine" ]; then
        kill "$(cat "$work/docker.pid")" 2>/dev/null || true
        for _ in $(seq 1 50); do [ -e "$work/docker.pid" ] || break; sleep 0.2; done
        umount "$work/exec/netns/default" 2>/dev/null || true
    fi
}
trap cleanup EXIT

if ! docker info >/dev/null 2>&1; then
    if [ "$(id -u)" != 0 ]; then
        echo "error: no Docker engine answers and this is not root: start one (dockerd) or run as root" >&2
        exit 2
    fi
    if ! command -v dockerd >/dev/null || ! command -v debootstrap >/dev/null; then
        echo "==> installing Docker's engine and debootstrap (apt-get)"
        apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq docker.io debootstrap >/dev/null
    fi
    echo "==> starting a private Docker engine ($work)"
    dockerd --iptables=false --bridge=none --data-root "$work/data" --exec-root "$work/exec" \
        --pidfile "$work/docker.pid" -H "unix://$work/docker.sock" >"$work/dockerd.log" 2>&1 &
    started_engine=1
    export DOCKER_HOST="unix://$work/docker.sock"
    for _ in $(seq 1 150); do docker info >/dev/null 2>&1 && break; sleep 0.2; done
    docker info >/dev/null 2>&1 || { echo "error: dockerd did not start:" >&2; tail -20 "$work/dockerd.log" >&2; exit 2; }
fi

docker/base-images.sh "$work"

echo "==> docker build -f docker/Dockerfile -t $image ."
started=$(date +%s)
# The legacy builder: no buildx plugin here. --network=host: the build's apt-get, npm
# and cargo reach their registries through this machine's network.
DOCKER_BUILDKIT=0 docker build --network=host -f docker/Dockerfile -t "$image" . >"$work/build.log" 2>&1 || {
    echo "error: the image did not build:" >&2
    tail -40 "$work/build.log" >&2
    exit 1
}
echo "    built in $(($(date +%s) - started)) s ($(docker image inspect "$image" --format '{{.Size}}' | awk '{printf "%.0f MB", $1/1e6}'))"

for port in 50051 8080; do
    if (exec 3<>"/dev/tcp/127.0.0.1/$port") 2>/dev/null; then
        echo "error: port $port is taken on this machine; the container's server needs it (host network)" >&2
        exit 2
    fi
done
echo "==> docker run $image (host network, the shared data read-only)"
volume=()
[ -d "$data_dir" ] && volume=(-v "$(cd "$data_dir" && pwd):/data:ro")
container=$(docker run -d --network=host -e CUTSIM_OPERATOR_TOKEN="$operator" "${volume[@]}" "$image")

echo "==> waiting for the image's HEALTHCHECK (cutsim-server health)"
status=starting
for _ in $(seq 1 90); do
    status=$(docker inspect --format '{{.State.Health.Status}}' "$container")
    [ "$status" = healthy ] && break
    [ "$(docker inspect --format '{{.State.Running}}' "$container")" = true ] || break
    sleep 1
done
if [ "$status" != healthy ]; then
    echo "error: the container is $status, not healthy:" >&2
    docker inspect --format '{{json .State.Health}}' "$container" >&2 || true
    docker logs "$container" 2>&1 | tail -20 >&2
    exit 1
fi
echo "    healthy: $(docker inspect --format '{{(index .State.Health.Log 0).Output}}' "$container" | tr -d '\n')"

echo "==> the viewer from the container, with its Content-Security-Policy"
page=$(exec 3<>/dev/tcp/127.0.0.1/8080; printf 'GET / HTTP/1.1\r\nHost: 127.0.0.1:8080\r\nConnection: close\r\n\r\n' >&3; cat <&3)
echo "$page" | head -1 | grep -q " 200 " || { echo "error: GET / did not answer 200: $(echo "$page" | head -1)" >&2; exit 1; }
echo "$page" | grep -qi "^content-security-policy: default-src 'none'; script-src 'self' 'sha256-" || { echo "error: no strict CSP on the viewer page" >&2; exit 1; }

echo "==> cut-bot (from the same image) runs an example script against the containerized server"
docker run --rm --network=host -e CUTSIM_OPERATOR_TOKEN="$operator" --entrypoint cut-bot "$image" \
    run /opt/cutsim/examples/skin-patch-straight.json --server http://127.0.0.1:50051 >"$work/cut-bot.log" 2>&1 || {
    echo "error: the example script did not pass against the container:" >&2
    tail -20 "$work/cut-bot.log" >&2
    exit 1
}
grep -E "^result" "$work/cut-bot.log" | sed 's/^/    /'
# An anonymous client cannot create a session in the container either.
if docker run --rm --network=host --entrypoint cut-bot "$image" run /opt/cutsim/examples/skin-patch-straight.json --server http://127.0.0.1:50051 >/dev/null 2>&1; then
    echo "error: cut-bot without an operator token created a session" >&2
    exit 1
fi
echo "==> the container image works"
