//! A learner that stops draining for longer than `wait_before_close` (its task paused, as a
//! long update, a checkpoint or a starved core would): the actors run into flow control,
//! zenoh keeps every transport open, and afterwards every trajectory and evaluation sent
//! in the meantime has arrived exactly once.
//!
//! The learner's session is the router on loopback and the actors connect to it, as
//! `deploy/local.sh` runs them: zenoh's receive threads (two, shared by every session of a
//! process) then only read and hand messages to callbacks, and never push towards another
//! session of this process (which could block both threads while the session they push to
//! waits for one to read; `common::bus` tells the whole story).

mod support;

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Duration;

use pbrl_actor::runner::{self, ActorConfig, Task};
use pbrl_actor::WorldConfig;
use pbrl_common::bus::{wait_until, WeightsClient};
use pbrl_common::connect::{free_local_port, ConnectArgs};
use pbrl_common::Keys;
use pbrl_learner::run::service;

/// Run `fut`, not polling it while `paused` holds true.
async fn pausable<F: std::future::Future>(
    fut: F,
    mut paused: tokio::sync::watch::Receiver<bool>,
) -> F::Output {
    tokio::pin!(fut);
    loop {
        if *paused.borrow_and_update() {
            let _ = paused.wait_for(|p| !*p).await;
            continue;
        }
        tokio::select! {
            out = &mut fut => return out,
            _ = paused.changed() => {}
        }
    }
}

const WAIT_BEFORE_CLOSE_MS: u64 = 300;

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn a_paused_learner_loses_nothing_and_no_transport_closes() {
    assert_eq!(support::closed_transports(), 0);
    let dir = tempfile::tempdir().unwrap();
    let config = Some(support::short_wait_config(dir.path(), WAIT_BEFORE_CLOSE_MS));
    let endpoint = format!("tcp/127.0.0.1:{}", free_local_port().unwrap());
    let session = ConnectArgs {
        config: config.clone(),
        ..ConnectArgs::router_on(&endpoint)
    }
    .open()
    .await
    .unwrap();
    let connect = ConnectArgs {
        config: config.clone(),
        ..ConnectArgs::connecting_to(&endpoint)
    };
    let run = "pause-test";
    let keys = Keys::new(run).unwrap();
    // The actors' share of a version is large during SAC's random steps (the rest of them):
    // paused there, the learner is sent hundreds of trajectories, more than zenoh's default
    // FIFO of 256 would hold.
    let cfg = support::bus_learner(run, 40_000, 36_000, 50);

    // An observer on the learner's session counts every trajectory the actors publish.
    let published = Arc::new(AtomicU64::new(0));
    let counter = published.clone();
    let _watch = session
        .declare_subscriber(keys.all_trajectories())
        .callback(move |_| {
            counter.fetch_add(1, Ordering::Relaxed);
        })
        .await
        .unwrap();
    let mut weights = WeightsClient::new(&session, &keys).await.unwrap();

    let (pause, paused) = tokio::sync::watch::channel(false);
    let learner = tokio::spawn(pausable(
        service::run(cfg, session.clone(), std::future::pending()),
        paused,
    ));
    let mut actors = Vec::new();
    for id in 0..2 {
        let session = connect.open().await.unwrap();
        let acfg = ActorConfig {
            id,
            run: run.into(),
            task: Task::Point,
            world: WorldConfig::default(),
            seed: 3,
        };
        actors.push(tokio::spawn(runner::run(
            acfg,
            session,
            std::future::pending(),
        )));
    }

    // Once training is under way, pause the learner: nothing drains its inbox.
    let first = tokio::time::timeout(Duration::from_secs(60), weights.next())
        .await
        .unwrap()
        .unwrap();
    pause.send(true).unwrap();
    let at_pause = published.load(Ordering::Relaxed);
    let share = first.episodes_per_actor as u64;
    assert!(share > 150, "the actors' share is large ({share})");
    // The actors run on into flow control: hundreds of trajectories reach the paused
    // learner's session, and stay there longer than zenoh waits before closing.
    wait_until(Duration::from_secs(120), || async {
        Ok(published.load(Ordering::Relaxed) >= at_pause + 300)
    })
    .await
    .expect("the actors keep publishing while the learner is paused");
    tokio::time::sleep(Duration::from_millis(3 * WAIT_BEFORE_CLOSE_MS)).await;
    let during = published.load(Ordering::Relaxed) - at_pause;
    pause.send(false).unwrap();

    let summary = support::run_ends(learner, actors, 180).await;
    assert_eq!(support::closed_transports(), 0, "no transport closed");
    let received: u64 = summary.episodes_by_actor.values().sum();
    assert!(during >= 300, "{during} trajectories came while paused");
    // Every trajectory published until the learner went on reached it (later ones may
    // come after the total), none twice: no gap in any actor's numbers, nothing sent again.
    assert!(
        received >= at_pause + during,
        "received {received}, published {} by the end of the pause",
        at_pause + during
    );
    let last = summary.rows.last().unwrap();
    assert_eq!(last.lost_messages, 0, "no trajectory missing");
    assert_eq!(last.retried_messages, 0, "nothing sent or asked again");
    assert_eq!(summary.dropped_messages, 0);
    assert_eq!(summary.rows.len(), 4);
    for row in &summary.rows {
        assert_eq!(row.eval_episodes, 4, "every row evaluated: {row:?}");
        assert!(row.eval_sampled_success_rate.is_finite());
    }
}
