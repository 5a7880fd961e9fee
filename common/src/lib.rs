//! Types shared by every pbrl process: the trajectory record an actor publishes, the wire
//! messages and their key expressions, the observation normaliser, the allocator's settings.

pub mod alloc;
pub mod bus;
pub mod connect;
pub mod flags;
pub mod keys;
pub mod nets;
pub mod normalize;
pub mod par;
pub mod trajectory;
pub mod wire;

pub use keys::Keys;
pub use normalize::RunningNorm;
pub use trajectory::{Outcome, Replay, StepRewards, Trajectory, TrajectoryError};
