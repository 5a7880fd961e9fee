#!/usr/bin/env bash
# Certificates and the router's config for pbrl across machines over Zenoh's TLS, with
# mutual authentication and access control by role (docs/deploy.md says what goes where).
#
#   bash deploy/certs.sh [--out DIR] [--run RUN] [--router-listen ENDPOINT] ROLE:NAME[@IP] ...
#
# ROLE is router, learner, actor or teacher; NAME names the host (letters, digits, - and
# _); IP (or a DNS name) is the address others reach it at, written into its certificate
# (the router's, and a learner's that listens, must have one). ROLE page makes the HTTPS
# certificate of a labelling page (`pbrl teacher --teacher human --https-cert`), reached
# at IP; it is no Zenoh role. It makes, in DIR (default deploy/certs):
#   ca.pem, ca.key         the certificate authority (keep ca.key on this machine only)
#   ROLE-NAME.pem, .key    one certificate and key per role and host, common name
#                          pbrl-ROLE-NAME: the router's access control keys on it
#   router-tls.json5       the stock zenohd's config: TLS only, mutual authentication,
#                          multicast off, and what each role may publish and read, for run
#                          RUN (default: any run, "*")
# Run it again with more ROLE:NAME to add hosts: the CA and existing certificates are kept
# and the router's config is written for every certificate in DIR.
set -euo pipefail
out=deploy/certs
run='*'
listen=
hosts=()
while [ $# -gt 0 ]; do
    case $1 in
    --out) out=$2; shift 2 ;;
    --run) run=$2; shift 2 ;;
    --router-listen) listen=$2; shift 2 ;;
    -h | --help) sed -n '2,21p' "$0" | sed 's/^# \{0,1\}//'; exit 0 ;;
    -*) echo "certs.sh: unknown flag $1 (see --help)" >&2; exit 2 ;;
    *) hosts+=("$1"); shift ;;
    esac
done
command -v openssl >/dev/null || { echo "certs.sh: openssl is needed (Debian: openssl)" >&2; exit 1; }
if [ "$run" != '*' ] && ! [[ $run =~ ^[A-Za-z0-9_.-]+$ ]]; then
    echo "certs.sh: --run $run: a run id is letters, digits, _ . - (or '*' for any run)" >&2
    exit 2
fi
mkdir -p "$out"
chmod 700 "$out"
days=825

if [ ! -f "$out/ca.pem" ]; then
    openssl req -x509 -newkey ec -pkeyopt ec_paramgen_curve:prime256v1 -nodes \
        -keyout "$out/ca.key" -out "$out/ca.pem" -days "$days" -subj "/CN=pbrl-ca" \
        -addext "basicConstraints=critical,CA:TRUE" \
        -addext "keyUsage=critical,keyCertSign,cRLSign" 2>/dev/null
    chmod 600 "$out/ca.key"
    echo "made $out/ca.pem (keep $out/ca.key here)"
fi

router_ip=
for h in "${hosts[@]}"; do
    spec=${h%@*}
    addr=
    [[ $h == *@* ]] && addr=${h#*@}
    role=${spec%%:*}
    name=${spec#*:}
    case $role in router | learner | actor | teacher | page) ;; *)
        echo "certs.sh: $h: the role is router, learner, actor, teacher or page" >&2; exit 2 ;;
    esac
    if [ "$name" = "$spec" ] || ! [[ $name =~ ^[A-Za-z0-9_-]+$ ]]; then
        echo "certs.sh: $h: give ROLE:NAME[@IP], NAME of letters, digits, - and _" >&2
        exit 2
    fi
    if [[ $role == router || $role == page ]] && [ -z "$addr" ]; then
        echo "certs.sh: $h: a $role certificate needs the address others reach it at ($role:NAME@IP)" >&2
        exit 2
    fi
    [ "$role" = router ] && router_ip=$addr
    base="$out/$role-$name"
    if [ -f "$base.pem" ]; then
        echo "kept $base.pem"
        continue
    fi
    san="DNS:$name"
    if [ -n "$addr" ]; then
        if [[ $addr =~ ^[0-9.]+$ || $addr == *:* ]]; then san="$san,IP:$addr"; else san="$san,DNS:$addr"; fi
    fi
    openssl req -newkey ec -pkeyopt ec_paramgen_curve:prime256v1 -nodes \
        -keyout "$base.key" -out "$base.csr" -subj "/CN=pbrl-$role-$name" 2>/dev/null
    openssl x509 -req -in "$base.csr" -CA "$out/ca.pem" -CAkey "$out/ca.key" -CAcreateserial \
        -out "$base.pem" -days "$days" -extfile <(printf '%s\n' \
            "basicConstraints=critical,CA:FALSE" \
            "keyUsage=critical,digitalSignature" \
            "extendedKeyUsage=serverAuth,clientAuth" \
            "subjectAltName=$san") 2>/dev/null
    rm -f "$base.csr"
    chmod 600 "$base.key"
    echo "made $base.pem (CN pbrl-$role-$name, $san)"
