#!/usr/bin/env bash
# Learner and actors as separate processes on this machine, joined through a router on
# loopback (the learner's session listens; the actors connect to it).
#   bash deploy/local.sh [ACTORS] [extra pbrl learner flags...]
# e.g. bash deploy/local.sh 2 --algo sac --steps 200000 --task feeding
set -euo pipefail
cd "$(dirname "$0")/.."
actors=${1:-2}
shift || true
port=${PBRL_PORT:-7447}
run=${PBRL_RUN:-local}
bin=target/release/pbrl
[ -x "$bin" ] || cargo build --release
task=feeding
for ((i = 1; i <= $#; i++)); do
    if [ "${!i}" = "--task" ]; then j=$((i + 1)); task=${!j}; fi
done
"$bin" learner --mode router --listen "tcp/127.0.0.1:$port" --run "$run" --actors "$actors" "$@" &
learner=$!
trap 'kill $learner ${pids[*]:-} 2>/dev/null || true' EXIT INT TERM
pids=()
for ((i = 0; i < actors; i++)); do
    "$bin" actor --connect "tcp/127.0.0.1:$port" --run "$run" --id "$i" --task "$task" &
    pids+=($!)
done
wait "$learner"
wait "${pids[@]}" 2>/dev/null || true
