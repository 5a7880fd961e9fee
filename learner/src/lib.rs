//! The learner, in three rooms that depend downwards only (`run` -> `pref` -> `rl`):
//! - `rl`: the RL backbones, SAC and PPO, each in one file that reads like its paper;
//! - `pref`: preference learning: the reward ensemble, query selection, the k-NN
//!   state-entropy bonus, the label store and the feedback schedule;
//! - `run`: the service that runs Algorithm 1 over Zenoh, the learning curve, checkpoints
//!   and the run folder.
//!
//! `optim` (Adam) and `state` (saved generators) serve the rooms below; `bench` measures
//! them all.

pub mod bench;
pub mod optim;
pub mod pref;
pub mod rl;
pub mod run;
pub mod state;
#[cfg(test)]
mod testutil;
