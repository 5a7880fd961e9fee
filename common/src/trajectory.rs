//! The trajectory record: one whole episode as an actor publishes it.
//!
//! Everything is `f32` and flattened row-major (`obs` holds `steps + 1` rows of `obs_dim`
//! numbers, `actions` holds `steps` rows of `act_dim`), so a 200-step feeding episode with
//! replay data is about 60 KB in bincode.

use serde::{Deserialize, Serialize};

/// Version of the record's layout; bumped whenever a field changes meaning or order.
pub const TRAJECTORY_FORMAT: u16 = 1;

/// The seven preference terms of the paper's Eq. 6, in the order of the weight vector `w`:
/// `[C_d, C_e, C_v, C_f, C_hf, C_fd, C_fdv]`.
pub const PREFERENCE_TERMS: [&str; 7] = ["C_d", "C_e", "C_v", "C_f", "C_hf", "C_fd", "C_fdv"];

/// How many designer-computed comfort features a step has ([`StepRewards::features`]).
pub const FEATURES: usize = 6;

/// Their names, in order.
pub const FEATURE_NAMES: [&str; FEATURES] = [
    "eaten",
    "ee_speed",
    "force",
    "spoon_force_high",
    "food_hits",
    "eaten_speed",
];

/// Every reward part of one env step, kept apart.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct StepRewards {
    /// Robot task reward r_R = -d - 0.01 ||a|| + 20 eaten - 5 spilled.
    pub robot: f32,
    /// The preference terms `[C_d, C_e, C_v, C_f, C_hf, C_fd, C_fdv]` (unweighted).
    pub terms: [f32; 7],
    /// Human preference reward r_H = w . terms.
    pub human: f32,
    /// Ground truth r = r_R + r_H (what the scripted teacher and the curves use).
    pub truth: f32,
    /// Sketchy task reward r_task = -d (paper Eq. 7).
    pub task: f32,
}

impl StepRewards {
    /// The designer-computed comfort features of this step, what a reward model may read
    /// beside the observation (`--reward-features`): the measurements behind the paper's
    /// preference terms but C_d (which the observation holds), unweighted and as
    /// magnitudes: food eaten, EE speed, contact force on the person, the spoon's force
    /// where it reaches the profile's high-force threshold (10 N by default; the spoon's
    /// force is also the observation's last number, one step later), new food hits on the
    /// person, the summed speed of the food eaten. They say what happened, not how a person weighs it: the weights, and any
    /// taste outside them, are what the labels teach. Zero on tasks without them.
    pub fn features(&self) -> [f32; FEATURES] {
        let mut f = [0f32; FEATURES];
        f.iter_mut()
            .zip(&self.terms[1..])
            .for_each(|(f, t)| *f = t.abs());
        f
    }
}

/// How an episode ended and what it achieved.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Outcome {
    /// Env steps taken.
    pub steps: u32,
    /// The episode reached a terminal state of the task.
    pub terminated: bool,
    /// The episode was cut by the time limit.
    pub truncated: bool,
    /// Food particles that reached the mouth.
    pub eaten: u32,
    /// Food particles spilled (farther than the spill distance from the spoon).
    pub spilled: u32,
    /// Food particles that touched the person.
    pub hits: u32,
    /// Food particles at the start.
    pub food: u32,
    /// At least the success fraction of the food was eaten.
    pub success: bool,
    /// Sum of the ground-truth reward r.
    pub return_truth: f32,
    /// Sum of r_H (the preference return).
    pub return_human: f32,
    /// Sum of r_R.
    pub return_robot: f32,
    /// Sum of r_task.
    pub return_task: f32,
}

/// What a person needs to watch an episode again: poses per step (`steps + 1` rows, the
/// first is the state after reset). Poses are `[x, y, z, qx, qy, qz, qw]` in the world frame.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Replay {
    /// The robot base pose (fixed for the episode).
    pub base: [f32; 7],
    /// The person's body: true for the larger body.
    pub large_body: bool,
    /// Centre of the bowl on the table.
    pub bowl: [f32; 3],
    /// Spoon pose per step.
    pub spoon: Vec<[f32; 7]>,
    /// Head pose per step.
    pub head: Vec<[f32; 7]>,
    /// Mouth target per step.
    pub mouth: Vec<[f32; 3]>,
    /// Joint angles per step.
    pub joints: Vec<[f32; 7]>,
    /// Food centres per step, `food` rows each (row-major: step, particle).
    pub food: Vec<[f32; 3]>,
    /// Number of food particles (the row length of `food`).
    pub n_food: u32,
    /// What became of each particle at the end: 0 on the spoon, 1 eaten, 2 spilled.
    pub food_outcome: Vec<u8>,
}

/// One whole episode.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Trajectory {
    /// Layout version, [`TRAJECTORY_FORMAT`] when written by this build.
    pub format: u16,
    /// Seed of the episode's reset.
    pub seed: u64,
    /// Version of the policy that acted (0 for scripted controllers).
    pub policy_version: u64,
    /// Length of one observation.
    pub obs_dim: u32,
    /// Length of one action.
    pub act_dim: u32,
    /// `steps + 1` observations, flattened.
    pub obs: Vec<f32>,
    /// `steps` actions as the policy gave them (before clipping), flattened.
    pub actions: Vec<f32>,
    /// Reward parts per step.
    pub rewards: Vec<StepRewards>,
    /// How it ended.
    pub outcome: Outcome,
    /// Replay data (absent for tasks with nothing to draw).
    pub replay: Option<Replay>,
}

