#!/usr/bin/env bash
# A soak of the bus: 16 actor processes and 4 labellers against one learner through the
# stock zenohd router on loopback, for MINUTES, then a report.
#
#   bash deploy/soak.sh MINUTES [OUT]        (OUT default /tmp/pbrl-soak; emptied first)
#
# The learner trains Decoupled PEBBLE on the feeding world from people at a labelling page
# (`pbrl teacher --teacher human`); the labellers are scripted clients of its HTTP API
# (deploy/label.py): two at a person's pace (a pair every 3 s), one every 0.5 s and one as
# fast as it can. The budget never runs out in a soak. At the end the labellers stop, the
# teacher's last answers reach the learner, and it prints: env steps/s, answers given and
# stored (each once), transports zenoh closed, and the peak and final resident memory of
# each process kind (the largest of its processes), with the figure after the warm-up (a
# quarter of the way in) to compare the final with.
# PBRL_BIN (default target/release/pbrl) and PBRL_ZENOHD (default: zenohd on the PATH or in
# $CARGO_HOME/bin; bash deploy/setup.sh builds it) pick the programs.
set -euo pipefail
cd "$(dirname "$0")/.."
minutes=${1:?usage: deploy/soak.sh MINUTES [OUT]}
out=${2:-/tmp/pbrl-soak}
bin=${PBRL_BIN:-target/release/pbrl}
zenohd=${PBRL_ZENOHD:-$(command -v zenohd || echo "${CARGO_HOME:-$HOME/.cargo}/bin/zenohd")}
[ -x "$bin" ] || { echo "soak: $bin not built (cargo build --release)" >&2; exit 1; }
[ -x "$zenohd" ] || { echo "soak: no zenohd (bash deploy/setup.sh builds it)" >&2; exit 1; }
port=${PBRL_SOAK_PORT:-17457}
# The learner's two buffers grow by design until full: the replay buffer (264 bytes a
# transition on the feeding world; default 1M) and the annotation buffer (about 31 kB a
# trajectory; default 10,000). Here they hold 100,000 transitions and 500 trajectories, so
# both are full within the warm-up (about 100 s here) and a learner's memory that still
# grows after it is a leak. PBRL_SOAK_REPLAY and PBRL_SOAK_ANNOTATION set them.
replay=${PBRL_SOAK_REPLAY:-100000}
annotation=${PBRL_SOAK_ANNOTATION:-500}
http=${PBRL_SOAK_HTTP:-18190}
rm -rf "$out"
mkdir -p "$out"
export RUST_LOG=${RUST_LOG:-warn,pbrl=info,pbrl_learner=info,pbrl_teacher=info,pbrl_actor=info}
sed "s#tcp/127.0.0.1:7447#tcp/127.0.0.1:$port#" deploy/router.json5 > "$out/router.json5"
connect=(--connect "tcp/127.0.0.1:$port")
pids=()
kinds=()
start() { # KIND LOG PROGRAM ARGS...
    local kind=$1 log=$2
    shift 2
    "$@" > "$log.out" 2> "$log" &
    pids+=($!)
    kinds+=("$kind")
}
cleanup() { kill "${pids[@]}" 2>/dev/null || true; }
trap cleanup EXIT

start router "$out/zenohd.log" "$zenohd" -c "$out/router.json5"
until (exec 3<> "/dev/tcp/127.0.0.1/$port") 2>/dev/null; do sleep 0.2; done
start learner "$out/learner.log" "$bin" learner --task feeding --algo sac --reward decoupled \
    --actors 16 --teacher human --steps 100000000 --max-feedback 1000000 \
    --sac-replay-capacity "$replay" --annotation-capacity "$annotation" \
    --unsup-steps 2000 --feedback-interval 2000 --queries-per-session 50 --log-every 10000 \
    --quiet --run soak --out "$out/run" "${connect[@]}"
learner=${pids[-1]}
for i in $(seq 0 15); do
    start actor "$out/actor-$i.log" "$bin" actor --task feeding --run soak --id "$i" "${connect[@]}"
done
start teacher "$out/teacher.log" "$bin" teacher --teacher human --run soak --http "127.0.0.1:$http" \
    --undo-s 0 --teacher-state "$out/teacher.sqlite" "${connect[@]}"
teacher=${pids[-1]}
until (exec 3<> "/dev/tcp/127.0.0.1/$http") 2>/dev/null; do sleep 0.2; done
labellers=()
for spec in ana:3 ben:3 cat:0.5 dan:0; do
    start labeller "$out/label-${spec%%:*}.log" python3 deploy/label.py --url "http://127.0.0.1:$http" \
        --name "${spec%%:*}" --answer alternate --count 100000000 --pace "${spec#*:}" \
        --timeout $((minutes * 60 + 600))
    labellers+=(${pids[-1]})
done

# Resident memory of every process every 5 s: "seconds kind pid kB".
secs=$((minutes * 60))
t0=$SECONDS
date +%s > "$out/t0"  # the epoch second of t = 0, to line the labels' times up with rss.txt
while [ $((SECONDS - t0)) -lt "$secs" ]; do
    for k in "${!pids[@]}"; do
        kb=$(awk '/^VmRSS/ { print $2 }' "/proc/${pids[$k]}/status" 2>/dev/null || true)
        [ -n "$kb" ] && echo "$((SECONDS - t0)) ${kinds[$k]} ${pids[$k]} $kb"
    done >> "$out/rss.txt"
    if ! kill -0 "$learner" 2>/dev/null; then echo "soak: the learner exited early (see $out/learner.log)" >&2; exit 1; fi
    sleep 5
