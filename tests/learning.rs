//! The RL backbones learn a task made for tests (a point reaching a goal) within seconds.

use pbrl_actor::point::{point_episode, POINT_ACT, POINT_OBS};
use pbrl_learner::rl::ppo::{Ppo, PpoConfig};
use pbrl_learner::rl::sac::{Sac, SacConfig};
use rand::{Rng, SeedableRng};

const HORIZON: u32 = 30;

fn evaluate(mut policy: impl FnMut(&[f32]) -> Vec<f32>) -> f32 {
    let eval: Vec<f32> = (0..20)
        .map(|s| {
            point_episode(1_000_000 + s, HORIZON, &mut policy)
                .outcome
                .return_truth
        })
        .collect();
    eval.iter().sum::<f32>() / eval.len() as f32
}

#[test]
fn sac_learns_to_reach_the_point() {
    let cfg = SacConfig {
        hidden: vec![64, 64],
        batch: 64,
        lr: 1e-3,
        random_steps: 300,
        update_every: 1,
        seed: 3,
        ..SacConfig::default()
    };
    let mut sac = Sac::new(cfg, POINT_OBS, POINT_ACT).unwrap();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(9);
    let random = evaluate(|_| {
        (0..POINT_ACT)
            .map(|_| rng.random_range(-1.0..1.0))
            .collect()
    });
    let mut episode = 0;
    while sac.env_steps < 3_000 {
        let t = if sac.env_steps < sac.cfg.random_steps {
            point_episode(episode, HORIZON, |_| {
                (0..POINT_ACT)
                    .map(|_| rng.random_range(-1.0..1.0))
                    .collect()
            })
        } else {
            point_episode(episode, HORIZON, |o| sac.act_stochastic(o).unwrap())
        };
        episode += 1;
        sac.observe(&t);
        for _ in 0..sac.updates_due() {
            sac.update(|b| Ok(b.truth.clone())).unwrap();
        }
    }
    let learnt = evaluate(|o| sac.act_deterministic(o).unwrap());
    eprintln!(
        "SAC after {} env steps, {} updates: {learnt:.2} (random {random:.2})",
        sac.env_steps, sac.updates
    );
    // A random walk scores about -30; heading straight for the goal about -5.
    assert!(
        learnt > -9.0,
        "SAC after {} env steps: {learnt} (random {random})",
        sac.env_steps
    );
}

#[test]
fn ppo_learns_to_reach_the_point() {
    let total = 40_000u64;
    let cfg = PpoConfig {
        hidden: vec![64, 64],
        rollout_steps: 32 * HORIZON as usize,
        minibatch: 128,
        lr: 3e-3,
        // A 30-step task: a shorter horizon than feeding's learns faster.
        gamma: 0.95,
        gae_lambda: 0.95,
        seed: 5,
        ..PpoConfig::default()
    };
    let mut ppo = Ppo::new(cfg, POINT_OBS, POINT_ACT).unwrap();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
    let before = evaluate(|o| ppo.act_deterministic(o).unwrap());
    let mut episode = 0;
    while ppo.env_steps < total {
        let rollout: Vec<_> = (0..32)
            .map(|_| {
                episode += 1;
                point_episode(episode, HORIZON, |o| {
                    let noise: Vec<f32> = (0..POINT_ACT)
                        .map(|_| rng.sample(rand_distr::StandardNormal))
                        .collect();
                    ppo.act_stochastic(o, &noise).unwrap()
                })
            })
            .collect();
        let rewards: Vec<Vec<f32>> = rollout
            .iter()
            .map(|t| t.rewards.iter().map(|r| r.truth).collect())
            .collect();
        ppo.train(&rollout, &rewards, total).unwrap();
    }
    let learnt = evaluate(|o| ppo.act_deterministic(o).unwrap());
    eprintln!(
        "PPO after {} env steps, {} updates: {learnt:.2} (untrained {before:.2})",
        ppo.env_steps, ppo.updates
    );
    // Untrained it scores about -35; heading straight for the goal about -5.
    assert!(
        learnt > -13.0,
        "PPO after {} env steps: {learnt} (untrained {before})",
        ppo.env_steps
    );
}
