#!/usr/bin/env bash
# Runs every test of cutsim: Rust unit, integration and end-to-end tests (real server,
# real gRPC and WebSocket clients), then the browser tests of the web viewer (Debian's
# chromium, headless). This is the README's test command and what CI runs.
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

# Each phase's line says how long the run has taken so far (CI allows 90 minutes: the
# timings show where they go).
started=$SECONDS
phase() { echo "==> [$(( (SECONDS - started) / 60 )) min $(( (SECONDS - started) % 60 )) s] $*"; }

if ! command -v python3 >/dev/null; then
    echo "error: python3 is needed for the scikit-fem reference and the Python client example's test" >&2
    exit 2
fi
phase "scikit-fem reference solutions (tools/reference; a virtual environment made on the first run)"
tools/reference/run.sh

phase "generated cut scripts: the CT skin's examples and test fixture are what their generator writes"
python3 scripts/skin-real-examples.py --check

phase "cargo test (unit, integration and end-to-end tests)"
# CI's log keeps the head and the tail of a long run: a failing test's message, printed
# where its binary ran, can fall in the cut middle. On failure the failures are printed
# again at the end.
mkdir -p target
cargo_log=target/cargo-test.log
if ! cargo test --workspace --locked 2>&1 | tee "$cargo_log"; then
    echo "==> cargo test failed; its failures again (the whole output is above and in $cargo_log):"
    grep -E -A40 '^---- .* stdout ----$' "$cargo_log" | head -400 || true
    grep -E '^test .* FAILED$|^error: test failed' "$cargo_log" || true
    exit 1
fi

phase "fuzzing: every cargo-fuzz target for 20,000 inputs (docs/fuzzing.md)"
fuzz/run.sh 20000

# The server binary below is the one `cargo test --workspace` built (its end-to-end tests
# run it), as is the short load-and-fault run (clients/load-test/tests/short_run.rs). A
# `cargo build -p …` here would resolve the workspace's features differently and rebuild
# the network stack: about 4 minutes each.
phase "HTTP API fuzzing: schemathesis against docs/openapi.yaml and a real server (tools/api-fuzz)"
tools/api-fuzz/run.sh 100

phase "Python client example (grpcio stubs from proto/cutsim.proto) against a real server"
clients/python/setup.sh >/dev/null
CUTSIM_SERVER_BIN="$(pwd)/target/debug/cutsim-server" clients/python/.venv/bin/python -m unittest discover -s clients/python -p "test_*.py"

phase "browser tests (web viewer in headless chromium)"
if ! command -v npm >/dev/null; then
    echo "error: npm (Node.js) is needed for the browser tests; install Node.js 18 or newer" >&2
    exit 2
fi
chromium="${CHROMIUM:-/usr/bin/chromium}"
if [ ! -x "$chromium" ]; then
    if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
        phase "installing Debian's chromium (apt-get)"
        apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null
    else
        echo "error: chromium not found at $chromium; install it (apt-get install chromium) or set CHROMIUM" >&2
        exit 2
    fi
fi
(cd web-viewer && npm ci --no-audit --no-fund --loglevel=error)
(cd tests/browser && npm ci --no-audit --no-fund --loglevel=error && CUTSIM_SERVER_BIN="$(pwd)/../../target/debug/cutsim-server" npm test)

phase "the container image: docker/Dockerfile built and run (health check, viewer, cut-bot)"
docker/test-image.sh

phase "all tests passed"
