#!/usr/bin/env bash
# Runs cutsim-server on the default scene with the web viewer: the README's run command.
# Installs the viewer's JavaScript dependencies (npm, seconds) and builds the server
# (cargo, release) on the first run. Arguments go to `cutsim-server serve`.
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

exec cargo run --release -p cutsim-server -- serve "$@"
