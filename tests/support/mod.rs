//! Shared by the integration tests, the one way each starts processes ([`proc`]), waits
//! ([`poll`]), reads a store ([`store`]) and meets a page ([`web`], [`page`]); a deployment
//! through the stock router ([`deploy`]); and here, for in-process runs: zenoh's closed
//! transports counted, a config that closes them sooner, every kind of bad message, and
//! small learner configs.
#![allow(dead_code)] // NOTE: each test file uses its own part.

pub mod deploy;
pub mod page;
pub mod poll;
pub mod proc;
pub mod store;
pub mod web;

use pbrl_actor::runner::Task;
use pbrl_common::bus::wait_until;
use pbrl_common::trajectory::TRAJECTORY_FORMAT;
use pbrl_common::wire::{self, Body};
use pbrl_common::{StepRewards, Trajectory};
use pbrl_learner::rl::ppo::PpoConfig;
use pbrl_learner::rl::sac::SacConfig;
use pbrl_learner::run::config;
use pbrl_learner::run::service::{Algo, LearnerConfig, RewardSource};

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Once;

use tracing::field::{Field, Visit};
use tracing_subscriber::layer::{Context, SubscriberExt};
use tracing_subscriber::util::SubscriberInitExt;
use tracing_subscriber::Layer;

static CLOSED: AtomicU64 = AtomicU64::new(0);

/// Counts zenoh's "Unable to push non droppable network message ... Closing transport!".
struct CloseCounter;

struct Message(bool);

impl Visit for Message {
    fn record_debug(&mut self, field: &Field, value: &dyn std::fmt::Debug) {
        if field.name() == "message" && format!("{value:?}").contains("Closing transport") {
            self.0 = true;
        }
    }
}

impl<S: tracing::Subscriber> Layer<S> for CloseCounter {
    fn on_event(&self, event: &tracing::Event<'_>, _: Context<'_, S>) {
        let mut m = Message(false);
        event.record(&mut m);
        if m.0 {
            CLOSED.fetch_add(1, Ordering::Relaxed);
        }
    }
}

/// Transports zenoh closed in this process because a push could not wait any longer (the
/// counter is installed at the first call).
pub fn closed_transports() -> u64 {
    static INSTALL: Once = Once::new();
    INSTALL.call_once(|| {
        let filter =
            tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "warn".into());
        tracing_subscriber::registry()
            .with(CloseCounter.with_filter(tracing_subscriber::filter::LevelFilter::ERROR))
            .with(
                tracing_subscriber::fmt::layer()
                    .with_test_writer()
                    .with_filter(filter),
            )
            .init();
    });
    CLOSED.load(Ordering::Relaxed)
}

/// A Zenoh config (`ConnectArgs` with `config`) whose blocked pushes give up after `ms`,
/// with small TCP buffers (16 KiB), so that a reader that stops shows within a few hundred
/// small messages rather than megabytes.
pub fn short_wait_config(dir: &std::path::Path, ms: u64) -> std::path::PathBuf {
    let path = dir.join("zenoh.json5");
    let text = format!(
        "{{ transport: {{ link: {{ tx: {{ queue: {{ congestion_control: {{ block: {{ wait_before_close: {} }} }} }} }}, tcp: {{ so_sndbuf: 16384, so_rcvbuf: 16384 }} }} }} }}",
        ms * 1000
    );
    std::fs::write(&path, text).unwrap();
    path
}

/// A wire envelope by hand (format, run, body), as a foreign client could send it.
pub fn envelope(format: u16, run: &str, body: &Body) -> Vec<u8> {
    bincode::serde::encode_to_vec((format, run, body), bincode::config::standard()).unwrap()
}

/// Every way a message for `good`'s key can be bad: (what, payload).
pub fn bad_payloads(
    run: &str,
    good: &Body,
    wrong_dims: Option<Body>,
    nan: Option<Body>,
    other: Body,
) -> Vec<(&'static str, Vec<u8>)> {
    let mut bad = vec![
        ("garbage", vec![1u8, 2, 3, 250, 251, 252]),
        ("empty", Vec::new()),
        ("another format", envelope(wire::WIRE_FORMAT + 1, run, good)),
        ("another run", wire::encode("another-run", good)),
        ("64 MB", vec![7u8; 64 << 20]),
        ("another kind of message", wire::encode(run, &other)),
    ];
    if let Some(b) = wrong_dims {
        bad.push(("wrong dimensions", wire::encode(run, &b)));
    }
    if let Some(b) = nan {
        bad.push(("NaN", wire::encode(run, &b)));
    }
    // The hand-made envelope is the real one: with this build's format it decodes.
    assert_eq!(
        wire::decode(run, &envelope(wire::WIRE_FORMAT, run, good)).unwrap(),
        *good
    );
    bad
}

/// A learner config for the point task, small enough for tests (2 actors, no evaluation,
/// no run folder).
pub fn point_learner(run: &str, algo: Algo, total: u64) -> LearnerConfig {
    let (obs_dim, act_dim) = Task::Point.dims();
    let mut cfg = LearnerConfig::new(run, algo, RewardSource::Truth, obs_dim, act_dim);
    cfg.total_steps = total;
    cfg.sac = SacConfig {
        hidden: vec![32, 32],
        batch: 32,
        random_steps: 300,
        update_every: 2,
        ..SacConfig::default()
    };
    cfg.ppo = PpoConfig {
        hidden: vec![32, 32],
        rollout_steps: 300,
        minibatch: 64,
        ..PpoConfig::default()
    };
    cfg.publish_every = 20;
    cfg.log_every = 1000;
    // NOTE: the tests' runs evaluate and checkpoint only where they say so.
    cfg.eval_episodes = 0;
    cfg.eval_sampled = false;
    cfg.checkpoint_every = 0;
    cfg.checkpoint_secs = 0;
    cfg.keep_checkpoints = 2;
    cfg.actors = 2;
    cfg.episode_steps = pbrl_actor::runner::POINT_HORIZON;
    cfg
}

