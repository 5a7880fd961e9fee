//! The feeding world: reset, step, observation, food bookkeeping and rewards.
//!
//! How it is simulated:
//! - The food, the spoon, the arm's links, the person and the furniture live in a rapier3d
//!   world. The food is dynamic (with gravity); everything else is kinematic or fixed.
//! - The arm is simulated in joint space: each joint is a position motor with a torque cap
//!   (the original's PyBullet gain, force cap and damping) driving an effective inertia
//!   fitted so that the joints respond as the original's do (`feeding.md`, Action).
//!   Contacts of the arm and spoon with the person and furniture are solved on those joint
//!   velocities (a projected Gauss-Seidel over non-penetration constraints), which gives
//!   the contact forces the rewards need; the kinematic bodies then follow the joints.
//! - One env step is `substeps` physics substeps of `substep_dt`; the arm's targets are
//!   held over them.

mod arm;
mod build;

use nalgebra::{Isometry3, Point3, UnitQuaternion, Vector3};
use pbrl_common::StepRewards;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rapier3d::parry::query;
use rapier3d::parry::shape::Ball;
use rapier3d::prelude::*;

use crate::config::{BasePlacement, ConfigError, Taste, WorldConfig};
use crate::kinematics::{Arm, ArmFrames, JOINT_LIMITS, NJ};
use crate::scene::{self, Owner, Person};
use arm::{ContactRow, SpoonBox};

/// Length of the observation.
pub const OBS_DIM: usize = 25;
/// Length of the action.
pub const ACT_DIM: usize = NJ;

/// What went wrong in the world; every message names the offending value.
#[derive(Debug, thiserror::Error)]
pub enum WorldError {
    #[error("action has {found} numbers, expected {expected}")]
    ActionLength { found: usize, expected: usize },
    #[error("action[{index}] = {value} is not finite")]
    ActionNotFinite { index: usize, value: f32 },
    #[error("step called before reset")]
    NotReset,
    #[error("the episode ended after {steps} steps: call reset")]
    EpisodeOver { steps: u32 },
    #[error("reset with seed {seed} found no robot base from which IK reaches the start pose and the mouth ({tries} tries)")]
    ResetFailed { seed: u64, tries: u32 },
    #[error(transparent)]
    Config(#[from] ConfigError),
    #[error("the policy failed: {0}")]
    Policy(String),
}

/// Food counts: this step's and the episode's.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct FoodCounts {
    pub eaten: u32,
    pub spilled: u32,
    pub hits: u32,
    pub eaten_total: u32,
    pub spilled_total: u32,
    pub hits_total: u32,
}

