//! A point that must reach a goal on a plane: a task small enough for an RL backbone to
//! learn in seconds, for tests. Observation: position and goal minus position (4);
//! action: a velocity (2), clipped to [-1, 1]; reward: minus the distance to the goal.

use pbrl_common::trajectory::TRAJECTORY_FORMAT;
use pbrl_common::{Outcome, StepRewards, Trajectory};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

pub const POINT_OBS: usize = 4;
pub const POINT_ACT: usize = 2;
/// Distance moved per step at full action, per axis.
const SPEED: f32 = 0.1;

fn observe(pos: [f32; 2], goal: [f32; 2]) -> [f32; POINT_OBS] {
    [pos[0], pos[1], goal[0] - pos[0], goal[1] - pos[1]]
}

/// One episode of `horizon` steps from `seed`, acting with `policy` (observation to action).
pub fn point_episode(
    seed: u64,
    horizon: u32,
    mut policy: impl FnMut(&[f32]) -> Vec<f32>,
) -> Trajectory {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut pos = [rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0)];
    let goal = [rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0)];
    let mut t = Trajectory {
        format: TRAJECTORY_FORMAT,
        seed,
        obs_dim: POINT_OBS as u32,
        act_dim: POINT_ACT as u32,
        ..Trajectory::default()
    };
    t.obs.extend_from_slice(&observe(pos, goal));
    let mut ret = 0.0;
    for _ in 0..horizon {
        let a = policy(&observe(pos, goal));
        for (k, p) in pos.iter_mut().enumerate() {
            let ak = a.get(k).copied().unwrap_or(0.0);
            let ak = if ak.is_finite() {
                ak.clamp(-1.0, 1.0)
            } else {
                0.0
            };
            *p = (*p + SPEED * ak).clamp(-1.5, 1.5);
            t.actions.push(ak);
        }
        let d = ((goal[0] - pos[0]).powi(2) + (goal[1] - pos[1]).powi(2)).sqrt();
        t.obs.extend_from_slice(&observe(pos, goal));
        t.rewards.push(StepRewards {
            robot: -d,
            truth: -d,
            task: -d,
            ..StepRewards::default()
        });
        ret -= d;
    }
    let last_d = -t.rewards.last().map(|r| r.task).unwrap_or(0.0);
    t.outcome = Outcome {
        steps: horizon,
        truncated: true,
        success: last_d < 0.05,
        return_truth: ret,
        return_task: ret,
        return_robot: ret,
        ..Outcome::default()
    };
    t
}
