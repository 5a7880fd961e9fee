//! A scripted teacher (`pbrl teacher`) killed with SIGKILL while its answers wait for the
//! learner, and restarted on its file: it sends what it had answered, judges nothing twice,
//! and every answer reaches the label store exactly once.

use std::collections::{BTreeMap, BTreeSet};
use std::path::Path;
use std::time::Duration;

use pbrl_common::bus::{Inbox, MessagePublisher};
use pbrl_common::connect::{free_local_port, ConnectArgs};
use pbrl_common::wire::{Answer, Body, Query};
use pbrl_common::Keys;
use pbrl_learner::pref::labels::LabelStore;

mod support;

use support::proc::{pbrl, Proc};
use support::store::{sql, store_until};

const RUN: &str = "teacher-crash";
const TEACHER: &str = "noisy-0";

fn log_text(path: &Path) -> String {
    std::fs::read_to_string(path).unwrap_or_default()
}

/// The queries a teacher's log says it judged, in order ("judged a query", at debug).
fn judged(log: &Path) -> Vec<u64> {
    let text = log_text(log);
    text.lines()
        .filter(|l| l.contains("judged a query"))
        .map(|l| {
            // NOTE: fields may be wrapped in colour escapes; the digits after "query" are
            // the id either way.
            let at = l.find("query").expect("a judged line names its query") + "query".len();
            let digits: String = l[at..]
                .chars()
                .skip_while(|c| !c.is_ascii_digit())
                .take_while(|c| c.is_ascii_digit())
                .collect();
            digits.parse().expect("a query id")
        })
        .collect()
}