/// The result of one env step.
#[derive(Clone, Debug, PartialEq)]
pub struct Step {
    pub obs: [f32; OBS_DIM],
    pub rewards: StepRewards,
    /// The task reached a terminal state. The feeding task has none (as the original):
    /// always false; kept apart from `truncated` all the same.
    pub terminated: bool,
    /// The time limit ended the episode.
    pub truncated: bool,
    pub food: FoodCounts,
    /// Enough food eaten so far for the episode to count as a success.
    pub success: bool,
    /// Total normal force of the spoon on the person (N), the largest over the step's
    /// substeps (observation entry 24, C_hf).
    pub spoon_force: f32,
    /// Total normal force of arm and spoon on the person (N), the largest over the step's
    /// substeps (C_f).
    pub robot_force: f32,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[repr(u8)]
enum FoodState {
    OnSpoon = 0,
    Eaten = 1,
    Spilled = 2,
}

struct Food {
    body: RigidBodyHandle,
    collider: ColliderHandle,
    state: FoodState,
    /// Counted as a hit on the person (once per particle).
    hit: bool,
    /// Touched the person during the current env step.
    touched: bool,
}

/// A static or moving obstacle for the arm's contact solver.
struct Obstacle {
    owner: Owner,
    pose: Pose,
    shape: SharedShape,
    sphere: (Point3<f64>, f64),
}

struct Head {
    rest: [f64; 3],
    /// Joint limits of the head (rad), after any impairment.
    limits: [f64; 3],
    angles: [f64; 3],
    tremor: [f64; 3],
    sign: f64,
    body: RigidBodyHandle,
}

struct Episode {
    seed: u64,
    base: Isometry3<f64>,
    person: Person,
    bowl: [f64; 3],
    q: [f64; NJ],
    qd: [f64; NJ],
    q_target: [f64; NJ],
    frames: ArmFrames,
    start_spoon: Isometry3<f64>,
    start_q: [f64; NJ],
    head: Head,
    phys: PhysicsWorld,
    links: [RigidBodyHandle; NJ],
    spoon: RigidBodyHandle,
    food: Vec<Food>,
    obstacles: Vec<Obstacle>,
    head_obstacle: usize,
    steps: u32,
    counts: FoodCounts,
    /// Food reached the mouth in the step before (a bite goes on).
    ate_last_step: bool,
}

/// The feeding world. `reset` draws a new episode from a seed; `step` advances it.
pub struct FeedingWorld {
    cfg: WorldConfig,
    arm: Arm,
    spoon_boxes: Vec<SpoonBox>,
    ep: Option<Episode>,
    /// Scratch space of the contact solver, kept to avoid allocating every substep.
    rows: Vec<ContactRow>,
}

fn to_pose(iso: &Isometry3<f64>) -> Pose {
    let t = iso.translation.vector;
    let r = iso.rotation.coords;
    Pose::from_parts(
        Vector::new(t.x as f32, t.y as f32, t.z as f32),
        Rotation::from_xyzw(r.x as f32, r.y as f32, r.z as f32, r.w as f32),
    )
}

fn to_point(v: Vector) -> Point3<f64> {
    Point3::new(v.x as f64, v.y as f64, v.z as f64)
}

/// Wrap an angle to [-pi, pi].
pub fn wrap_angle(a: f64) -> f64 {
    let two_pi = std::f64::consts::TAU;
    let w = (a + std::f64::consts::PI).rem_euclid(two_pi) - std::f64::consts::PI;
    if w < -std::f64::consts::PI {
        w + two_pi
    } else {
        w
    }
}

impl FeedingWorld {
    /// A world for `cfg`; the config is checked here.
    pub fn new(cfg: WorldConfig) -> Result<Self, WorldError> {
        cfg.validate()?;
        let spoon_boxes = scene::spoon_boxes(&cfg)
            .iter()
            .map(|s| {
                let (pose, shape) = build::parry_shape(s);
                SpoonBox {
                    pose,
                    shape,
                    sphere: s.bounding_sphere(),
                }
            })
            .collect();
        Ok(Self {
            cfg,
            arm: Arm::baxter(),
            spoon_boxes,
            ep: None,
            rows: Vec::new(),
        })
    }

    pub fn config(&self) -> &WorldConfig {
        &self.cfg
    }

    pub fn arm(&self) -> &Arm {
        &self.arm
    }

    fn ep(&self) -> Result<&Episode, WorldError> {
        self.ep.as_ref().ok_or(WorldError::NotReset)
    }

    /// Start a new episode from `seed` and return its first observation: sample the
    /// person and the start, place the arm, build the scene, let the food settle.
    pub fn reset(&mut self, seed: u64) -> Result<[f32; OBS_DIM], WorldError> {
        // NOTE: a failed reset must not leave the previous episode steppable.
        self.ep = None;
        let cfg = &self.cfg;
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let draw = build::sample(cfg, &self.arm, &mut rng);
        let placed = build::place_arm(cfg, &self.arm, &self.spoon_boxes, &draw, &mut rng).ok_or(
            WorldError::ResetFailed {
                seed,
                tries: match cfg.base {
                    BasePlacement::Nominal => cfg.ik_tries,
                    BasePlacement::Random => cfg.base_tries.saturating_mul(cfg.ik_tries),
                },
            },
        )?;
        self.ep = Some(build::episode(cfg, &self.spoon_boxes, seed, draw, placed));
        // Let the food settle on the still spoon; hits during settling do not count.
        for _ in 0..self.cfg.settle_substeps {
            self.substep();
        }
        let ep = self.ep.as_mut().expect("episode was set just above");
        for f in &mut ep.food {
            f.touched = false;
        }
        Ok(self.observation(0.0))
    }

