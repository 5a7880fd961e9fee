//! Soft actor-critic (Haarnoja et al. 2018) with twin Q critics and a learned entropy
//! temperature, as PEBBLE uses it (`shared/method.md` section 6).
//!
//! The learner feeds it whole trajectories ([`Sac::observe`]); the update-to-data ratio is
//! enforced here ([`Sac::updates_due`]): one gradient step per `update_every` env steps,
//! however many actors there are and however fast they run.

use candle_core::backprop::GradStore;
use candle_core::{DType, Device, Result, Tensor, Var};
use candle_nn::VarMap;
use pbrl_common::nets::{export, GaussianPolicy, Owned, PolicyTape, TwinQ};
use pbrl_common::par::Par;
use pbrl_common::Trajectory;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;
use serde::{Deserialize, Serialize};

use crate::optim::{Adam, AdamState};
use crate::rl::replay::{Batch, Replay};
use crate::state::RngState;

/// SAC's settings (defaults from `shared/method.md`, at the 256x256 size of SB3 and
/// CleanRL; the authors' 512x512 / batch 512 is the `paper` preset). Each is a flag of
/// `pbrl train` (`--sac-...`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, clap::Args)]
pub struct SacConfig {
    /// SAC: hidden layer sizes of the actor and of each critic.
    #[arg(id = "sac_hidden", long = "sac-hidden", value_delimiter = ',', default_values_t = [256, 256])]
    pub hidden: Vec<usize>,
    /// SAC: minibatch size of a gradient step.
    #[arg(id = "sac_batch", long = "sac-batch", default_value_t = 256)]
    pub batch: usize,
    /// SAC: discount.
    #[arg(id = "sac_gamma", long = "sac-gamma", default_value_t = 0.99)]
    pub gamma: f64,
    /// SAC: Polyak rate of the target critics.
    #[arg(id = "sac_tau", long = "sac-tau", default_value_t = 0.005)]
    pub tau: f64,
    /// SAC: Adam learning rate of actor, critics and temperature.
    #[arg(id = "sac_lr", long = "sac-lr", default_value_t = 3e-4)]
    pub lr: f64,
    /// SAC: initial entropy temperature.
    #[arg(id = "sac_init_alpha", long = "sac-init-alpha", default_value_t = 0.1)]
    pub init_alpha: f64,
    /// SAC: target entropy (default: minus the action dimension).
    #[arg(id = "sac_target_entropy", long = "sac-target-entropy")]
    pub target_entropy: Option<f64>,
    /// SAC: replay buffer capacity (transitions).
    #[arg(
        id = "sac_replay_capacity",
        long = "sac-replay-capacity",
        default_value_t = 1_000_000
    )]
    pub replay_capacity: usize,
    /// SAC: env steps of uniformly random actions before learning starts.
    #[arg(
        id = "sac_random_steps",
        long = "sac-random-steps",
        default_value_t = 600
    )]
    pub random_steps: u64,
    /// SAC: one gradient step per this many env steps (the update-to-data ratio's inverse).
    #[arg(
        id = "sac_update_every",
        long = "sac-update-every",
        default_value_t = 10
    )]
    pub update_every: u64,
    /// SAC: the reward trained on is multiplied by this (the SAC paper's reward scale):
    /// the critics' targets keep the size their learning rate suits when the reward is
    /// large. Decoupled PEBBLE's default is 1 / lambda_0 (its lambda_t r_task is lambda_0
    /// times the task baseline's reward), 1 elsewhere and in `--preset paper`.
    #[arg(
        id = "sac_reward_scale",
        long = "sac-reward-scale",
        default_value_t = 1.0
    )]
    #[serde(default = "one")]
    pub reward_scale: f64,
    /// SAC, decoupled reward: also divide the reward by max(1, lambda_t) at each
    /// gradient step, so that its task part keeps the task baseline's size while
    /// lambda_t decays and r_hat's share grows as the schedule says (the fixed
    /// 1 / lambda_0 scale shrinks the whole reward with lambda_t instead).
    #[arg(id = "sac_lambda_scale", long = "sac-lambda-scale")]
    #[serde(default)]
    pub lambda_scale: bool,
    /// SAC, while labels are still asked: this share of each minibatch comes from the
    /// newest `--sac-hybrid-steps` transitions, the rest from the whole buffer (QPA's
    /// hybrid experience replay: the policy improves where the queries are asked; 0: off).
    #[arg(
        id = "sac_hybrid_share",
        long = "sac-hybrid-share",
        default_value_t = 0.5
    )]
    #[serde(default)]
    pub hybrid_share: f64,
    /// SAC: the newest transitions the hybrid share draws from (QPA: the last 10
    /// episodes, 2,000 feeding steps).
    #[arg(
        id = "sac_hybrid_steps",
        long = "sac-hybrid-steps",
        default_value_t = 2_000
    )]
    #[serde(default = "hybrid_steps")]
    pub hybrid_steps: usize,
    /// Seed of initialisation, minibatches and sampling noise (the run's `--seed`).
    #[arg(skip)]
    pub seed: u64,
}

