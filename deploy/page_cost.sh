#!/usr/bin/env bash
# What the labelling page costs the learner: env steps/s of the same 40k-step Decoupled
# PEBBLE run (2 actors, seed 1, first session at 2k steps, 100 queries a session every 2k)
# with (a) the scripted oracle in-process, (b) the human teacher with two terminal clients
# answering (each pair replayed and drawn by the teacher; every PACE seconds, default as
# fast as they can), (c) the human teacher with nobody labelling. Prints the last curve
# row's env_steps_per_s and, for (b), the median and 90th percentile of the time to serve a
# pair (the /next round trip, as the clients measure it).
set -euo pipefail
bin=${PBRL_BIN:-target/release/pbrl}
out=${1:-/tmp/page-cost}
rm -rf "$out"; mkdir -p "$out"
common=(--steps 40000 --actors 2 --seed 1 --unsup-steps 2000 --feedback-interval 2000 --log-every 10000 --quiet)
rate() { tail -n 1 "$1/curve.csv" | python3 -c "import sys,csv; r=next(csv.reader(sys.stdin)); print(r[0], 'env steps,', r[22], 'env steps/s')"; }
"$bin" train "${common[@]}" --teacher oracle --run pc-oracle --out "$out/oracle" > "$out/oracle.log" 2>&1
echo "oracle in-process:        $(rate "$out/oracle")"
"$bin" train "${common[@]}" --teacher human --http 127.0.0.1:18181 --undo-s 0 --shadow oracle --repeat-share 0.2 --run pc-human --out "$out/human" > "$out/human.log" 2>&1 &
train=$!
clients=()
for name in ann bob; do
  python3 deploy/label.py --url http://127.0.0.1:18181 --name $name --answer alternate --count 100000 --timeout 600 --pace "${PACE:-0}" --timing > "$out/$name.log" 2>&1 &
  clients+=($!)
done
wait $train || true
kill "${clients[@]}" 2>/dev/null || true
echo "human, 2 clients labelling: $(rate "$out/human") ; answers: $(grep -c answered "$out/ann.log") + $(grep -c answered "$out/bob.log")"
cat "$out/ann.log" "$out/bob.log" | python3 -c "
import re, statistics, sys
ms = sorted(float(m.group(1)) for m in re.finditer(r'^served query \d+ in (\d+) ms', sys.stdin.read(), re.M))
if ms:
    print(f'serving a pair: median {statistics.median(ms):.0f} ms, 90th percentile {ms[int(0.9 * (len(ms) - 1))]:.0f} ms, {len(ms)} pairs')"
"$bin" labels stats "$out/human"
"$bin" train "${common[@]}" --teacher human --http 127.0.0.1:18182 --run pc-idle --out "$out/idle" > "$out/idle.log" 2>&1
echo "human, nobody labelling:  $(rate "$out/idle")"