    /// One physics substep: head, arm motors and contacts, then rapier.
    /// Returns the spoon's and the whole robot's normal force on the person (N).
    fn substep(&mut self) -> (f64, f64) {
        let cfg = &self.cfg;
        let dt = cfg.substep_dt as f64;
        let ep = self.ep.as_mut().expect("substep runs inside an episode");
        let head_pose = ep.move_head(cfg);
        let (m_inv, qd) = arm::dynamics(cfg, &ep.frames, &ep.qd);
        let error: [f64; NJ] = std::array::from_fn(|i| ep.q_target[i] - ep.q[i]);
        let mut rows = std::mem::take(&mut self.rows);
        arm::contact_rows(
            cfg,
            &self.spoon_boxes,
            &ep.frames,
            &ep.obstacles,
            &m_inv,
            &mut rows,
        );
        let (qd, f_spoon, f_robot) = arm::solve(cfg, &error, &m_inv, qd, &mut rows);
        self.rows = rows;
        ep.qd = qd.into();

        // Integrate, never past the limits.
        for ((q, qd), [lo, hi]) in ep.q.iter_mut().zip(&mut ep.qd).zip(JOINT_LIMITS) {
            *q += dt * *qd;
            if *q <= lo {
                *q = lo;
                *qd = qd.max(0.0);
            } else if *q >= hi {
                *q = hi;
                *qd = qd.min(0.0);
            }
        }
        ep.frames = self.arm.frames(&ep.base, &ep.q);
        let bodies = &mut ep.phys.bodies;
        for (i, h) in ep.links.iter().enumerate() {
            bodies[*h].set_next_kinematic_position(to_pose(&ep.frames.joints[i]));
        }
        bodies[ep.spoon].set_next_kinematic_position(to_pose(&ep.frames.spoon));
        bodies[ep.head.body].set_next_kinematic_position(to_pose(&head_pose));
        ep.phys.step();
        ep.mark_touches();
        (f_spoon, f_robot)
    }

    /// Advance one env step with `action` (7 numbers; clipped to [-1, 1]).
    pub fn step(&mut self, action: &[f32]) -> Result<Step, WorldError> {
        if action.len() != ACT_DIM {
            return Err(WorldError::ActionLength {
                found: action.len(),
                expected: ACT_DIM,
            });
        }
        if let Some((index, &value)) = action.iter().enumerate().find(|(_, a)| !a.is_finite()) {
            return Err(WorldError::ActionNotFinite { index, value });
        }
        let ep = self.ep.as_mut().ok_or(WorldError::NotReset)?;
        if ep.steps >= self.cfg.episode_steps {
            return Err(WorldError::EpisodeOver { steps: ep.steps });
        }
        let scale = self.cfg.action_scale as f64;
        for i in 0..NJ {
            let a = (action[i] as f64).clamp(-1.0, 1.0);
            let [lo, hi] = JOINT_LIMITS[i];
            ep.q_target[i] = (ep.q[i] + scale * a).clamp(lo, hi);
        }
        ep.head.sign = -ep.head.sign;
        let before = ep.counts;
        let (mut f_spoon, mut f_robot) = (0.0, 0.0);
        for _ in 0..self.cfg.substeps {
            // NOTE: the original reads contact forces once per step, at its last substep; we
            // keep the largest over the step's substeps so that a short hit is never missed.
            let (s, r) = self.substep();
            f_spoon = f_spoon.max(s);
            f_robot = f_robot.max(r);
        }
        let cfg = &self.cfg;
        let ep = self.ep.as_mut().expect("checked above");
        let head = head_pose(&ep.person, &ep.head.angles);
        let mouth = head * Point3::from(ep.person.mouth_local);
        let spoon = to_pose(&ep.frames.spoon);
        let eaten_speed = ep.food_step(cfg, &self.spoon_boxes, &spoon, &mouth);
        ep.steps += 1;
        let counts = FoodCounts {
            eaten: ep.counts.eaten_total - before.eaten_total,
            spilled: ep.counts.spilled_total - before.spilled_total,
            hits: ep.counts.hits_total - before.hits_total,
            ..ep.counts
        };
        let felt = Felt {
            head,
            mouth,
            spoon,
            eaten_speed,
            f_spoon,
            f_robot,
        };
        let rewards = ep.rewards(cfg, action, &counts, &felt);
        ep.ate_last_step = counts.eaten > 0;
        let truncated = ep.steps >= cfg.episode_steps;
        let success = counts.eaten_total >= cfg.food_for_success();
        Ok(Step {
            obs: self.observation(f_spoon),
            rewards,
            terminated: false,
            truncated,
            food: counts,
            success,
            spoon_force: f_spoon as f32,
            robot_force: f_robot as f32,
        })
    }

