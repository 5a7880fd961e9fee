#!/usr/bin/env bash
# What TLS with access control costs: the same run (SAC on the feeding world's truth, 2
# actor processes, seed 1, STEPS env steps, default 20,000) as separate processes through
# the stock zenohd on loopback, over plain TCP (deploy/router.json5) and over TLS with
# mutual authentication and the role rules (deploy/certs.sh), alternated ROUNDS times
# (default 2). Prints each run's env steps/s (the whole run: the last curve row's env steps
# over its wall time) and the ratio of the means.
#   bash deploy/bench-tls.sh [STEPS] [ROUNDS]
set -euo pipefail
cd "$(dirname "$0")/.."
steps=${1:-20000}
rounds=${2:-2}
bin=${PBRL_BIN:-target/release/pbrl}
zenohd=${PBRL_ZENOHD:-$(command -v zenohd || echo "${CARGO_HOME:-$HOME/.cargo}/bin/zenohd")}
out=$(mktemp -d /tmp/pbrl-bench-tls.XXXXXX)
trap 'kill $(jobs -p) 2>/dev/null || true; rm -rf "$out"' EXIT
port=17467
sed "s#tcp/127.0.0.1:7447#tcp/127.0.0.1:$port#" deploy/router.json5 > "$out/tcp.json5"
bash deploy/certs.sh --out "$out/certs" --run bench --router-listen "tls/127.0.0.1:$port" \
    router:hub@127.0.0.1 learner:l actor:a > /dev/null 2>&1
one() { # tcp|tls ROUND
    local kind=$1 dir=$out/$1-$2 cfg lc ac
    if [ "$kind" = tcp ]; then
        cfg=$out/tcp.json5
        lc=(--connect "tcp/127.0.0.1:$port")
        ac=("${lc[@]}")
    else
        cfg=$out/certs/router-tls.json5
        local c=$out/certs
        lc=(--connect "tls/127.0.0.1:$port" --tls-ca "$c/ca.pem" --tls-cert "$c/learner-l.pem" --tls-key "$c/learner-l.key")
        ac=(--connect "tls/127.0.0.1:$port" --tls-ca "$c/ca.pem" --tls-cert "$c/actor-a.pem" --tls-key "$c/actor-a.key")
    fi
    "$zenohd" -c "$cfg" > /dev/null 2> "$out/zenohd-$kind-$2.log" &
    local router=$!
    until (exec 3<> "/dev/tcp/127.0.0.1/$port") 2>/dev/null; do sleep 0.2; done
    for i in 0 1; do
        "$bin" actor --task feeding --run bench --id "$i" "${ac[@]}" > /dev/null 2>&1 &
    done
    "$bin" learner --task feeding --algo sac --reward truth --actors 2 --seed 1 \
        --steps "$steps" --log-every "$steps" --eval-episodes 0 --quiet --run bench \
        --out "$dir" "${lc[@]}" > "$out/learner-$kind-$2.log" 2>&1
    wait $(jobs -p | grep -v "^$router$") 2>/dev/null || true
    kill "$router"
    wait "$router" 2>/dev/null || true
    python3 -c "
import csv, sys
r = list(csv.DictReader(open('$dir/curve.csv')))[-1]
print(int(r['env_steps']) / float(r['wall_s']))"
}
declare -A sum=([tcp]=0 [tls]=0)
for r in $(seq "$rounds"); do
    for kind in tcp tls; do
        rate=$(one "$kind" "$r")
        printf '%s, round %d: %.0f env steps/s\n' "$kind" "$r" "$rate"
        sum[$kind]=$(python3 -c "print(${sum[$kind]} + $rate)")
    done
done
python3 -c "print(f'TLS with access control: {${sum[tls]} / ${sum[tcp]}:.2f}x the env steps/s of plain TCP ($rounds rounds of $steps env steps)')"
