//! Proximal policy optimisation (Schulman et al. 2017), as PrefPPO uses it
//! (`shared/method.md` section 6): separate policy and value MLPs, GAE, clipped surrogate
//! with learning rate and clip range decaying linearly to 0, early stop on approximate KL,
//! advantages normalised per minibatch, observations normalised by running statistics.
//!
//! Synchronous: [`Ppo::train`] takes the trajectories of one rollout, all acted by the
//! current weights (the caller drops those of older versions), so the old log-probabilities
//! are recomputed here with the very policy and normaliser that acted.

use candle_core::backprop::GradStore;
use candle_core::{DType, Device, Result, Tensor};
use pbrl_common::nets::{GaussianPolicy, Owned, ValueNet};
use pbrl_common::par::Par;
use pbrl_common::{RunningNorm, Trajectory};
use rand::seq::SliceRandom;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use crate::optim::{clip_grad_norm, Adam, AdamState};
use crate::state::RngState;

/// PPO's settings (defaults from `shared/method.md`). Each is a flag of `pbrl train`
/// (`--ppo-...`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, clap::Args)]
pub struct PpoConfig {
    /// PPO: hidden layer sizes of the policy and of the value network (authors: 512x512).
    #[arg(id = "ppo_hidden", long = "ppo-hidden", value_delimiter = ',', default_values_t = [512, 512])]
    pub hidden: Vec<usize>,
    /// PPO: env steps per rollout (16 envs x 200 steps).
    #[arg(
        id = "ppo_rollout_steps",
        long = "ppo-rollout-steps",
        default_value_t = 3200
    )]
    pub rollout_steps: usize,
    /// PPO: passes over a rollout.
    #[arg(id = "ppo_epochs", long = "ppo-epochs", default_value_t = 10)]
    pub epochs: usize,
    /// PPO: minibatch size.
    #[arg(id = "ppo_minibatch", long = "ppo-minibatch", default_value_t = 256)]
    pub minibatch: usize,
    /// PPO: discount.
    #[arg(id = "ppo_gamma", long = "ppo-gamma", default_value_t = 0.99)]
    pub gamma: f64,
    /// PPO: GAE lambda.
    #[arg(id = "ppo_gae_lambda", long = "ppo-gae-lambda", default_value_t = 0.98)]
    pub gae_lambda: f64,
    /// PPO: clip range at the start; decays linearly to 0 over the run.
    #[arg(id = "ppo_clip", long = "ppo-clip", default_value_t = 0.2)]
    pub clip: f64,
    /// PPO: learning rate at the start; decays linearly to 0 over the run.
    #[arg(id = "ppo_lr", long = "ppo-lr", default_value_t = 3e-4)]
    pub lr: f64,
    /// PPO: value loss coefficient.
    #[arg(id = "ppo_value_coef", long = "ppo-value-coef", default_value_t = 0.5)]
    pub value_coef: f64,
    /// PPO: gradient norm clip.
    #[arg(
        id = "ppo_max_grad_norm",
        long = "ppo-max-grad-norm",
        default_value_t = 0.5
    )]
    pub max_grad_norm: f64,
    /// PPO: stop a rollout's epochs once the approximate KL exceeds 1.5 x this.
    #[arg(id = "ppo_target_kl", long = "ppo-target-kl", default_value_t = 0.03)]
    pub target_kl: f64,
    /// PPO: clip of normalised observations.
    #[arg(id = "ppo_obs_clip", long = "ppo-obs-clip", default_value_t = 10.0)]
    pub obs_clip: f64,
    /// Seed (the run's `--seed`).
    #[arg(skip)]
    pub seed: u64,
}

impl Default for PpoConfig {
    /// Every field at its flag's default.
    fn default() -> Self {
        pbrl_common::flags::defaults()
    }
}