    fn observation(&self, spoon_force: f64) -> [f32; OBS_DIM] {
        let ep = self.ep.as_ref().expect("observation inside an episode");
        let inv = ep.base.inverse();
        let spoon = inv * ep.frames.spoon;
        let head = inv * head_pose(&ep.person, &ep.head.angles);
        let rel = inv.rotation * (ep.frames.spoon.translation.vector - mouth_of(ep).coords);
        let mut o = [0.0f32; OBS_DIM];
        let mut put = |at: usize, xs: &[f64]| {
            for (k, x) in xs.iter().enumerate() {
                o[at + k] = *x as f32;
            }
        };
        put(0, spoon.translation.vector.as_slice());
        put(3, spoon.rotation.coords.as_slice());
        put(7, rel.as_slice());
        put(10, &ep.q.map(wrap_angle));
        put(17, head.translation.vector.as_slice());
        put(20, head.rotation.coords.as_slice());
        put(24, &[spoon_force]);
        o
    }

    // ---- read access for controllers, replay and tests ----

    /// Joint angles.
    pub fn joints(&self) -> Result<[f64; NJ], WorldError> {
        Ok(self.ep()?.q)
    }

    /// Joint angles at the start of the episode.
    pub fn start_joints(&self) -> Result<[f64; NJ], WorldError> {
        Ok(self.ep()?.start_q)
    }

    /// Frames of the arm now.
    pub fn frames(&self) -> Result<&ArmFrames, WorldError> {
        Ok(&self.ep()?.frames)
    }

    /// The spoon pose at the start of the episode (the level pose a feeder keeps).
    pub fn start_spoon(&self) -> Result<Isometry3<f64>, WorldError> {
        Ok(self.ep()?.start_spoon)
    }

    /// The mouth target now.
    pub fn mouth(&self) -> Result<Point3<f64>, WorldError> {
        Ok(mouth_of(self.ep()?))
    }

    /// The head pose now.
    pub fn head(&self) -> Result<Isometry3<f64>, WorldError> {
        let ep = self.ep()?;
        Ok(head_pose(&ep.person, &ep.head.angles))
    }

    /// The robot base pose of this episode.
    pub fn base(&self) -> Result<Isometry3<f64>, WorldError> {
        Ok(self.ep()?.base)
    }

    /// The person of this episode.
    pub fn person(&self) -> Result<&Person, WorldError> {
        Ok(&self.ep()?.person)
    }

    /// The bowl centre of this episode.
    pub fn bowl(&self) -> Result<[f64; 3], WorldError> {
        Ok(self.ep()?.bowl)
    }

