//! A `pbrl train` process killed with SIGKILL while its queries are in flight: the teacher
//! answers them while it is down, and once it resumes every answer reaches the label store
//! exactly once.

use std::collections::{BTreeMap, BTreeSet};
use std::path::Path;
use std::time::Duration;

use pbrl_common::bus::{Inbox, MessagePublisher};
use pbrl_common::connect::{free_local_port, ConnectArgs};
use pbrl_common::wire::{Answer, Body, Query};
use pbrl_common::Keys;
use pbrl_learner::pref::labels::LabelStore;
use pbrl_teacher::scripted::{Scripted, ScriptedConfig, TeacherKind};
use pbrl_teacher::service::Judge;

mod support;

use support::proc::{pbrl, Proc};

fn spawn(args: &[String], log: &Path) -> Proc {
    pbrl(args)
        .append_log(log)
        .rust_log("warn,pbrl=info,pbrl_learner=info")
        .spawn()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn a_learner_killed_with_queries_in_flight_gets_every_answer_once_after_resume() {
    let endpoint = format!("tcp/127.0.0.1:{}", free_local_port().unwrap());
    // The test's session is the router: the learner process comes and goes, the teacher
    // here stays.
    let router = ConnectArgs::router_on(&endpoint).open().await.unwrap();
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("run");
    let log = dir.path().join("train.log");
    let run = "crash-test";
    let args = support::crash_learner_args(&endpoint, &out, run, &[]);
    let keys = Keys::new(run).unwrap();
    let mut queries = Inbox::queries(&router, &keys).await.unwrap();
    let mut acks = Inbox::answer_acks(&router, &keys, "slow-0").await.unwrap();
    let answers_out = MessagePublisher::new(
        &router,
        &keys,
        keys.answer("slow-0"),
        zenoh::qos::Priority::DataHigh,
    )
    .await
    .unwrap();

    let mut child = spawn(&args, &log);
    // A slow teacher: it reads the first session's queries and answers none yet.
    let mut seen: BTreeMap<u64, Query> = BTreeMap::new();
    while seen.len() < 10 {
        let q = tokio::time::timeout(Duration::from_secs(120), queries.next())
            .await
            .unwrap_or_else(|_| {
                panic!(
                    "no queries; log: {}",
                    std::fs::read_to_string(&log).unwrap_or_default()
                )
            })
            .unwrap();
        seen.insert(q.id, *q);
    }
    child.signal("-KILL");
    child.wait();

    // Answered while the learner is down: nobody stores them yet.
    let mut oracle = Scripted::new(ScriptedConfig {
        r_min: -100.0,
        ..ScriptedConfig::of(TeacherKind::Oracle, 0)
    })
    .unwrap();
    let answers: BTreeMap<u64, Answer> = seen
        .values()
        .map(|q| {
            (
                q.id,
                Answer::scripted(q.id, oracle.judge(q), "oracle", "slow-0", 5),
            )
        })
        .collect();
    for a in answers.values() {
        answers_out.send(&Body::Answer(a.clone())).await.unwrap();
    }

    // The learner resumes; the teacher sends what is unacknowledged every second, as the
    // teacher service does, until every answer is acknowledged.
    let mut child = spawn(&args, &log);
    let mut unacked: BTreeSet<u64> = answers.keys().copied().collect();
    let mut tick = tokio::time::interval(Duration::from_secs(1));
    let deadline = tokio::time::Instant::now() + Duration::from_secs(120);
    while !unacked.is_empty() {
        assert!(
            tokio::time::Instant::now() < deadline,
            "answers never acknowledged: {unacked:?}; log: {}",
            std::fs::read_to_string(&log).unwrap_or_default()
        );
        tokio::select! {
            a = acks.next() => {
                for id in a.unwrap().queries {
                    unacked.remove(&id);
                }
            }
            _ = tick.tick() => {
                for id in &unacked {
                    answers_out.send(&Body::Answer(answers[id].clone())).await.unwrap();
                }
            }
            // NOTE: the resumed learner asks its open queries again; the answers above
            // are what it gets.
            _ = queries.next() => {}
        }
    }
    child.signal("-TERM");
    child.wait();

    // Every answer is in D once, as given.
    let store = LabelStore::open(&out.join("labels.sqlite"), run).unwrap();
    let d = store.labels_since(0).unwrap();
    for a in answers.values() {
        let rows: Vec<_> = d.iter().filter(|r| r.query == a.query).collect();
        assert_eq!(rows.len(), 1, "query {} in D {} times", a.query, rows.len());
        assert_eq!(rows[0].preference, a.preference);
    }
    assert!(store.counts().unwrap().answered >= answers.len() as u64);
}
