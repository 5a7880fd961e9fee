//! The actor: the rapier3d feeding world (`shared/feeding.md`), the controllers that act in
//! it, episode rollouts into trajectory records, and the `pbrl env` commands.

pub mod config;
pub mod kinematics;
pub mod people;
pub mod point;
pub mod policy;
pub mod runner;
pub mod scene;
pub mod world;

pub use config::{Profile, WorldConfig};
pub use world::{FeedingWorld, Step, WorldError, ACT_DIM, OBS_DIM};
pub mod cli;
pub mod controller;
pub mod evaluate;
pub mod render;
pub mod replay;
pub mod rollout;
