//! What the policy trains on, in one place (`shared/method.md` sections 1, 5 and 6):
//!
//! - `truth`: the ground truth r (a baseline; only it reads the truth);
//! - `task`: the sketchy task reward r_task alone (a baseline);
//! - `pref` (PEBBLE, PrefPPO): the k-NN state-entropy bonus while pretraining, then the
//!   learnt r_hat, the mean of the ensemble's members;
//! - `decoupled`: `lambda_t r_task + r_hat`, lambda_t decaying linearly or exponentially.
//!
//! SAC forms the reward of each minibatch when it is drawn ([`TrainReward::minibatch`],
//! lambda at every gradient step); PPO forms the rollout's once ([`TrainReward::per_step`],
//! lambda fixed per rollout).

use std::sync::Arc;

use anyhow::Result;
use candle_core::{Device, Tensor};
use pbrl_common::Trajectory;
use serde::{Deserialize, Serialize};

use crate::pref::config::{PrefConfig, Schedule};
use crate::pref::entropy::StateEntropy;
use crate::pref::reward_model::RewardModel;
use crate::rl::replay::Batch;

/// The reward the policy is trained on.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "kebab-case")]
pub enum RewardSource {
    /// The ground truth r = r_R + r_H (a baseline).
    #[serde(alias = "true")]
    #[value(alias = "true")]
    Truth,
    /// The sketchy task reward r_task = -d alone (a baseline).
    Task,
    /// Learnt from preferences alone (PEBBLE, PrefPPO).
    Pref,
    /// lambda_t r_task + the learnt reward (Decoupled PEBBLE, Decoupled PrefPPO).
    Decoupled,
}

impl RewardSource {
    /// Learnt from a teacher's preferences.
    pub fn learnt(self) -> bool {
        matches!(self, RewardSource::Pref | RewardSource::Decoupled)
    }

    pub fn name(self) -> &'static str {
        match self {
            RewardSource::Truth => "truth",
            RewardSource::Task => "task",
            RewardSource::Pref => "pref",
            RewardSource::Decoupled => "decoupled",
        }
    }
}

/// lambda_t at `t` env steps of a run of `total` (0 past the end of the linear schedule).
pub fn lambda(schedule: Schedule, lambda0: f64, rho: f64, t: u64, total: u64) -> f64 {
    match schedule {
        Schedule::Linear => lambda0 * (total.saturating_sub(t)) as f64 / total.max(1) as f64,
        // NOTE: t, not the t/2 of the authors' SAC code (method.md section 5).
        Schedule::Exp => lambda0 * (1.0 - rho).powf(t as f64),
    }
}

/// The task guard (`--task-guard`): the task is never traded away for the learnt taste.
/// It keeps the success of the newest [`TaskGuard::WINDOW`] training episodes (food reached
/// the mouth: the task's own measure, not the person's taste) and the best such rate the
/// run has reached; while the rate is below `ratio` times the best, lambda_t is multiplied
/// by `1 + gain * shortfall` (shortfall in [0, 1], from 0 at `ratio * best` to 1 at no
/// success), so the task's weight grows and the learnt reward's share (r_hat / lambda_t
/// under `--sac-lambda-scale`) shrinks until the robot feeds as it did.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct TaskGuard {
    /// Success of the newest training episodes, oldest first.
    recent: std::collections::VecDeque<bool>,
    /// The best success rate over a full window so far.
    best: f64,
}

impl TaskGuard {
    /// Training episodes the rate is taken over.
    pub const WINDOW: usize = 100;
    /// Below this best rate the guard does not act (too few successes to tell a fall).
    pub const MIN_BEST: f64 = 0.1;

    /// A training episode ended.
    pub fn add(&mut self, success: bool) {
        if self.recent.len() == Self::WINDOW {
            self.recent.pop_front();
        }
        self.recent.push_back(success);
        if self.recent.len() == Self::WINDOW {
            self.best = self.best.max(self.rate());
        }
    }

