//! TLS with mutual authentication and access control by role, at the stock `zenohd` router
//! with the config `deploy/certs.sh` makes: a process without a certificate the CA signed
//! cannot connect at all; a teacher's certificate cannot publish weights, trajectories or
//! another run's answers; an actor's cannot read queries. What the router forwards is seen
//! by an observer subscribed to everything (a test-only subject added to the made config),
//! so "refused" means nobody received it, not only the one subscriber asked.
//!
//! Needs `zenohd` (`bash deploy/setup.sh` builds it at the zenoh version of Cargo.lock).

use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use pbrl_common::connect::{free_local_port, ConnectArgs};

mod support;

use support::deploy::{self, zenohd};
use support::poll::{poll, poll_async};
use support::proc::{Launch, Proc};

/// `deploy/certs.sh` into `dir` for run `run` and the router on `port`: the CA, a router,
/// a learner, an actor, a teacher and the observer (a learner's certificate, given the
/// right to read everything below).
fn certs(dir: &Path, run: &str, port: u16) -> PathBuf {
    let path = deploy::certs(
        dir,
        run,
        Some(&format!("tls/127.0.0.1:{port}")),
        &[
            "router:hub@127.0.0.1",
            "learner:srv",
            "actor:lab1",
            "teacher:ward",
            "learner:observer",
        ],
    );
    let made = std::fs::read_to_string(&path).unwrap();
    // NOTE: test-only: the observer also reads every key under pbrl/.
    let observed = made
        .replacen(
            "    rules: [\n",
            "    rules: [\n      { id: \"observer\", permission: \"allow\", flows: [\"ingress\", \"egress\"],\n        messages: [\"put\", \"declare_subscriber\"], key_exprs: [\"pbrl/**\"] },\n",
            1,
        )
        .replacen(
            "    policies: [\n",
            "    policies: [\n      { rules: [\"observer\"], subjects: [\"observer\"] },\n",
            1,
        )
        .replacen(
            "    subjects: [\n",
            "    subjects: [\n      { id: \"observer\", cert_common_names: [\"pbrl-learner-observer\"] },\n",
            1,
        );
    assert_ne!(
        observed, made,
        "the made config has rules, subjects and policies"
    );
    std::fs::write(&path, observed).unwrap();
    path
}

/// The stock router with `config`, up once it accepts TCP connections on `port`.
fn router(config: &Path, port: u16, dir: &Path) -> Proc {
    let mut p = Launch::new(zenohd(), [Path::new("-c"), config])
        .dir(dir)
        .log("zenohd")
        .rust_log("warn,zenoh::net::routing::interceptor=debug")
        .spawn();
    poll(
        30,
        || format!("zenohd to listen on {port}"),
        || {
            if let Some(status) = p.child.try_wait().unwrap() {
                panic!("zenohd exited: {status}: {}", p.log());
            }
            std::net::TcpStream::connect(("127.0.0.1", port)).ok()
        },
    );
    p
}

/// Connection flags with the certificate `name` of `dir` (`None`: only the CA).
fn flags(dir: &Path, port: u16, name: Option<&str>) -> ConnectArgs {
    let mut c = ConnectArgs::connecting_to(&format!("tls/127.0.0.1:{port}"));
    c.tls_ca = Some(dir.join("ca.pem"));
    if let Some(n) = name {
        c.tls_cert = Some(dir.join(format!("{n}.pem")));
        c.tls_key = Some(dir.join(format!("{n}.key")));
    }
    c
}

/// Payloads received on a subscription, in order, with their keys.
type Seen = Arc<Mutex<Vec<(String, String)>>>;

async fn subscribe(s: &zenoh::Session, key: &str) -> (zenoh::pubsub::Subscriber<()>, Seen) {
    let seen: Seen = Arc::default();
    let into = seen.clone();
    let sub = s
        .declare_subscriber(key)
        .callback(move |sample| {
            let payload = String::from_utf8_lossy(&sample.payload().to_bytes()).to_string();
            into.lock()
                .unwrap()
                .push((sample.key_expr().to_string(), payload));
        })
        .await
        .unwrap();
    (sub, seen)
}

/// Wait until `seen` holds a sample with `payload` (panics after 30 s).
async fn until_seen(seen: &Seen, payload: &str, what: &str) {
    poll_async(
        30,
        || format!("{what}: {:?}", seen.lock().unwrap()),
        || {
            let seen = seen.lock().unwrap();
            seen.iter().any(|(_, p)| p == payload).then_some(())
        },
    )
    .await
}

