//! Timing of the learner's unit of work: a SAC gradient step, a PPO minibatch update, and
//! what preference learning adds (the ensemble relabelling each SAC minibatch, an epoch of
//! ensemble training) on feeding-sized inputs (observation 25, action 7), synthetic data;
//! and what a checkpoint costs with a full replay buffer.

use std::time::Instant;

use candle_core::Result;
use pbrl_common::trajectory::TRAJECTORY_FORMAT;
use pbrl_common::{StepRewards, Trajectory};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::pref::reward::{Pool, RewardSource, TrainReward};
use crate::pref::reward_model::{Labelled, RewardModel, RewardModelConfig, Segment};
use crate::rl::ppo::{Ppo, PpoConfig};
use crate::rl::sac::{Sac, SacConfig};
use crate::run::backbone::Backbone;
use crate::run::checkpoint::{open_folder, Checkpoints, Of};
use crate::run::config::{Algo, LearnerConfig};
use crate::run::curve::Curve;
use crate::run::progress::Progress;
use crate::run::run_folder::RunFolder;

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

/// Milliseconds per SAC gradient step on `threads` learner threads (median of `reps`
/// timings of `steps` steps each).
pub fn sac_step_ms(
    hidden: usize,
    batch: usize,
    steps: usize,
    reps: usize,
    threads: usize,
) -> Result<f64> {
    sac_step_with(hidden, batch, steps, reps, threads, None)
}

/// Milliseconds per SAC gradient step whose minibatch reward is the mean of a reward
/// ensemble of `members` x `reward_hidden` (PEBBLE's relabelling).
pub fn sac_step_relabelled_ms(
    hidden: usize,
    batch: usize,
    steps: usize,
    reps: usize,
    reward_hidden: &[usize],
    threads: usize,
) -> Result<f64> {
    let cfg = RewardModelConfig {
        hidden: reward_hidden.to_vec(),
        ..RewardModelConfig::plain()
    };
    let model = RewardModel::new(cfg, OBS, ACT)?;
    sac_step_with(hidden, batch, steps, reps, threads, Some(&model))
}