done

# The labellers stop; the teacher hands on what it was given; then the learner stops.
kill "${labellers[@]}" 2>/dev/null || true
acked() { python3 -c "
import sqlite3, sys
c = sqlite3.connect('file:$out/teacher.sqlite?mode=ro', uri=True, timeout=5)
print(*c.execute('SELECT count(*), coalesce(sum(acked), 0) FROM outbox').fetchone())"; }
for _ in $(seq 120); do
    read -r n a < <(acked)
    [ "$n" = "$a" ] && break
    sleep 0.5
done
kill -TERM "$learner"
wait "$learner" || true
kill -TERM "$teacher" 2>/dev/null || true
wait "$teacher" 2>/dev/null || true

python3 - "$out" "$secs" <<'EOF'
import collections, csv, glob, sqlite3, sys
out, secs = sys.argv[1], int(sys.argv[2])
rows = list(csv.DictReader(open(f"{out}/run/curve.csv")))
last = rows[-1]
steps, wall = int(last["env_steps"]), float(last["wall_s"])
print(f"soak of {secs // 60} min: {steps:,} env steps in {wall:.0f} s, {steps / wall:,.0f} env steps/s "
      f"(last row: {float(last['env_steps_per_s']):,.0f})")
ro = lambda p: sqlite3.connect(f"file:{p}?mode=ro", uri=True, timeout=5)
given = [q for (q,) in ro(f"{out}/teacher.sqlite").execute("SELECT query FROM outbox WHERE repeat = 0")]
stored = [q for (q,) in ro(f"{out}/run/labels.sqlite").execute(
    "SELECT id FROM queries WHERE answer IS NOT NULL")]
repeats = ro(f"{out}/teacher.sqlite").execute("SELECT count(*) FROM outbox WHERE repeat = 1").fetchone()[0]
missing, extra = set(given) - set(stored), set(stored) - set(given)
print(f"answers: {len(given)} given (+{repeats} repeats), {len(stored)} stored, "
      f"{len(missing)} given and not stored, {len(extra)} stored and not given, "
      f"{len(given) - len(set(given))} given twice")
closed = sum(open(f).read().count("Closing transport") for f in glob.glob(f"{out}/*.log"))
print(f"transports closed: {closed}")
samples = collections.defaultdict(lambda: collections.defaultdict(int))
for line in open(f"{out}/rss.txt"):
    t, kind, pid, kb = line.split()
    samples[kind][int(t)] = max(samples[kind][int(t)], int(kb))
kinds = ["router", "learner", "actor", "teacher", "labeller"]
# A kind's sample nearest a time: the loop above stamps each line with its own second, so
# two kinds' samples of one round may fall a second apart.
nearest = lambda s, x: min(s, key=lambda t: abs(t - x))
ts = sorted(samples["learner"])
t_warm = nearest(ts, secs / 4)
print(f"{'process':10} {'after warm-up':>14} {'peak':>9} {'final':>9}  (MiB, largest of its kind)")
for kind in kinds:
    s = samples[kind]
    mib = lambda kb: f"{kb / 1024:,.0f}"
    print(f"{kind:10} {mib(s[nearest(s, secs / 4)]):>14} {mib(max(s.values())):>9} {mib(s[max(s)]):>9}")
# The learner holds D, the labelled segments, by design: what it grew after the warm-up set
# beside what D grew by over the same window (each side's steps of observation, action and
# comfort features, 4 bytes a number).
t0 = int(open(f"{out}/t0").read())
labels = ro(f"{out}/run/labels.sqlite")
def d_at(t):
    return labels.execute("""
        SELECT count(*), coalesce(sum(
            l.first_len * (a.obs_dim + a.act_dim + coalesce(length(a.features), 0) / 4 / a.steps)
          + l.second_len * (b.obs_dim + b.act_dim + coalesce(length(b.features), 0) / 4 / b.steps)), 0) * 4
        FROM labels l JOIN trajectories a ON a.id = l.first JOIN trajectories b ON b.id = l.second
        WHERE l.answered_at_ms <= ?""", ((t0 + t) * 1000,)).fetchone()
(n0, b0), (n1, b1) = d_at(t_warm), d_at(ts[-1])
grew = (samples["learner"][ts[-1]] - samples["learner"][t_warm]) / 1024
print(f"learner from {t_warm} s to {ts[-1]} s: grew {grew:,.1f} MiB while D grew from {n0:,} to {n1:,} "
      f"labels, {(b1 - b0) / 2**20:,.1f} MiB ({(b1 - b0) / max(n1 - n0, 1) / 1000:,.1f} kB a label)")
# Every 30 s: each kind's memory, the labels stored and D's size (rss-30s.csv).
with open(f"{out}/rss-30s.csv", "w") as f:
    print("# largest resident memory (MiB) of each process kind, the sample nearest each 30 s; "
          "labels stored by then and D's segments (MiB)", file=f)
    print("seconds," + ",".join(f"{k}_mib" for k in kinds) + ",labels_stored,d_mib", file=f)
    for mark in range(0, ts[-1] + 1, 30):
        t = nearest(ts, mark)
        n, b = d_at(t)
        mibs = [f"{samples[k][nearest(samples[k], t)] / 1024:.0f}" for k in kinds]
        print(",".join([str(t), *mibs, str(n), f"{b / 2**20:.1f}"]), file=f)
EOF
