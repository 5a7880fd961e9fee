//! A policy judged on many episodes at once: each episode's measures of the task and of
//! what a person minds ([`EpisodeStats`]), over fixed seeds, spread over threads. Each
//! episode is run exactly as an actor runs the learner's evaluation episodes, so a run's
//! last checkpoint on the curve's seeds gives the curve's last row.

use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Mutex;

use anyhow::{Context, Result};
use pbrl_common::wire::Weights;
use pbrl_common::Trajectory;
use serde::Serialize;

use crate::config::{PreferenceWeights, WorldConfig};
use crate::policy::Policy;
use crate::runner::{episode, noise};
use crate::world::FeedingWorld;

/// The preference terms by name, in the world's order (`StepRewards::terms`).
pub const TERM_NAMES: [&str; 7] = [
    "distance",
    "eaten",
    "velocity",
    "force",
    "high_force",
    "food_hit",
    "food_velocity",
];

/// What one episode did, on the measures a person minds.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct EpisodeStats {
    pub seed: u64,
    pub steps: u32,
    /// At least the world's success fraction of the food was eaten.
    pub success: bool,
    /// Sums of the ground truth r, the preference reward r_H and the task reward r_task.
    pub return_truth: f64,
    pub return_human: f64,
    pub return_task: f64,
    /// Each preference term's part of r_H over the episode: w_i times the sum of term i
    /// (the world's weights of the person evaluated for), in [`TERM_NAMES`] order; they add
    /// up to `return_human` with `taste`.
    pub terms: [f64; 7],
    /// The part of r_H from the person's taste that no comfort feature names (where the
    /// spoon comes from, bites; `Taste`): r_H less the seven weighted terms. 0 for most.
    pub taste: f64,
    /// Food particles eaten, spilled and that touched the person, of `food`.
    pub eaten: u32,
    pub spilled: u32,
    pub on_person: u32,
    pub food: u32,
    /// The spoon's closest approach to the mouth (m), its top speed (m/s) and the peak
    /// force of arm and spoon on the person (N).
    pub closest_m: f64,
    pub top_speed: f64,
    pub peak_force: f64,
}

impl EpisodeStats {
    /// The measures of a feeding trajectory, its terms weighted by `w`.
    pub fn of(t: &Trajectory, w: &PreferenceWeights) -> Self {
        let w = w.as_array();
        let mut terms = [0f64; 7];
        let (mut top_speed, mut peak_force) = (0f64, 0f64);
        // NOTE: the first observation holds spoon minus mouth at 7..10 (`Task::goal_obs`);
        // after each step the task reward is -d.
        let d0 = t.obs.get(7..10).map_or(f64::INFINITY, |v| {
            v.iter().map(|x| (*x as f64).powi(2)).sum::<f64>().sqrt()
        });
        let mut closest = d0;
        let mut taste = 0f64;
        for r in &t.rewards {
            let (mut named, mut size) = (0f64, 1f64);
            for (i, term) in r.terms.iter().enumerate() {
                let part = w[i] as f64 * *term as f64;
                terms[i] += part;
                named += part;
                size += part.abs();
            }
            // NOTE: r_H is kept in f32; what is left within its rounding is not taste.
            let left = r.human as f64 - named;
            if left.abs() > 4.0 * f32::EPSILON as f64 * (size + r.human.abs() as f64) {
                taste += left;
            }
            // NOTE: C_v = -(EE speed), C_f = -(force on the person), unweighted.
            top_speed = top_speed.max(r.terms[2].abs() as f64);
            peak_force = peak_force.max(r.terms[3].abs() as f64);
            closest = closest.min(-r.task as f64);
        }
        let o = &t.outcome;
        Self {
            seed: t.seed,
            steps: o.steps,
            success: o.success,
            return_truth: o.return_truth as f64,
            return_human: o.return_human as f64,
            return_task: o.return_task as f64,
            terms,
            taste,
            eaten: o.eaten,
            spilled: o.spilled,
            on_person: o.hits,
            food: o.food,
            closest_m: closest,
            top_speed,
            peak_force,
        }
    }
}