fn sac_step_with(
    hidden: usize,
    batch: usize,
    steps: usize,
    reps: usize,
    threads: usize,
    model: Option<&RewardModel>,
) -> Result<f64> {
    let reward = |b: &crate::rl::replay::Batch| match model {
        Some(m) => m.predict_tensor(&b.obs, &b.act, b.features.as_ref()),
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
    sac.set_threads(threads)?;
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

/// Milliseconds per PPO minibatch update (policy and value) on `threads` learner threads,
/// one epoch over a rollout.
pub fn ppo_update_ms(
    hidden: usize,
    minibatch: usize,
    rollout: usize,
    threads: usize,
) -> Result<f64> {
    let cfg = PpoConfig {
        hidden: vec![hidden, hidden],
        minibatch,
        epochs: 1,
        target_kl: f64::INFINITY,
        ..PpoConfig::default()
    };
    let mut ppo = Ppo::new(cfg, OBS, ACT)?;
    ppo.set_threads(threads)?;
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

/// Seconds for one training epoch (all members) over `labels` random pairs of `steps`-step
/// feeding-sized segments (observation 25, action 7), with hidden layers `hidden` and the
/// other settings at their defaults.
pub fn bench_epoch(labels: usize, steps: usize, hidden: &[usize]) -> Result<f64> {
    let cfg = RewardModelConfig {
        hidden: hidden.to_vec(),
        max_epochs: 1,
        stop_accuracy: f64::INFINITY,
        max_pairs: 0,
        ..RewardModelConfig::plain()
    };
    Ok(bench_training(cfg, labels, steps)?.0)
}

/// Seconds for one whole training of the ensemble `cfg` (as the learner runs it after a
/// session of queries) over `labels` random pairs of `steps`-step feeding-sized segments
/// (with comfort features where `cfg` reads them), and what it did. Random answers are
/// never fitted, so the training runs to its bound (`max_epochs` or `max_pairs`): the cost
/// of the longest training.
pub fn bench_training(
    cfg: RewardModelConfig,
    labels: usize,
    steps: usize,
) -> Result<(f64, crate::pref::reward_model::TrainStats)> {
    let feat = if cfg.features {
        pbrl_common::trajectory::FEATURES
    } else {
        0
    };
    let mut model = RewardModel::new(cfg, OBS, ACT)?;
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    let mut segment = || {
        std::sync::Arc::new(Segment {
            obs: (0..steps * OBS)
                .map(|_| rng.random_range(-2.0..2.0))
                .collect(),
            actions: (0..steps * ACT)
                .map(|_| rng.random_range(-1.0..1.0))
                .collect(),
            features: (0..steps * feat)
                .map(|_| rng.random_range(0.0..1.0))
                .collect(),
        })
    };
    let data: Vec<Labelled> = (0..labels)
        .map(|i| Labelled {
            first: segment(),
            second: segment(),
            target: (i % 2) as f32,
        })
        .collect();
    let t = std::time::Instant::now();
    let stats = model.train(&data)?;
    Ok((t.elapsed().as_secs_f64(), stats))
}

/// What checkpoints cost with a full replay buffer (`pbrl bench checkpoint`).
#[derive(Clone, Debug)]
pub struct CheckpointCost {
    pub transitions: u64,
    /// The first checkpoint: the whole buffer as one segment.
    pub full_ms: f64,
    pub full_bytes: u64,
    /// A checkpoint after `increment` more transitions: only they are written.
    pub increment: u64,
    pub increment_ms: f64,
    pub increment_bytes: u64,
    /// Reading the newest checkpoint back (checks, networks, replay buffer).
    pub restore_ms: f64,
}

/// Fill a feeding-sized SAC (obs 25, action 7, 256x256) replay buffer with `transitions`
/// random transitions (whole 200-step episodes), checkpoint it into `dir`, add
/// `increment`, checkpoint again, and restore.
pub fn checkpoint(
    dir: &std::path::Path,
    transitions: u64,
    increment: u64,
) -> anyhow::Result<CheckpointCost> {
    const EPISODE: u64 = 200;
    let mut cfg = LearnerConfig::new("bench", Algo::Sac, RewardSource::Truth, OBS, ACT);
    cfg.total_steps = transitions + increment;
    cfg.sac.replay_capacity = transitions as usize;
    cfg.out = Some(dir.to_path_buf());
    let folder = RunFolder::new(dir);
    let mut backbone = Backbone::new(&cfg)?;
    let (file, _, segments) = open_folder(&folder, &cfg, &mut backbone)?;
    let mut checkpoints = Checkpoints::new(&cfg, Some(RunFolder::new(dir)), segments);
    let reward = TrainReward::new(
        RewardSource::Truth,
        &cfg.pref,
        cfg.total_steps,
        OBS,
        Pool::AtOnce,
    );
    let curve = Curve::new(Some(file), 0, None);
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    let mut fill = |backbone: &mut Backbone, n: u64| {
        if let Backbone::Sac(sac) = backbone {
            for seed in 0..n.div_ceil(EPISODE) {
                sac.observe(&synthetic(&mut rng, seed, EPISODE as usize));
            }
        }
    };
    let mut timed = |backbone: &Backbone, env_steps: u64| -> anyhow::Result<(f64, u64)> {
        let before: u64 = checkpoints.segments().iter().map(|s| s.bytes).sum();
        let start = Instant::now();
        let p = Progress {
            version: 1,
            env_steps,
            ..Progress::default()
        };
        let of = Of {
            backbone,
            feedback: None,
            reward: &reward,
            curve: &curve,
        };
        checkpoints.write(&cfg, of, &p)?;
        let ms = start.elapsed().as_secs_f64() * 1e3;
        let after: u64 = checkpoints.segments().iter().map(|s| s.bytes).sum();
        let nets: u64 = folder
            .latest_checkpoint()?
            .map_or(0, |c| c.manifest.files.iter().map(|f| f.bytes).sum());
        Ok((ms, after.saturating_sub(before) + nets))
    };
    fill(&mut backbone, transitions);
    let (full_ms, full_bytes) = timed(&backbone, transitions)?;
    fill(&mut backbone, increment);
    let (increment_ms, increment_bytes) = timed(&backbone, transitions + increment)?;
    let start = Instant::now();
    let mut fresh = Backbone::new(&cfg)?;
    open_folder(&folder, &cfg, &mut fresh)?;
    Ok(CheckpointCost {
        transitions,
        full_ms,
        full_bytes,
        increment,
        increment_ms,
        increment_bytes,
        restore_ms: start.elapsed().as_secs_f64() * 1e3,
    })
}
