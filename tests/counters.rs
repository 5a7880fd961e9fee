//! The run's counters are counted in one place: the curve's `dropped_messages` and the run
//! summary's agree, and both count a bad message on the bus and an answer to a query the
//! run never asked.

mod support;

use std::time::Duration;

use pbrl_actor::runner::{self, ActorConfig, Task};
use pbrl_actor::WorldConfig;
use pbrl_common::bus::wait_until;
use pbrl_common::connect::{free_local_port, ConnectArgs};
use pbrl_common::wire::{self, Answer, Body, Preference};
use pbrl_common::Keys;
use pbrl_learner::run::service::{self, Algo, RewardSource};

/// The `dropped_messages` column of the newest row of `curve`, if it has a row.
fn newest_dropped(curve: &std::path::Path) -> Option<u64> {
    let text = std::fs::read_to_string(curve).ok()?;
    let mut lines = text.lines();
    let col = lines
        .next()?
        .split(',')
        .position(|c| c == "dropped_messages")?;
    lines.last()?.split(',').nth(col)?.parse().ok()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_curve_and_the_summary_count_one_unknown_answer_and_one_bad_message() {
    let endpoint = format!("tcp/127.0.0.1:{}", free_local_port().unwrap());
    let session = ConnectArgs::router_on(&endpoint).open().await.unwrap();
    let run = "counters-test";
    let dir = tempfile::tempdir().unwrap();
    // NOTE: far more env steps than the test needs: it stops the run once a row has
    // counted both messages.
    let mut cfg = support::point_learner(run, Algo::Sac, 10_000_000);
    cfg.reward = RewardSource::Pref;
    cfg.actors = 1;
    cfg.log_every = 300;
    cfg.out = Some(dir.path().to_path_buf());
    cfg.pref.unsup_steps = 600;
    cfg.pref.model.hidden = vec![16];
    let (stop, stopped) = tokio::sync::watch::channel(false);
    let until_stopped = |mut rx: tokio::sync::watch::Receiver<bool>| async move {
        let _ = rx.wait_for(|s| *s).await;
    };
    let learner = tokio::spawn(service::run(
        cfg,
        session.clone(),
        until_stopped(stopped.clone()),
    ));
    let actor_cfg = ActorConfig {
        id: 0,
        run: run.into(),
        task: Task::Point,
        world: WorldConfig::default(),
        seed: 1,
    };
    let actor = tokio::spawn(runner::run(
        actor_cfg,
        session.clone(),
        until_stopped(stopped.clone()),
    ));

    // A foreign client: one message that is not pbrl's on the trajectories' key, and one
    // well-formed answer to a query this run never asked.
    let foreign = ConnectArgs::connecting_to(&endpoint).open().await.unwrap();
    let keys = Keys::new(run).unwrap();
    support::put_all(&foreign, &keys.trajectory(0), &[b"not a message".to_vec()]).await;
    let unknown = Answer::scripted(1_000_000, Preference::First, "oracle", "foreign-0", 1);
    let answer = wire::encode(run, &Body::Answer(unknown));
    support::put_all(&foreign, &keys.answer("foreign-0"), &[answer]).await;
    let curve = dir.path().join("curve.csv");
    wait_until(Duration::from_secs(120), || async {
        Ok(newest_dropped(&curve).is_some_and(|d| d >= 2))
    })
    .await
    .expect("a row counts both messages");
    stop.send(true).unwrap();

    let summary = tokio::time::timeout(Duration::from_secs(60), learner)
        .await
        .expect("the learner stops")
        .unwrap()
        .unwrap();
    tokio::time::timeout(Duration::from_secs(30), actor)
        .await
        .expect("the actor stops")
        .unwrap()
        .unwrap();
    let last = summary.rows.last().expect("the run wrote rows");
    assert_eq!(
        summary.feedback.as_ref().map(|f| f.unknown_answers),
        Some(1),
        "{:?}",
        summary.feedback
    );
    assert_eq!(last.dropped_messages, 2, "the curve: {last:?}");
    assert_eq!(
        summary.dropped_messages, last.dropped_messages,
        "the summary and the curve agree"
    );
}
