//! The actor service: run episodes with the newest weights and publish whole trajectories,
//! tagged with the policy version that acted.

use std::future::Future;
use std::time::Duration;

use anyhow::{Context, Result};
use pbrl_common::bus::{
    wait_until, MessagePublisher, MessageSubscriber, TrajectoryPublisher, WeightsClient,
};
use pbrl_common::wire::{Body, EvalRequest, EvalResult};
use pbrl_common::{Keys, Trajectory};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use zenoh::qos::Priority;
use zenoh::Session;

use crate::config::WorldConfig;
use crate::point::{point_episode, POINT_ACT, POINT_OBS};
use crate::policy::Policy;
use crate::rollout::run_episode_with;
use crate::world::{FeedingWorld, WorldError, ACT_DIM, OBS_DIM};

/// The task the actors run.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "kebab-case")]
pub enum Task {
    /// The feeding world.
    Feeding,
    /// A point reaching a goal (30 steps), for tests.
    Point,
}

impl Task {
    /// Observation and action lengths.
    pub fn dims(self) -> (usize, usize) {
        match self {
            Task::Feeding => (OBS_DIM, ACT_DIM),
            Task::Point => (POINT_OBS, POINT_ACT),
        }
    }
}

/// Steps of one point-task episode.
pub const POINT_HORIZON: u32 = 30;

/// One actor's settings.
#[derive(Clone, Debug)]
pub struct ActorConfig {
    /// This actor's number (its key expression and its share of the seeds).
    pub id: u32,
    /// Run id.
    pub run: String,
    pub task: Task,
    pub world: WorldConfig,
    /// Seed of the run; episode seeds follow from it, the actor id and the episode count.
    pub seed: u64,
}

/// The seed of episode `k` that actor `actor` runs with weights made at `made_at` env
/// steps, in a run of seed `run_seed` (a SplitMix64 mix; below 2^63, apart from the
/// evaluation seeds).
pub fn episode_seed(run_seed: u64, actor: u32, made_at: u64, k: u32) -> u64 {
    let mut z = run_seed;
    for x in [actor as u64, made_at, k as u64] {
        z = z.wrapping_add(0x9e37_79b9_7f4a_7c15).wrapping_add(x);
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^= z >> 31;
    }
    z >> 1
}

/// One episode of `task` with `policy` (the mean action when `deterministic`).
fn episode(
    world: Option<&mut FeedingWorld>,
    policy: &Policy,
    seed: u64,
    rng: &mut ChaCha8Rng,
    deterministic: bool,
) -> Result<Trajectory> {
    let mut t = match world {
        Some(w) => run_episode_with(w, seed, |_, obs| {
            let a = policy
                .act(obs, rng, deterministic)
                .map_err(|e| WorldError::Policy(e.to_string()))?;
            let mut out = [0.0f32; ACT_DIM];
            out.copy_from_slice(&a[..ACT_DIM]);
            Ok(out)
        })?,
        None => {
            // NOTE: the point task takes infallible actions; keep the first policy error
            // and report it after the episode.
            let mut failed = None;
            let t = point_episode(seed, POINT_HORIZON, |obs| {
                policy.act(obs, rng, deterministic).unwrap_or_else(|e| {
                    failed.get_or_insert(e);
                    vec![0.0; POINT_ACT]
                })
            });
            if let Some(e) = failed {
                return Err(e.context("the policy failed"));
            }
            t
        }
    };
    t.policy_version = policy.version;
    Ok(t)
}

/// Run the deterministic evaluation episodes `req` asks for.
pub fn evaluate(
    world: Option<&mut FeedingWorld>,
    req: &EvalRequest,
    actor: u32,
) -> Result<EvalResult> {
    let policy = Policy::from_weights(&req.weights)?;
    // NOTE: the mean action draws no noise; the generator is only a parameter.
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    let mut world = world;
    let episodes = req
        .seeds
        .iter()
        .map(|&seed| Ok(episode(world.as_deref_mut(), &policy, seed, &mut rng, true)?.outcome))
        .collect::<Result<Vec<_>>>()?;
    Ok(EvalResult {
        id: req.id,
        actor,
        version: policy.version,
        episodes,
    })
}

