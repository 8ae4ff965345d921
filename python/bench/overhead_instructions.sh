#!/usr/bin/env bash
# The overhead of a torch block-drop epoch over the Rust call, in instructions (valgrind's
# callgrind counts them the same whatever else the machine is doing). Three processes with
# one rayon thread each, all of which set up and run one epoch of each kind as a warm-up:
# that alone, then N more Rust epochs, then N more torch epochs; the overhead is
# (torch − setup) / (rust − setup) − 1.
#
#     bash bench/overhead_instructions.sh [N]
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")"
n="${1:-2}"
py="${PYTHON:-python}"
out="$(mktemp -d)"
trap 'rm -rf "$out"' EXIT
count() {
    RAYON_NUM_THREADS=1 valgrind --tool=callgrind --callgrind-out-file="$out/cg.%p" \
        "$py" epoch.py "$1" "$n" >/dev/null 2>"$out/log"
    grep -h "Collected" "$out/log" | awk '{s += $4} END {printf "%.0f\n", s}'
}
setup=$(count none)
rust=$(count rust)
torch=$(count torch)
echo "instructions: setup $setup, + $n rust epochs $rust, + $n torch epochs $torch"
awk -v s="$setup" -v r="$rust" -v t="$torch" -v n="$n" 'BEGIN {
    printf "per epoch: rust %.4g, torch %.4g instructions; overhead %+.2f %%\n",
        (r - s) / n, (t - s) / n, 100 * ((t - s) / (r - s) - 1) }'
