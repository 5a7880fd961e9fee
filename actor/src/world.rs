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

use nalgebra::{Isometry3, Point3, UnitQuaternion, Vector3};
use pbrl_common::StepRewards;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rapier3d::parry::query;
use rapier3d::parry::shape::{Ball, Capsule, Cuboid};
use rapier3d::prelude::*;

use crate::config::{BasePlacement, BodySize, ConfigError, Impairment, Taste, WorldConfig};
use crate::kinematics::{random_rest, Arm, ArmFrames, JOINT_LIMITS, NEUTRAL, NJ};
use crate::scene::{self, Owner, Person, Shape};

/// Length of the observation.
pub const OBS_DIM: usize = 25;
/// Length of the action.
pub const ACT_DIM: usize = NJ;

const PERSON_TAG: u128 = 1;
const FOOD: Group = Group::GROUP_1;

type Matrix7 = nalgebra::SMatrix<f64, NJ, NJ>;
type Vector7 = nalgebra::SVector<f64, NJ>;
/// Projected Gauss-Seidel passes of the arm's motor and contact solver.
const SOLVER_ITERATIONS: usize = 10;
/// The first arm link (w0 onwards) whose collider the food can touch.
const FIRST_FOOD_LINK: usize = 4;

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
    spoon_boxes: Vec<(Pose, SharedShape, (Point3<f64>, f64))>,
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

fn parry_shape(shape: &Shape) -> (Pose, SharedShape) {
    let v = |p: &Point3<f64>| Vector::new(p.x as f32, p.y as f32, p.z as f32);
    match shape {
        Shape::Capsule { a, b, radius } => (
            Pose::identity(),
            SharedShape::new(Capsule::new(v(a), v(b), *radius as f32)),
        ),
        Shape::Ball { centre, radius } => (
            Pose::from_translation(v(centre)),
            SharedShape::new(Ball::new(*radius as f32)),
        ),
        Shape::Cuboid { centre, half } => (
            Pose::from_translation(v(centre)),
            SharedShape::new(Cuboid::new(Vector::new(
                half.x as f32,
                half.y as f32,
                half.z as f32,
            ))),
        ),
    }
}

