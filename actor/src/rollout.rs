//! One episode into a trajectory record.

use nalgebra::Isometry3;
use pbrl_common::trajectory::TRAJECTORY_FORMAT;
use pbrl_common::{Outcome, Replay, Trajectory};

use crate::controller::Controller;
use crate::world::{FeedingWorld, WorldError, ACT_DIM, OBS_DIM};

fn pose7(iso: &Isometry3<f64>) -> [f32; 7] {
    let t = iso.translation.vector;
    let r = iso.rotation.coords;
    [t.x, t.y, t.z, r.x, r.y, r.z, r.w].map(|x| x as f32)
}

fn snapshot(world: &FeedingWorld, replay: &mut Replay) -> Result<(), WorldError> {
    replay.spoon.push(pose7(&world.frames()?.spoon));
    replay.head.push(pose7(&world.head()?));
    replay
        .mouth
        .push(world.mouth()?.coords.map(|x| x as f32).into());
    replay.joints.push(world.joints()?.map(|x| x as f32));
    for p in world.food_positions()? {
        replay.food.push(p.coords.map(|x| x as f32).into());
    }
    Ok(())
}

/// Reset `world` with `seed` and run `controller` for a whole episode.
pub fn run_episode(
    world: &mut FeedingWorld,
    controller: &mut Controller,
    seed: u64,
) -> Result<Trajectory, WorldError> {
    controller.reset(seed);
    run_episode_with(world, seed, |w, _| controller.act(w))
}

/// Reset `world` with `seed` and run a whole episode with `act` (the world and its newest
/// observation to an action).
pub fn run_episode_with(
    world: &mut FeedingWorld,
    seed: u64,
    mut act: impl FnMut(&FeedingWorld, &[f32]) -> Result<[f32; ACT_DIM], WorldError>,
) -> Result<Trajectory, WorldError> {
    let obs = world.reset(seed)?;
    let steps = world.config().episode_steps as usize;
    let n_food = world.config().food_count;
    let mut replay = Replay {
        base: pose7(&world.base()?),
        large_body: world.person()?.large,
        bowl: world.bowl()?.map(|x| x as f32),
        n_food,
        ..Replay::default()
    };
    snapshot(world, &mut replay)?;
    let mut t = Trajectory {
        format: TRAJECTORY_FORMAT,
        seed,
        policy_version: 0,
        obs_dim: OBS_DIM as u32,
        act_dim: ACT_DIM as u32,
        obs: Vec::with_capacity((steps + 1) * OBS_DIM),
        actions: Vec::with_capacity(steps * ACT_DIM),
        rewards: Vec::with_capacity(steps),
        outcome: Outcome {
            food: n_food,
            ..Outcome::default()
        },
        replay: None,
    };
    t.obs.extend_from_slice(&obs);
    loop {
        let last = t.obs.len() - OBS_DIM;
        let action = act(world, &t.obs[last..])?;
        let step = world.step(&action)?;
        snapshot(world, &mut replay)?;
        t.obs.extend_from_slice(&step.obs);
        t.actions.extend_from_slice(&action);
        t.rewards.push(step.rewards);
        let o = &mut t.outcome;
        o.steps += 1;
        o.return_truth += step.rewards.truth;
        o.return_human += step.rewards.human;
        o.return_robot += step.rewards.robot;
        o.return_task += step.rewards.task;
        o.eaten = step.food.eaten_total;
        o.spilled = step.food.spilled_total;
        o.hits = step.food.hits_total;
        o.success = step.success;
        o.terminated = step.terminated;
        o.truncated = step.truncated;
        if step.terminated || step.truncated {
            break;
        }
    }
    replay.food_outcome = world.food_outcomes()?;
    t.replay = Some(replay);
    Ok(t)
}
