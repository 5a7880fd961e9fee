//! The RL backbone behind one enum: SAC (PEBBLE's) or PPO (PrefPPO's). The learner hands
//! it each trajectory ([`Backbone::observe`]); the backbone decides what to train, when
//! to publish, what the actors' normaliser is and how much each actor may run ahead. It
//! owns its replay buffer: a checkpoint reads it through [`Backbone::replay_rows`].

use anyhow::Result;
use pbrl_common::nets::export;
use pbrl_common::wire::Weights;
use pbrl_common::{RunningNorm, Trajectory};
use serde::{Deserialize, Serialize};

use crate::pref::reward::TrainReward;
use crate::rl::ppo::{Ppo, PpoState, PpoStats};
use crate::rl::sac::{Sac, SacLosses, SacState};
use crate::run::config::{Algo, LearnerConfig};

pub enum Backbone {
    Sac(Box<Sac>),
    /// PPO and the rollout being collected.
    Ppo(Box<Ppo>, Vec<Trajectory>),
}

/// What the backbone keeps between publications (saved with the checkpoint).
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct Publication {
    /// SAC gradient steps since the last publication.
    pub since: u64,
    /// Episodes of the current version received (deterministic mode).
    pub episodes: u64,
    /// Env steps the current version was made at.
    pub env_steps: u64,
}

/// Losses of the newest update.
#[derive(Clone, Copy, Debug)]
pub enum Losses {
    Sac(SacLosses),
    Ppo(PpoStats),
}

/// The newest losses of each backbone, for the curve (NaN until its first update, and
/// always for the other backbone's).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct LastLosses {
    /// SAC.
    pub critic: f64,
    pub actor: f64,
    pub alpha: f64,
    /// PPO.
    pub value: f64,
    pub policy: f64,
    pub approx_kl: f64,
}

impl Default for LastLosses {
    fn default() -> Self {
        let nan = f64::NAN;
        Self {
            critic: nan,
            actor: nan,
            alpha: nan,
            value: nan,
            policy: nan,
            approx_kl: nan,
        }
    }
}

impl LastLosses {
    pub fn record(&mut self, losses: Losses) {
        match losses {
            Losses::Sac(l) => {
                (self.critic, self.actor, self.alpha) =
                    (l.critic as f64, l.actor as f64, l.alpha as f64)
            }
            Losses::Ppo(s) => {
                (self.value, self.policy, self.approx_kl) = (
                    s.value_loss as f64,
                    s.policy_loss as f64,
                    s.approx_kl as f64,
                )
            }
        }
    }
}

/// SAC trains on raw observations: the normaliser that travels with its weights changes
/// nothing (`(x - 0) / sqrt(1 - 1e-8 + 1e-8)`, no clip).
pub fn identity_norm(obs_dim: usize) -> RunningNorm {
    RunningNorm {
        mean: vec![0.0; obs_dim],
        var: vec![1.0 - 1e-8; obs_dim],
        count: 1.0,
        clip: f32::MAX as f64,
    }
}

/// What observing one trajectory did.
#[derive(Clone, Copy, Debug, Default)]
pub struct Observed {
    /// Gradient steps (SAC) or minibatch updates (PPO) taken.
    pub updates: u64,
    pub losses: Option<Losses>,
    /// New weights are due.
    pub publish: bool,
}

#[derive(Serialize, Deserialize)]
pub enum BackboneState {
    Sac(SacState),
    Ppo(PpoState),
}

impl Backbone {
    pub fn new(cfg: &LearnerConfig) -> Result<Self> {
        let threads = cfg.learner_threads;
        Ok(match cfg.algo {
            Algo::Sac => {
                let mut sac = Sac::new(cfg.sac.clone(), cfg.obs_dim, cfg.act_dim)?;
                sac.set_threads(threads)?;
                if cfg.reward.learnt() && cfg.pref.model.features {
                    sac.keep_features();
                }
                Backbone::Sac(Box::new(sac))
            }
            Algo::Ppo => {
                let mut ppo = Ppo::new(cfg.ppo.clone(), cfg.obs_dim, cfg.act_dim)?;
                ppo.set_threads(threads)?;
                Backbone::Ppo(Box::new(ppo), Vec::new())
            }
        })
    }

    /// Whether a trajectory acted by `version` is trained on when the current version is
    /// `current`. PPO trains only on the current version's data, and so does the
    /// deterministic mode; SAC takes any.
    pub fn takes(&self, cfg: &LearnerConfig, version: u64, current: u64) -> bool {
        version == current || !(cfg.sync || matches!(self, Backbone::Ppo(..)))
    }

