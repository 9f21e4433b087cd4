#!/usr/bin/env bash
# Forceps lifting a fold of the default skin through the real haptic bridge (`sim:grasp`),
# run by run under four couplings in turn: the grasp damper or the free-motion damper,
# each with and without the local model of the tissue's stiffness
# (docs/haptic-bridge.md, "The local model"). Prints each run's pull while lifted and
# held (2.2–3.0 s) and its swing, then how many runs of each coupling held the fold's
# full pull steadily.
#
#   scripts/bridge-grasp-trials.sh [RUNS] [--load]
#
# RUNS: runs per coupling (default 3). --load: two busy loops keep both cores loaded
# while the runs go (the harshest case the docs quote). Needs nothing but the repository;
# builds the release server and bridge first.
set -euo pipefail
cd "$(dirname "$0")/.."
runs="${1:-3}"
load="${2:-}"
cargo build --release -q -p cutsim-server -p haptic-bridge
work="$(mktemp -d)"
pids=()
cleanup() {
    for p in "${pids[@]}"; do kill "$p" 2>/dev/null || true; done
    rm -rf "$work"
}
trap cleanup EXIT

# A server that waits a second for a busy bridge's commands before lifting its tool.
echo '{"limits": {"stale_command_ms": 1000}}' > "$work/server.json"
./target/release/cutsim-server serve --grpc-addr 127.0.0.1:0 --http-addr 127.0.0.1:0 --config "$work/server.json" --recordings-dir "$work/recordings" > "$work/server.log" 2>&1 &
pids+=($!)
for _ in $(seq 100); do grep -q "control token" "$work/server.log" && break; sleep 0.1; done
grpc="$(sed -n 's/^grpc listening on //p' "$work/server.log")"
session="$(sed -n 's/^session \([0-9a-f]*\) on scene.*/\1/p' "$work/server.log")"
token="$(sed -n 's/^ *control token: *//p' "$work/server.log")"
[ -n "$grpc" ] && [ -n "$session" ] && [ -n "$token" ] || { echo "error: the server did not start:" >&2; cat "$work/server.log" >&2; exit 1; }

if [ "$load" = "--load" ]; then
    for _ in 1 2; do sh -c 'while :; do :; done' & pids+=($!); done
fi

# name, local model's largest stiffness (0: off), grasp damper (2: the free-motion one's)
couplings=("grasp-damper+model 3000 6" "grasp-damper 0 6" "free-damper+model 3000 2" "free-damper 0 2")
for i in $(seq "$runs"); do
    for c in "${couplings[@]}"; do
        read -r name stiffness damping <<< "$c"
        echo "{\"coupling\": {\"local_max_stiffness_n_per_m\": $stiffness, \"grasp_damping_n_s_per_m\": $damping}}" > "$work/$name.json"
        ./target/release/haptic-bridge --server "http://$grpc" --session "$session" --token "$token" --tool 2 --device sim:grasp \
            --duration-s 3.5 --max-force-n 3.3 --max-force-rate-n-per-s 100 --stale-ms 1000 \
            --config "$work/$name.json" --report "$work/$name-$i.json" --trace "$work/$name-$i.csv" 2>/dev/null
        sleep 0.5
    done
done

python3 - "$work" "$runs" "${couplings[@]}" <<'PY'
import csv, json, sys
work, runs, couplings = sys.argv[1], int(sys.argv[2]), [c.split()[0] for c in sys.argv[3:]]
held = {}
for i in range(1, runs + 1):
    for name in couplings:
        rows = list(csv.DictReader(open(f"{work}/{name}-{i}.csv")))
        lifted = [float(r["fz_n"]) for r in rows if 2.2 < float(r["t_s"]) < 3.0]
        report = json.load(open(f"{work}/{name}-{i}.json"))
        pull, swing = -sum(lifted) / len(lifted), max(lifted) - min(lifted)
        # The fold's full pull is 0.63 N (docs/haptic-bridge.md); held steadily: within
        # 0.05 N of it, swinging by less than 0.05 N.
        steady = abs(pull - 0.63) < 0.05 and swing < 0.05
        held.setdefault(name, []).append(steady)
        print(f"run {i} {name:>20}: pulled {pull:.3f} N, swinging {swing:.3f} N peak to peak; local stiffness up to {report['max_local_stiffness_n_per_m']:.0f} N/m; rate-limited {report['rate_limited']} ticks")
for name in couplings:
    print(f"{name:>20}: held the full pull steadily in {sum(held[name])} of {len(held[name])} runs")
PY
