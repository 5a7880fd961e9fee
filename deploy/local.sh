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
# The learner in its own session: a Ctrl-C reaches this script, which passes one SIGTERM
# on (the learner checkpoints and stops its actors; a second signal would skip that).
setsid "$bin" learner --mode router --listen "tcp/127.0.0.1:$port" --run "$run" --actors "$actors" "$@" &
learner=$!
trap 'kill -TERM $learner 2>/dev/null || true; wait $learner || true' INT TERM
trap 'kill ${pids[*]:-} 2>/dev/null || true' EXIT
pids=()
for ((i = 0; i < actors; i++)); do
    "$bin" actor --connect "tcp/127.0.0.1:$port" --run "$run" --id "$i" --task "$task" &
    pids+=($!)
done
wait "$learner"
wait "${pids[@]}" 2>/dev/null || true
