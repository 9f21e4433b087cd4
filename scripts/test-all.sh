#!/usr/bin/env bash
# Runs every test of cutsim. This is the README's test command and what CI runs.
set -euo pipefail
cd "$(dirname "$0")/.."

# Anatomical test data lives beside the repository (../shared/data) unless
# CUTSIM_DATA_DIR says otherwise.
data_dir="${CUTSIM_DATA_DIR:-$(pwd)/../shared/data}"
if [ ! -d "$data_dir" ]; then
    echo "error: shared data not found at $data_dir; set CUTSIM_DATA_DIR to the shared data directory" >&2
    exit 2
fi
export CUTSIM_DATA_DIR="$data_dir"

echo "==> cargo test (unit, integration and end-to-end tests)"
cargo test --workspace --locked
