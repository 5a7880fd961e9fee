//! The learner service: take trajectories from the actors, train SAC or PPO on the chosen
//! reward, publish weights, write the learning curve.

use std::future::Future;
use std::io::Write;
use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, Result};
use pbrl_common::bus::{TrajectorySubscriber, WeightsServer};
use pbrl_common::nets::export;
use pbrl_common::wire::{self, Body, Weights};
use pbrl_common::{Keys, RunningNorm, StepRewards, Trajectory};
use serde::{Deserialize, Serialize};
use zenoh::qos::CongestionControl;
use zenoh::Session;

use crate::ppo::{Ppo, PpoConfig};
use crate::sac::{Sac, SacConfig};

/// The RL backbone.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "kebab-case")]
pub enum Algo {
    Sac,
    Ppo,
}

/// The reward the policy is trained on: one pluggable piece (preference learning adds the
/// learnt ensemble here).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "kebab-case")]
pub enum RewardSource {
    /// The ground truth r = r_R + r_H.
    True,
    /// The sketchy task reward r_task = -d alone.
    Task,
}

impl RewardSource {
    pub fn of(self, r: &StepRewards) -> f32 {
        match self {
            RewardSource::True => r.truth,
            RewardSource::Task => r.task,
        }
    }
}

/// The learner's settings.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct LearnerConfig {
    pub run: String,
    pub algo: Algo,
    pub reward: RewardSource,
    /// Env steps of the run.
    pub total_steps: u64,
    pub obs_dim: usize,
    pub act_dim: usize,
    pub sac: SacConfig,
    pub ppo: PpoConfig,
    /// SAC: publish new weights every this many gradient steps.
    pub publish_every: u64,
    /// Env steps between rows of the learning curve.
    pub log_every: u64,
    /// Actors feeding this learner (for flow control).
    pub actors: u32,
    /// Env steps of one episode (for flow control).
    pub episode_steps: u32,
    /// Run folder for the curve (`curve.csv`) and the resolved config; none in tests.
    pub out: Option<PathBuf>,
}

/// One row of the learning curve (training episodes since the previous row).
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct CurveRow {
    pub env_steps: u64,
    pub episodes: u64,
    pub return_truth: f64,
    pub success_rate: f64,
    pub return_human: f64,
    pub return_task: f64,
    pub loss_critic_or_value: f64,
    pub loss_actor: f64,
    pub alpha_or_kl: f64,
    pub env_steps_per_s: f64,
    pub updates_per_s: f64,
    pub updates: u64,
    pub policy_version: u64,
    pub dropped_messages: u64,
    pub stale_trajectories: u64,
}

const CURVE_HEADER: &str = "env_steps,episodes,return_truth,success_rate,return_human,return_task,loss_critic_or_value,loss_actor,alpha_or_kl,env_steps_per_s,updates_per_s,updates,policy_version,dropped_messages,stale_trajectories";

impl CurveRow {
    fn csv(&self) -> String {
        format!(
            "{},{},{:.4},{:.4},{:.4},{:.4},{:.6},{:.6},{:.6},{:.1},{:.2},{},{},{},{}",
            self.env_steps,
            self.episodes,
            self.return_truth,
            self.success_rate,
            self.return_human,
            self.return_task,
            self.loss_critic_or_value,
            self.loss_actor,
            self.alpha_or_kl,
            self.env_steps_per_s,
            self.updates_per_s,
            self.updates,
            self.policy_version,
            self.dropped_messages,
            self.stale_trajectories
        )
    }
}

/// What a finished run did.
#[derive(Clone, Debug, Default)]
pub struct Summary {
    pub env_steps: u64,
    pub updates: u64,
    pub policy_version: u64,
    pub rows: Vec<CurveRow>,
    pub dropped_messages: u64,
    pub stale_trajectories: u64,
    /// Episodes received from each actor.
    pub episodes_by_actor: std::collections::BTreeMap<u32, u64>,
    /// The policy version of each actor's first episode.
    pub first_version_by_actor: std::collections::BTreeMap<u32, u64>,
}

enum Backbone {
    Sac(Box<Sac>),
    Ppo(Box<Ppo>, Vec<Trajectory>),
}

/// Episode statistics accumulated between curve rows.
#[derive(Default)]
struct Window {
    episodes: u64,
    truth: f64,
    success: f64,
    human: f64,
    task: f64,
}