fn one() -> f64 {
    1.0
}

fn hybrid_steps() -> usize {
    2_000
}

impl Default for SacConfig {
    /// Every field at its flag's default.
    fn default() -> Self {
        pbrl_common::flags::defaults()
    }
}

/// The soft Bellman target y = r + gamma (1 - done) (min(Q1', Q2') - alpha log pi(a'|s')).
pub fn soft_q_target(
    reward: &Tensor,
    done: &Tensor,
    q1_next: &Tensor,
    q2_next: &Tensor,
    logp_next: &Tensor,
    alpha: f64,
    gamma: f64,
) -> Result<Tensor> {
    let soft = (q1_next.minimum(q2_next)? - (logp_next * alpha)?)?;
    // NOTE: `done` is termination only; a time limit (truncation) still bootstraps.
    let not_done = done.affine(-1.0, 1.0)?;
    reward + ((not_done * soft)? * gamma)?
}

/// The temperature loss -mean(log_alpha (log pi + target_entropy)), the log-probabilities
/// taken as constants.
pub fn temperature_loss(log_alpha: &Tensor, logp: &Tensor, target_entropy: f64) -> Result<Tensor> {
    let gap = (logp.detach() + target_entropy)?;
    (gap.broadcast_mul(log_alpha)?.mean_all()?).neg()
}

/// Losses of one gradient step.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct SacLosses {
    pub critic: f32,
    pub actor: f32,
    pub alpha_loss: f32,
    pub alpha: f32,
    pub entropy: f32,
}

/// The SAC learner state.
pub struct Sac {
    pub cfg: SacConfig,
    act_dim: usize,
    pub policy: Owned<GaussianPolicy>,
    critic: Owned<TwinQ>,
    target: Owned<TwinQ>,
    log_alpha: Var,
    pi_opt: Adam,
    q_opt: Adam,
    alpha_opt: Adam,
    replay: Replay,
    rng: ChaCha8Rng,
    /// Where the step's pairs of independent work run.
    par: Par,
    /// Env steps observed.
    pub env_steps: u64,
    /// Gradient steps taken.
    pub updates: u64,
    /// Labels are still asked: minibatches take their hybrid share (`hybrid_share`).
    pub hybrid: bool,
}

/// SAC's state beside its networks and replay buffer.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SacState {
    pub pi_opt: AdamState,
    pub q_opt: AdamState,
    pub alpha_opt: AdamState,
    pub log_alpha: f32,
    pub rng: RngState,
    pub env_steps: u64,
    pub updates: u64,
}

/// Polyak: `target <- tau * critic + (1 - tau) * target`.
fn polyak(critic: &VarMap, target: &VarMap, tau: f64) -> Result<()> {
    let poisoned = || candle_core::Error::Msg("poisoned".into());
    let src = critic.data().lock().map_err(|_| poisoned())?;
    let dst = target.data().lock().map_err(|_| poisoned())?;
    let flat = |t: &Var| t.flatten_all()?.to_vec1::<f32>();
    let (a, b) = (tau as f32, (1.0 - tau) as f32);
    for (name, t) in dst.iter() {
        let (s, mut d) = (flat(&src[name])?, flat(t)?);
        for (d, s) in d.iter_mut().zip(&s) {
            *d = a * s + b * *d;
        }
        t.set(&Tensor::from_vec(d, t.shape(), t.device())?)?;
    }
    Ok(())
}

