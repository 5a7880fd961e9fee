//! The actor service: run episodes with the newest weights and publish whole trajectories,
//! tagged with the policy version that acted.

use std::future::Future;
use std::time::Duration;

use anyhow::{Context, Result};
use pbrl_common::bus::{wait_until, TrajectoryPublisher, WeightsClient};
use pbrl_common::Keys;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
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

/// Run episodes until `shutdown` resolves or the learner says stop.
pub async fn run(
    cfg: ActorConfig,
    session: Session,
    shutdown: impl Future<Output = ()>,
) -> Result<()> {
    let keys = Keys::new(&cfg.run)?;
    let weights = WeightsClient::new(&session, &keys).await?;
    let publisher = TrajectoryPublisher::new(&session, &keys, cfg.id).await?;
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
    let mut rng = ChaCha8Rng::seed_from_u64(
        cfg.seed ^ (0x9e37_79b9_7f4a_7c15u64.wrapping_mul(cfg.id as u64 + 1)),
    );
    let mut episode: u64 = 0;
    let mut on_version = 0u32;
    loop {
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
                    tracing::info!(actor = cfg.id, episodes = episode, "the learner says stop");
                    return Ok(());
                }
                w = weights.next() => {
                    let w = w?;
                    if w.version > policy.version {
                        policy = Policy::from_weights(&w).with_context(|| format!("actor {}", cfg.id))?;
                        on_version = 0;
                    }
                }
            }
        }
        on_version += 1;
        // Seeds: actor i of the run plays seeds seed * 2^32 + i + k * 2^16 (k = episode).
        let seed = (cfg.seed << 32) ^ (cfg.id as u64) ^ (episode << 16);
        episode += 1;
        // NOTE: an episode is CPU work (a few ms for feeding); run it without holding up
        // the runtime's other tasks.
        let trajectory = tokio::task::block_in_place(|| -> Result<_> {
            let mut t = match world.as_mut() {
                Some(w) => run_episode_with(w, seed, |_, obs| {
                    let a = policy
                        .act(obs, &mut rng, false)
                        .map_err(|e| WorldError::Policy(e.to_string()))?;
                    let mut out = [0.0f32; ACT_DIM];
                    out.copy_from_slice(&a[..ACT_DIM]);
                    Ok(out)
                })?,
                None => {
                    // NOTE: the point task takes infallible actions; keep the first
                    // policy error and report it after the episode.
                    let mut failed = None;
                    let t = point_episode(seed, POINT_HORIZON, |obs| {
                        policy.act(obs, &mut rng, false).unwrap_or_else(|e| {
                            failed.get_or_insert(e);
                            vec![0.0; POINT_ACT]
                        })
                    });
                    if let Some(e) = failed {
                        return Err(e.context(format!("actor {}: the policy failed", cfg.id)));
                    }
                    t
                }
            };
            t.policy_version = policy.version;
            Ok(t)
        })?;
        tokio::select! {
            biased;
            _ = &mut shutdown => return Ok(()),
            r = publisher.publish(trajectory, false) => r?,
        }
        if let Ok(Some(_)) = stop.try_recv() {
            tracing::info!(actor = cfg.id, episodes = episode, "the learner says stop");
            return Ok(());
        }
    }
}