fn weights_of(
    cfg: &LearnerConfig,
    backbone: &Backbone,
    version: u64,
    env_steps: u64,
) -> Result<Weights> {
    let (obs_dim, act_dim) = (cfg.obs_dim, cfg.act_dim);
    // Flow control: each actor runs only its share of the env steps this version is for
    // (SAC: until the next publication, or the random steps; PPO: one rollout), plus one.
    let per_version = match backbone {
        Backbone::Sac(s) if env_steps < s.cfg.random_steps => s.cfg.random_steps - env_steps,
        Backbone::Sac(s) => cfg.publish_every * s.cfg.update_every,
        Backbone::Ppo(p, _) => p.cfg.rollout_steps as u64,
    };
    let share = per_version.div_ceil(cfg.actors.max(1) as u64 * cfg.episode_steps.max(1) as u64);
    let (tensors, norm, random) = match backbone {
        Backbone::Sac(s) => (
            export(&s.policy.varmap)?,
            // NOTE: SAC trains on raw observations; an identity normaliser travels.
            RunningNorm {
                mean: vec![0.0; obs_dim],
                var: vec![1.0 - 1e-8; obs_dim],
                count: 1.0,
                clip: f32::MAX as f64,
            },
            env_steps < s.cfg.random_steps,
        ),
        Backbone::Ppo(p, _) => (export(&p.policy.varmap)?, p.norm.clone(), false),
    };
    Ok(Weights {
        version,
        env_steps,
        obs_dim: obs_dim as u32,
        act_dim: act_dim as u32,
        tensors,
        obs_mean: norm.mean.iter().map(|x| *x as f32).collect(),
        obs_var: norm.var.iter().map(|x| *x as f32).collect(),
        obs_clip: norm.clip as f32,
        random_actions: random,
        episodes_per_actor: (share + 1).min(u32::MAX as u64) as u32,
    })
}

/// Write `varmap` as `<dir>/<name>.safetensors` atomically: a temporary file, synced, then
/// renamed over the old one.
fn save_atomic(dir: &std::path::Path, name: &str, varmap: &candle_nn::VarMap) -> Result<()> {
    let tmp = dir.join(format!("{name}.safetensors.tmp"));
    varmap
        .save(&tmp)
        .with_context(|| format!("writing {}", tmp.display()))?;
    std::fs::File::open(&tmp)
        .and_then(|f| f.sync_all())
        .with_context(|| format!("syncing {}", tmp.display()))?;
    let dst = dir.join(format!("{name}.safetensors"));
    std::fs::rename(&tmp, &dst)
        .with_context(|| format!("renaming {} to {}", tmp.display(), dst.display()))
}

/// The networks of the run, under `<out>/checkpoint/`, with `checkpoint.json` (version,
/// env steps, updates) written last. (Full checkpoints for resuming, with optimiser state,
/// replay buffer and RNGs, come with run resume.)
fn save_networks(
    out: &std::path::Path,
    backbone: &Backbone,
    version: u64,
    env_steps: u64,
    updates: u64,
) -> Result<()> {
    let dir = out.join("checkpoint");
    std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
    match backbone {
        Backbone::Sac(s) => {
            save_atomic(&dir, "policy", &s.policy.varmap)?;
            save_atomic(&dir, "critic", s.critic_varmap())?;
            save_atomic(&dir, "target_critic", s.target_varmap())?;
        }
        Backbone::Ppo(p, _) => {
            save_atomic(&dir, "policy", &p.policy.varmap)?;
            save_atomic(&dir, "value", &p.value.varmap)?;
        }
    }
    let manifest =
        serde_json::json!({ "version": version, "env_steps": env_steps, "updates": updates });
    let tmp = dir.join("checkpoint.json.tmp");
    std::fs::write(&tmp, manifest.to_string())
        .with_context(|| format!("writing {}", tmp.display()))?;
    std::fs::rename(&tmp, dir.join("checkpoint.json"))
        .with_context(|| format!("renaming {}", tmp.display()))
}

