#!/usr/bin/env bash
# Regenerates the scikit-fem reference solutions in tools/reference/results: exports the
# reference problems' level-0 voxel meshes from cutsim (accuracy-speed export-problems),
# then solves them with scikit-fem in a local virtual environment (made on first use).
# Run by scripts/test-all.sh before the Rust tests that compare against the results.
#   tools/reference/run.sh [PROBLEM ...]
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
root="$(cd "$here/../.." && pwd)"
. "$root/tools/python-venv.sh"
python_venv "$here"
problems="${CARGO_TARGET_DIR:-$root/target}/reference-problems"
(cd "$root" && cargo run --quiet --locked -p cutsim-sim --bin accuracy-speed -- export-problems "$problems")
"$here/.venv/bin/python" "$here/solve.py" "$problems" "$here/results" "$@"