/// Generalised advantage estimation over one episode.
///
/// `values` has one more entry than `rewards`: the value of the state after the last step,
/// used to bootstrap when the episode was cut by the time limit (`terminated == false`).
/// Returns (advantages, returns = advantages + values).
pub fn gae(
    rewards: &[f32],
    values: &[f32],
    terminated: bool,
    gamma: f64,
    lambda: f64,
) -> (Vec<f32>, Vec<f32>) {
    let n = rewards.len();
    let mut adv = vec![0.0f32; n];
    let mut running = 0.0f64;
    for t in (0..n).rev() {
        // NOTE: only a real terminal state cuts the bootstrap; a time limit does not.
        let next_value = if t + 1 == n && terminated {
            0.0
        } else {
            values[t + 1] as f64
        };
        let delta = rewards[t] as f64 + gamma * next_value - values[t] as f64;
        running = delta + gamma * lambda * running;
        adv[t] = running as f32;
    }
    let ret = adv.iter().zip(values).map(|(a, v)| a + v).collect();
    (adv, ret)
}

/// The clipped surrogate loss -mean(min(r A, clip(r, 1 - eps, 1 + eps) A)),
/// r = exp(logp_new - logp_old).
pub fn clipped_policy_loss(
    logp_new: &Tensor,
    logp_old: &Tensor,
    adv: &Tensor,
    clip: f64,
) -> Result<Tensor> {
    let (unclipped, clipped) = surrogates(logp_new, logp_old, adv, clip)?;
    unclipped.minimum(&clipped)?.mean_all()?.neg()
}

/// `r A` and `clip(r, 1 - eps, 1 + eps) A`.
fn surrogates(
    logp_new: &Tensor,
    logp_old: &Tensor,
    adv: &Tensor,
    clip: f64,
) -> Result<(Tensor, Tensor)> {
    let ratio = (logp_new - logp_old)?.exp()?;
    let unclipped = (&ratio * adv)?;
    let clipped = (ratio.clamp(1.0 - clip, 1.0 + clip)? * adv)?;
    Ok((unclipped, clipped))
}

/// [`clipped_policy_loss`] and its gradient with respect to `logp_new` (`[batch, 1]`):
/// `-r A / batch` where the unclipped term is the minimum, else 0 (where both are equal
/// and the clip is active, `A` is 0).
pub fn clipped_policy_loss_and_grad(
    logp_new: &Tensor,
    logp_old: &Tensor,
    adv: &Tensor,
    clip: f64,
) -> Result<(Tensor, Tensor)> {
    let (unclipped, clipped) = surrogates(logp_new, logp_old, adv, clip)?;
    let loss = unclipped.minimum(&clipped)?.mean_all()?.neg()?;
    let taken = unclipped.le(&clipped)?.to_dtype(DType::F32)?;
    let grad = ((unclipped * taken)? * (-1.0 / logp_new.dim(0)? as f64))?;
    Ok((loss, grad))
}

/// One minibatch's log-probabilities, losses and gradients.
struct Minibatch {
    logp: Tensor,
    policy_loss: Tensor,
    /// The value loss without its coefficient.
    value_loss: Tensor,
    policy_grads: GradStore,
    value_grads: GradStore,
}

/// What one rollout's training did.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct PpoStats {
    pub policy_loss: f32,
    pub value_loss: f32,
    pub approx_kl: f32,
    pub clip_fraction: f32,
    pub epochs_run: usize,
    pub minibatch_updates: u64,
    pub lr: f64,
    pub clip: f64,
}

/// The PPO learner state.
pub struct Ppo {
    pub cfg: PpoConfig,
    obs_dim: usize,
    act_dim: usize,
    pub policy: Owned<GaussianPolicy>,
    pub value: Owned<ValueNet>,
    pi_opt: Adam,
    v_opt: Adam,
    pub norm: RunningNorm,
    rng: ChaCha8Rng,
    /// Where a minibatch's policy and value gradients run.
    par: Par,
    /// Env steps trained on.
    pub env_steps: u64,
    /// Minibatch updates made.
    pub updates: u64,
}

/// PPO's state beside its networks (the learning-rate and clip schedules follow from
/// `env_steps` and the run's budget).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PpoState {
    pub pi_opt: AdamState,
    pub v_opt: AdamState,
    pub norm: RunningNorm,
    pub rng: RngState,
    pub env_steps: u64,
    pub updates: u64,
}

