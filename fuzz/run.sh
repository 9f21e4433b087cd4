#!/usr/bin/env bash
# Runs every cargo-fuzz target for a fixed number of inputs (default 2000 each; the test
# command's short run) and reports how long each ran without a crash.
#   fuzz/run.sh [RUNS] [TARGET ...]
# Needs the nightly toolchain (rustup) and cargo-fuzz (installed here when missing).
# Seeds: the bundled scenes, the example cut scripts, the shared data's meshes and label
# images (../shared/data or $CUTSIM_DATA_DIR), and fuzz/seeds. New corpus entries go to a
# temporary directory; a crash stops the run and leaves its input in fuzz/artifacts/.
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
root="$(cd "$here/.." && pwd)"
runs="${1:-2000}"
shift || true
targets=("$@")
if [ ${#targets[@]} -eq 0 ]; then
    targets=(scene cut_script obj vtk nifti vti messages)
fi
data="${CUTSIM_DATA_DIR:-$root/../shared/data}"

if ! rustup toolchain list | grep -q '^nightly'; then
    echo "==> installing the nightly toolchain (cargo-fuzz needs it)" >&2
    rustup toolchain install nightly --profile minimal
fi
if ! cargo fuzz --version >/dev/null 2>&1; then
    echo "==> installing cargo-fuzz" >&2
    cargo install cargo-fuzz --locked
fi

corpus="$(mktemp -d)"
trap 'rm -rf "$corpus"' EXIT
seeds_of() {
    case "$1" in
        scene) echo "$root/server/scenes" ;;
        cut_script) echo "$root/clients/cut-bot/examples" ;;
        obj) [ -d "$data/sofa-liver" ] && echo "$data/sofa-liver" ;;
        vtk) [ -d "$data/sofa-liver" ] && echo "$data/sofa-liver" ;;
        nifti) echo "$here/seeds/nifti"; [ -d "$data/totalsegmentator" ] && echo "$data/totalsegmentator" ;;
        vti) echo "$here/seeds/vti" ;;
        messages) ;;
    esac
}

cd "$here"
echo "==> building the fuzz targets (nightly, address sanitizer)" >&2
cargo +nightly fuzz build -O >/dev/null
for target in "${targets[@]}"; do
    mkdir -p "$corpus/$target"
    # shellcheck disable=SC2046
    start=$(date +%s.%N)
    cargo +nightly fuzz run -O "$target" "$corpus/$target" $(seeds_of "$target") -- \
        -runs="$runs" -max_len=262144 -rss_limit_mb=2048 -timeout=10 -print_final_stats=1 2> "$corpus/$target.log" \
        || { cat "$corpus/$target.log" >&2; echo "error: fuzz target $target crashed (input in fuzz/artifacts/$target/)" >&2; exit 1; }
    end=$(date +%s.%N)
    execs=$(grep -o 'stat::number_of_executed_units: *[0-9]*' "$corpus/$target.log" | grep -o '[0-9]*$' || echo "?")
    printf "%-12s %8s inputs in %6.1f s without a crash\n" "$target" "$execs" "$(awk "BEGIN { print $end - $start }")"
done