    /// Success rate of the newest window (0 before any episode).
    pub fn rate(&self) -> f64 {
        let n = self.recent.len().max(1) as f64;
        self.recent.iter().filter(|s| **s).count() as f64 / n
    }

    /// The best full-window rate so far.
    pub fn best(&self) -> f64 {
        self.best
    }

    /// lambda_t's multiplier for `ratio` (0: off) and `gain`.
    pub fn multiplier(&self, ratio: f64, gain: f64) -> f64 {
        if ratio <= 0.0 || self.best < Self::MIN_BEST || self.recent.len() < Self::WINDOW {
            return 1.0;
        }
        let floor = ratio * self.best;
        let shortfall = ((floor - self.rate()) / floor).clamp(0.0, 1.0);
        1.0 + gain * shortfall
    }
}

/// The reward the policy trains on now.
pub struct TrainReward {
    pub source: RewardSource,
    pub schedule: Schedule,
    pub lambda0: f64,
    pub rho: f64,
    pub total_steps: u64,
    /// The newest trained ensemble (none until the first is trained: pretraining).
    pub model: Option<Arc<RewardModel>>,
    /// The state-entropy bonus of the pretraining (learnt rewards only).
    pub entropy: Option<StateEntropy>,
    /// Divide a SAC minibatch's decoupled reward by max(1, lambda_t)
    /// (`--sac-lambda-scale`).
    pub lambda_scale: bool,
    /// When trajectories' states join the entropy bonus's pool ([`TrainReward::observe`]).
    pub pool: Pool,
    /// States of the rollout being collected, for the pool once it is trained (PPO).
    rollout_states: Vec<f32>,
    /// The task guard's episodes (decoupled only).
    pub guard: TaskGuard,
    /// `--task-guard` and `--task-guard-gain` (a ratio of 0: off).
    pub guard_ratio: f64,
    pub guard_gain: f64,
}

/// When a trajectory's states join the entropy bonus's pool: the states the backbone
/// trains on are in it, the ones it has not seen yet are not.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Pool {
    /// At once: SAC's minibatches are drawn from its replay, which holds them already.
    AtOnce,
    /// After the rollout they belong to is trained on (PPO: a rollout's rewards are
    /// taken against the states of earlier rollouts).
    AfterRollout,
}

impl TrainReward {
    /// What `source` trains on with preference learning's settings `pref` over a run of
    /// `total_steps`: learnt rewards start on the entropy bonus over `obs_dim` observations.
    pub fn new(
        source: RewardSource,
        pref: &PrefConfig,
        total_steps: u64,
        obs_dim: usize,
        pool: Pool,
    ) -> Self {
        Self {
            source,
            schedule: pref.lambda_schedule,
            lambda0: pref.lambda0,
            rho: pref.rho,
            total_steps,
            model: None,
            entropy: source
                .learnt()
                .then(|| StateEntropy::new(obs_dim, pref.knn_k, pref.knn_pool)),
            lambda_scale: false,
            pool,
            rollout_states: Vec::new(),
            guard: TaskGuard::default(),
            guard_ratio: pref.task_guard,
            guard_gain: pref.task_guard_gain,
        }
    }

    /// A trajectory the backbone is about to train on: while pretraining, its states join
    /// the entropy bonus's pool (when, [`Pool`] says).
    pub fn observe(&mut self, t: &Trajectory) {
        if self.source == RewardSource::Decoupled {
            self.guard.add(t.outcome.success);
        }
        if self.model.is_some() {
            return;
        }
        let Some(e) = self.entropy.as_mut() else {
            return;
        };
        let states = &t.obs[..t.steps() * t.obs_dim as usize];
        match self.pool {
            Pool::AtOnce => e.add(states),
            Pool::AfterRollout => self.rollout_states.extend_from_slice(states),
        }
    }

