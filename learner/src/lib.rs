//! The learner: the RL backbones (SAC and PPO, each in one file that reads like its
//! paper), preference learning (the reward ensemble, query selection, the k-NN
//! state-entropy bonus, the label store and the feedback loop), the service that runs
//! Algorithm 1 over Zenoh, and the run folder with its checkpoints.

pub mod backbone;
pub mod bench;
pub mod checkpoint;
pub mod config;
pub mod curve;
pub mod entropy;
pub mod evaluation;
pub mod feedback;
pub mod label_stats;
pub mod labels;
pub mod optim;
pub mod ppo;
pub mod query;
pub mod reward;
pub mod reward_model;
pub mod run_folder;
pub mod sac;
pub mod service;
pub mod state;
#[cfg(test)]
mod testutil;
