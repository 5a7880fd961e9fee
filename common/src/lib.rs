//! Types shared by every pbrl process: the trajectory record an actor publishes (and, with
//! the actor-learner core, the wire messages, key expressions and networks).

pub mod trajectory;

pub use trajectory::{Outcome, Replay, StepRewards, Trajectory, TrajectoryError};