/// Train until `total_steps` env steps or `shutdown`; then tell the actors to stop.
pub async fn run(
    cfg: LearnerConfig,
    session: Session,
    shutdown: impl Future<Output = ()>,
) -> Result<Summary> {
    let keys = Keys::new(&cfg.run)?;
    let server = WeightsServer::new(&session, &keys).await?;
    let trajectories = TrajectorySubscriber::new(&session, &keys).await?;
    let stop = session
        .declare_publisher(keys.stop())
        .congestion_control(CongestionControl::Block)
        .await
        .map_err(|e| anyhow::anyhow!("declaring the stop publisher: {e}"))?;
    let mut curve = match &cfg.out {
        Some(dir) => {
            std::fs::create_dir_all(dir)
                .with_context(|| format!("creating run folder {}", dir.display()))?;
            let config = serde_json::to_string_pretty(&cfg)?;
            std::fs::write(dir.join("config.json"), config)
                .with_context(|| format!("writing {}/config.json", dir.display()))?;
            let path = dir.join("curve.csv");
            let mut f = std::fs::File::create(&path)
                .with_context(|| format!("creating {}", path.display()))?;
            writeln!(f, "{CURVE_HEADER}")?;
            Some(f)
        }
        None => None,
    };
    tracing::info!(config = %serde_json::to_string(&cfg)?, "learner starts");

    let (obs_dim, act_dim) = (cfg.obs_dim, cfg.act_dim);
    let mut backbone = match cfg.algo {
        Algo::Sac => Backbone::Sac(Box::new(Sac::new(cfg.sac.clone(), obs_dim, act_dim)?)),
        Algo::Ppo => Backbone::Ppo(
            Box::new(Ppo::new(cfg.ppo.clone(), obs_dim, act_dim)?),
            Vec::new(),
        ),
    };
    let mut version = 1u64;
    server
        .publish(&weights_of(&cfg, &backbone, version, 0)?)
        .await?;

    let mut summary = Summary::default();
    let (mut env_steps, mut updates, mut since_publish) = (0u64, 0u64, 0u64);
    let mut window = Window::default();
    let mut next_row = cfg.log_every;
    let (mut last_loss, mut last_actor, mut last_aux) = (0.0f64, 0.0f64, 0.0f64);
    let start = Instant::now();
    tokio::pin!(shutdown);
    while env_steps < cfg.total_steps {
        let msg = tokio::select! {
            _ = &mut shutdown => break,
            m = trajectories.next() => m?,
        };
        let t = msg.trajectory;
        *summary.episodes_by_actor.entry(msg.actor).or_default() += 1;
        summary
            .first_version_by_actor
            .entry(msg.actor)
            .or_insert(t.policy_version);
        let mut publish = false;
        match &mut backbone {
            Backbone::Sac(sac) => {
                let was_random = sac.env_steps < sac.cfg.random_steps;
                sac.observe(&t, |r| cfg.reward.of(r));
                let due = sac.updates_due();
                if due > 0 {
                    let losses = tokio::task::block_in_place(|| -> Result<_> {
                        let mut last = None;
                        for _ in 0..due {
                            last = Some(sac.update()?);
                        }
                        Ok(last)
                    })?;
                    if let Some(l) = losses {
                        (last_loss, last_actor, last_aux) =
                            (l.critic as f64, l.actor as f64, l.alpha as f64);
                    }
                    updates += due;
                    since_publish += due;
                }
                publish = since_publish >= cfg.publish_every
                    || (was_random && sac.env_steps >= sac.cfg.random_steps);
            }
            Backbone::Ppo(ppo, rollout) => {
                // NOTE: synchronous PPO trains only on the current version's data; older
                // trajectories are dropped and counted.
                if t.policy_version != version {
                    summary.stale_trajectories += 1;
                    continue;
                }
                rollout.push(t.clone());
                let steps: usize = rollout.iter().map(|t| t.steps()).sum();
                if steps >= ppo.cfg.rollout_steps {
                    let total = cfg.total_steps;
                    let stats = tokio::task::block_in_place(|| {
                        ppo.train(rollout, |r| cfg.reward.of(r), total)
                    })?;
                    (last_loss, last_actor, last_aux) = (
                        stats.value_loss as f64,
                        stats.policy_loss as f64,
                        stats.approx_kl as f64,
                    );
                    updates += stats.minibatch_updates;
                    rollout.clear();
                    publish = true;
                }
            }
        }
        env_steps += t.steps() as u64;
        window.episodes += 1;
        window.truth += t.outcome.return_truth as f64;
        window.human += t.outcome.return_human as f64;
        window.task += t.outcome.return_task as f64;
        window.success += t.outcome.success as u8 as f64;
        if publish {
            version += 1;
            since_publish = 0;
            server
                .publish(&weights_of(&cfg, &backbone, version, env_steps)?)
                .await?;
        }
        if env_steps >= next_row || env_steps >= cfg.total_steps {
            next_row += cfg.log_every;
            let secs = start.elapsed().as_secs_f64().max(1e-9);
            let n = window.episodes.max(1) as f64;
            let row = CurveRow {
                env_steps,
                episodes: window.episodes,
                return_truth: window.truth / n,
                success_rate: window.success / n,
                return_human: window.human / n,
                return_task: window.task / n,
                loss_critic_or_value: last_loss,
                loss_actor: last_actor,
                alpha_or_kl: last_aux,
                env_steps_per_s: env_steps as f64 / secs,
                updates_per_s: updates as f64 / secs,
                updates,
                policy_version: version,
                dropped_messages: trajectories.dropped.get(),
                stale_trajectories: summary.stale_trajectories,
            };
            tracing::info!(
                env_steps,
                return_truth = row.return_truth,
                success_rate = row.success_rate,
                steps_per_s = row.env_steps_per_s,
                version,
                "charts"
            );
            if let Some(f) = curve.as_mut() {
                writeln!(f, "{}", row.csv())?;
                f.flush()?;
            }
            if let Some(out) = &cfg.out {
                save_networks(out, &backbone, version, env_steps, updates)?;
            }
            summary.rows.push(row);
            window = Window::default();
        }
    }
    let _ = stop.put(wire::encode(&cfg.run, &Body::Stop)).await;
    summary.env_steps = env_steps;
    summary.updates = updates;
    summary.policy_version = version;
    summary.dropped_messages = trajectories.dropped.get();
    Ok(summary)
}
