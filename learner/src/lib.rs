//! The learner: the RL backbones (SAC and PPO, each in one file that reads like its
//! paper), the service that trains them over Zenoh, the run folder with its checkpoints,
//! and the label store (the preference dataset D). The reward ensemble and query
//! selection come with their issues.

pub mod bench;
pub mod entropy;
pub mod labels;
pub mod optim;
pub mod ppo;
pub mod query;
pub mod run_folder;
pub mod sac;
pub mod service;
pub mod state;
#[cfg(test)]
mod testutil;