async fn put(s: &zenoh::Session, key: &str, payload: &str) {
    s.put(key, payload.to_string())
        .congestion_control(zenoh::qos::CongestionControl::Block)
        .await
        .unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn roles_publish_and_read_only_what_they_may_and_no_stranger_connects() {
    let dir = tempfile::tempdir().unwrap();
    let port = free_local_port().unwrap();
    let run = "ward-7";
    let config = certs(dir.path(), run, port);
    let _router = router(&config, port, dir.path());
    let p = format!("pbrl/{run}");

    let open = |name: &str| {
        let c = flags(dir.path(), port, Some(name));
        async move { c.open().await }
    };
    let observer = open("learner-observer")
        .await
        .expect("the observer connects");
    let (_all, seen) = subscribe(&observer, "pbrl/**").await;
    let learner = open("learner-srv").await.expect("the learner connects");
    let actor = open("actor-lab1").await.expect("the actor connects");
    let teacher = open("teacher-ward").await.expect("the teacher connects");
    let (_t, learner_saw) = subscribe(&learner, &format!("{p}/actor/*/trajectory")).await;
    let (_w, actor_saw) = subscribe(&actor, &format!("{p}/learner/0/weights")).await;
    let (_q, actor_queries) = subscribe(&actor, &format!("{p}/learner/0/query")).await;
    let (_tq, teacher_queries) = subscribe(&teacher, &format!("{p}/learner/0/query")).await;

    // What each role may do arrives (the routes are up once the first of each arrives).
    let deadline = Instant::now() + Duration::from_secs(30);
    let mut n = 0;
    while !seen
        .lock()
        .unwrap()
        .iter()
        .any(|(_, v)| v.starts_with("weights"))
        || learner_saw.lock().unwrap().is_empty()
        || actor_saw.lock().unwrap().is_empty()
        || teacher_queries.lock().unwrap().is_empty()
    {
        assert!(
            Instant::now() < deadline,
            "legitimate messages never arrived"
        );
        n += 1;
        put(
            &learner,
            &format!("{p}/learner/0/weights"),
            &format!("weights {n}"),
        )
        .await;
        put(
            &actor,
            &format!("{p}/actor/1/trajectory"),
            &format!("trajectory {n}"),
        )
        .await;
        put(
            &learner,
            &format!("{p}/learner/0/query"),
            &format!("query {n}"),
        )
        .await;
        tokio::time::sleep(Duration::from_millis(100)).await;
    }

    // The teacher's certificate: weights, a trajectory and another run's answer are
    // refused; then its own answer, sent after them on the same link and priority, arrives.
    put(
        &teacher,
        &format!("{p}/learner/0/weights"),
        "forged weights",
    )
    .await;
    put(
        &teacher,
        &format!("{p}/actor/1/trajectory"),
        "forged trajectory",
    )
    .await;
    put(
        &teacher,
        "pbrl/other-run/teacher/t/answer",
        "another run's answer",
    )
    .await;
    put(&teacher, &format!("{p}/teacher/t/answer"), "answer").await;
    until_seen(&seen, "answer", "the teacher's own answer").await;
    // The actor's certificate: it does not read queries (the teacher's did, above); a
    // query sent now reaches the teacher and the observer, not the actor.
    put(&learner, &format!("{p}/learner/0/query"), "query after").await;
    until_seen(&teacher_queries, "query after", "the query after").await;
    until_seen(&seen, "query after", "the query after (observer)").await;

    let all: Vec<String> = seen
        .lock()
        .unwrap()
        .iter()
        .map(|(_, v)| v.clone())
        .collect();
    for forged in [
        "forged weights",
        "forged trajectory",
        "another run's answer",
    ] {
        assert!(
            !all.iter().any(|v| v == forged),
            "{forged:?} went through: {all:?}"
        );
    }
    assert!(
        !actor_saw
            .lock()
            .unwrap()
            .iter()
            .any(|(_, v)| v.starts_with("forged")),
        "the actor received forged weights"
    );
    assert!(
        !learner_saw
            .lock()
            .unwrap()
            .iter()
            .any(|(_, v)| v.starts_with("forged")),
        "the learner received a forged trajectory"
    );
    assert!(
        actor_queries.lock().unwrap().is_empty(),
        "the actor's certificate read queries: {:?}",
        actor_queries.lock().unwrap()
    );

    // No certificate, one another CA signed, or plain TCP to the TLS port: no session.
    let mut bare = zenoh::Config::default();
    for (k, v) in [
        ("mode", "\"client\"".to_string()),
        ("scouting/multicast/enabled", "false".to_string()),
        ("connect/endpoints", format!("[\"tls/127.0.0.1:{port}\"]")),
        (
            "transport/link/tls/root_ca_certificate",
            format!("{:?}", dir.path().join("ca.pem").display().to_string()),
        ),
    ] {
        bare.insert_json5(k, &v).unwrap();
    }
    assert!(
        zenoh::open(bare).await.is_err(),
        "a client without a certificate connected"
    );
    let other = tempfile::tempdir().unwrap();
    certs(other.path(), run, port);
    assert!(
        flags(other.path(), port, Some("teacher-ward"))
            .open()
            .await
            .is_err(),
        "a certificate another CA signed connected"
    );
    let plain = ConnectArgs::connecting_to(&format!("tcp/127.0.0.1:{port}"));
    assert!(
        plain.open().await.is_err(),
        "plain TCP connected to the TLS router"
    );
}