    /// Seed of this episode.
    pub fn seed(&self) -> Result<u64, WorldError> {
        Ok(self.ep()?.seed)
    }

    /// Env steps taken in this episode.
    pub fn steps(&self) -> Result<u32, WorldError> {
        Ok(self.ep()?.steps)
    }

    /// Centre of every food particle (eaten ones where they were eaten).
    pub fn food_positions(&self) -> Result<Vec<Point3<f64>>, WorldError> {
        let ep = self.ep()?;
        Ok(ep
            .food
            .iter()
            .map(|f| to_point(ep.phys.bodies[f.body].translation()))
            .collect())
    }

    /// What became of each food particle: 0 still on the spoon, 1 eaten, 2 spilled.
    pub fn food_outcomes(&self) -> Result<Vec<u8>, WorldError> {
        Ok(self.ep()?.food.iter().map(|f| f.state as u8).collect())
    }

    /// Food counts of the episode so far.
    pub fn food_counts(&self) -> Result<FoodCounts, WorldError> {
        Ok(self.ep()?.counts)
    }
}

/// What an env step's rewards are computed from, besides the action and the food.
struct Felt {
    head: Isometry3<f64>,
    mouth: Point3<f64>,
    spoon: Pose,
    /// Summed speed of the particles eaten this step.
    eaten_speed: f64,
    f_spoon: f64,
    f_robot: f64,
}

impl Episode {
    /// The head follows its (tremor) target through a weak position motor; its obstacle
    /// follows. Returns the head's new pose.
    fn move_head(&mut self, cfg: &WorldConfig) -> Isometry3<f64> {
        let gain = cfg.head_motor_gain as f64;
        for k in 0..3 {
            let lim = self.head.limits[k];
            let target =
                (self.head.rest[k] + self.head.sign * self.head.tremor[k]).clamp(-lim, lim);
            self.head.angles[k] += gain * (target - self.head.angles[k]);
        }
        let head_pose = head_pose(&self.person, &self.head.angles);
        let hc = head_pose * Point3::from(self.person.head_centre_local);
        let head_obstacle = &mut self.obstacles[self.head_obstacle];
        head_obstacle.pose =
            Pose::from_translation(Vector::new(hc.x as f32, hc.y as f32, hc.z as f32));
        head_obstacle.sphere.0 = hc;
        head_pose
    }

    /// Marks food touching the person; counted as hits once per env step, after eating.
    fn mark_touches(&mut self) {
        for f in self
            .food
            .iter_mut()
            .filter(|f| !f.hit && !f.touched && f.state != FoodState::Eaten)
        {
            let colliders = &self.phys.colliders;
            f.touched = self
                .phys
                .narrow_phase
                .contact_pairs_with(f.collider)
                .any(|pair| {
                    let other = if pair.collider1 == f.collider {
                        pair.collider2
                    } else {
                        pair.collider1
                    };
                    pair.has_any_active_contact() && colliders[other].user_data == build::PERSON_TAG
                });
        }
    }

