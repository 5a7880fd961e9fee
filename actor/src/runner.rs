//! The actor service: run episodes with the newest weights and publish whole trajectories,
//! tagged with the policy version that acted.

use std::future::Future;
use std::time::Duration;

use anyhow::{Context, Result};
use pbrl_common::bus::{wait_until, Inbox, MessagePublisher, TrajectoryPublisher, WeightsClient};
use pbrl_common::wire::{Body, EvalRequest, EvalResult, EvalSteps, Weights};
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

    /// Where the observation holds the vector to the goal (first index, length), whose
    /// length is the task reward's d: feeding's spoon minus mouth, the point's goal minus
    /// position.
    pub fn goal_obs(self) -> [usize; 2] {
        match self {
            Task::Feeding => [7, 3],
            Task::Point => [2, 2],
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
pub(crate) fn episode(
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

/// The generator of an episode's sampling noise, from its seed.
pub(crate) fn noise(seed: u64) -> ChaCha8Rng {
    ChaCha8Rng::seed_from_u64(seed ^ 0x5eed_0fa0_c710_u64)
}

/// Run the evaluation episodes `req` asks for: every seed with the mean action and, if
/// asked, again with sampled actions (noise from the seed, as in training).
pub fn evaluate(
    world: Option<&mut FeedingWorld>,
    req: &EvalRequest,
    actor: u32,
) -> Result<EvalResult> {
    let policy = Policy::from_weights(&req.weights)?;
    let mut world = world;
    let mut steps = Vec::new();
    let mut run = |deterministic: bool| {
        req.seeds
            .iter()
            .map(|&seed| {
                // NOTE: the mean action draws no noise; the generator is then unused.
                let mut rng = noise(seed);
                let t = episode(world.as_deref_mut(), &policy, seed, &mut rng, deterministic)?;
                if deterministic && req.steps {
                    let n = t.actions.len() / t.act_dim.max(1) as usize;
                    steps.push(EvalSteps {
                        obs: t.obs[..n * t.obs_dim as usize].to_vec(),
                        actions: t.actions.clone(),
                        truth: t.rewards.iter().map(|r| r.truth).collect(),
                        human: t.rewards.iter().map(|r| r.human).collect(),
                        task: t.rewards.iter().map(|r| r.task).collect(),
                        features: t.features(),
                    });
                }
                Ok(t.outcome)
            })
            .collect::<Result<Vec<_>>>()
    };
    let episodes = run(true)?;
    let sampled = if req.sampled { run(false)? } else { Vec::new() };
    Ok(EvalResult {
        id: req.id,
        actor,
        version: policy.version,
        episodes,
        sampled,
        steps,
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

/// The first wait for the next weights version before the actor asks for it and sends
/// its unacknowledged trajectories again; it doubles up to [`RETRY_MAX`] while nothing
/// comes.
const RETRY_FIRST: Duration = Duration::from_secs(5);
const RETRY_MAX: Duration = Duration::from_secs(60);

/// Take `w` if it is newer than `policy`: forget the trajectories it acknowledges.
fn adopt(
    policy: &mut Policy,
    w: &Weights,
    publisher: &mut TrajectoryPublisher,
    actor: u32,
) -> Result<bool> {
    publisher.acknowledge(&w.acks);
    if w.version <= policy.version {
        return Ok(false);
    }
    *policy = Policy::from_weights(w).with_context(|| format!("actor {actor}"))?;
    // NOTE: until acknowledged, this version's episodes and the last one's are kept.
    publisher.hold_at_most(2 * (w.episodes_per_actor as usize + 1));
    Ok(true)
}

/// The next version is late (the actor's credit is spent). A weights message lost on the
/// way is asked for; if the learner answers with the version this actor has, it may be
/// waiting for trajectories lost on the way: they are sent again (the learner takes each
/// once). A learner that does not answer (paused, gone) is sent nothing more than its credit
/// allowed. True when new weights were adopted.
async fn chase_weights(
    session: &Session,
    weights: &mut WeightsClient,
    policy: &mut Policy,
    publisher: &mut TrajectoryPublisher,
    actor: u32,
) -> Result<bool> {
    let Some(w) = weights.fetch(session, Duration::from_secs(2)).await? else {
        tracing::debug!(actor, "the learner does not answer");
        return Ok(false);
    };
    if adopt(policy, &w, publisher, actor)? {
        tracing::warn!(
            actor,
            version = policy.version,
            "weights arrived only when asked for"
        );
        return Ok(true);
    }
    let n = publisher.resend().await?;
    if n > 0 {
        tracing::debug!(
            actor,
            trajectories = n,
            "no new weights yet; sent the unacknowledged trajectories again"
        );
    }
    Ok(false)
}

/// Run episodes until `shutdown` resolves or the learner says stop; run evaluation
/// episodes when the learner asks. Nothing here blocks the bus: every subscription is an
/// [`Inbox`], drained between episodes and while the actor waits for weights.
pub async fn run(
    cfg: ActorConfig,
    session: Session,
    shutdown: impl Future<Output = ()>,
) -> Result<()> {
    let keys = Keys::new(&cfg.run)?;
    let mut weights = WeightsClient::new(&session, &keys).await?;
    let mut publisher = TrajectoryPublisher::new(&session, &keys, cfg.id).await?;
    let mut eval_requests = Inbox::eval_requests(&session, &keys, cfg.id).await?;
    let eval_results =
        MessagePublisher::new(&session, &keys, keys.eval_result(cfg.id), Priority::Data).await?;
    let mut stops = Inbox::stops(&session, &keys).await?;
    tokio::pin!(shutdown);
    let stopping = |episodes: u64, publisher: &TrajectoryPublisher, weights: &WeightsClient| {
        tracing::info!(
            actor = cfg.id,
            episodes,
            resent = publisher.resent,
            forgotten = publisher.forgotten,
            dropped = weights.dropped.get(),
            "the learner says stop"
        );
    };

    // The current weights: asked for (an actor that joins late), else the next published.
    let first = tokio::select! {
        _ = &mut shutdown => return Ok(()),
        s = stops.next() => { s?; stopping(0, &publisher, &weights); return Ok(()) }
        w = async {
            match weights.fetch(&session, Duration::from_secs(2)).await? {
                Some(w) => Ok::<_, anyhow::Error>(w),
                None => weights.next().await,
            }
        } => w?,
    };
    let mut policy = Policy::from_weights(&first)?;
    publisher.hold_at_most(2 * (first.episodes_per_actor as usize + 1));
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
    let mut retry = RETRY_FIRST;
    loop {
        if stops.try_next().is_some() {
            stopping(episodes, &publisher, &weights);
            return Ok(());
        }
        if let Some(req) = eval_requests.try_next() {
            answer(world.as_mut(), &req, cfg.id, &eval_results).await?;
            continue;
        }
        if let Some(w) = weights.newest() {
            if adopt(&mut policy, &w, &mut publisher, cfg.id)? {
                on_version = 0;
                retry = RETRY_FIRST;
            }
        }
        // Flow control (credit): with the learner's share of unacknowledged trajectories out,
        // wait for the next version (its acknowledgements give new credit).
        while policy.episodes_allowed > 0
            && publisher.unacknowledged() >= policy.episodes_allowed as usize
        {
            tokio::select! {
                _ = &mut shutdown => return Ok(()),
                s = stops.next() => {
                    s?;
                    stopping(episodes, &publisher, &weights);
                    return Ok(());
                }
                w = weights.next() => {
                    if adopt(&mut policy, &w?, &mut publisher, cfg.id)? {
                        on_version = 0;
                        retry = RETRY_FIRST;
                    }
                }
                req = eval_requests.next() => {
                    let req = req?;
                    answer(world.as_mut(), &req, cfg.id, &eval_results).await?;
                }
                _ = tokio::time::sleep(retry) => {
                    retry = (retry * 2).min(RETRY_MAX);
                    if chase_weights(&session, &mut weights, &mut policy, &mut publisher, cfg.id).await? {
                        on_version = 0;
                        retry = RETRY_FIRST;
                    }
                }
            }
        }
        // Seeds follow from the run's seed, the actor, the env steps the weights were made
        // at and the episode's number on them: a resumed run (whose versions count on from
        // a gap) plays the same episodes as one never stopped, and episodes of a run get
        // distinct seeds (a 63-bit hash). Sampling noise restarts from the episode's seed.
        let seed = episode_seed(cfg.seed, cfg.id, policy.made_at, on_version);
        let mut rng = noise(seed);
        on_version += 1;
        episodes += 1;
        let trajectory =
            tokio::task::block_in_place(|| episode(world.as_mut(), &policy, seed, &mut rng, false))
                .with_context(|| format!("actor {}: episode seed {seed}", cfg.id))?;
        tokio::select! {
            biased;
            _ = &mut shutdown => return Ok(()),
            r = publisher.publish(trajectory) => r?,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::WorldConfig;
    use crate::controller::{Controller, ControllerKind};
    use crate::point::point_episode;
    use crate::rollout::run_episode;
    use crate::world::FeedingWorld;

    /// `-|obs[goal_obs]|` after each step is that step's task reward, on both tasks: what
    /// the reward model's anchor reads (`--reward-anchor`).
    #[test]
    fn the_goal_in_the_observation_gives_the_task_reward() {
        let mut world = FeedingWorld::new(WorldConfig::default()).unwrap();
        let mut c = Controller::new(ControllerKind::Random);
        let feeding = run_episode(&mut world, &mut c, 5).unwrap();
        let mut k = 0.0f32;
        let point = point_episode(5, POINT_HORIZON, |_| {
            k += 0.3;
            vec![k.sin(), k.cos()]
        });
        for (task, t) in [(Task::Feeding, feeding), (Task::Point, point)] {
            let [at, len] = task.goal_obs();
            let o = t.obs_dim as usize;
            assert_eq!(o, task.dims().0);
            for (i, r) in t.rewards.iter().enumerate() {
                let row = &t.obs[(i + 1) * o..(i + 2) * o];
                let d = row[at..at + len].iter().map(|x| x * x).sum::<f32>().sqrt();
                assert!(
                    (-d - r.task).abs() < 1e-5,
                    "{task:?} step {i}: -|goal| {} against r_task {}",
                    -d,
                    r.task
                );
            }
        }
    }
}
