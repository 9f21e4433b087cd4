#!/usr/bin/env bash
# Regenerates the scikit-fem reference solutions in tools/reference/results: exports the
# reference problems' level-0 voxel meshes from cutsim (accuracy-speed export-problems),
# then solves them with scikit-fem in a local virtual environment (made on first use).
# Run by scripts/test-all.sh before the Rust tests that compare against the results.
# Solutions of unchanged problems come from a cache (see below).
#   tools/reference/run.sh [PROBLEM ...]
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
root="$(cd "$here/../.." && pwd)"
. "$root/tools/python-venv.sh"
python_venv "$here"
problems="${CARGO_TARGET_DIR:-$root/target}/reference-problems"
(cd "$root" && cargo run --quiet --locked -p cutsim-sim --bin accuracy-speed -- export-problems "$problems")

# A problem solved before with the same mesh, the same solver and the same pinned
# packages has the same solution: it is taken from the cache (CUTSIM_REFERENCE_CACHE,
# by default ~/.cache/cutsim/reference) instead of being solved again (about 4 minutes
# of CI on a 2-core machine). CUTSIM_REFERENCE_FRESH=1 solves every problem anew.
cache="${CUTSIM_REFERENCE_CACHE:-${XDG_CACHE_HOME:-$HOME/.cache}/cutsim/reference}"
mkdir -p "$cache" "$here/results"
python_version="$("$here/.venv/bin/python" --version 2>&1)"
key_of() {
    { cat "$1" "$here/solve.py" "$here/requirements.txt"; echo "$python_version"; } | sha256sum | cut -c1-32
}
todo=()
for problem in "$problems"/*.json; do
    name="$(basename "$problem" .json)"
    if [ $# -gt 0 ] && ! printf '%s\n' "$@" | grep -qxF "$name"; then
        continue
    fi
    cached="$cache/$name-$(key_of "$problem").json"
    if [ "${CUTSIM_REFERENCE_FRESH:-0}" != 1 ] && [ -s "$cached" ]; then
        cp "$cached" "$here/results/$name.json"
        echo "$name: solved before for the same mesh, solver and packages (from $cached)"
    else
        todo+=("$name")
    fi
done
if [ ${#todo[@]} -gt 0 ]; then
    "$here/.venv/bin/python" "$here/solve.py" "$problems" "$here/results" "${todo[@]}"
    for name in "${todo[@]}"; do
        cp "$here/results/$name.json" "$cache/$name-$(key_of "$problems/$name.json").json"
    done
fi
