//! Controllers that act in the feeding world without learning: a scripted feeder, a random
//! policy and a zero policy. They give the task's reference points (what solving it and
//! what not trying look like).

use nalgebra::{Point3, Vector3, Vector6};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::kinematics::{dls_velocity_within_limits, posture_pull, NJ};
use crate::world::{FeedingWorld, WorldError, ACT_DIM};

/// Which controller to run.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum ControllerKind {
    /// A slow Jacobian reach to the mouth that keeps the spoon level.
    Scripted,
    /// Uniform random actions in [-1, 1].
    Random,
    /// All-zero actions (hold still).
    Zero,
}

/// The scripted feeder: reach a point in front of the mouth, then move in along the face's
/// normal, keeping the spoon at its start orientation.
#[derive(Clone, Debug)]
pub struct Scripted {
    /// Distance in front of the mouth of the first waypoint (m).
    pub approach: f64,
    /// Distance in front of the mouth where the spoon stops (m; negative goes past it).
    pub stop: f64,
    /// Top speed of the spoon on the way to the first waypoint (m/s).
    pub max_speed: f64,
    /// Top speed of the spoon from the waypoint in to the mouth (m/s).
    pub final_speed: f64,
    /// Proportional gain from position error to spoon velocity (1/s).
    pub gain: f64,
    near_mouth: bool,
}

impl Default for Scripted {
    fn default() -> Self {
        Self {
            approach: 0.06,
            stop: 0.02,
            max_speed: 0.08,
            final_speed: 0.05,
            gain: 1.5,
            near_mouth: false,
        }
    }
}

impl Scripted {
    /// A feeder that stops `stop` metres in front of the mouth (negative: pushes past it
    /// into the face), coming in from the waypoint at up to `final_speed` m/s.
    pub fn reaching(stop: f64, final_speed: f64) -> Self {
        Self {
            stop,
            final_speed,
            ..Self::default()
        }
    }

    /// The action for the world's current state.
    pub fn act(&mut self, world: &FeedingWorld) -> Result<[f32; ACT_DIM], WorldError> {
        let cfg = world.config();
        let frames = world.frames()?;
        let mouth = world.mouth()?;
        let forward = world.head()?.rotation * -Vector3::y();
        let spoon: Point3<f64> = frames.spoon.translation.vector.into();
        let waypoint = mouth + forward * self.approach;
        if !self.near_mouth && (spoon - waypoint).norm() < 0.015 {
            self.near_mouth = true;
        }
        let target = if self.near_mouth {
            mouth + forward * self.stop
        } else {
            waypoint
        };
        let top = if self.near_mouth {
            self.final_speed
        } else {
            self.max_speed
        };
        let mut v = (target - spoon) * self.gain;
        if v.norm() > top {
            v *= top / v.norm();
        }
        let level = world.start_spoon()?.rotation;
        let w = (level * frames.spoon.rotation.inverse()).scaled_axis() * 2.0;
        let twist = Vector6::new(v.x, v.y, v.z, w.x, w.y, w.z);
        let (q, q0) = (world.joints()?, world.start_joints()?);
        let pull = posture_pull(&q, &q0, 0.5, 0.1);
        let dq =
            dls_velocity_within_limits(&frames.spoon_jacobian(), &twist, 0.02, &pull, &q, 0.02);
        // A fast joint covers 1 - (1 - gain)^substeps of its target offset per env step.
        let per_step = 1.0 - (1.0 - cfg.motor_gain as f64).powi(cfg.substeps as i32);
        let to_action = cfg.control_dt() as f64 / (cfg.action_scale as f64 * per_step);
        let mut a: [f64; NJ] = dq.map(|x| x * to_action);
        let peak = a.iter().fold(0.0f64, |m, x| m.max(x.abs()));
        if peak > 1.0 {
            a = a.map(|x| x / peak);
        }
        Ok(a.map(|x| x as f32))
    }
}

/// A controller of one of the three kinds.
#[derive(Clone, Debug)]
pub enum Controller {
    Scripted(Scripted),
    /// Its random stream restarts from each episode's seed, so an episode's actions depend
    /// on its seed alone.
    Random(Box<ChaCha8Rng>),
    Zero,
}

/// Mixed into the episode seed for the random controller's stream, so that it differs from
/// the world's own stream of the same seed.
const RANDOM_SALT: u64 = 0x5eed_ac71_0c0f_fee5;

impl Controller {
    /// A fresh controller.
    pub fn new(kind: ControllerKind) -> Self {
        match kind {
            ControllerKind::Scripted => Self::Scripted(Scripted::default()),
            ControllerKind::Random => {
                Self::Random(Box::new(ChaCha8Rng::seed_from_u64(RANDOM_SALT)))
            }
            ControllerKind::Zero => Self::Zero,
        }
    }

    /// Start an episode of seed `episode_seed`: forget the scripted feeder's phase, restart
    /// the random stream.
    pub fn reset(&mut self, episode_seed: u64) {
        match self {
            Self::Scripted(s) => s.near_mouth = false,
            Self::Random(rng) => **rng = ChaCha8Rng::seed_from_u64(episode_seed ^ RANDOM_SALT),
            Self::Zero => {}
        }
    }

    /// The action for the world's current state.
    pub fn act(&mut self, world: &FeedingWorld) -> Result<[f32; ACT_DIM], WorldError> {
        match self {
            Self::Scripted(s) => s.act(world),
            Self::Random(rng) => Ok(std::array::from_fn(|_| rng.random_range(-1.0..=1.0))),
            Self::Zero => Ok([0.0; ACT_DIM]),
        }
    }
}
