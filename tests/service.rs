//! A learner and actors as services over an in-process Zenoh router on loopback.

mod support;

use support::joined;

use std::time::Duration;

use pbrl_actor::point::{POINT_ACT, POINT_OBS};
use pbrl_actor::runner::{self, ActorConfig, Task};
use pbrl_actor::WorldConfig;
use pbrl_common::bus::WeightsClient;
use pbrl_common::connect::{free_local_port, ConnectArgs};
use pbrl_common::Keys;
use pbrl_learner::run::service::{self, Algo, LearnerConfig};
use tokio::sync::oneshot;

fn actor(
    endpoint: &str,
    run: &str,
    id: u32,
) -> (
    oneshot::Sender<()>,
    tokio::task::JoinHandle<anyhow::Result<()>>,
) {
    let (tx, rx) = oneshot::channel::<()>();
    let endpoint = endpoint.to_string();
    let cfg = ActorConfig {
        id,
        run: run.into(),
        task: Task::Point,
        world: WorldConfig::default(),
        seed: 1,
    };
    let handle = tokio::spawn(async move {
        let session = ConnectArgs::connecting_to(&endpoint).open().await?;
        runner::run(cfg, session, async {
            let _ = rx.await;
        })
        .await
    });
    (tx, handle)
}

/// An in-process router on a free loopback port: its endpoint, and the session that keeps
/// it up.
async fn router() -> (String, impl Sized) {
    let endpoint = format!("tcp/127.0.0.1:{}", free_local_port().unwrap());
    let router = ConnectArgs::router_on(&endpoint).open().await.unwrap();
    (endpoint, router)
}

