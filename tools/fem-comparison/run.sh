#!/usr/bin/env bash
# Times cutsim's level-0 branched grid against MuJoCo's flex FEM on the same cantilever,
# side by side in one run (docs/fem-comparison.md). MuJoCo comes from PyPI into a local
# virtual environment made on first use; cutsim is the release server binary's headless
# run. Not part of the test command (it times; tests do not).
#   tools/fem-comparison/run.sh [--rounds N] [--steps N] [--out FILE]
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
root="$(cd "$here/../.." && pwd)"
. "$root/tools/python-venv.sh"
python_venv "$here"
(cd "$root" && cargo build --quiet --locked --release -p cutsim-server)
server="${CARGO_TARGET_DIR:-$root/target}/release/cutsim-server"
exec "$here/.venv/bin/python" "$here/compare.py" --server "$server" --out "$root/docs/fem-comparison.md" "$@"