    /// The food after an env step: eaten near the mouth, spilled far from the spoon, hits
    /// counted. Returns the summed speed of the particles eaten.
    fn food_step(
        &mut self,
        cfg: &WorldConfig,
        spoon_boxes: &[SpoonBox],
        spoon: &Pose,
        mouth: &Point3<f64>,
    ) -> f64 {
        let ball = Ball::new(cfg.food_radius);
        let mut eaten_speed = 0.0;
        for f in self
            .food
            .iter_mut()
            .filter(|f| f.state == FoodState::OnSpoon)
        {
            let body = &mut self.phys.bodies[f.body];
            let p = to_point(body.translation());
            if (p - mouth).norm() < cfg.eat_distance as f64 {
                f.state = FoodState::Eaten;
                self.counts.eaten_total += 1;
                eaten_speed += body.linvel().length() as f64;
                // NOTE: an eaten particle leaves the world but keeps its last position for
                // the replay.
                body.set_enabled(false);
                continue;
            }
            let ball_pose = Pose::from_translation(body.translation());
            let near = spoon_boxes.iter().any(|b| {
                query::distance(&(*spoon * b.pose), &*b.shape, &ball_pose, &ball)
                    .map(|d| d.distance <= cfg.spill_distance)
                    .unwrap_or(true)
            });
            if !near {
                f.state = FoodState::Spilled;
                self.counts.spilled_total += 1;
            }
        }
        // NOTE: a particle eaten this step may have brushed the lips on the way in; that
        // is eating, not a hit. Every other touch of the person counts once per particle.
        for f in self.food.iter_mut() {
            if f.touched && !f.hit && f.state != FoodState::Eaten {
                f.hit = true;
                self.counts.hits_total += 1;
            }
            f.touched = false;
        }
        eaten_speed
    }

    /// The step's rewards (feeding.md).
    fn rewards(
        &self,
        cfg: &WorldConfig,
        action: &[f32],
        counts: &FoodCounts,
        felt: &Felt,
    ) -> StepRewards {
        let d = (to_point(felt.spoon.translation) - felt.mouth).norm();
        let a_norm = action
            .iter()
            .map(|a| (*a as f64).powi(2))
            .sum::<f64>()
            .sqrt();
        let j = self.frames.ee_jacobian();
        let ee_speed = (0..3)
            .map(|k| (0..NJ).map(|i| j[(k, i)] * self.qd[i]).sum::<f64>().powi(2))
            .sum::<f64>()
            .sqrt();
        let robot = -d - 0.01 * a_norm + 20.0 * counts.eaten as f64 - 5.0 * counts.spilled as f64;
        let high = if felt.f_spoon >= cfg.profile.high_force_threshold as f64 {
            -felt.f_spoon
        } else {
            0.0
        };
        let terms = [
            -d,
            counts.eaten as f64,
            -ee_speed,
            -felt.f_robot,
            high,
            -(counts.hits as f64),
            -felt.eaten_speed,
        ];
        let w = cfg.profile.weights.as_array();
        let taste = self.taste_reward(&cfg.profile.taste, felt, d, counts.eaten);
        let human: f64 = terms.iter().zip(w).map(|(t, w)| t * w as f64).sum::<f64>() + taste;
        StepRewards {
            robot: robot as f32,
            terms: terms.map(|t| t as f32),
            human: human as f32,
            truth: (robot + human) as f32,
            task: -d as f32,
        }
    }

    /// The weighted taste terms of a step (`Taste`): C_ap on the spoon's way in, C_bite
    /// when a new bite starts.
    fn taste_reward(&self, taste: &Taste, felt: &Felt, d: f64, eaten: u32) -> f64 {
        let mut r = 0.0;
        let on_the_way = d < taste.approach_radius as f64 && d >= taste.approach_inner as f64;
        if taste.approach_weight != 0.0 && on_the_way && d > 1e-9 {
            let from_mouth =
                felt.head.rotation.inverse() * (to_point(felt.spoon.translation) - felt.mouth);
            let want = Vector3::from(taste.approach.map(f64::from));
            let cos = from_mouth.dot(&want) / (from_mouth.norm() * want.norm());
            r -= taste.approach_weight as f64 * (1.0 - cos);
        }
        if taste.bite_weight != 0.0 && eaten > 0 && !self.ate_last_step {
            r -= taste.bite_weight as f64;
        }
        r
    }
}

fn head_pose(person: &Person, angles: &[f64; 3]) -> Isometry3<f64> {
    person.head_rest * UnitQuaternion::from_euler_angles(angles[0], angles[1], angles[2])
}

fn mouth_of(ep: &Episode) -> Point3<f64> {
    head_pose(&ep.person, &ep.head.angles) * Point3::from(ep.person.mouth_local)
}