fn copy_vars(from: &VarMap, to: &VarMap) -> Result<()> {
    pbrl_common::nets::import(to, &export(from)?)
}

impl Sac {
    /// The replay's transitions: the first one it still holds and the number pushed.
    pub fn replay_span(&self) -> (u64, u64) {
        (
            self.replay.total - self.replay.len() as u64,
            self.replay.total,
        )
    }

    /// Rows of the replay's transitions `from..to` ([`Replay::rows`]).
    pub fn replay_rows(&self, from: u64, to: u64) -> Vec<f32> {
        self.replay.rows(from, to)
    }

    /// Keep each transition's comfort features in the replay (a reward model that reads
    /// them relabels the minibatches); before the first trajectory and any restore.
    pub fn keep_features(&mut self) {
        self.replay.keep_features(pbrl_common::trajectory::FEATURES);
    }

    /// Refill the empty replay from rows of transitions `from..` ([`Replay::restore`]).
    pub fn restore_replay(&mut self, from: u64, rows: &[f32]) -> Result<()> {
        self.replay.restore(from, rows)
    }

    pub fn new(cfg: SacConfig, obs_dim: usize, act_dim: usize) -> Result<Self> {
        let mut rng = ChaCha8Rng::seed_from_u64(cfg.seed);
        let h = cfg.hidden.clone();
        let policy = Owned::build(&mut rng, |vb| GaussianPolicy::new(vb, obs_dim, &h, act_dim))?;
        let critic = Owned::build(&mut rng, |vb| TwinQ::new(vb, obs_dim, act_dim, &h))?;
        let target = Owned::build(&mut rng, |vb| TwinQ::new(vb, obs_dim, act_dim, &h))?;
        copy_vars(&critic.varmap, &target.varmap)?;
        let log_alpha = Var::from_slice(&[cfg.init_alpha.ln() as f32], 1, &Device::Cpu)?;
        let pi_opt = Adam::for_varmap(&policy.varmap, cfg.lr)?;
        let q_opt = Adam::for_varmap(&critic.varmap, cfg.lr)?;
        let alpha_opt = Adam::new(vec![("log_alpha".into(), log_alpha.clone())], cfg.lr)?;
        let replay = Replay::new(obs_dim, act_dim, cfg.replay_capacity);
        Ok(Self {
            cfg,
            act_dim,
            policy,
            critic,
            target,
            log_alpha,
            pi_opt,
            q_opt,
            alpha_opt,
            replay,
            rng,
            par: Par::default(),
            env_steps: 0,
            updates: 0,
            hybrid: false,
        })
    }

    /// Run the step's pairs of independent work on `threads` threads (1 or 2; the default
    /// is 1). The step's results do not change.
    pub fn set_threads(&mut self, threads: usize) -> Result<()> {
        self.par = Par::new(threads).map_err(candle_core::Error::wrap)?;
        Ok(())
    }

    /// Threads the step runs on.
    pub fn threads(&self) -> usize {
        self.par.threads()
    }