/// `pbrl` with `args`, its log appended to `log` at `filter`.
fn spawn(args: &[String], log: &Path, filter: &str) -> Proc {
    pbrl(args).append_log(log).rust_log(filter).spawn()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn a_scripted_teacher_killed_mid_run_resends_its_answers_and_judges_nothing_twice() {
    let endpoint = format!("tcp/127.0.0.1:{}", free_local_port().unwrap());
    // The test's session is the router: the learner and the teacher come and go.
    let router = ConnectArgs::router_on(&endpoint).open().await.unwrap();
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("run");
    let state = dir.path().join("teacher.sqlite");
    let (train_log, log_1, log_2) = (
        dir.path().join("train.log"),
        dir.path().join("teacher-1.log"),
        dir.path().join("teacher-2.log"),
    );
    let learner_args =
        support::crash_learner_args(&endpoint, &out, RUN, &["--feedback-interval=600"]);
    let teacher_args: Vec<String> = [
        "teacher".to_string(),
        format!("--run={RUN}"),
        "--task=point".into(),
        "--teacher=noisy".into(),
        format!("--teacher-id={TEACHER}"),
        format!("--connect={endpoint}"),
        format!("--teacher-state={}", state.display()),
    ]
    .to_vec();
    let learner_log = "warn,pbrl=info,pbrl_learner=info";
    let teacher_log = "warn,pbrl=info,pbrl_teacher=debug";
    let keys = Keys::new(RUN).unwrap();
    let mut queries = Inbox::queries(&router, &keys).await.unwrap();
    let mut answers = Inbox::answers(&router, &keys).await.unwrap();
    let ask = MessagePublisher::new(
        &router,
        &keys,
        keys.queries(),
        zenoh::qos::Priority::DataHigh,
    )
    .await
    .unwrap();

    // The learner asks its first session's queries and is killed before anyone answers.
    let mut learner = spawn(&learner_args, &train_log, learner_log);
    let mut asked: BTreeMap<u64, Query> = BTreeMap::new();
    while asked.len() < 10 {
        let q = tokio::time::timeout(Duration::from_secs(120), queries.next())
            .await
            .unwrap_or_else(|_| panic!("no queries; log: {}", log_text(&train_log)))
            .unwrap();
        asked.insert(q.id, *q);
    }
    learner.signal("-KILL");
    learner.wait();

    // The teacher answers them (the test asks, as the learner would, until it hears every
    // answer); nobody acknowledges, and it is killed.
    let mut teacher = spawn(&teacher_args, &log_1, teacher_log);
    let mut given: BTreeMap<u64, Answer> = BTreeMap::new();
    let mut tick = tokio::time::interval(Duration::from_secs(1));
    let deadline = tokio::time::Instant::now() + Duration::from_secs(120);
    while given.len() < asked.len() {
        assert!(
            tokio::time::Instant::now() < deadline,
            "answered {:?} of {:?}; log: {}",
            given.keys(),
            asked.keys(),
            log_text(&log_1)
        );
        tokio::select! {
            a = answers.next() => {
                let a = a.unwrap();
                given.entry(a.query).or_insert(a);
            }
            _ = tick.tick() => {
                for (id, q) in &asked {
                    if !given.contains_key(id) {
                        ask.send(&Body::Query(Box::new(q.clone()))).await.unwrap();
                    }
                }
            }
        }
    }
    teacher.signal("-KILL");
    teacher.wait();
    let first_judged = judged(&log_1);
    assert_eq!(
        first_judged.iter().copied().collect::<BTreeSet<u64>>(),
        asked.keys().copied().collect::<BTreeSet<u64>>(),
        "the first teacher judged each query asked; log: {}",
        log_text(&log_1)
    );
    assert_eq!(first_judged.len(), asked.len(), "and each once");
    // Its disk holds every answer it sent, none acknowledged.
    let kept = sql(
        &state,
        &format!("SELECT query, acked FROM outbox WHERE teacher = '{TEACHER}' ORDER BY query"),
    )
    .unwrap();
    let kept_ids: Vec<u64> = kept.iter().map(|r| r["query"].as_u64().unwrap()).collect();
    assert_eq!(kept_ids, asked.keys().copied().collect::<Vec<u64>>());
    assert!(kept.iter().all(|r| r["acked"] == 0), "{kept:?}");

    // Both come back: the learner asks its open queries again, the teacher sends what it
    // had answered; training goes on to the next sessions.
    let mut teacher = spawn(&teacher_args, &log_2, teacher_log);
    let mut learner = spawn(&learner_args, &train_log, learner_log);
    let labels = out.join("labels.sqlite");
    let firsts: Vec<u64> = asked.keys().copied().collect();
    store_until(
        &labels,
        RUN,
        "the first session and two more",
        180,
        Some(&log_2),
        |s| {
            s.labels_since(0).is_ok_and(|d| {
                let stored: BTreeSet<u64> = d.iter().map(|r| r.query).collect();
                firsts.iter().all(|q| stored.contains(q)) && d.len() >= 3 * firsts.len()
            })
        },
    )
    .await;
    learner.signal("-TERM");
    learner.wait();
    teacher.signal("-TERM");
    teacher.wait();

    // Each query was judged once over the two teachers: the second judged only new ones.
    let second_judged = judged(&log_2);
    assert!(
        !second_judged.is_empty(),
        "the second teacher judged the new sessions' queries; log: {}",
        log_text(&log_2)
    );
    let mut all_judged = first_judged.clone();
    all_judged.extend(&second_judged);
    let once: BTreeSet<u64> = all_judged.iter().copied().collect();
    assert_eq!(
        once.len(),
        all_judged.len(),
        "a query judged twice: first {first_judged:?}, second {second_judged:?}"
    );
    assert!(
        log_text(&log_2).contains("the teacher's outbox is back"),
        "the second teacher found the first one's answers; log: {}",
        log_text(&log_2)
    );
    // Every answer is in D once, and the first session's are the first teacher's answers.
    let store = LabelStore::open(&labels, RUN).unwrap();
    let d = store.labels_since(0).unwrap();
    let stored: Vec<u64> = d.iter().map(|r| r.query).collect();
    let distinct: BTreeSet<u64> = stored.iter().copied().collect();
    assert_eq!(
        distinct.len(),
        stored.len(),
        "a query in D twice: {stored:?}"
    );
    for (id, a) in &given {
        let row = d.iter().find(|r| r.query == *id).unwrap();
        assert_eq!(row.preference, a.preference, "query {id}");
    }
    assert!(
        distinct.iter().all(|q| once.contains(q)),
        "D holds an answer nobody judged: D {distinct:?}, judged {once:?}"
    );
}