/// A SAC learner for the point task as the bus tests run it: a 16x16 net on minibatches
/// of 16, `random_steps` random steps, an update every `update_every` steps and 4 sampled
/// evaluation episodes per request, so that most of its time is on the bus.
pub fn bus_learner(run: &str, total: u64, random_steps: u64, update_every: u64) -> LearnerConfig {
    LearnerConfig {
        sac: SacConfig {
            hidden: vec![16, 16],
            batch: 16,
            random_steps,
            update_every,
            ..SacConfig::default()
        },
        ppo: PpoConfig::default(),
        log_every: 10_000,
        eval_episodes: 4,
        eval_sampled: true,
        ..point_learner(run, Algo::Sac, total)
    }
}

/// A spawned task's result, within `secs` seconds.
pub async fn joined<T>(task: tokio::task::JoinHandle<anyhow::Result<T>>, secs: u64) -> T {
    tokio::time::timeout(std::time::Duration::from_secs(secs), task)
        .await
        .expect("timed out")
        .expect("the task panicked")
        .expect("the task failed")
}

/// The learner's result once it ends (within `secs` seconds), after which every actor
/// ends too (within 30 s each), cleanly.
pub async fn run_ends<S, A>(
    learner: tokio::task::JoinHandle<anyhow::Result<S>>,
    actors: Vec<tokio::task::JoinHandle<anyhow::Result<A>>>,
    secs: u64,
) -> S {
    let summary = joined(learner, secs).await;
    for a in actors {
        joined(a, 30).await;
    }
    summary
}

/// `cfg` with one actor learning from preferences with `reward` on a feedback schedule
/// small enough for tests: sessions of `per_session` queries (five candidates for each) at
/// `first` env steps and every `every` after it, `budget` labels in all; the annotation
/// buffer and the entropy bonus's pool hold `buffer` and `pool` trajectories and states.
pub fn small_pref(
    cfg: &mut LearnerConfig,
    reward: RewardSource,
    [first, every, per_session, budget]: [u64; 4],
    [buffer, pool]: [usize; 2],
) {
    // NOTE: the tests' own small schedules: whole trajectories, fixed session sizes, no
    // label-efficiency pieces unless a test turns them on (the point preset's settings).
    config::apply_preset(cfg, &config::label_efficiency_off(), &Default::default())
        .expect("the label-efficiency settings fit the config");
    cfg.reward = reward;
    cfg.actors = 1;
    let p = &mut cfg.pref;
    (p.unsup_steps, p.feedback_interval) = (first, every);
    (p.queries_per_session, p.max_feedback) = (per_session, budget);
    p.candidate_factor = 5;
    (p.annotation_capacity, p.knn_pool) = (buffer, pool);
}

/// A 200-step trajectory of a 2-dimensional task (about 20 KB on the wire).
pub fn trajectory(seed: u64) -> Trajectory {
    Trajectory {
        format: TRAJECTORY_FORMAT,
        seed,
        policy_version: 3,
        obs_dim: 2,
        act_dim: 1,
        obs: vec![0.5; 2 * 201],
        actions: vec![0.1; 200],
        rewards: vec![StepRewards::default(); 200],
        outcome: Default::default(),
        replay: None,
    }
}

/// Put every payload on `key` from `session` (a foreign client), once a subscriber is
/// known.
pub async fn put_all(session: &zenoh::Session, key: &str, payloads: &[Vec<u8>]) {
    let raw = session
        .declare_publisher(key.to_string())
        .congestion_control(zenoh::qos::CongestionControl::Block)
        .await
        .unwrap();
    wait_until(std::time::Duration::from_secs(20), || async {
        Ok(raw.matching_status().await.unwrap().matching())
    })
    .await
    .unwrap();
    for bytes in payloads {
        raw.put(bytes.clone()).await.unwrap();
    }
}

/// The arguments of the `pbrl train` the crash tests kill: the point task learnt from an
/// external teacher's preferences with the default label-efficient settings, a checkpoint
/// every 600 steps, the first feedback session at 600, a budget of 40 asked over the
/// sessions of the next 3,000 env steps, queries resent after a second; `extra` flags after
/// these.
pub fn crash_learner_args(
    endpoint: &str,
    out: &std::path::Path,
    run: &str,
    extra: &[&str],
) -> Vec<String> {
    [
        "train",
        "--task=point",
        "--reward=pref",
        "--external-teacher",
        "--actors=1",
        "--steps=100000",
        "--eval-episodes=0",
        "--quiet",
        "--log-every=1000",
        "--checkpoint-every=600",
        "--unsup-steps=600",
        // NOTE: the default label-efficient settings (segments, the budget's schedule,
        // crops, features, hybrid replay), the schedule spanning the first sessions.
        "--label-efficient",
        "--max-feedback=40",
        "--feedback-span=3000",
        "--query-retry-s=1",
    ]
    .iter()
    .chain(extra)
    .map(|s| s.to_string())
    .chain([
        format!("--connect={endpoint}"),
        format!("--out={}", out.display()),
        format!("--run={run}"),
    ])
    .collect()
}