/// How episodes are acted.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Acting {
    /// The policy's mean action (the curve's evaluation).
    Mean,
    /// Sampled actions, the noise drawn from each episode's seed (as in training).
    Sampled,
}

/// One episode of `policy` in `world` from `seed`, acted as an actor's evaluation acts it
/// (the trajectory keeps its replay data: [`crate::replay`] draws it).
pub fn episode_with(
    policy: &Policy,
    world: &mut FeedingWorld,
    seed: u64,
    acting: Acting,
) -> Result<Trajectory> {
    // NOTE: as the actor's evaluation: the mean action draws no noise.
    let mut rng = noise(seed);
    episode(Some(world), policy, seed, &mut rng, acting == Acting::Mean)
        .with_context(|| format!("episode of seed {seed}"))
}

/// Run `weights`' policy on every seed in `world` over `threads` threads (each its own
/// world and policy; results in seed order, the same whatever the thread count).
/// `done` is called after each episode (a progress bar).
pub fn evaluate_seeds(
    weights: &Weights,
    world: &WorldConfig,
    seeds: &[u64],
    acting: Acting,
    threads: usize,
    done: &(dyn Fn() + Sync),
) -> Result<Vec<EpisodeStats>> {
    let next = AtomicUsize::new(0);
    let out: Mutex<Vec<Option<EpisodeStats>>> = Mutex::new(vec![None; seeds.len()]);
    let threads = threads.clamp(1, seeds.len().max(1));
    std::thread::scope(|scope| -> Result<()> {
        let workers: Vec<_> = (0..threads)
            .map(|_| {
                scope.spawn(|| -> Result<()> {
                    let policy = Policy::from_weights(weights)?;
                    let mut w =
                        FeedingWorld::new(world.clone()).context("building the feeding world")?;
                    loop {
                        let k = next.fetch_add(1, Ordering::Relaxed);
                        let Some(&seed) = seeds.get(k) else {
                            return Ok(());
                        };
                        let t = episode_with(&policy, &mut w, seed, acting)?;
                        let s = EpisodeStats::of(&t, &world.profile.weights);
                        out.lock().unwrap_or_else(|e| e.into_inner())[k] = Some(s);
                        done();
                    }
                })
            })
            .collect();
        for h in workers {
            // NOTE: a worker that panicked is reported as an error, not re-raised.
            h.join()
                .map_err(|_| anyhow::anyhow!("an evaluation thread panicked"))??;
        }
        Ok(())
    })?;
    out.into_inner()
        .unwrap_or_else(|e| e.into_inner())
        .into_iter()
        .enumerate()
        .map(|(k, s)| s.with_context(|| format!("episode {k} was not run")))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::controller::Controller;
    use crate::rollout::run_episode;

    #[test]
    fn the_terms_add_up_to_the_preference_return_and_the_measures_are_the_episodes() {
        let cfg = WorldConfig::default();
        let mut world = FeedingWorld::new(cfg.clone()).unwrap();
        let mut c = Controller::new(crate::controller::ControllerKind::Scripted);
        let t = run_episode(&mut world, &mut c, 3).unwrap();
        let s = EpisodeStats::of(&t, &cfg.profile.weights);
        let sum: f64 = s.terms.iter().sum();
        assert!(
            (sum - s.return_human).abs() < 1e-3 * (1.0 + s.return_human.abs()),
            "terms {:?} add to {sum}, r_H {}",
            s.terms,
            s.return_human
        );
        let speeds: Vec<f32> = t.rewards.iter().map(|r| -r.terms[2]).collect();
        assert_eq!(
            s.top_speed,
            speeds.iter().cloned().fold(0.0, f32::max) as f64
        );
        let d: Vec<f64> = t.rewards.iter().map(|r| -r.task as f64).collect();
        assert!(s.closest_m <= d.iter().cloned().fold(f64::INFINITY, f64::min));
        assert!(s.closest_m > 0.0 && s.closest_m.is_finite());
        assert_eq!((s.eaten, s.food), (t.outcome.eaten, t.outcome.food));
    }
}
