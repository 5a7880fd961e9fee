#!/usr/bin/env bash
# The bus under load: two SAC trainings with 2 actors each on this machine (the load an
# `exp run --parallel 2` grid puts on 2 cores), for MINUTES, then what the bus did:
# transports zenoh closed, curve rows without an evaluation, messages dropped, retried or
# lost, and each training's peak resident memory.
#   bash deploy/bench-bus.sh [MINUTES] [PBRL_BINARY] [extra pbrl train flags...]
# e.g. bash deploy/bench-bus.sh 20 target/release/pbrl
# The runs go to $PBRL_BENCH_DIR (default: a temporary folder, removed afterwards).
set -euo pipefail
cd "$(dirname "$0")/.."
minutes=${1:-20}
bin=${2:-target/release/pbrl}
shift 2 || shift $# || true
[ -x "$bin" ] || cargo build --release --locked
dir=${PBRL_BENCH_DIR:-$(mktemp -d)}
keep=${PBRL_BENCH_DIR:+1}
mkdir -p "$dir"
echo "bus load check: 2 x (pbrl train --algo sac, 2 actors) for $minutes min with $bin; runs in $dir"
pids=()
for seed in 1 2; do
    rm -rf "$dir/sac-s$seed" # NOTE: --fresh keeps the old train.log; start clean.
    # NOTE: RUST_LOG keeps zenoh's warnings and errors (a closed transport is one) in the
    # run's train.log whatever the binary's default filter.
    RUST_LOG=${RUST_LOG:-info,zenoh=warn,zenoh_transport=warn} \
        "$bin" train --algo sac --reward true --actors 2 --seed "$seed" --steps 100000000 \
        --quiet --fresh --out "$dir/sac-s$seed" "$@" >"$dir/out-$seed.txt" 2>&1 &
    pids+=($!)
done
trap 'kill -TERM ${pids[*]} 2>/dev/null || true' INT TERM EXIT
start=$(date +%s)
end=$((start + minutes * 60))
peak=(0 0)
while [ "$(date +%s)" -lt "$end" ]; do
    sleep 10
    for k in 0 1; do
        # VmHWM: the process's peak resident set so far.
        hwm=$(awk '/VmHWM/ { print $2 }' "/proc/${pids[$k]}/status" 2>/dev/null || echo 0)
        [ "${hwm:-0}" -gt "${peak[$k]}" ] && peak[$k]=$hwm
    done
    if [ $((($(date +%s) - start) % 60)) -lt 10 ]; then
        for seed in 1 2; do
            rows=$(($(wc -l <"$dir/sac-s$seed/curve.csv" 2>/dev/null || echo 1) - 1))
            printf '  %4d s: run %d, %d curve rows\n' $(($(date +%s) - start)) "$seed" "$rows"
        done
    fi
done
kill -TERM "${pids[@]}" 2>/dev/null || true
wait "${pids[@]}" 2>/dev/null || true

col() { # the index (1-based) of column $2 in CSV header file $1, or 0
    head -1 "$1" | tr ',' '\n' | grep -nx "$2" | cut -d: -f1 || echo 0
}
printf '%-8s %10s %6s %14s %12s %8s %8s %8s %10s\n' run env_steps rows rows_no_eval closed_transp dropped retried lost peak_rss_mb
for seed in 1 2; do
    run="$dir/sac-s$seed"
    curve="$run/curve.csv"
    ev=$(col "$curve" eval_episodes)
    rows=$(($(wc -l <"$curve") - 1))
    noeval=$(awk -F, -v c="$ev" 'NR > 1 && $c == 0 { n++ } END { print n + 0 }' "$curve")
    steps=$(tail -1 "$curve" | cut -d, -f1)
    closed=$(grep -c "Closing transport" "$run/train.log" || true)
    dropped=0; retried=0; lost=0
    c=$(col "$curve" dropped_messages); [ "$c" -gt 0 ] && dropped=$(tail -1 "$curve" | cut -d, -f"$c")
    c=$(col "$curve" retried_messages); [ "$c" -gt 0 ] && retried=$(tail -1 "$curve" | cut -d, -f"$c")
    c=$(col "$curve" lost_messages); [ "$c" -gt 0 ] && lost=$(tail -1 "$curve" | cut -d, -f"$c")
    # Older builds count no retries; their re-asked evaluations are in the log.
    [ "$retried" = 0 ] && retried=$(grep -c "asking another actor" "$run/train.log" || true)
    rss=$((peak[seed - 1] / 1024))
    printf '%-8s %10s %6d %14d %12d %8s %8s %8s %10s\n' "sac-s$seed" "$steps" "$rows" "$noeval" "$closed" "$dropped" "$retried" "$lost" "$rss"
done
[ -n "$keep" ] || rm -rf "$dir"