done

# The common names of every certificate in DIR, by role, as a json5 list.
names() {
    local list=() f
    for f in "$out/$1"-*.pem; do
        [ -f "$f" ] || continue
        f=${f##*/}
        list+=("\"pbrl-${f%.pem}\"")
    done
    local IFS=,
    echo "[${list[*]}]"
}
if [ -z "$listen" ]; then
    if [ -z "$router_ip" ]; then
        for f in "$out"/router-*.pem; do
            [ -f "$f" ] || continue
            router_ip=$(openssl x509 -in "$f" -noout -ext subjectAltName 2>/dev/null |
                grep -oE 'IP Address:[0-9.]+' | head -1 | cut -d: -f2)
        done
    fi
    listen="tls/${router_ip:-127.0.0.1}:7447"
fi
router_cert=$(ls "$out"/router-*.pem 2>/dev/null | head -1)
if [ -z "$router_cert" ]; then
    echo "certs.sh: no router certificate in $out yet (add router:NAME@IP)" >&2
    exit 2
fi
p="pbrl/$run"
# NOTE: zenoh refuses an empty list of common names: a role without certificates has no
# subject and no policy (nothing it could do is allowed).
subjects=
policies=
declare -A rules=(
    [learner]='"learner-publishes", "learner-asked-for-weights", "learner-told-of-readers", "learner-reads", "learner-receives"'
    [actor]='"actor-publishes", "actor-told-of-readers", "actor-reads", "actor-receives"'
    [teacher]='"teacher-publishes", "teacher-told-of-readers", "teacher-reads", "teacher-receives"')
for role in learner actor teacher; do
    if [ "$(names $role)" = "[]" ]; then
        echo "note: no $role certificate in $out yet" >&2
        continue
    fi
    subjects+="      { id: \"${role}s\", cert_common_names: $(names $role) },"$'\n'
    policies+="      { rules: [${rules[$role]}], subjects: [\"${role}s\"] },"$'\n'
done
cat > "$out/router-tls.json5" <<EOF
// The stock zenohd for pbrl over TLS with mutual authentication and access control by
// role, made by deploy/certs.sh for run "$run":   zenohd -c $out/router-tls.json5
// (paths are relative to where zenohd starts). Only certificates signed by ca.pem connect;
// each role may publish and read only what docs/bus.md says it does; nobody else anything.
{
  mode: "router",
  listen: { endpoints: ["$listen"] },
  scouting: { multicast: { enabled: false }, gossip: { enabled: false } },
  transport: {
    link: {
      protocols: ["tls"],
      tx: { lease: 60000 },
      tls: {
        root_ca_certificate: "$out/ca.pem",
        listen_certificate: "$router_cert",
        listen_private_key: "${router_cert%.pem}.key",
        enable_mtls: true,
        close_link_on_expiration: true,
      },
    },
  },
  access_control: {
    enabled: true,
    default_permission: "deny",
    rules: [
      // The learner: weights (published and answered as a query), evaluation requests,
      // the stop, queries, acks and its status; it reads trajectories, evaluations,
      // answers and the labellers' tokens.
      { id: "learner-publishes", permission: "allow", flows: ["ingress"],
        messages: ["put", "declare_queryable", "reply"],
        key_exprs: ["$p/learner/0/weights", "$p/learner/0/eval/*", "$p/learner/0/stop",
                    "$p/learner/0/query", "$p/learner/0/ack/*", "$p/learner/0/status"] },
      { id: "learner-asked-for-weights", permission: "allow", flows: ["egress"],
        messages: ["query"], key_exprs: ["$p/learner/0/weights"] },
      // Told who reads what it publishes: a zenoh session sends a put only where the
      // router has told it of a subscriber.
      { id: "learner-told-of-readers", permission: "allow", flows: ["egress"],
        messages: ["declare_subscriber"],
        key_exprs: ["$p/learner/0/weights", "$p/learner/0/eval/*", "$p/learner/0/stop",
                    "$p/learner/0/query", "$p/learner/0/ack/*", "$p/learner/0/status"] },
      { id: "learner-reads", permission: "allow", flows: ["ingress"],
        messages: ["declare_subscriber", "declare_liveliness_subscriber", "liveliness_query"],
        key_exprs: ["$p/actor/*/trajectory", "$p/actor/*/eval", "$p/teacher/*/answer",
                    "$p/teacher/*/labeller/*"] },
      { id: "learner-receives", permission: "allow", flows: ["egress"],
        messages: ["put", "liveliness_token", "reply"],
        key_exprs: ["$p/actor/*/trajectory", "$p/actor/*/eval", "$p/teacher/*/answer",
                    "$p/teacher/*/labeller/*"] },
      // An actor: its trajectories and evaluations; it reads weights (and asks for them),
      // evaluation requests and the stop.
      { id: "actor-publishes", permission: "allow", flows: ["ingress"],
        messages: ["put"], key_exprs: ["$p/actor/*/trajectory", "$p/actor/*/eval"] },
      { id: "actor-told-of-readers", permission: "allow", flows: ["egress"],
        messages: ["declare_subscriber", "declare_queryable"],
        key_exprs: ["$p/actor/*/trajectory", "$p/actor/*/eval", "$p/learner/0/weights"] },
      { id: "actor-reads", permission: "allow", flows: ["ingress"],
        messages: ["declare_subscriber", "query"],
        key_exprs: ["$p/learner/0/weights", "$p/learner/0/eval/*", "$p/learner/0/stop"] },
      { id: "actor-receives", permission: "allow", flows: ["egress"],
        messages: ["put", "reply"],
        key_exprs: ["$p/learner/0/weights", "$p/learner/0/eval/*", "$p/learner/0/stop"] },
      // A teacher: answers and the labellers' tokens; it reads queries, acks and status.
      { id: "teacher-publishes", permission: "allow", flows: ["ingress"],
        messages: ["put", "liveliness_token"],
        key_exprs: ["$p/teacher/*/answer", "$p/teacher/*/labeller/*"] },
      { id: "teacher-told-of-readers", permission: "allow", flows: ["egress"],
        messages: ["declare_subscriber", "declare_liveliness_subscriber"],
        key_exprs: ["$p/teacher/*/answer", "$p/teacher/*/labeller/*"] },
      { id: "teacher-reads", permission: "allow", flows: ["ingress"],
        messages: ["declare_subscriber"],
        key_exprs: ["$p/learner/0/query", "$p/learner/0/ack/*", "$p/learner/0/status"] },
      { id: "teacher-receives", permission: "allow", flows: ["egress"],
        messages: ["put"],
        key_exprs: ["$p/learner/0/query", "$p/learner/0/ack/*", "$p/learner/0/status"] },
    ],
    subjects: [
$subjects    ],
    policies: [
$policies    ],
  },
}
EOF
echo "wrote $out/router-tls.json5 (run \"$run\", listening on $listen)"
