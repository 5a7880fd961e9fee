//! A scripted teacher at a person's pace, and a learner that keeps time with it: with
//! `--label-slack-steps 0`, no query is asked a feedback interval or more past another
//! before that other's answer is in; without it, the learner runs past the person.

use std::path::Path;

use serde_json::Value;

mod support;

use support::proc::pbrl;
use support::store::sql;

/// Env steps between feedback sessions in these runs.
const INTERVAL: u64 = 1_000;

/// A point-task run of `pbrl train` whose oracle answers at 0.4 s an answer, with `extra`;
/// its queries as the label store keeps them.
fn run(dir: &Path, extra: &[&str]) -> Vec<Value> {
    std::fs::create_dir_all(dir).unwrap();
    let out = dir.join("run");
    let interval = format!("--feedback-interval={INTERVAL}");
    let args = [
        "train",
        "--task=point",
        "--reward=pref",
        "--actors=1",
        "--steps=8000",
        "--eval-episodes=0",
        "--quiet",
        "--unsup-steps=600",
        "--label-efficient",
        "--max-feedback=12",
        "--feedback-span=2000",
        &interval,
        "--answer-s=0.4",
    ];
    let o = pbrl(args.iter().chain(extra))
        .args([format!("--out={}", out.display())])
        .output();
    assert!(
        o.status.success(),
        "pbrl train failed: {}",
        String::from_utf8_lossy(&o.stderr)
    );
    sql(
        &out.join("labels.sqlite"),
        "SELECT id, env_steps, asked_at_ms, answered_at_ms, took_ms, answer FROM queries ORDER BY id",
    )
    .unwrap()
}

/// Pairs (answered query, query asked a feedback interval or more later in env steps)
/// where the later one was asked before the earlier one's answer came.
fn ran_past(rows: &[Value]) -> Vec<(u64, u64)> {
    let n = |r: &Value, k: &str| r[k].as_u64();
    let mut past = Vec::new();
    for a in rows {
        let Some(answered) = n(a, "answered_at_ms") else {
            continue;
        };
        for b in rows {
            let later = n(b, "env_steps").unwrap() >= n(a, "env_steps").unwrap() + INTERVAL;
            if later && n(b, "asked_at_ms").unwrap() < answered {
                past.push((n(a, "id").unwrap(), n(b, "id").unwrap()));
            }
        }
    }
    past
}

#[test]
fn a_learner_that_keeps_time_asks_no_further_session_before_the_answers_are_in() {
    let dir = tempfile::tempdir().unwrap();
    let held = run(&dir.path().join("held"), &["--label-slack-steps=0"]);
    assert_eq!(held.len(), 12, "the whole budget asked: {held:?}");
    assert!(
        held.iter().all(|r| r["answer"].is_string()),
        "every query answered before the run ended: {held:?}"
    );
    assert!(
        held.iter().all(|r| r["took_ms"].as_u64() == Some(400)),
        "each answer took the person's 0.4 s: {held:?}"
    );
    let sessions_apart = held.iter().any(|b| {
        held.iter()
            .any(|a| b["env_steps"].as_u64() >= a["env_steps"].as_u64().map(|e| e + INTERVAL))
    });
    assert!(sessions_apart, "queries of sessions apart: {held:?}");
    assert_eq!(ran_past(&held), Vec::<(u64, u64)>::new(), "{held:?}");

    // The same person without keeping time: the learner runs past them.
    let free = run(&dir.path().join("free"), &[]);
    let outran = !ran_past(&free).is_empty()
        || free.len() < 12
        || free.iter().any(|r| r["answer"].is_null());
    assert!(
        outran,
        "a learner that never waits outruns a person at 0.4 s an answer: {free:?}"
    );
}