fn uniform(rng: &mut impl Rng, half: f64) -> f64 {
    if half > 0.0 {
        rng.random_range(-half..=half)
    } else {
        0.0
    }
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
                let (pose, shape) = parry_shape(s);
                (pose, shape, s.bounding_sphere())
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

    /// Start a new episode from `seed` and return its first observation.
    pub fn reset(&mut self, seed: u64) -> Result<[f32; OBS_DIM], WorldError> {
        // NOTE: a failed reset must not leave the previous episode steppable.
        self.ep = None;
        let cfg = &self.cfg;
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let large = match cfg.profile.body {
            BodySize::Random => rng.random_bool(0.5),
            BodySize::Large => true,
            BodySize::Small => false,
        };
        let impairment = match cfg.profile.impairment {
            Impairment::Random => [
                Impairment::None,
                Impairment::Limits,
                Impairment::Weakness,
                Impairment::Tremor,
            ][rng.random_range(0..4)],
            other => other,
        };
        let limit_scale = if impairment == Impairment::Limits {
            rng.random_range(cfg.limits_scale_min as f64..=1.0)
        } else {
            1.0
        };
        let head_limits: [f64; 3] =
            std::array::from_fn(|k| (cfg.head_limit_deg[k] as f64 * limit_scale).to_radians());
        let head_rest: [f64; 3] = std::array::from_fn(|k| {
            let lim = head_limits[k];
            uniform(&mut rng, (cfg.head_angle_deg as f64).to_radians()).clamp(-lim, lim)
        });
        let tremor: [f64; 3] = std::array::from_fn(|_| {
            if impairment == Impairment::Tremor {
                uniform(&mut rng, (cfg.tremor_deg as f64).to_radians())
            } else {
                0.0
            }
        });
        let person = scene::person(large);
        let head_pose = head_pose(&person, &head_rest);
        let mouth = head_pose * Point3::from(person.mouth_local);
        let [sx, sy, sz] = cfg.start_ee.map(f64::from);
        let noise = cfg.start_ee_noise as f64;
        let start_pos = Vector3::new(
            sx + uniform(&mut rng, noise),
            sy + uniform(&mut rng, noise),
            sz + uniform(&mut rng, noise),
        );
        let [r, p, y] = cfg.start_ee_rpy.map(f64::from);
        let start_rot = UnitQuaternion::from_euler_angles(r, p, y);
        let start_ee = Isometry3::from_parts(start_pos.into(), start_rot);
        // The EE pose that puts the spoon origin on the mouth, spoon as level as at the start.
        let spoon_offset = start_rot * self.arm.spoon_in_ee().translation.vector;
        let mouth_ee = Isometry3::from_parts((mouth.coords - spoon_offset).into(), start_rot);

        // Static obstacles of the arm's contact solver (head added per reset below).
        let bowl = [
            cfg.bowl[0] as f64 + uniform(&mut rng, cfg.bowl_noise as f64),
            cfg.bowl[1] as f64 + uniform(&mut rng, cfg.bowl_noise as f64),
            cfg.bowl[2] as f64,
        ];
        let mut parts = person.parts.clone();
        parts.extend(scene::furniture(cfg, bowl));
        let mut obstacles: Vec<Obstacle> = parts
            .iter()
            .map(|p| {
                let (pose, shape) = parry_shape(&p.shape);
                Obstacle {
                    owner: p.owner,
                    pose,
                    shape,
                    sphere: p.shape.bounding_sphere(),
                }
            })
            .collect();
        let head_obstacle = obstacles.len();
        let head_centre = head_pose * Point3::from(person.head_centre_local);
        obstacles.push(Obstacle {
            owner: Owner::Person,
            pose: Pose::from_translation(Vector::new(
                head_centre.x as f32,
                head_centre.y as f32,
                head_centre.z as f32,
            )),
            shape: SharedShape::new(Ball::new(person.head_radius as f32)),
            sphere: (head_centre, person.head_radius),
        });

        let (pos_tol, rot_tol) = (cfg.ik_pos_tol as f64, cfg.ik_rot_tol as f64);
        let mut found = None;
        'bases: for _ in 0..cfg.base_tries {
            let [bx, by, bz] = cfg.base_nominal.map(f64::from);
            let base = match cfg.base {
                BasePlacement::Nominal => Isometry3::translation(bx, by, bz),
                BasePlacement::Random => {
                    let x = bx
                        + rng.random_range(cfg.base_x_range[0] as f64..=cfg.base_x_range[1] as f64);
                    let y = by
                        + rng.random_range(cfg.base_y_range[0] as f64..=cfg.base_y_range[1] as f64);
                    let [lo, hi] = cfg.base_yaw_deg_range.map(|d| (d as f64).to_radians());
                    let yaw = rng.random_range(lo..=hi);
                    Isometry3::from_parts(
                        nalgebra::Translation3::new(x, y, bz),
                        UnitQuaternion::from_euler_angles(0.0, 0.0, yaw),
                    )
                }
            };
            for attempt in 0..cfg.ik_tries {
                let rest = if attempt == 0 {
                    NEUTRAL
                } else {
                    random_rest(&mut rng, 0.8)
                };
                // NOTE: solve for the mouth first and then for the start pose from there, so
                // that the start posture lies on the same IK branch as the mouth and a
                // smooth reach connects the two.
                let (q_mouth, reach) = self.arm.ik(&base, &mouth_ee, &rest, pos_tol, rot_tol);
                if !reach {
                    continue;
                }
                let (q, ok) = self.arm.ik(&base, &start_ee, &q_mouth, pos_tol, rot_tol);
                if !ok {
                    continue;
                }
                let frames = self.arm.frames(&base, &q);
                if !self.arm_touches(&frames, &obstacles) {
                    found = Some((base, q, frames));
                    break 'bases;
                }
            }
            if cfg.base == BasePlacement::Nominal {
                // The nominal base does not change; the rest poses above were its tries.
                break;
            }
        }
        let Some((base, q, frames)) = found else {
            return Err(WorldError::ResetFailed {
                seed,
                tries: match cfg.base {
                    BasePlacement::Nominal => cfg.ik_tries,
                    BasePlacement::Random => cfg.base_tries.saturating_mul(cfg.ik_tries),
                },
            });
        };

        // The physics world.
        let mut phys = PhysicsWorld::new();
        phys.gravity = Vector::new(0.0, 0.0, -cfg.gravity);
        phys.integration_parameters.dt = cfg.substep_dt;
        phys.integration_parameters.length_unit = 0.01;
        phys.integration_parameters.num_solver_iterations = cfg.solver_iterations as usize;
        let only_food = InteractionGroups::new(Group::GROUP_2, FOOD, InteractionTestMode::And);
        for (part, obstacle) in parts.iter().zip(&obstacles) {
            let tag = if part.owner == Owner::Person {
                PERSON_TAG
            } else {
                0
            };
            phys.colliders.insert(
                ColliderBuilder::new(obstacle.shape.clone())
                    .position(obstacle.pose)
                    .friction(0.5)
                    .collision_groups(only_food)
                    .user_data(tag),
            );
        }
        let head_body = phys
            .bodies
            .insert(RigidBodyBuilder::kinematic_position_based().pose(to_pose(&head_pose)));
        let hc = person.head_centre_local;
        phys.colliders.insert_with_parent(
            ColliderBuilder::ball(person.head_radius as f32)
                .translation(Vector::new(hc.x as f32, hc.y as f32, hc.z as f32))
                .collision_groups(only_food)
                .user_data(PERSON_TAG),
            head_body,
            &mut phys.bodies,
        );
        // NOTE: only the wrist links, which pass near the spoon, carry colliders the food can
        // touch; the upper arm is far from the food and skipping it saves a sixth of the
        // physics time. Every link still meets the person and the table in the arm's own
        // contact solver.
        let segments = frames.link_segments();
        let links: [RigidBodyHandle; NJ] = std::array::from_fn(|i| {
            let body = phys.bodies.insert(
                RigidBodyBuilder::kinematic_position_based().pose(to_pose(&frames.joints[i])),
            );
            if i >= FIRST_FOOD_LINK {
                let (a, b, _) = segments[i];
                let inv = frames.joints[i].inverse();
                let (la, lb) = (inv * a, inv * b);
                phys.colliders.insert_with_parent(
                    ColliderBuilder::capsule_from_endpoints(
                        Vector::new(la.x as f32, la.y as f32, la.z as f32),
                        Vector::new(lb.x as f32, lb.y as f32, lb.z as f32),
                        scene::LINK_RADII[i] as f32,
                    )
                    .collision_groups(only_food),
                    body,
                    &mut phys.bodies,
                );
            }
            body
        });
        let spoon = phys
            .bodies
            .insert(RigidBodyBuilder::kinematic_position_based().pose(to_pose(&frames.spoon)));
        let compound: Vec<(Pose, SharedShape)> = self
            .spoon_boxes
            .iter()
            .map(|(p, s, _)| (*p, s.clone()))
            .collect();
        phys.colliders.insert_with_parent(
            ColliderBuilder::compound(compound)
                .friction(cfg.food_friction)
                .collision_groups(only_food),
            spoon,
            &mut phys.bodies,
        );
        let spoon_origin = frames.spoon.translation.vector;
        let food = scene::food_offsets(cfg.food_count)
            .into_iter()
            .map(|off| {
                let c = spoon_origin + off;
                let body = phys.bodies.insert(
                    RigidBodyBuilder::dynamic()
                        .translation(Vector::new(c.x as f32, c.y as f32, c.z as f32))
                        .linear_damping(0.04)
                        .angular_damping(0.04),
                );
                let collider = phys.colliders.insert_with_parent(
                    ColliderBuilder::ball(cfg.food_radius)
                        .mass(cfg.food_mass)
                        .friction(cfg.food_friction)
                        .restitution(0.0),
                    body,
                    &mut phys.bodies,
                );
                Food {
                    body,
                    collider,
                    state: FoodState::OnSpoon,
                    hit: false,
                    touched: false,
                }
            })
            .collect();

        let start_spoon = frames.spoon;
        self.ep = Some(Episode {
            seed,
            base,
            person,
            bowl,
            q,
            qd: [0.0; NJ],
            q_target: q,
            frames,
            start_spoon,
            start_q: q,
            head: Head {
                rest: head_rest,
                limits: head_limits,
                angles: head_rest,
                tremor,
                sign: 1.0,
                body: head_body,
            },
            phys,
            links,
            spoon,
            food,
            obstacles,
            head_obstacle,
            steps: 0,
            counts: FoodCounts::default(),
            ate_last_step: false,
        });
        // Let the food settle on the still spoon; hits during settling do not count.
        let settle = self.cfg.settle_substeps;
        for _ in 0..settle {
            self.substep();
        }
        let ep = self.ep.as_mut().expect("episode was set just above");
        for f in &mut ep.food {
            f.touched = false;
        }
        Ok(self.observation(0.0))
    }

    /// Whether any arm link or the spoon penetrates an obstacle.
    fn arm_touches(&self, frames: &ArmFrames, obstacles: &[Obstacle]) -> bool {
        let mut touching = false;
        self.for_each_contact(frames, obstacles, 0.0, |c| {
            if c.dist < 0.0 {
                touching = true;
            }
        });
        touching
    }

    /// Calls `f` for every contact (within `prediction`) of the arm and spoon with the
    /// obstacles.
    fn for_each_contact(
        &self,
        frames: &ArmFrames,
        obstacles: &[Obstacle],
        prediction: f32,
        mut f: impl FnMut(ArmContact),
    ) {
        let margin = prediction as f64 + 1e-3;
        let spoon_pose = to_pose(&frames.spoon);
        let links = frames.link_segments().map(|(a, b, link)| {
            let r = scene::LINK_RADII[link];
            let sphere = (nalgebra::center(&a, &b), (b - a).norm() / 2.0 + r);
            let to_v = |p: Point3<f64>| Vector::new(p.x as f32, p.y as f32, p.z as f32);
            (Capsule::new(to_v(a), to_v(b), r as f32), sphere, link)
        });
        let spoon_spheres: Vec<(Point3<f64>, f64)> = self
            .spoon_boxes
            .iter()
            .map(|(_, _, s)| (frames.spoon * s.0, s.1))
            .collect();
        for (oi, o) in obstacles.iter().enumerate() {
            for (cap, sphere, link) in &links {
                if (sphere.0 - o.sphere.0).norm() > sphere.1 + o.sphere.1 + margin {
                    continue;
                }
                if let Ok(Some(ct)) =
                    query::contact(&Pose::identity(), cap, &o.pose, &*o.shape, prediction)
                {
                    f(ArmContact {
                        obstacle: oi,
                        link: *link,
                        spoon: false,
                        point: to_point(ct.point1),
                        normal: -to_point(ct.normal1).coords,
                        dist: ct.dist,
                    });
                }
            }
            for ((local, shape, _), sphere) in self.spoon_boxes.iter().zip(&spoon_spheres) {
                if (sphere.0 - o.sphere.0).norm() > sphere.1 + o.sphere.1 + margin {
                    continue;
                }
                let pose = spoon_pose * *local;
                if let Ok(Some(ct)) =
                    query::contact(&pose, &**shape, &o.pose, &*o.shape, prediction)
                {
                    f(ArmContact {
                        obstacle: oi,
                        link: NJ - 1,
                        spoon: true,
                        point: to_point(ct.point1),
                        normal: -to_point(ct.normal1).coords,
                        dist: ct.dist,
                    });
                }
            }
        }
    }

    /// One physics substep: head, arm motors and contacts, then rapier.
    /// Returns the spoon's and the whole robot's normal force on the person (N).
    fn substep(&mut self) -> (f64, f64) {
        let cfg = &self.cfg;
        let dt = cfg.substep_dt as f64;
        let ep = self.ep.as_mut().expect("substep runs inside an episode");

        // The head follows its (tremor) target through a weak position motor.
        let gain = cfg.head_motor_gain as f64;
        for k in 0..3 {
            let lim = ep.head.limits[k];
            let target = (ep.head.rest[k] + ep.head.sign * ep.head.tremor[k]).clamp(-lim, lim);
            ep.head.angles[k] += gain * (target - ep.head.angles[k]);
        }
        let head_pose = head_pose(&ep.person, &ep.head.angles);
        let hc = head_pose * Point3::from(ep.person.head_centre_local);
        let head_obstacle = &mut ep.obstacles[ep.head_obstacle];
        head_obstacle.pose =
            Pose::from_translation(Vector::new(hc.x as f32, hc.y as f32, hc.z as f32));
        head_obstacle.sphere.0 = hc;

        // The arm's joint-space mass matrix: the fitted joint inertias plus the spoon (a
        // 1 kg body at the end of the chain, which couples the joints).
        let (kp, cap, damping) = (
            cfg.motor_gain as f64,
            cfg.motor_max_force as f64,
            cfg.joint_damping as f64,
        );
        let js = ep.frames.spoon_jacobian();
        let (jv, jw) = (js.fixed_rows::<3>(0), js.fixed_rows::<3>(3));
        let mut mass = Matrix7::from_diagonal(&Vector7::from(cfg.joint_inertia.map(f64::from)));
        mass += (jv.transpose() * jv) * cfg.spoon_mass as f64
            + (jw.transpose() * jw) * cfg.spoon_inertia as f64;
        // Joint damping, implicit so that light joints stay stable: (M + c dt) qd' = M qd.
        let damped = mass + Matrix7::identity() * (damping * dt);
        // NOTE: cannot fail: the config bounds the inertias to [1e-4, 1e3] and the spoon's
        // terms are Gram matrices, so both matrices are symmetric positive definite.
        let (Some(m_inv), Some(d_inv)) = (mass.cholesky(), damped.cholesky()) else {
            unreachable!("a diagonal of positive inertias plus Gram matrices is positive definite");
        };
        let m_inv = m_inv.inverse();
        let mut qd = d_inv.solve(&(mass * Vector7::from(ep.qd)));

        // Position motors as PyBullet makes them: a velocity constraint asking for
        // gain * error / dt, its impulse capped by the force limit, solved together with
        // the contacts below (so a blocked joint pushes with its whole force limit).
        let v_motor: [f64; NJ] = std::array::from_fn(|i| kp * (ep.q_target[i] - ep.q[i]) / dt);
        let mut motor_impulse = [0.0f64; NJ];

        // Contacts: one non-penetration constraint per contact point along its normal.
        let mut rows = std::mem::take(&mut self.rows);
        rows.clear();
        let erp = cfg.contact_erp as f64;
        let slop = cfg.contact_slop as f64;
        let frames = ep.frames.clone();
        let obstacles = std::mem::take(&mut ep.obstacles);
        self.for_each_contact(&frames, &obstacles, 0.005, |c| {
            let j = frames.jacobian_at(&c.point, c.link);
            let jc = Vector7::from_fn(|i, _| (0..3).map(|k| c.normal[k] * j[(k, i)]).sum());
            let w = m_inv * jc;
            let m_inv_n = jc.dot(&w);
            if m_inv_n < 1e-12 {
                return;
            }
            let depth = -c.dist as f64;
            // Speculative below zero depth: the gap may close, no more.
            let target = if depth > 0.0 {
                erp * (depth - slop).max(0.0) / dt
            } else {
                -(-depth) / dt
            };
            let person = obstacles[c.obstacle].owner == Owner::Person;
            rows.push(ContactRow {
                jc,
                w,
                target,
                m_eff: 1.0 / m_inv_n,
                lambda: 0.0,
                person,
                spoon: c.spoon,
            });
        });
        let ep = self.ep.as_mut().expect("substep runs inside an episode");
        ep.obstacles = obstacles;
        for _ in 0..SOLVER_ITERATIONS {
            for i in 0..NJ {
                let m_eff = 1.0 / m_inv[(i, i)];
                let new =
                    (motor_impulse[i] + m_eff * (v_motor[i] - qd[i])).clamp(-cap * dt, cap * dt);
                qd += m_inv.column(i) * (new - motor_impulse[i]);
                motor_impulse[i] = new;
            }
            for row in rows.iter_mut() {
                let vn = row.jc.dot(&qd);
                let new = (row.lambda + row.m_eff * (row.target - vn)).max(0.0);
                qd += row.w * (new - row.lambda);
                row.lambda = new;
            }
        }
        ep.qd = qd.into();
        let (mut f_spoon, mut f_robot) = (0.0, 0.0);
        for row in rows.iter().filter(|r| r.person) {
            f_robot += row.lambda / dt;
            if row.spoon {
                f_spoon += row.lambda / dt;
            }
        }
        self.rows = rows;

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

        // Food touching the person; counted as hits once per env step, after eating.
        for f in ep
            .food
            .iter_mut()
            .filter(|f| !f.hit && !f.touched && f.state != FoodState::Eaten)
        {
            let colliders = &ep.phys.colliders;
            f.touched = ep
                .phys
                .narrow_phase
                .contact_pairs_with(f.collider)
                .any(|pair| {
                    let other = if pair.collider1 == f.collider {
                        pair.collider2
                    } else {
                        pair.collider1
                    };
                    pair.has_any_active_contact() && colliders[other].user_data == PERSON_TAG
                });
        }
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
        let n = self.cfg.substeps;
        for _ in 0..n {
            // NOTE: the original reads contact forces once per step, at its last substep; we
            // keep the largest over the step's substeps so that a short hit is never missed.
            let (s, r) = self.substep();
            f_spoon = f_spoon.max(s);
            f_robot = f_robot.max(r);
        }

        // Food: eaten near the mouth, spilled far from the spoon.
        let cfg = &self.cfg;
        let ep = self.ep.as_mut().expect("checked above");
        let mouth = mouth_of(ep);
        let spoon_pose = to_pose(&ep.frames.spoon);
        let ball = Ball::new(cfg.food_radius);
        let mut eaten_speed = 0.0;
        for f in ep.food.iter_mut().filter(|f| f.state == FoodState::OnSpoon) {
            let body = &mut ep.phys.bodies[f.body];
            let p = to_point(body.translation());
            if (p - mouth).norm() < cfg.eat_distance as f64 {
                f.state = FoodState::Eaten;
                ep.counts.eaten_total += 1;
                eaten_speed += body.linvel().length() as f64;
                // NOTE: an eaten particle leaves the world but keeps its last position for
                // the replay.
                body.set_enabled(false);
                continue;
            }
            let ball_pose = Pose::from_translation(body.translation());
            let near = self.spoon_boxes.iter().any(|(local, shape, _)| {
                query::distance(&(spoon_pose * *local), &**shape, &ball_pose, &ball)
                    .map(|d| d.distance <= cfg.spill_distance)
                    .unwrap_or(true)
            });
            if !near {
                f.state = FoodState::Spilled;
                ep.counts.spilled_total += 1;
            }
        }
        // NOTE: a particle eaten this step may have brushed the lips on the way in; that
        // is eating, not a hit. Every other touch of the person counts once per particle.
        for f in ep.food.iter_mut() {
            if f.touched && !f.hit && f.state != FoodState::Eaten {
                f.hit = true;
                ep.counts.hits_total += 1;
            }
            f.touched = false;
        }
        ep.steps += 1;
        let counts = FoodCounts {
            eaten: ep.counts.eaten_total - before.eaten_total,
            spilled: ep.counts.spilled_total - before.spilled_total,
            hits: ep.counts.hits_total - before.hits_total,
            ..ep.counts
        };

        // Rewards (feeding.md).
        let d = (to_point(spoon_pose.translation) - mouth).norm();
        let a_norm = action
            .iter()
            .map(|a| (*a as f64).powi(2))
            .sum::<f64>()
            .sqrt();
        let j = ep.frames.ee_jacobian();
        let ee_speed = (0..3)
            .map(|k| (0..NJ).map(|i| j[(k, i)] * ep.qd[i]).sum::<f64>().powi(2))
            .sum::<f64>()
            .sqrt();
        let robot = -d - 0.01 * a_norm + 20.0 * counts.eaten as f64 - 5.0 * counts.spilled as f64;
        let high = if f_spoon >= cfg.profile.high_force_threshold as f64 {
            -f_spoon
        } else {
            0.0
        };
        let terms = [
            -d,
            counts.eaten as f64,
            -ee_speed,
            -f_robot,
            high,
            -(counts.hits as f64),
            -eaten_speed,
        ];
        let w = cfg.profile.weights.as_array();
        let taste = taste_reward(&cfg.profile.taste, ep, &spoon_pose, &mouth, d, counts.eaten);
        ep.ate_last_step = counts.eaten > 0;
        let human: f64 = terms.iter().zip(w).map(|(t, w)| t * w as f64).sum::<f64>() + taste;
        let rewards = StepRewards {
            robot: robot as f32,
            terms: terms.map(|t| t as f32),
            human: human as f32,
            truth: (robot + human) as f32,
            task: -d as f32,
        };
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

/// One non-penetration constraint of the arm's contact solver.
struct ContactRow {
    /// Normal velocity per unit joint velocity.
    jc: Vector7,
    /// Joint velocity change per unit impulse (M^-1 jc).
    w: Vector7,
    /// Normal velocity the constraint asks for (at least).
    target: f64,
    /// Effective mass along the normal.
    m_eff: f64,
    /// Accumulated impulse.
    lambda: f64,
    person: bool,
    spoon: bool,
}

/// One contact of the arm or spoon with an obstacle.
struct ArmContact {
    obstacle: usize,
    link: usize,
    spoon: bool,
    /// On the arm, world.
    point: Point3<f64>,
    /// Pushes the arm out of the obstacle.
    normal: Vector3<f64>,
    dist: f32,
}

fn head_pose(person: &Person, angles: &[f64; 3]) -> Isometry3<f64> {
    person.head_rest * UnitQuaternion::from_euler_angles(angles[0], angles[1], angles[2])
}

/// The weighted taste terms of a step (`Taste`): C_ap on the spoon's way in, C_bite when
/// a new bite starts.
fn taste_reward(
    taste: &Taste,
    ep: &Episode,
    spoon: &Pose,
    mouth: &Point3<f64>,
    d: f64,
    eaten: u32,
) -> f64 {
    let mut r = 0.0;
    let on_the_way = d < taste.approach_radius as f64 && d >= taste.approach_inner as f64;
    if taste.approach_weight != 0.0 && on_the_way && d > 1e-9 {
        let head = head_pose(&ep.person, &ep.head.angles);
        let from_mouth = head.rotation.inverse() * (to_point(spoon.translation) - mouth);
        let want = Vector3::from(taste.approach.map(f64::from));
        let cos = from_mouth.dot(&want) / (from_mouth.norm() * want.norm());
        r -= taste.approach_weight as f64 * (1.0 - cos);
    }
    if taste.bite_weight != 0.0 && eaten > 0 && !ep.ate_last_step {
        r -= taste.bite_weight as f64;
    }
    r
}

fn mouth_of(ep: &Episode) -> Point3<f64> {
    head_pose(&ep.person, &ep.head.angles) * Point3::from(ep.person.mouth_local)
}
