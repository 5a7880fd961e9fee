//! The learner: the RL backbones (SAC now; PPO, the reward ensemble and query selection
//! come with their issues), each in one file that reads like its paper.

pub mod bench;
pub mod optim;
pub mod ppo;
pub mod run_folder;
pub mod sac;
pub mod service;
pub mod state;
