#!/usr/bin/env bash
# Fuzzes the HTTP API with schemathesis against its OpenAPI description
# (docs/openapi.yaml) and a real cutsim-server: every operation with generated valid and
# invalid requests (coverage, fuzzing and stateful phases), checking that nothing answers
# 5xx, every status code and body matches the description, invalid data is refused,
# operations that need a token refuse requests without one, and so on.
#
#   tools/api-fuzz/run.sh [MAX_EXAMPLES]      (default 100 per operation)
#
# The server binary is $CUTSIM_SERVER_BIN (default target/debug/cutsim-server, which
# `cargo build -p cutsim-server` makes). A virtual environment with the pinned
# schemathesis is made on the first run. The WebSocket upgrade is left to the cargo-fuzz
# `messages` target and the end-to-end tests (schemathesis speaks HTTP only).
set -euo pipefail
cd "$(dirname "$0")"
here=$(pwd)
root=$(cd ../.. && pwd)
examples="${1:-100}"
server_bin="${CUTSIM_SERVER_BIN:-$root/target/debug/cutsim-server}"
if [ ! -x "$server_bin" ]; then
    echo "error: $server_bin not found; run cargo build -p cutsim-server (or set CUTSIM_SERVER_BIN)" >&2
    exit 2
fi
if [ ! -x .venv/bin/schemathesis ]; then
    python3 -m venv .venv
    .venv/bin/pip install --quiet --disable-pip-version-check -r requirements.txt
fi

work=$(mktemp -d)
operator="api-fuzz-operator-token-$(date +%s%N)"
# Every request comes from 127.0.0.1: the request rate is raised out of the way (the rate
# limits have end-to-end tests of their own).
cat >"$work/server.json" <<JSON
{"limits": {"requests_per_second_per_client": 1000000, "request_burst_per_client": 1000000}}
JSON
CUTSIM_OPERATOR_TOKEN="$operator" RUST_LOG=warn "$server_bin" serve --grpc-addr 127.0.0.1:0 --http-addr 127.0.0.1:0 \
    --recordings-dir "$work/recordings" --config "$work/server.json" >"$work/stdout" 2>"$work/stderr" &
server=$!
trap 'kill $server 2>/dev/null || true; wait $server 2>/dev/null || true; rm -rf "$work"' EXIT
for _ in $(seq 1 600); do
    http=$(sed -n 's/^http listening on //p' "$work/stdout")
    [ -n "$http" ] && break
    if ! kill -0 $server 2>/dev/null; then
        echo "error: cutsim-server exited:" >&2
        cat "$work/stderr" >&2
        exit 2
    fi
    sleep 0.1
done
[ -n "$http" ] || { echo "error: cutsim-server did not start" >&2; exit 2; }

# ignored_auth is left out: a token that belongs to no session gets 404 for a session
# id that does not exist (as gRPC's NOT_FOUND) where the check expects 401; requests with
# no credentials at all are still checked, and refused with 401 before any lookup.
.venv/bin/schemathesis run "$root/docs/openapi.yaml" \
    --url "http://$http" \
    --header "cutsim-token: $operator" \
    --checks all --exclude-checks ignored_auth \
    --exclude-path '/ws/sessions/{id}' \
    --max-examples "$examples" \
    --seed 20261123 \
    --report junit --report-dir "$root/target/api-fuzz" \
    --no-color
if grep -q "panicked" "$work/stderr"; then
    echo "error: the server panicked during the run:" >&2
    cat "$work/stderr" >&2
    exit 1
fi