impl Ppo {
    /// The networks by name (for checkpoints).
    pub fn networks(&self) -> [(&'static str, &candle_nn::VarMap); 2] {
        [
            ("policy", &self.policy.varmap),
            ("value", &self.value.varmap),
        ]
    }

    /// Optimisers, normaliser, generator and counters (for checkpoints).
    pub fn state(&self) -> Result<PpoState> {
        Ok(PpoState {
            pi_opt: self.pi_opt.state()?,
            v_opt: self.v_opt.state()?,
            norm: self.norm.clone(),
            rng: RngState::of(&self.rng),
            env_steps: self.env_steps,
            updates: self.updates,
        })
    }

    /// Continue from `s` (the networks are restored apart).
    pub fn restore(&mut self, s: &PpoState) -> Result<()> {
        self.pi_opt.restore(&s.pi_opt)?;
        self.v_opt.restore(&s.v_opt)?;
        self.norm = s.norm.clone();
        self.rng = s.rng.restore();
        self.env_steps = s.env_steps;
        self.updates = s.updates;
        Ok(())
    }

    /// A new value network and its optimiser (PrefPPO, after the unsupervised pretraining).
    pub fn reset_value(&mut self) -> Result<()> {
        let (obs_dim, h) = (self.obs_dim, self.cfg.hidden.clone());
        self.value = Owned::build(&mut self.rng, |vb| ValueNet::new(vb, obs_dim, &h))?;
        self.v_opt = Adam::for_varmap(&self.value.varmap, self.v_opt.lr)?;
        Ok(())
    }

    pub fn new(cfg: PpoConfig, obs_dim: usize, act_dim: usize) -> Result<Self> {
        let mut rng = ChaCha8Rng::seed_from_u64(cfg.seed);
        let h = cfg.hidden.clone();
        let policy = Owned::build(&mut rng, |vb| GaussianPolicy::new(vb, obs_dim, &h, act_dim))?;
        let value = Owned::build(&mut rng, |vb| ValueNet::new(vb, obs_dim, &h))?;
        let pi_opt = Adam::for_varmap(&policy.varmap, cfg.lr)?;
        let v_opt = Adam::for_varmap(&value.varmap, cfg.lr)?;
        let norm = RunningNorm::new(obs_dim, cfg.obs_clip);
        Ok(Self {
            cfg,
            obs_dim,
            act_dim,
            policy,
            value,
            pi_opt,
            v_opt,
            norm,
            rng,
            par: Par::default(),
            env_steps: 0,
            updates: 0,
        })
    }

    /// Take each minibatch's policy and value gradients on `threads` threads (1 or 2; the
    /// default is 1), side by side on two. The updates do not change.
    pub fn set_threads(&mut self, threads: usize) -> Result<()> {
        self.par = Par::new(threads).map_err(candle_core::Error::wrap)?;
        Ok(())
    }

    /// Normalised observations of `t` as a `[steps + 1, obs_dim]` tensor.
    fn normalised(&self, t: &Trajectory) -> Result<Tensor> {
        let mut obs = t.obs.clone();
        for row in obs.chunks_exact_mut(self.obs_dim) {
            self.norm.apply(row);
        }
        Tensor::from_vec(obs, (t.steps() + 1, self.obs_dim), &Device::Cpu)
    }

    /// One minibatch's losses and gradients (by hand: see `nets::Mlp::backward`): the
    /// clipped surrogate for the policy, `value_coef * mean((v - ret)^2)` for the value.
    fn minibatch_gradients(
        &self,
        obs: &Tensor,
        act: &Tensor,
        logp_old: &Tensor,
        adv: &Tensor,
        ret: &Tensor,
        clip: f64,
    ) -> Result<Minibatch> {
        // The policy here, the value network beside it (they share nothing).
        let (value, obs_v, ret) = (self.value.net.clone(), obs.clone(), ret.clone());
        let value_coef = self.cfg.value_coef;
        let (policy, value) = self.par.join(
            || {
                let (logp, tape) = self.policy.net.log_prob_taped(obs, act)?;
                let (loss, dlogp) = clipped_policy_loss_and_grad(&logp, logp_old, adv, clip)?;
                let mut grads = GradStore::default();
                self.policy
                    .net
                    .backward_log_prob(&tape, &dlogp, &mut grads)?;
                Ok::<_, candle_core::Error>((logp, loss, grads))
            },
            move || {
                let (v, tape) = value.forward_taped(&obs_v)?;
                let err = (v - ret)?;
                let loss = err.sqr()?.mean_all()?;
                let scale = 2.0 * value_coef / err.dim(0)? as f64;
                let mut grads = GradStore::default();
                value.backward(&tape, &(err * scale)?, &mut grads)?;
                Ok::<_, candle_core::Error>((loss, grads))
            },
        );
        let ((logp, policy_loss, policy_grads), (value_loss, value_grads)) = (policy?, value?);
        Ok(Minibatch {
            logp,
            policy_loss,
            value_loss,
            policy_grads,
            value_grads,
        })
    }

    /// Train on one rollout, `rewards[i]` being the per-step reward trained on for
    /// trajectory `i`. `total_steps` is the run's budget (for the linear decays).
    pub fn train(
        &mut self,
        rollout: &[Trajectory],
        rewards: &[Vec<f32>],
        total_steps: u64,
    ) -> Result<PpoStats> {
        if rewards.len() != rollout.len()
            || rollout
                .iter()
                .zip(rewards)
                .any(|(t, r)| t.steps() != r.len())
        {
            candle_core::bail!("PPO: the rewards do not match the rollout's trajectories");
        }
        // 1. Targets: values, GAE, old log-probabilities, all with the acting weights.
        let (mut obs, mut act, mut old_logp, mut adv, mut ret) =
            (vec![], vec![], vec![], vec![], vec![]);
        for (t, r) in rollout.iter().zip(rewards) {
            let o = self.normalised(t)?;
            let v = self
                .value
                .net
                .forward(&o)?
                .flatten_all()?
                .to_vec1::<f32>()?;
            let (a, g) = gae(
                r,
                &v,
                t.outcome.terminated,
                self.cfg.gamma,
                self.cfg.gae_lambda,
            );
            let steps = t.steps();
            let o_steps = o.narrow(0, 0, steps)?;
            let acts = Tensor::from_slice(&t.actions, (steps, self.act_dim), &Device::Cpu)?;
            old_logp.extend(
                self.policy
                    .net
                    .log_prob(&o_steps, &acts)?
                    .flatten_all()?
                    .to_vec1::<f32>()?,
            );
            obs.extend(o_steps.flatten_all()?.to_vec1::<f32>()?);
            act.extend_from_slice(&t.actions);
            adv.extend(a);
            ret.extend(g);
        }
        let n = adv.len();
        let dev = Device::Cpu;
        let obs = Tensor::from_vec(obs, (n, self.obs_dim), &dev)?;
        let act = Tensor::from_vec(act, (n, self.act_dim), &dev)?;
        let old_logp = Tensor::from_vec(old_logp, (n, 1), &dev)?;
        let adv = Tensor::from_vec(adv, (n, 1), &dev)?;
        let ret = Tensor::from_vec(ret, (n, 1), &dev)?;

        // 2. Schedules: learning rate and clip decay linearly to 0 over the run.
        let frac = 1.0 - (self.env_steps as f64 / total_steps.max(1) as f64).min(1.0);
        let (lr, clip) = (self.cfg.lr * frac, self.cfg.clip * frac);
        self.pi_opt.lr = lr;
        self.v_opt.lr = lr;

        // 3. Epochs of shuffled minibatches, stopping early on a large KL.
        let mut stats = PpoStats {
            lr,
            clip,
            ..PpoStats::default()
        };
        let mut order: Vec<u32> = (0..n as u32).collect();
        'epochs: for _ in 0..self.cfg.epochs {
            order.shuffle(&mut self.rng);
            stats.epochs_run += 1;
            for chunk in order.chunks(self.cfg.minibatch) {
                let idx = Tensor::from_slice(chunk, chunk.len(), &dev)?;
                let (o, a) = (obs.index_select(&idx, 0)?, act.index_select(&idx, 0)?);
                let (lp_old, r) = (old_logp.index_select(&idx, 0)?, ret.index_select(&idx, 0)?);
                let mb_adv = adv.index_select(&idx, 0)?;
                // NOTE: advantages normalised per minibatch.
                let mean = mb_adv.mean_all()?;
                let std = mb_adv.broadcast_sub(&mean)?.sqr()?.mean_all()?.sqrt()?;
                let mb_adv = mb_adv.broadcast_sub(&mean)?.broadcast_div(&(std + 1e-8)?)?;

                let mb = self.minibatch_gradients(&o, &a, &lp_old, &mb_adv, &r, clip)?;
                let (lp, pi_loss, v_loss) = (mb.logp, mb.policy_loss, mb.value_loss);
                let log_ratio = (&lp - &lp_old)?;
                // Approximate KL (Schulman's k3): mean((r - 1) - log r).
                let kl = ((log_ratio.exp()? - 1.0)? - &log_ratio)?
                    .mean_all()?
                    .to_scalar::<f32>()?;
                let mut g = mb.policy_grads;
                clip_grad_norm(&self.pi_opt.vars, &mut g, self.cfg.max_grad_norm)?;
                self.pi_opt.step(&g)?;
                let mut g = mb.value_grads;
                clip_grad_norm(&self.v_opt.vars, &mut g, self.cfg.max_grad_norm)?;
                self.v_opt.step(&g)?;
                self.updates += 1;
                stats.minibatch_updates += 1;
                stats.policy_loss = pi_loss.to_scalar::<f32>()?;
                stats.value_loss = v_loss.to_scalar::<f32>()?;
                stats.approx_kl = kl;
                let outside = log_ratio.exp()?.affine(1.0, -1.0)?.abs()?.gt(clip)?;
                stats.clip_fraction = outside
                    .to_dtype(candle_core::DType::F32)?
                    .mean_all()?
                    .to_scalar::<f32>()?;
                if (kl as f64) > 1.5 * self.cfg.target_kl {
                    break 'epochs;
                }
            }
        }

        // 4. The normaliser learns this rollout's observations for the next weights.
        for t in rollout {
            self.norm.update(&t.obs[..t.steps() * self.obs_dim]);
        }
        self.env_steps += n as u64;
        Ok(stats)
    }