    /// Train on one trajectory: SAC stores its transitions and takes the gradient steps
    /// owed; PPO adds it to the rollout and trains once the rollout is full. `env_steps`
    /// counts the steps before this trajectory.
    pub fn observe(
        &mut self,
        cfg: &LearnerConfig,
        t: Trajectory,
        reward: &mut TrainReward,
        env_steps: u64,
        publication: &mut Publication,
    ) -> Result<Observed> {
        publication.episodes += 1;
        let mut out = Observed::default();
        match self {
            Backbone::Sac(sac) => {
                let was_random = sac.env_steps < sac.cfg.random_steps;
                sac.observe(&t);
                let random_ended = was_random && sac.env_steps >= sac.cfg.random_steps;
                let due = sac.updates_due();
                if due > 0 {
                    let now = env_steps + t.steps() as u64;
                    let losses = tokio::task::block_in_place(|| -> Result<_> {
                        let mut last = None;
                        for _ in 0..due {
                            last = Some(sac.update(|b| {
                                reward
                                    .minibatch(b, now)
                                    .map_err(|e| candle_core::Error::Msg(format!("{e:#}")))
                            })?);
                        }
                        Ok(last)
                    })?;
                    out.losses = losses.map(Losses::Sac);
                    out.updates = due;
                    publication.since += due;
                }
                out.publish = if cfg.sync {
                    publication.episodes
                        >= self.share(cfg, publication.env_steps) * cfg.actors as u64
                } else {
                    publication.since >= cfg.publish_every || random_ended
                };
            }
            Backbone::Ppo(ppo, rollout) => {
                rollout.push(t);
                let steps: usize = rollout.iter().map(|t| t.steps()).sum();
                if steps >= ppo.cfg.rollout_steps {
                    let now = env_steps + rollout.last().map_or(0, |t| t.steps() as u64);
                    let total = cfg.total_steps;
                    let stats = tokio::task::block_in_place(|| -> Result<_> {
                        let rewards = reward.per_step(rollout, now)?;
                        Ok(ppo.train(rollout, &rewards, total)?)
                    })?;
                    out.losses = Some(Losses::Ppo(stats));
                    out.updates = stats.minibatch_updates;
                    rollout.clear();
                    out.publish = true;
                }
            }
        }
        Ok(out)
    }

    /// The pretraining is over (PEBBLE, PrefPPO): the values learnt for the entropy bonus
    /// mean nothing for r_hat. SAC resets its critics, PPO its value network.
    pub fn reset_after_pretraining(&mut self) -> Result<()> {
        match self {
            Backbone::Sac(sac) => sac.reset_critics()?,
            Backbone::Ppo(ppo, _) => ppo.reset_value()?,
        }
        Ok(())
    }

    /// Episodes each actor runs with the version published at `env_steps`: its share of
    /// the env steps that version is for (SAC: until the next publication, or the random
    /// steps; PPO: one rollout).
    pub fn share(&self, cfg: &LearnerConfig, env_steps: u64) -> u64 {
        let per_version = match self {
            Backbone::Sac(s) if env_steps < s.cfg.random_steps => s.cfg.random_steps - env_steps,
            Backbone::Sac(s) => cfg.publish_every * s.cfg.update_every,
            Backbone::Ppo(p, _) => p.cfg.rollout_steps as u64,
        };
        per_version
            .div_ceil(cfg.actors.max(1) as u64 * cfg.episode_steps.max(1) as u64)
            .max(1)
    }

    /// The weights actors act with, and their credit.
    pub fn weights(&self, cfg: &LearnerConfig, version: u64, env_steps: u64) -> Result<Weights> {
        let (obs_dim, act_dim) = (cfg.obs_dim, cfg.act_dim);
        let share = self.share(cfg, env_steps);
        let (tensors, norm, random) = match self {
            Backbone::Sac(s) => (
                export(&s.policy.varmap)?,
                identity_norm(obs_dim),
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
            // NOTE: the credit each actor gets: its share of the steps until the next
            // version, and one more to keep it busy while that version comes (the
            // deterministic mode runs exactly the share). What waits for the learner is at
            // most this per actor.
            episodes_per_actor: (share + (!cfg.sync) as u64).min(u32::MAX as u64) as u32,
            acks: Vec::new(),
        })
    }

    /// The networks by name (for checkpoints).
    pub fn networks(&self) -> Vec<(&'static str, &candle_nn::VarMap)> {
        match self {
            Backbone::Sac(s) => s.networks().to_vec(),
            Backbone::Ppo(p, _) => p.networks().to_vec(),
        }
    }

    pub fn state(&self) -> Result<BackboneState> {
        Ok(match self {
            Backbone::Sac(s) => BackboneState::Sac(s.state()?),
            Backbone::Ppo(p, _) => BackboneState::Ppo(p.state()?),
        })
    }

    /// Continue from a checkpoint's state (the networks are loaded apart, into
    /// [`Backbone::networks`]); SAC's replay buffer is refilled from `replay`, the rows
    /// of its transitions from the first one saved on.
    pub fn restore(
        &mut self,
        s: &BackboneState,
        replay: impl FnOnce() -> Result<(u64, Vec<f32>)>,
    ) -> Result<()> {
        match (self, s) {
            (Backbone::Sac(sac), BackboneState::Sac(s)) => {
                sac.restore(s)?;
                let (from, rows) = replay()?;
                sac.restore_replay(from, &rows)?;
            }
            (Backbone::Ppo(ppo, _), BackboneState::Ppo(s)) => ppo.restore(s)?,
            _ => anyhow::bail!("the checkpoint is of another algorithm"),
        }
        Ok(())
    }

    /// The replay buffer's transitions (SAC): the first one it still holds and the number
    /// pushed so far. None for PPO, which keeps no replay.
    pub fn replay_span(&self) -> Option<(u64, u64)> {
        match self {
            Backbone::Sac(s) => Some(s.replay_span()),
            Backbone::Ppo(..) => None,
        }
    }

    /// Rows of the replay's transitions `from..to` (all still held), for a checkpoint.
    pub fn replay_rows(&self, from: u64, to: u64) -> Vec<f32> {
        match self {
            Backbone::Sac(s) => s.replay_rows(from, to),
            Backbone::Ppo(..) => Vec::new(),
        }
    }
}
