//! The RL backbones, each in one file that reads like its paper: SAC (PEBBLE's, with its
//! replay buffer) and PPO (PrefPPO's). They know nothing of preferences or of the run:
//! SAC asks its caller for each minibatch's reward, PPO is handed each rollout's.

pub mod ppo;
pub mod replay;
pub mod sac;