/// Why a trajectory could not be decoded or is inconsistent.
#[derive(Debug, thiserror::Error)]
pub enum TrajectoryError {
    #[error("trajectory does not decode: {0}")]
    Decode(String),
    #[error("trajectory format {found} is not the supported format {expected}")]
    Format { found: u16, expected: u16 },
    #[error("trajectory field {field} has {found} numbers, expected {expected}")]
    Shape {
        field: &'static str,
        found: usize,
        expected: usize,
    },
    #[error("trajectory field {field} holds a non-finite value at index {index}")]
    NonFinite { field: &'static str, index: usize },
}

impl Trajectory {
    /// Number of env steps.
    pub fn steps(&self) -> usize {
        self.rewards.len()
    }

    /// Observation `t` (0..=steps).
    pub fn obs_at(&self, t: usize) -> &[f32] {
        let d = self.obs_dim as usize;
        &self.obs[t * d..(t + 1) * d]
    }

    /// Action `t` (0..steps).
    pub fn action_at(&self, t: usize) -> &[f32] {
        let d = self.act_dim as usize;
        &self.actions[t * d..(t + 1) * d]
    }

    /// Every step's [`StepRewards::features`], `steps` rows of [`FEATURES`], flattened.
    pub fn features(&self) -> Vec<f32> {
        self.rewards.iter().flat_map(|r| r.features()).collect()
    }

    /// Encode with bincode (standard configuration).
    pub fn encode(&self) -> Vec<u8> {
        // NOTE: encoding plain data into a Vec cannot fail (no I/O, no size limit).
        bincode::serde::encode_to_vec(self, bincode::config::standard())
            .expect("encoding a trajectory into memory cannot fail")
    }

    /// Decode and check shape, format and finiteness.
    pub fn decode(bytes: &[u8]) -> Result<Self, TrajectoryError> {
        let (t, _): (Trajectory, usize) =
            bincode::serde::decode_from_slice(bytes, bincode::config::standard())
                .map_err(|e| TrajectoryError::Decode(e.to_string()))?;
        t.validate()?;
        Ok(t)
    }

    /// Check that every field has the length its header says and holds finite numbers.
    pub fn validate(&self) -> Result<(), TrajectoryError> {
        if self.format != TRAJECTORY_FORMAT {
            return Err(TrajectoryError::Format {
                found: self.format,
                expected: TRAJECTORY_FORMAT,
            });
        }
        let steps = self.rewards.len();
        let check = |field, found, expected| {
            if found == expected {
                Ok(())
            } else {
                Err(TrajectoryError::Shape {
                    field,
                    found,
                    expected,
                })
            }
        };
        check("obs", self.obs.len(), (steps + 1) * self.obs_dim as usize)?;
        check("actions", self.actions.len(), steps * self.act_dim as usize)?;
        let finite = |field, xs: &[f32]| match xs.iter().position(|x| !x.is_finite()) {
            Some(index) => Err(TrajectoryError::NonFinite { field, index }),
            None => Ok(()),
        };
        finite("obs", &self.obs)?;
        finite("actions", &self.actions)?;
        for (i, r) in self.rewards.iter().enumerate() {
            let all = [r.robot, r.human, r.truth, r.task];
            if all.iter().chain(r.terms.iter()).any(|x| !x.is_finite()) {
                return Err(TrajectoryError::NonFinite {
                    field: "rewards",
                    index: i,
                });
            }
        }
        if let Some(rp) = &self.replay {
            if rp.n_food == 0 {
                return Err(TrajectoryError::Shape {
                    field: "replay.n_food",
                    found: 0,
                    expected: 1,
                });
            }
            let poses = rp.spoon.iter().chain(&rp.head).chain(&rp.joints).flatten();
            let points = rp.mouth.iter().chain(&rp.food).flatten();
            if poses.chain(points).any(|x| !x.is_finite()) {
                return Err(TrajectoryError::NonFinite {
                    field: "replay",
                    index: 0,
                });
            }
            check("replay.spoon", rp.spoon.len(), steps + 1)?;
            check("replay.head", rp.head.len(), steps + 1)?;
            check("replay.mouth", rp.mouth.len(), steps + 1)?;
            check("replay.joints", rp.joints.len(), steps + 1)?;
            check(
                "replay.food",
                rp.food.len(),
                (steps + 1) * rp.n_food as usize,
            )?;
            check(
                "replay.food_outcome",
                rp.food_outcome.len(),
                rp.n_food as usize,
            )?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tiny() -> Trajectory {
        Trajectory {
            format: TRAJECTORY_FORMAT,
            seed: 3,
            policy_version: 1,
            obs_dim: 2,
            act_dim: 1,
            obs: vec![0.0, 1.0, 2.0, 3.0],
            actions: vec![0.5],
            rewards: vec![StepRewards::default()],
            outcome: Outcome::default(),
            replay: None,
        }
    }

    #[test]
    fn round_trip() {
        let t = tiny();
        let back = Trajectory::decode(&t.encode()).unwrap();
        assert_eq!(t, back);
        assert_eq!(back.obs_at(1), &[2.0, 3.0]);
    }

    #[test]
    fn refuses_wrong_shape_format_and_nan() {
        let mut t = tiny();
        t.obs.pop();
        assert!(matches!(
            Trajectory::decode(&t.encode()),
            Err(TrajectoryError::Shape { field: "obs", .. })
        ));
        let mut t = tiny();
        t.format = 99;
        assert!(matches!(
            Trajectory::decode(&t.encode()),
            Err(TrajectoryError::Format { found: 99, .. })
        ));
        let mut t = tiny();
        t.actions[0] = f32::NAN;
        assert!(matches!(
            Trajectory::decode(&t.encode()),
            Err(TrajectoryError::NonFinite {
                field: "actions",
                ..
            })
        ));
        assert!(matches!(
            Trajectory::decode(&[1, 2, 3]),
            Err(TrajectoryError::Decode(_))
        ));
    }
}
