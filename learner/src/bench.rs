//! Timing of the learner's unit of work: a SAC gradient step, a PPO minibatch update, and
//! what preference learning adds (the ensemble relabelling each SAC minibatch, an epoch of
//! ensemble training) on feeding-sized inputs (observation 25, action 7), synthetic data.

use std::time::Instant;

use candle_core::Result;
use pbrl_common::trajectory::TRAJECTORY_FORMAT;
use pbrl_common::{StepRewards, Trajectory};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::ppo::{Ppo, PpoConfig};
use crate::sac::{Sac, SacConfig};

const OBS: usize = 25;
const ACT: usize = 7;

fn synthetic(rng: &mut ChaCha8Rng, seed: u64, steps: usize) -> Trajectory {
    Trajectory {
        format: TRAJECTORY_FORMAT,
        seed,
        obs_dim: OBS as u32,
        act_dim: ACT as u32,
        obs: (0..(steps + 1) * OBS)
            .map(|_| rng.random_range(-1.0..1.0))
            .collect(),
        actions: (0..steps * ACT)
            .map(|_| rng.random_range(-0.99..0.99))
            .collect(),
        rewards: (0..steps)
            .map(|_| {
                let r = rng.random_range(-1.0..0.0);
                StepRewards {
                    truth: r,
                    task: r,
                    robot: r,
                    ..StepRewards::default()
                }
            })
            .collect(),
        ..Trajectory::default()
    }
}

/// Milliseconds per SAC gradient step (median of `reps` timings of `steps` steps each).
pub fn sac_step_ms(hidden: usize, batch: usize, steps: usize, reps: usize) -> Result<f64> {
    sac_step_with(hidden, batch, steps, reps, None)
}

/// Milliseconds per SAC gradient step whose minibatch reward is the mean of a reward
/// ensemble of `members` x `reward_hidden` (PEBBLE's relabelling).
pub fn sac_step_relabelled_ms(
    hidden: usize,
    batch: usize,
    steps: usize,
    reps: usize,
    reward_hidden: &[usize],
) -> Result<f64> {
    let cfg = crate::reward_model::RewardModelConfig {
        hidden: reward_hidden.to_vec(),
        ..Default::default()
    };
    let model = crate::reward_model::RewardModel::new(cfg, OBS, ACT)?;
    sac_step_with(hidden, batch, steps, reps, Some(&model))
}

fn sac_step_with(
    hidden: usize,
    batch: usize,
    steps: usize,
    reps: usize,
    model: Option<&crate::reward_model::RewardModel>,
) -> Result<f64> {
    let reward = |b: &crate::sac::Batch| match model {
        Some(m) => m.predict_tensor(&b.obs, &b.act),
        None => Ok(b.truth.clone()),
    };
    let cfg = SacConfig {
        hidden: vec![hidden, hidden],
        batch,
        random_steps: 0,
        update_every: 1,
        replay_capacity: 100_000,
        ..SacConfig::default()
    };
    let mut sac = Sac::new(cfg, OBS, ACT)?;
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    for s in 0..50 {
        sac.observe(&synthetic(&mut rng, s, 200));
    }
    for _ in 0..3 {
        sac.update(reward)?;
    }
    let mut times = Vec::new();
    for _ in 0..reps {
        let t = Instant::now();
        for _ in 0..steps {
            sac.update(reward)?;
        }
        times.push(t.elapsed().as_secs_f64() * 1e3 / steps as f64);
    }
    times.sort_by(f64::total_cmp);
    Ok(times[times.len() / 2])
}

/// Milliseconds per PPO minibatch update (policy and value), one epoch over a rollout.
pub fn ppo_update_ms(hidden: usize, minibatch: usize, rollout: usize) -> Result<f64> {
    let cfg = PpoConfig {
        hidden: vec![hidden, hidden],
        minibatch,
        epochs: 1,
        target_kl: f64::INFINITY,
        ..PpoConfig::default()
    };
    let mut ppo = Ppo::new(cfg, OBS, ACT)?;
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    let data: Vec<Trajectory> = (0..(rollout / 200) as u64)
        .map(|s| synthetic(&mut rng, s, 200))
        .collect();
    let rewards: Vec<Vec<f32>> = data
        .iter()
        .map(|t| t.rewards.iter().map(|r| r.truth).collect())
        .collect();
    ppo.train(&data, &rewards, u64::MAX)?;
    let t = Instant::now();
    let stats = ppo.train(&data, &rewards, u64::MAX)?;
    Ok(t.elapsed().as_secs_f64() * 1e3 / stats.minibatch_updates.max(1) as f64)
}