    /// A trained ensemble: r_hat takes over from the entropy bonus (the first one ends the
    /// pretraining: returns true then).
    pub fn install(&mut self, model: Arc<RewardModel>) -> bool {
        let first = self.model.is_none();
        self.model = Some(model);
        if first {
            self.entropy = None;
            self.rollout_states.clear();
        }
        first
    }

    /// Pretraining on the state-entropy bonus: a learnt reward with no trained model yet.
    pub fn pretraining(&self) -> bool {
        self.source.learnt() && self.model.is_none()
    }

    /// The task reward's weight at `t` env steps (0 unless decoupled): the schedule's,
    /// times the task guard's multiplier once the learnt reward has taken over.
    pub fn lambda(&self, t: u64) -> f64 {
        match self.source {
            RewardSource::Decoupled => {
                let guard = if self.model.is_some() {
                    self.guard.multiplier(self.guard_ratio, self.guard_gain)
                } else {
                    1.0
                };
                lambda(self.schedule, self.lambda0, self.rho, t, self.total_steps) * guard
            }
            _ => 0.0,
        }
    }

    /// The learnt part for rows `obs` x `act` (`[n, 1]`): the state-entropy bonus while
    /// pretraining, r_hat after.
    fn learnt(&mut self, obs: &Tensor, act: &Tensor, features: Option<&Tensor>) -> Result<Tensor> {
        if let Some(model) = &self.model {
            return Ok(model.predict_tensor(obs, act, features)?);
        }
        let n = obs.dim(0)?;
        let entropy = self
            .entropy
            .as_mut()
            .ok_or_else(|| anyhow::anyhow!("a learnt reward without its entropy bonus"))?;
        let rows = obs.flatten_all()?.to_vec1::<f32>()?;
        // NOTE: a SAC minibatch is drawn from states already in the pool.
        let bonus = entropy.reward(&rows, true);
        Ok(Tensor::from_vec(bonus, (n, 1), &Device::Cpu)?)
    }

    /// The reward of a SAC minibatch at `t` env steps (`[n, 1]`).
    pub fn minibatch(&mut self, b: &Batch, t: u64) -> Result<Tensor> {
        Ok(match self.source {
            RewardSource::Truth => b.truth.clone(),
            RewardSource::Task => b.task.clone(),
            RewardSource::Pref => self.learnt(&b.obs, &b.act, b.features.as_ref())?,
            RewardSource::Decoupled => {
                let l = self.lambda(t);
                let learnt = self.learnt(&b.obs, &b.act, b.features.as_ref())?;
                if self.pretraining() {
                    learnt
                } else if self.lambda_scale && l > 1.0 {
                    (&b.task + (learnt / l)?)?
                } else {
                    ((&b.task * l)? + learnt)?
                }
            }
        })
    }