    /// A sampled action for one raw observation (normalised here, as actors do).
    pub fn act_stochastic(&self, obs: &[f32], noise: &[f32]) -> Result<Vec<f32>> {
        let mut o = obs.to_vec();
        self.norm.apply(&mut o);
        self.policy.net.act_one(o, Some(noise.to_vec()))
    }

    /// The deterministic action for one raw observation.
    pub fn act_deterministic(&self, obs: &[f32]) -> Result<Vec<f32>> {
        let mut o = obs.to_vec();
        self.norm.apply(&mut o);
        self.policy.net.act_one(o, None)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testutil::{assert_same_gradients, uniform_tensors};

    #[test]
    fn gae_matches_the_reference() {
        // Reference (Python, CleanRL's loop for one episode cut by the time limit):
        //   r, v, gamma, lam = [1.0, 0.0, 2.0], [0.5, 0.4, 0.3, 0.2], 0.9, 0.8
        //   adv, last = [0.0] * 3, 0.0
        //   for t in reversed(range(3)):
        //       delta = r[t] + gamma * v[t + 1] - v[t]
        //       last = delta + gamma * lam * last; adv[t] = last
        //   print(adv)  # [1.740992, 1.2236, 1.88]
        let (adv, ret) = gae(&[1.0, 0.0, 2.0], &[0.5, 0.4, 0.3, 0.2], false, 0.9, 0.8);
        let want = [1.740_992, 1.2236, 1.88];
        for (a, w) in adv.iter().zip(want) {
            assert!((a - w).abs() < 1e-5, "{adv:?}");
        }
        assert!((ret[0] - (1.740_992 + 0.5)).abs() < 1e-5);
        // A terminal state does not bootstrap: the last delta is 2.0 - 0.3 = 1.7.
        let (adv, _) = gae(&[1.0, 0.0, 2.0], &[0.5, 0.4, 0.3, 0.2], true, 0.9, 0.8);
        assert!((adv[2] - 1.7).abs() < 1e-6, "{adv:?}");
    }

    #[test]
    fn clipped_loss_matches_the_reference() {
        // Reference (Python):
        //   lp_new, lp_old, adv, eps = [0.0, -1.0, 0.5], [-0.5, -0.5, 0.5], [1.0, 2.0, -1.0], 0.2
        //   r = [math.exp(a - b) for a, b in zip(lp_new, lp_old)]   # [1.6487, 0.6065, 1.0]
        //   -sum(min(ri * A, max(1 - eps, min(1 + eps, ri)) * A)
        //        for ri, A in zip(r, adv)) / 3                       # -0.4710204
        let t = |v: &[f32]| Tensor::from_slice(v, (v.len(), 1), &Device::Cpu).unwrap();
        let loss = clipped_policy_loss(
            &t(&[0.0, -1.0, 0.5]),
            &t(&[-0.5, -0.5, 0.5]),
            &t(&[1.0, 2.0, -1.0]),
            0.2,
        )
        .unwrap()
        .to_scalar::<f32>()
        .unwrap();
        assert!((loss - (-0.471_02)).abs() < 1e-4, "{loss}");
    }

    #[test]
    fn hand_gradients_of_both_losses_are_candle_autodiffs() {
        let cfg = PpoConfig {
            hidden: vec![16, 12],
            seed: 4,
            ..PpoConfig::default()
        };
        let ppo = Ppo::new(cfg, 5, 2).unwrap();
        let mut t = uniform_tensors(8);
        let (obs, act, adv, ret) = (t(40, 5, 2.0), t(40, 2, 0.99), t(40, 1, 1.5), t(40, 1, 3.0));
        // Old log-probabilities off by up to 0.4: ratios on both sides of the clip.
        let lp = ppo.policy.net.log_prob(&obs, &act).unwrap();
        let lp_old = (lp.detach() + t(40, 1, 0.4)).unwrap();
        let clip = 0.2;
        let mb = ppo
            .minibatch_gradients(&obs, &act, &lp_old, &adv, &ret, clip)
            .unwrap();
        assert_eq!(
            mb.logp.flatten_all().unwrap().to_vec1::<f32>().unwrap(),
            lp.flatten_all().unwrap().to_vec1::<f32>().unwrap()
        );
        let ratio = (&lp - &lp_old).unwrap().exp().unwrap();
        let outside = ratio
            .affine(1.0, -1.0)
            .unwrap()
            .abs()
            .unwrap()
            .gt(clip)
            .unwrap();
        let n_out = outside.to_dtype(DType::F32).unwrap().sum_all().unwrap();
        assert!(
            n_out.to_scalar::<f32>().unwrap() >= 5.0,
            "some ratios are clipped"
        );

        let want = clipped_policy_loss(&lp, &lp_old, &adv, clip).unwrap();
        assert_eq!(
            mb.policy_loss.to_scalar::<f32>().unwrap(),
            want.to_scalar::<f32>().unwrap()
        );
        assert_same_gradients(
            &ppo.pi_opt.vars,
            &mb.policy_grads,
            &want.backward().unwrap(),
        );

        let v_loss = (ppo.value.net.forward(&obs).unwrap() - &ret)
            .unwrap()
            .sqr()
            .unwrap()
            .mean_all()
            .unwrap();
        assert_eq!(
            mb.value_loss.to_scalar::<f32>().unwrap(),
            v_loss.to_scalar::<f32>().unwrap()
        );
        let want = (&v_loss * ppo.cfg.value_coef).unwrap().backward().unwrap();
        assert_same_gradients(&ppo.v_opt.vars, &mb.value_grads, &want);
    }
}