    /// The networks by name (for checkpoints).
    pub fn networks(&self) -> [(&'static str, &VarMap); 3] {
        [
            ("policy", &self.policy.varmap),
            ("critic", &self.critic.varmap),
            ("target_critic", &self.target.varmap),
        ]
    }

    /// Optimisers, temperature, generator and counters (for checkpoints).
    pub fn state(&self) -> Result<SacState> {
        Ok(SacState {
            pi_opt: self.pi_opt.state()?,
            q_opt: self.q_opt.state()?,
            alpha_opt: self.alpha_opt.state()?,
            log_alpha: self.log_alpha.as_tensor().to_vec1::<f32>()?[0],
            rng: RngState::of(&self.rng),
            env_steps: self.env_steps,
            updates: self.updates,
        })
    }

    /// Continue from `s` (the networks and replay buffer are restored apart).
    pub fn restore(&mut self, s: &SacState) -> Result<()> {
        self.pi_opt.restore(&s.pi_opt)?;
        self.q_opt.restore(&s.q_opt)?;
        self.alpha_opt.restore(&s.alpha_opt)?;
        self.log_alpha
            .set(&Tensor::from_slice(&[s.log_alpha], 1, &Device::Cpu)?)?;
        self.rng = s.rng.restore();
        self.env_steps = s.env_steps;
        self.updates = s.updates;
        Ok(())
    }

    pub fn alpha(&self) -> Result<f64> {
        Ok(self.log_alpha.as_tensor().exp()?.to_vec1::<f32>()?[0] as f64)
    }

    /// Store every transition of `t` with its task reward and ground truth (the reward
    /// trained on is formed when a minibatch is drawn).
    pub fn observe(&mut self, t: &Trajectory) {
        let last = t.steps().saturating_sub(1);
        for k in 0..t.steps() {
            let done = k == last && t.outcome.terminated;
            let r = &t.rewards[k];
            self.replay.push(
                t.obs_at(k),
                t.action_at(k),
                [r.task, r.truth],
                t.obs_at(k + 1),
                done,
                &r.features(),
            );
        }
        self.env_steps += t.steps() as u64;
    }

    /// New critics, target critics and critic optimiser (PEBBLE, after the unsupervised
    /// pretraining: the values learnt for the entropy bonus mean nothing for r_hat).
    pub fn reset_critics(&mut self) -> Result<()> {
        let (obs_dim, h) = (self.replay.obs_dim, self.cfg.hidden.clone());
        let act_dim = self.act_dim;
        self.critic = Owned::build(&mut self.rng, |vb| TwinQ::new(vb, obs_dim, act_dim, &h))?;
        self.target = Owned::build(&mut self.rng, |vb| TwinQ::new(vb, obs_dim, act_dim, &h))?;
        copy_vars(&self.critic.varmap, &self.target.varmap)?;
        self.q_opt = Adam::for_varmap(&self.critic.varmap, self.cfg.lr)?;
        Ok(())
    }

    /// Gradient steps owed: one per `update_every` env steps once the random steps are
    /// done, less those taken.
    pub fn updates_due(&self) -> u64 {
        if self.env_steps < self.cfg.random_steps.max(self.cfg.batch as u64) {
            return 0;
        }
        (self.env_steps / self.cfg.update_every.max(1)).saturating_sub(self.updates)
    }

    fn noise(&mut self, n: usize) -> Result<Tensor> {
        Tensor::from_vec(self.noise_vec(n), (n, self.act_dim), &Device::Cpu)
    }

    /// `n` rows of standard normal noise from the learner's generator.
    fn noise_vec(&mut self, n: usize) -> Vec<f32> {
        (0..n * self.act_dim)
            .map(|_| self.rng.sample(StandardNormal))
            .collect()
    }

    /// The critics' loss `mean((q1 - y)^2) + mean((q2 - y)^2)` and its gradients (by hand:
    /// see `nets::Mlp::backward`).
    fn critic_gradients(
        &self,
        obs: &Tensor,
        act: &Tensor,
        y: &Tensor,
    ) -> Result<(Tensor, GradStore)> {
        let ((q1, q2), tapes) = self.critic.net.forward_taped(obs, act, &self.par)?;
        let (e1, e2) = ((q1 - y)?, (q2 - y)?);
        let loss = (e1.sqr()?.mean_all()? + e2.sqr()?.mean_all()?)?;
        let scale = 2.0 / e1.dim(0)? as f64;
        let mut grads = GradStore::default();
        self.critic.net.backward(
            &tapes,
            [&(e1 * scale)?, &(e2 * scale)?],
            Some(&mut grads),
            false,
            &self.par,
        )?;
        Ok((loss, grads))
    }

    /// The actor's loss `mean(alpha log pi(a|s) - min(q1, q2)(s, a))` for the policy's
    /// sample `a` (with its log-probabilities), and that loss's gradient with respect to `a`
    /// (by hand; the critics only pass it on).
    fn actor_loss(
        &self,
        obs: &Tensor,
        a: &Tensor,
        logp: &Tensor,
        alpha: f64,
    ) -> Result<(Tensor, Tensor)> {
        let ((q1, q2), tapes) = self.critic.net.forward_taped(obs, a, &self.par)?;
        let loss = ((logp * alpha)? - q1.minimum(&q2)?)?.mean_all()?;
        // d/dq of -mean(min(q1, q2)): to the smaller one, halved on a tie (as candle).
        let n = q1.dim(0)? as f64;
        let (lt, tie) = (
            q1.lt(&q2)?.to_dtype(DType::F32)?,
            q1.eq(&q2)?.to_dtype(DType::F32)?,
        );
        let to_q1 = (lt + (tie * 0.5)?)?;
        let dq1 = (&to_q1 * (-1.0 / n))?;
        let dq2 = (to_q1.affine(-1.0, 1.0)? * (-1.0 / n))?;
        let da = self
            .critic
            .net
            .backward(&tapes, [&dq1, &dq2], None, true, &self.par)?
            .ok_or_else(|| candle_core::Error::Msg("no action gradient".into()))?;
        Ok((loss, da))
    }

    /// The policy's gradients of the actor's loss, from the sample's tape and the loss's
    /// gradient `da` with respect to the sampled action.
    fn policy_gradients(&self, tape: &PolicyTape, da: &Tensor, alpha: f64) -> Result<GradStore> {
        let mut grads = GradStore::default();
        let dlogp = alpha / da.dim(0)? as f64;
        self.policy
            .net
            .backward_sample(tape, da, dlogp, &mut grads, &self.par)?;
        Ok(grads)
    }

    /// One gradient step on critics, actor and temperature, then the target update.
    /// `reward` forms the reward of the drawn minibatch (`[n, 1]`) from what its rows hold.
    ///
    /// With two threads ([`Sac::set_threads`]) the pairs of independent work run side by
    /// side: the policy on the next states and on the states, the two critics (forward and
    /// backward), and the target update beside the policy's backward pass. Every piece sees
    /// the same inputs as in one thread, so the step is the same to the bit.
    pub fn update(&mut self, reward: impl FnOnce(&Batch) -> Result<Tensor>) -> Result<SacLosses> {
        let n = self.cfg.batch;
        let recent = if self.hybrid && self.cfg.hybrid_share > 0.0 {
            (
                (self.cfg.hybrid_share.min(1.0) * n as f64).round() as usize,
                self.cfg.hybrid_steps,
            )
        } else {
            (0, 0)
        };
        let batch = self.replay.sample(&mut self.rng, n, recent)?;
        let rew = reward(&batch)?;
        let rew = if self.cfg.reward_scale == 1.0 {
            rew
        } else {
            (rew * self.cfg.reward_scale)?
        };
        let Batch {
            obs,
            act,
            next_obs,
            done,
            ..
        } = batch;
        let alpha = self.alpha()?;
        // The noise of the targets' actions, then of the actor's.
        let (eps_next, eps) = (self.noise(n)?, self.noise(n)?);

        // The policy on both minibatches: it changes only after the critics, so the actor's
        // sample is drawn now.
        let (policy, obs_a) = (self.policy.net.clone(), obs.clone());
        let (next, sample) = self.par.join(
            || self.policy.net.sample(&next_obs, &eps_next),
            move || policy.sample_taped(&obs_a, &eps),
        );
        let ((a_next, logp_next), (a, logp, tape)) = (next?, sample?);

        // Targets, without gradients.
        let (q1n, q2n) = self.target.net.forward(&next_obs, &a_next, &self.par)?;
        let y = soft_q_target(&rew, &done, &q1n, &q2n, &logp_next, alpha, self.cfg.gamma)?.detach();

        // Critics, then the actor through the updated critics.
        let (critic_loss, grads) = self.critic_gradients(&obs, &act, &y)?;
        self.q_opt.step(&grads)?;
        let (actor_loss, da) = self.actor_loss(&obs, &a, &logp, alpha)?;
        // The policy's gradients beside the target update (they share nothing).
        let (critic, target, tau) = (
            self.critic.varmap.clone(),
            self.target.varmap.clone(),
            self.cfg.tau,
        );
        let (grads, polyak) = self.par.join(
            || self.policy_gradients(&tape, &da, alpha),
            move || polyak(&critic, &target, tau),
        );
        self.pi_opt.step(&grads?)?;
        polyak?;

        // Temperature.
        let target_entropy = self.cfg.target_entropy.unwrap_or(-(self.act_dim as f64));
        let alpha_loss = temperature_loss(self.log_alpha.as_tensor(), &logp, target_entropy)?;
        self.alpha_opt.step(&alpha_loss.backward()?)?;

        self.updates += 1;
        let scalar = |t: &Tensor| -> Result<f32> { t.to_dtype(DType::F32)?.to_scalar::<f32>() };
        Ok(SacLosses {
            critic: scalar(&critic_loss)?,
            actor: scalar(&actor_loss)?,
            alpha_loss: scalar(&alpha_loss)?,
            alpha: alpha as f32,
            entropy: -scalar(&logp.mean_all()?)?,
        })
    }

    /// The deterministic action for one observation.
    pub fn act_deterministic(&self, obs: &[f32]) -> Result<Vec<f32>> {
        self.policy.net.act_one(obs.to_vec(), None)
    }

    /// A sampled action for one observation.
    pub fn act_stochastic(&mut self, obs: &[f32]) -> Result<Vec<f32>> {
        let eps = self.noise_vec(1);
        self.policy.net.act_one(obs.to_vec(), Some(eps))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testutil::{assert_same_gradients, uniform_tensors};

    fn col(v: &[f32]) -> Tensor {
        Tensor::from_slice(v, (v.len(), 1), &Device::Cpu).unwrap()
    }

    #[test]
    fn soft_target_matches_the_reference() {
        // Reference (Python):
        //   r, d, q1, q2, lp = [1.0, -0.5], [0.0, 1.0], [2.0, 3.0], [1.5, 4.0], [-1.0, 0.5]
        //   alpha, gamma = 0.2, 0.99
        //   [ri + gamma * (1 - di) * (min(a, b) - alpha * l)
        //    for ri, di, a, b, l in zip(r, d, q1, q2, lp)]   # [2.683, -0.5]
        let y = soft_q_target(
            &col(&[1.0, -0.5]),
            &col(&[0.0, 1.0]),
            &col(&[2.0, 3.0]),
            &col(&[1.5, 4.0]),
            &col(&[-1.0, 0.5]),
            0.2,
            0.99,
        )
        .unwrap();
        let y = y.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        assert!(
            (y[0] - 2.683).abs() < 1e-5 && (y[1] + 0.5).abs() < 1e-6,
            "{y:?}"
        );
    }

    #[test]
    fn temperature_loss_and_its_gradient_match_the_reference() {
        // Reference (Python): log_alpha = -1.0, logp = [-3.0, -5.0], target = -2.0
        //   loss = -mean(log_alpha * (lp + target)) = -(-1) * mean([-5, -7]) = -6.0
        //   d loss / d log_alpha = -mean([-5, -7]) = 6.0  (alpha grows when entropy is low)
        let la = Var::from_slice(&[-1.0f32], 1, &Device::Cpu).unwrap();
        let loss = temperature_loss(la.as_tensor(), &col(&[-3.0, -5.0]), -2.0).unwrap();
        assert!((loss.to_scalar::<f32>().unwrap() + 6.0).abs() < 1e-6);
        let g = loss.backward().unwrap();
        let g = g.get(&la).unwrap().to_vec1::<f32>().unwrap();
        assert!((g[0] - 6.0).abs() < 1e-6, "{g:?}");
    }

    #[test]
    fn updates_follow_the_update_to_data_ratio() {
        let cfg = SacConfig {
            hidden: vec![8],
            batch: 4,
            random_steps: 20,
            update_every: 10,
            ..SacConfig::default()
        };
        let mut sac = Sac::new(cfg, 2, 1).unwrap();
        let t = Trajectory {
            format: pbrl_common::trajectory::TRAJECTORY_FORMAT,
            obs_dim: 2,
            act_dim: 1,
            obs: vec![0.1; 2 * 11],
            actions: vec![0.5; 10],
            rewards: vec![pbrl_common::StepRewards::default(); 10],
            ..Trajectory::default()
        };
        sac.observe(&t);
        assert_eq!(sac.updates_due(), 0, "still in the random steps");
        sac.observe(&t);
        sac.observe(&t);
        assert_eq!(sac.env_steps, 30);
        assert_eq!(sac.updates_due(), 3);
        sac.update(|b| Ok(b.truth.clone())).unwrap();
        assert_eq!(sac.updates_due(), 2);
    }

    #[test]
    fn two_threads_take_the_same_steps_to_the_bit() {
        let cfg = SacConfig {
            hidden: vec![32, 24],
            batch: 64,
            random_steps: 0,
            update_every: 1,
            seed: 5,
            ..SacConfig::default()
        };
        let flat = |t: &Tensor| t.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        let mut t = uniform_tensors(4);
        let (obs, actions) = (flat(&t(201, 5, 2.0)), flat(&t(200, 2, 0.99)));
        let truth = flat(&t(200, 1, 1.0));
        let traj = Trajectory {
            format: pbrl_common::trajectory::TRAJECTORY_FORMAT,
            obs_dim: 5,
            act_dim: 2,
            obs,
            actions,
            rewards: truth
                .iter()
                .map(|&r| pbrl_common::StepRewards {
                    truth: r,
                    ..Default::default()
                })
                .collect(),
            ..Trajectory::default()
        };
        let weights = |threads: usize| {
            let mut sac = Sac::new(cfg.clone(), 5, 2).unwrap();
            sac.set_threads(threads).unwrap();
            assert_eq!(sac.threads(), threads);
            sac.observe(&traj);
            let losses: Vec<SacLosses> = (0..20)
                .map(|_| sac.update(|b| Ok(b.truth.clone())).unwrap())
                .collect();
            let nets: Vec<Vec<(String, Vec<f32>)>> = sac
                .networks()
                .iter()
                .map(|(_, vm)| {
                    pbrl_common::nets::named_vars(vm)
                        .unwrap()
                        .into_iter()
                        .map(|(n, v)| (n, flat(v.as_tensor())))
                        .collect()
                })
                .collect();
            (losses, nets, sac.alpha().unwrap())
        };
        let (one, two) = (weights(1), weights(2));
        assert_eq!(one.0, two.0, "the losses of every step");
        assert_eq!(one.1, two.1, "policy, critics and targets");
        assert_eq!(one.2, two.2, "the temperature");
    }

    #[test]
    fn hand_gradients_of_both_losses_are_candle_autodiffs() {
        let cfg = SacConfig {
            hidden: vec![16, 12],
            batch: 32,
            seed: 3,
            ..SacConfig::default()
        };
        let sac = Sac::new(cfg, 5, 2).unwrap();
        let mut t = uniform_tensors(9);
        let (obs, act, y, eps) = (t(32, 5, 2.0), t(32, 2, 0.99), t(32, 1, 3.0), t(32, 2, 1.5));

        let (loss, got) = sac.critic_gradients(&obs, &act, &y).unwrap();
        let (q1, q2) = sac.critic.net.forward(&obs, &act, &sac.par).unwrap();
        let want = ((q1 - &y).unwrap().sqr().unwrap().mean_all().unwrap()
            + (q2 - &y).unwrap().sqr().unwrap().mean_all().unwrap())
        .unwrap();
        assert_eq!(
            loss.to_scalar::<f32>().unwrap(),
            want.to_scalar::<f32>().unwrap()
        );
        assert_same_gradients(&sac.q_opt.vars, &got, &want.backward().unwrap());

        // A temperature that weighs the log-probability as much as the critics do.
        let alpha = 0.7;
        let (a, logp, tape) = sac.policy.net.sample_taped(&obs, &eps).unwrap();
        let (loss, da) = sac.actor_loss(&obs, &a, &logp, alpha).unwrap();
        let got = sac.policy_gradients(&tape, &da, alpha).unwrap();
        let (a, want_logp) = sac.policy.net.sample(&obs, &eps).unwrap();
        let (q1, q2) = sac.critic.net.forward(&obs, &a, &sac.par).unwrap();
        let want = ((&want_logp * alpha).unwrap() - q1.minimum(&q2).unwrap())
            .unwrap()
            .mean_all()
            .unwrap();
        assert_eq!(
            logp.flatten_all().unwrap().to_vec1::<f32>().unwrap(),
            want_logp.flatten_all().unwrap().to_vec1::<f32>().unwrap()
        );
        assert_eq!(
            loss.to_scalar::<f32>().unwrap(),
            want.to_scalar::<f32>().unwrap()
        );
        assert_same_gradients(&sac.pi_opt.vars, &got, &want.backward().unwrap());
    }
}
