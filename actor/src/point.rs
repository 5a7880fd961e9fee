//! A point that must reach a goal on a plane: a task small enough for an RL backbone to
//! learn in seconds, for tests. Observation: position and goal minus position (4);
//! action: a velocity (2), clipped to [-1, 1].
//!
//! Rewards, shaped like feeding's: the task reward r_task = -d (minus the distance to the
//! goal after the step), and a preference term the task reward does not hold, "arrive and
//! keep still": r_H = 1 - |a|^2 / 2 for each step that ends within [`POINT_NEAR`] of the
//! goal, 0 elsewhere. The ground truth is r = r_task + r_H; success is ending within
//! 0.05 of the goal.

use pbrl_common::trajectory::TRAJECTORY_FORMAT;
use pbrl_common::{Outcome, StepRewards, Trajectory};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

pub const POINT_OBS: usize = 4;
pub const POINT_ACT: usize = 2;
/// Distance moved per step at full action, per axis.
const SPEED: f32 = 0.1;
/// The preference term pays only within this distance of the goal.
pub const POINT_NEAR: f32 = 0.15;

/// The preference term of one step that ends at distance `d` after action `a` (clipped).
pub fn point_preference(d: f32, a: &[f32]) -> f32 {
    if d < POINT_NEAR {
        1.0 - 0.5 * a.iter().map(|x| x * x).sum::<f32>()
    } else {
        0.0
    }
}

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
    let (mut ret, mut human) = (0.0, 0.0);
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
        let n = t.actions.len();
        let h = point_preference(d, &t.actions[n - POINT_ACT..]);
        t.rewards.push(StepRewards {
            robot: -d,
            human: h,
            truth: h - d,
            task: -d,
            ..StepRewards::default()
        });
        ret -= d;
        human += h;
    }
    let last_d = -t.rewards.last().map(|r| r.task).unwrap_or(0.0);
    t.outcome = Outcome {
        steps: horizon,
        truncated: true,
        success: last_d < 0.05,
        return_truth: ret + human,
        return_human: human,
        return_task: ret,
        return_robot: ret,
        ..Outcome::default()
    };
    t
}
