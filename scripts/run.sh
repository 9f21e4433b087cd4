#!/usr/bin/env bash
# Runs cutsim-server on the default scene with the web viewer: the README's run command.
# Installs the viewer's JavaScript dependencies (npm, seconds) and builds the server and
# the clients (cargo, release) on the first run. Arguments go to `cutsim-server serve`.
# docker/Dockerfile repeats these set-up steps word for word (tests/e2e/deploy.rs checks).
set -euo pipefail
cd "$(dirname "$0")/.."

if [ ! -d web-viewer/node_modules ]; then
    if ! command -v npm >/dev/null; then
        echo "error: npm (Node.js) is needed for the web viewer's libraries; install Node.js 18 or newer" >&2
        exit 2
    fi
    echo "==> installing the web viewer's libraries (npm ci)" >&2
    (cd web-viewer && npm ci --no-audit --no-fund)
fi

cargo build --release --locked -p cutsim-server -p cut-bot -p haptic-bridge
exec cargo run --release --locked -p cutsim-server -- serve "$@"