/// Run the evaluation `req` asks for and publish its result.
async fn answer(
    world: Option<&mut FeedingWorld>,
    req: &EvalRequest,
    actor: u32,
    results: &MessagePublisher,
) -> Result<()> {
    let r = tokio::task::block_in_place(|| evaluate(world, req, actor))
        .with_context(|| format!("actor {actor}: evaluation {}", req.id))?;
    results.send(&Body::EvalResult(r)).await
}

/// Run episodes until `shutdown` resolves or the learner says stop; run evaluation
/// episodes when the learner asks.
pub async fn run(
    cfg: ActorConfig,
    session: Session,
    shutdown: impl Future<Output = ()>,
) -> Result<()> {
    let keys = Keys::new(&cfg.run)?;
    let weights = WeightsClient::new(&session, &keys).await?;
    let publisher = TrajectoryPublisher::new(&session, &keys, cfg.id).await?;
    let eval_requests = MessageSubscriber::new(&session, &keys, keys.eval_request(cfg.id)).await?;
    let eval_results =
        MessagePublisher::new(&session, &keys, keys.eval_result(cfg.id), Priority::Data).await?;
    let pick = |b: Body| match b {
        Body::EvalRequest(r) => Some(r),
        _ => None,
    };
    let stop = session
        .declare_subscriber(keys.stop())
        .await
        .map_err(|e| anyhow::anyhow!("declaring the stop subscriber: {e}"))?;
    tokio::pin!(shutdown);

    // The current weights: asked for (an actor that joins late), else the next published.
    let first = tokio::select! {
        _ = &mut shutdown => return Ok(()),
        w = async {
            match weights.fetch(&session, Duration::from_secs(2)).await? {
                Some(w) => Ok::<_, anyhow::Error>(w),
                None => weights.next().await,
            }
        } => w?,
    };
    let mut policy = Policy::from_weights(&first)?;
    tracing::info!(
        actor = cfg.id,
        version = policy.version,
        "actor has weights"
    );
    tokio::select! {
        _ = &mut shutdown => return Ok(()),
        r = wait_until(Duration::from_secs(60), || publisher.has_subscribers()) => r?,
    }

    let mut world = match cfg.task {
        Task::Feeding => Some(FeedingWorld::new(cfg.world.clone())?),
        Task::Point => None,
    };
    let mut episodes: u64 = 0;
    let mut on_version = 0u32;
    loop {
        if let Some(req) = eval_requests.try_next(pick)? {
            answer(world.as_mut(), &req, cfg.id, &eval_results).await?;
            continue;
        }
        if let Some(w) = weights.newest() {
            if w.version > policy.version {
                policy = Policy::from_weights(&w).with_context(|| format!("actor {}", cfg.id))?;
                on_version = 0;
            }
        }
        // Flow control: once this version's share of episodes is run, wait for the next.
        while policy.episodes_allowed > 0 && on_version >= policy.episodes_allowed {
            tokio::select! {
                _ = &mut shutdown => return Ok(()),
                _ = stop.recv_async() => {
                    tracing::info!(actor = cfg.id, episodes, "the learner says stop");
                    return Ok(());
                }
                w = weights.next() => {
                    let w = w?;
                    if w.version > policy.version {
                        policy = Policy::from_weights(&w).with_context(|| format!("actor {}", cfg.id))?;
                        on_version = 0;
                    }
                }
                req = eval_requests.next(pick) => {
                    let req = req?;
                    answer(world.as_mut(), &req, cfg.id, &eval_results).await?;
                }
            }
        }
        // Seeds follow from the run's seed, the actor, the env steps the weights were made
        // at and the episode's number on them: a resumed run (whose versions count on from
        // a gap) plays the same episodes as one never stopped, and episodes of a run get
        // distinct seeds (a 63-bit hash). Sampling noise restarts from the episode's seed.
        let seed = episode_seed(cfg.seed, cfg.id, policy.made_at, on_version);
        let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0x5eed_0fa0_c710_u64);
        on_version += 1;
        episodes += 1;
        let trajectory =
            tokio::task::block_in_place(|| episode(world.as_mut(), &policy, seed, &mut rng, false))
                .with_context(|| format!("actor {}: episode seed {seed}", cfg.id))?;
        tokio::select! {
            biased;
            _ = &mut shutdown => return Ok(()),
            r = publisher.publish(trajectory, false) => r?,
        }
        if let Ok(Some(_)) = stop.try_recv() {
            tracing::info!(actor = cfg.id, episodes, "the learner says stop");
            return Ok(());
        }
    }
}