    /// Per-step rewards of a PPO rollout at `t` env steps (lambda fixed for the rollout).
    pub fn per_step(&mut self, rollout: &[Trajectory], t: u64) -> Result<Vec<Vec<f32>>> {
        let l = self.lambda(t);
        let mut out = Vec::with_capacity(rollout.len());
        for tr in rollout {
            let task: Vec<f32> = tr.rewards.iter().map(|r| r.task).collect();
            let r = match self.source {
                RewardSource::Truth => tr.rewards.iter().map(|r| r.truth).collect(),
                RewardSource::Task => task,
                RewardSource::Pref | RewardSource::Decoupled => {
                    let (n, o, a) = (tr.steps(), tr.obs_dim as usize, tr.act_dim as usize);
                    let rows = &tr.obs[..n * o];
                    let pretraining = self.pretraining();
                    let learnt = if pretraining {
                        let e = self
                            .entropy
                            .as_mut()
                            .ok_or_else(|| anyhow::anyhow!("no entropy bonus"))?;
                        // NOTE: PPO's rollout states are added to the pool after this.
                        e.reward(rows, false)
                    } else {
                        let obs = Tensor::from_slice(rows, (n, o), &Device::Cpu)?;
                        let act = Tensor::from_slice(&tr.actions, (n, a), &Device::Cpu)?;
                        let features = Tensor::from_vec(
                            tr.features(),
                            (n, pbrl_common::trajectory::FEATURES),
                            &Device::Cpu,
                        )?;
                        self.learnt(&obs, &act, Some(&features))?
                            .flatten_all()?
                            .to_vec1::<f32>()?
                    };
                    if self.source == RewardSource::Decoupled && !pretraining {
                        learnt
                            .iter()
                            .zip(&task)
                            .map(|(h, t)| (l as f32) * t + h)
                            .collect()
                    } else {
                        learnt
                    }
                }
            };
            out.push(r);
        }
        // NOTE: the rollout's states join the pool only now, after its rewards are taken.
        let states = std::mem::take(&mut self.rollout_states);
        if let Some(e) = self.entropy.as_mut().filter(|_| self.model.is_none()) {
            e.add(&states);
        }
        Ok(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn schedules_at_the_start_the_middle_and_the_end() {
        // Reference: linear: 15 * (T - t) / T at t = 0, T/2, T -> 15, 7.5, 0.
        //            exp: 10 * (1 - 1e-5)^t at t = 0, 5e5, 1e6 -> 10, 10 * e^(5e5 ln(1 - 1e-5))
        //            = 10 * 0.0067379 = 0.067379..., 10 * 4.5399e-5 = 4.5399e-4.
        let t = 1_000_000;
        assert_eq!(lambda(Schedule::Linear, 15.0, 0.0, 0, t), 15.0);
        assert_eq!(lambda(Schedule::Linear, 15.0, 0.0, t / 2, t), 7.5);
        assert_eq!(lambda(Schedule::Linear, 15.0, 0.0, t, t), 0.0);
        assert_eq!(lambda(Schedule::Linear, 15.0, 0.0, t + 5, t), 0.0);
        assert_eq!(lambda(Schedule::Exp, 10.0, 1e-5, 0, t), 10.0);
        let mid = lambda(Schedule::Exp, 10.0, 1e-5, t / 2, t);
        assert!((mid - 0.067_379).abs() < 1e-5, "{mid}");
        let end = lambda(Schedule::Exp, 10.0, 1e-5, t, t);
        assert!((end - 4.5399e-4).abs() < 1e-7, "{end}");
    }

    #[test]
    fn the_lambda_scale_keeps_the_task_part_and_shrinks_r_hat() {
        use crate::pref::reward_model::RewardModelConfig;
        let model = RewardModel::new(RewardModelConfig::plain(), 2, 1).unwrap();
        let dev = &Device::Cpu;
        let obs = Tensor::new(&[[0.1f32, -0.2], [0.3, 0.4]], dev).unwrap();
        let act = Tensor::new(&[[0.5f32], [-0.5]], dev).unwrap();
        let task = Tensor::new(&[[-0.3f32], [-0.1]], dev).unwrap();
        let b = Batch {
            obs: obs.clone(),
            act: act.clone(),
            task: task.clone(),
            truth: task.clone(),
            next_obs: obs.clone(),
            done: task.zeros_like().unwrap(),
            features: None,
        };
        let r_hat: Vec<f32> = model
            .predict_tensor(&obs, &act, None)
            .unwrap()
            .flatten_all()
            .unwrap()
            .to_vec1()
            .unwrap();
        let mut reward = TrainReward {
            source: RewardSource::Decoupled,
            schedule: Schedule::Linear,
            lambda0: 10.0,
            rho: 0.0,
            total_steps: 100,
            model: Some(Arc::new(model)),
            entropy: None,
            lambda_scale: false,
            pool: Pool::AtOnce,
            rollout_states: Vec::new(),
            guard: TaskGuard::default(),
            guard_ratio: 0.0,
            guard_gain: 0.0,
        };
        let rows = |r: &mut TrainReward, t| -> Vec<f32> {
            r.minibatch(&b, t)
                .unwrap()
                .flatten_all()
                .unwrap()
                .to_vec1()
                .unwrap()
        };
        let close = |a: &[f32], b: &[f32]| a.iter().zip(b).all(|(x, y)| (x - y).abs() < 1e-6);
        let task = [-0.3f32, -0.1];
        // t = 50: lambda 5. Plain: 5 r_task + r_hat; scaled: r_task + r_hat / 5.
        let plain = rows(&mut reward, 50);
        assert!(
            close(
                &plain,
                &[5.0 * task[0] + r_hat[0], 5.0 * task[1] + r_hat[1]]
            ),
            "{plain:?}"
        );
        reward.lambda_scale = true;
        let scaled = rows(&mut reward, 50);
        assert!(
            close(
                &scaled,
                &[task[0] + r_hat[0] / 5.0, task[1] + r_hat[1] / 5.0]
            ),
            "{scaled:?}"
        );
        // t = 95: lambda 0.5 < 1, nothing to divide: 0.5 r_task + r_hat either way.
        let late = rows(&mut reward, 95);
        assert!(
            close(&late, &[0.5 * task[0] + r_hat[0], 0.5 * task[1] + r_hat[1]]),
            "{late:?}"
        );
    }

    #[test]
    fn the_task_guard_raises_lambda_only_while_success_is_below_its_best() {
        let mut g = TaskGuard::default();
        // Not a full window yet: no best, no action.
        for _ in 0..99 {
            g.add(true);
        }
        assert_eq!(g.multiplier(0.9, 9.0), 1.0);
        g.add(true);
        assert_eq!(g.best(), 1.0);
        assert_eq!(g.multiplier(0.9, 9.0), 1.0, "at its best");
        // 60 failures: rate 0.4 against a floor of 0.9: shortfall (0.9 - 0.4) / 0.9.
        for _ in 0..60 {
            g.add(false);
        }
        assert!((g.rate() - 0.4).abs() < 1e-12);
        assert_eq!(g.best(), 1.0, "the best stays");
        let m = g.multiplier(0.9, 9.0);
        assert!((m - (1.0 + 9.0 * 0.5 / 0.9)).abs() < 1e-9, "{m}");
        assert_eq!(g.multiplier(0.0, 9.0), 1.0, "off");
        // Back to feeding: the multiplier goes back to 1.
        for _ in 0..100 {
            g.add(true);
        }
        assert_eq!(g.multiplier(0.9, 9.0), 1.0);
        // A run that never fed: the guard has nothing to keep.
        let mut never = TaskGuard::default();
        for i in 0..200 {
            never.add(i % 20 == 0);
        }
        assert_eq!(never.multiplier(0.9, 9.0), 1.0);
    }

    #[test]
    fn the_guard_scales_lambda_once_the_learnt_reward_took_over() {
        use crate::pref::reward_model::RewardModelConfig;
        let pref = PrefConfig {
            task_guard: 0.9,
            task_guard_gain: 4.0,
            lambda_schedule: Schedule::Linear,
            lambda0: 10.0,
            ..PrefConfig::default()
        };
        let mut r = TrainReward::new(RewardSource::Decoupled, &pref, 100, 2, Pool::AtOnce);
        let ep = |success| {
            let mut t = Trajectory::default();
            t.outcome.success = success;
            t
        };
        for _ in 0..100 {
            r.observe(&ep(true));
        }
        for _ in 0..100 {
            r.observe(&ep(false));
        }
        // Pretraining: the schedule's lambda alone.
        assert_eq!(r.lambda(50), 5.0);
        let model = RewardModel::new(RewardModelConfig::plain(), 2, 1).unwrap();
        r.install(Arc::new(model));
        // No success against a best of 1: shortfall 1, lambda 5 * (1 + 4).
        assert_eq!(r.lambda(50), 25.0);
        // Not for the other rewards.
        let task = TrainReward::new(RewardSource::Task, &pref, 100, 2, Pool::AtOnce);
        assert_eq!(task.lambda(50), 0.0);
    }
}
