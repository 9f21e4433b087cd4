#!/usr/bin/env bash
# Makes the base images docker/Dockerfile names, on a machine that reaches no container
# registry (only Debian's package mirror): `debian:bookworm-slim` from debootstrap, and
# `rust:1.95-bookworm` from it with gcc and this machine's Rust toolchain (the same
# Debian userland), trusting the certificate authorities this machine adds to Debian's
# (/usr/local/share/ca-certificates: here, the egress proxy's), so that the image build's
# npm and cargo reach their registries the way this machine does. Where a registry is
# reachable, `docker build` pulls the real ones and this script is not needed. Images
# already present are kept.
#
#   docker/base-images.sh [WORK_DIR]     (default target/docker)
set -euo pipefail
cd "$(dirname "$0")/.."
work="${1:-target/docker}"
mkdir -p "$work"
work=$(cd "$work" && pwd)
rust_version=1.95

if ! docker image inspect debian:bookworm-slim >/dev/null 2>&1; then
    echo "==> debian:bookworm-slim from debootstrap (Debian's mirror)"
    rm -rf "$work/rootfs"
    debootstrap --variant=minbase bookworm "$work/rootfs" http://deb.debian.org/debian >"$work/debootstrap.log" 2>&1 || {
        echo "error: debootstrap failed:" >&2
        tail -20 "$work/debootstrap.log" >&2
        exit 2
    }
    rm -rf "$work/rootfs/var/cache/apt/archives/"*.deb "$work/rootfs/var/lib/apt/lists/"*
    tar --numeric-owner -C "$work/rootfs" -cf "$work/rootfs.tar" .
    docker import "$work/rootfs.tar" debian:bookworm-slim >/dev/null
    rm -rf "$work/rootfs" "$work/rootfs.tar"
fi

if ! docker image inspect "rust:$rust_version-bookworm" >/dev/null 2>&1; then
    sysroot=$(rustc --print sysroot)
    version=$(rustc --version | awk '{print $2}')
    case "$version" in
        "$rust_version".*) ;;
        *) echo "error: this machine's rustc is $version; docker/Dockerfile builds with $rust_version" >&2; exit 2 ;;
    esac
    echo "==> rust:$rust_version-bookworm from debian:bookworm-slim, gcc and this machine's Rust $version"
    context="$work/rust-context"
    rm -rf "$context"
    mkdir -p "$context/rust" "$context/extra-ca"
    cp -a "$sysroot/bin" "$sysroot/lib" "$context/rust/"
    cp /usr/local/share/ca-certificates/*.crt "$context/extra-ca/" 2>/dev/null || true
    cat >"$context/Dockerfile" <<'EOF'
FROM debian:bookworm-slim
COPY extra-ca/ /usr/local/share/ca-certificates/
RUN apt-get update && apt-get install -y --no-install-recommends gcc libc6-dev ca-certificates \
    && update-ca-certificates && rm -rf /var/lib/apt/lists/*
COPY rust /usr/local/rust
# Node (npm) keeps its own list of authorities unless told to read the system's.
ENV PATH=/usr/local/rust/bin:/usr/local/cargo/bin:/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin \
    CARGO_HOME=/usr/local/cargo \
    NODE_EXTRA_CA_CERTS=/etc/ssl/certs/ca-certificates.crt
RUN cargo --version && rustc --version
EOF
    DOCKER_BUILDKIT=0 docker build --network=host -t "rust:$rust_version-bookworm" "$context" >"$work/rust-image.log" 2>&1 || {
        echo "error: the Rust base image did not build:" >&2
        tail -20 "$work/rust-image.log" >&2
        exit 2
    }
    rm -rf "$context"
fi