/// The learner service on its own session.
async fn learner(
    endpoint: &str,
    cfg: LearnerConfig,
) -> tokio::task::JoinHandle<anyhow::Result<service::Summary>> {
    let session = ConnectArgs::connecting_to(endpoint).open().await.unwrap();
    tokio::spawn(service::run(cfg, session, std::future::pending()))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn learner_and_actors_train_a_late_actor_joins_a_killed_actor_does_not_stop_it() {
    let (endpoint, _router) = router().await;
    let run = "service-test";
    let learner = learner(&endpoint, support::point_learner(run, Algo::Sac, 6_000)).await;

    let (_stop_a, actor_a) = actor(&endpoint, run, 0);
    let (stop_b, actor_b) = actor(&endpoint, run, 1);

    // Wait until the learner has moved past its first versions, then add a late actor.
    let watcher = ConnectArgs::connecting_to(&endpoint).open().await.unwrap();
    let mut weights = WeightsClient::new(&watcher, &Keys::new(run).unwrap())
        .await
        .unwrap();
    let current = loop {
        let w = tokio::time::timeout(Duration::from_secs(60), weights.next())
            .await
            .unwrap()
            .unwrap();
        if w.version >= 4 {
            break w.version;
        }
    };
    let (_stop_c, actor_c) = actor(&endpoint, run, 2);
    // Kill actor 1 outright; the learner must go on with the others.
    actor_b.abort();
    drop(stop_b);

    let summary = joined(learner, 120).await;
    assert!(summary.env_steps >= 6_000);
    assert_eq!(
        summary.updates,
        (summary.env_steps / 2).min(summary.updates),
        "UTD is kept"
    );
    assert!(summary.policy_version > current, "weights kept coming");
    assert!(summary.episodes_by_actor.get(&0).copied().unwrap_or(0) > 0);
    let late = summary
        .first_version_by_actor
        .get(&2)
        .copied()
        .expect("the late actor sent episodes");
    assert!(
        late >= current,
        "the late actor started from version {late}, the learner was at {current}"
    );
    assert_eq!(summary.dropped_messages, 0);
    // The learner's stop ends the remaining actors.
    for a in [actor_a, actor_c] {
        joined(a, 30).await;
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn ppo_trains_only_on_the_current_version() {
    let (endpoint, _router) = router().await;
    let run = "ppo-test";
    let dir = tempfile::tempdir().unwrap();
    let cfg = LearnerConfig {
        out: Some(dir.path().to_path_buf()),
        ..support::point_learner(run, Algo::Ppo, 3_000)
    };
    let learner = learner(&endpoint, cfg).await;
    let (_a, actor_a) = actor(&endpoint, run, 0);
    let (_b, actor_b) = actor(&endpoint, run, 1);
    let summary = joined(learner, 120).await;
    assert!(summary.env_steps >= 3_000);
    // One version per rollout of 300 steps (10 episodes), counted only from fresh data.
    assert!(summary.policy_version >= 9, "{summary:?}");
    assert!(summary.updates > 0);
    // The run folder: config, curve with a row per 1000 env steps, and the networks.
    let curve = std::fs::read_to_string(dir.path().join("curve.csv")).unwrap();
    assert_eq!(curve.lines().count(), 1 + summary.rows.len());
    assert!(curve.starts_with("env_steps,wall_s,eval_episodes,eval_return_truth,eval_success_rate"));
    let folder = pbrl_learner::run::run_folder::RunFolder::new(dir.path());
    let last = folder
        .latest_checkpoint()
        .unwrap()
        .expect("a final checkpoint");
    assert_eq!(last.manifest.version, summary.policy_version);
    assert_eq!(last.manifest.env_steps, summary.env_steps);
    assert!(folder.finished_steps().unwrap() >= Some(3_000));
    let (obs_dim, act_dim) = Task::Point.dims();
    let mut rng = rand::rngs::ThreadRng::default();
    let mut policy = pbrl_common::nets::Owned::build(&mut rng, |vb| {
        pbrl_common::nets::GaussianPolicy::new(vb, obs_dim, &[32, 32], act_dim)
    })
    .unwrap();
    policy
        .varmap
        .load(last.dir.join("policy.safetensors"))
        .unwrap();
    assert!(dir.path().join("config.json").exists());
    for a in [actor_a, actor_b] {
        joined(a, 30).await;
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn every_curve_row_holds_a_deterministic_evaluation_of_its_weights() {
    let (endpoint, _router) = router().await;
    let run = "eval-test";
    let watcher = ConnectArgs::connecting_to(&endpoint).open().await.unwrap();
    let mut weights = WeightsClient::new(&watcher, &Keys::new(run).unwrap())
        .await
        .unwrap();
    let cfg = LearnerConfig {
        eval_episodes: 4,
        eval_sampled: true,
        ..support::point_learner(run, Algo::Sac, 3_000)
    };
    let learner = learner(&endpoint, cfg).await;
    let (_stop_a, actor_a) = actor(&endpoint, run, 0);
    let (_stop_b, actor_b) = actor(&endpoint, run, 1);
    let summary = joined(learner, 120).await;
    assert_eq!(summary.rows.len(), 3, "one row per 1,000 env steps");
    for (k, row) in summary.rows.iter().enumerate() {
        let due = 1_000 * (k as u64 + 1);
        assert!(
            (due..due + 30).contains(&row.env_steps),
            "row {k} at {} env steps",
            row.env_steps
        );
        assert_eq!(row.eval_episodes, 4, "row {k} has its evaluation");
        assert_eq!(row.eval_version, row.policy_version, "row {k}");
        assert!(row.eval_return_truth.is_finite() && row.eval_return_truth < 0.0);
        assert!((0.0..=1.0).contains(&row.eval_success_rate));
        assert!(
            row.eval_sampled_return_truth.is_finite(),
            "row {k} has its sampled evaluation"
        );
        assert!((0.0..=1.0).contains(&row.eval_sampled_success_rate));
    }
    for a in [actor_a, actor_b] {
        joined(a, 30).await;
    }

    // The same request gives the same episodes: the mean action, fixed seeds.
    let w = weights.newest().expect("the watcher saw weights");
    let request = pbrl_common::wire::EvalRequest {
        id: 7,
        actor: 0,
        weights: w,
        seeds: vec![service::EVAL_SEED_BASE, service::EVAL_SEED_BASE + 1],
        sampled: true,
        steps: true,
    };
    let a = runner::evaluate(None, &request, 0).unwrap();
    let b = runner::evaluate(None, &request, 1).unwrap();
    assert_eq!(a.episodes, b.episodes);
    // The steps of each mean-action episode, whose truth adds up to its return.
    assert_eq!(a.steps.len(), 2);
    for (s, o) in a.steps.iter().zip(&a.episodes) {
        assert_eq!(s.truth.len(), o.steps as usize);
        assert_eq!(s.obs.len(), s.truth.len() * POINT_OBS);
        assert_eq!(s.actions.len(), s.truth.len() * POINT_ACT);
        let sum: f32 = s.truth.iter().sum();
        assert!(
            (sum - o.return_truth).abs() < 1e-3,
            "{sum} vs {}",
            o.return_truth
        );
    }
    assert_eq!(a.sampled, b.sampled, "sampled noise follows from the seed");
    assert_eq!(a.sampled.len(), 2);
    assert_ne!(
        a.episodes[0].return_truth, a.sampled[0].return_truth,
        "the sampled episode is another episode"
    );
    assert_eq!(a.version, request.weights.version);
    assert_ne!(
        a.episodes[0].return_truth, a.episodes[1].return_truth,
        "different seeds, different episodes"
    );
}
