//! An episode's scene, built once per reset (as rapier's own examples build a scene and
//! then step it): [`sample`] draws the person, the start and the bowl from the seed,
//! [`place_arm`] finds a robot base and posture that reach both, and [`episode`] builds the
//! physics world around them.

use nalgebra::{Isometry3, Point3, UnitQuaternion, Vector3};
use rand::Rng;
use rapier3d::parry::shape::Ball;
use rapier3d::prelude::*;

use super::arm::{arm_touches, SpoonBox};
use super::{head_pose, to_pose, Episode, Food, FoodCounts, FoodState, Head, Obstacle};
use crate::config::{BasePlacement, BodySize, Impairment, WorldConfig};
use crate::kinematics::{random_rest, Arm, ArmFrames, NEUTRAL, NJ};
use crate::scene::{self, Owner, Part, Person, Shape};

/// Marks the person's colliders (food touching them is a hit).
pub(super) const PERSON_TAG: u128 = 1;
const FOOD: Group = Group::GROUP_1;
/// The first arm link (w0 onwards) whose collider the food can touch.
const FIRST_FOOD_LINK: usize = 4;

/// What a seed draws before the arm is placed: the person, where the spoon starts and
/// where the mouth is, and the obstacles the arm must not touch.
pub(super) struct Draw {
    person: Person,
    head_rest: [f64; 3],
    head_limits: [f64; 3],
    tremor: [f64; 3],
    head_pose: Isometry3<f64>,
    start_ee: Isometry3<f64>,
    /// The EE pose that puts the spoon origin on the mouth, spoon as level as at the start.
    mouth_ee: Isometry3<f64>,
    bowl: [f64; 3],
    /// The person's parts and the furniture, one obstacle each, then the head's.
    parts: Vec<Part>,
    obstacles: Vec<Obstacle>,
}

/// A robot base and a start posture that reaches the start pose, the mouth from there, and
/// touches nothing.
pub(super) struct Placed {
    base: Isometry3<f64>,
    q: [f64; NJ],
    frames: ArmFrames,
}

pub(super) fn uniform(rng: &mut impl Rng, half: f64) -> f64 {
    if half > 0.0 {
        rng.random_range(-half..=half)
    } else {
        0.0
    }
}

pub(super) fn parry_shape(shape: &Shape) -> (Pose, SharedShape) {
    let v = |p: &Point3<f64>| Vector::new(p.x as f32, p.y as f32, p.z as f32);
    match shape {
        Shape::Capsule { a, b, radius } => (
            Pose::identity(),
            SharedShape::new(rapier3d::parry::shape::Capsule::new(
                v(a),
                v(b),
                *radius as f32,
            )),
        ),
        Shape::Ball { centre, radius } => (
            Pose::from_translation(v(centre)),
            SharedShape::new(Ball::new(*radius as f32)),
        ),
        Shape::Cuboid { centre, half } => (
            Pose::from_translation(v(centre)),
            SharedShape::new(rapier3d::parry::shape::Cuboid::new(Vector::new(
                half.x as f32,
                half.y as f32,
                half.z as f32,
            ))),
        ),
    }
}

/// The person (body, impairment, head), the start pose and the bowl, in the order the
/// seed's numbers are drawn.
pub(super) fn sample(cfg: &WorldConfig, arm: &Arm, rng: &mut impl Rng) -> Draw {
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
        uniform(rng, (cfg.head_angle_deg as f64).to_radians()).clamp(-lim, lim)
    });
    let tremor: [f64; 3] = std::array::from_fn(|_| {
        if impairment == Impairment::Tremor {
            uniform(rng, (cfg.tremor_deg as f64).to_radians())
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
        sx + uniform(rng, noise),
        sy + uniform(rng, noise),
        sz + uniform(rng, noise),
    );
    let [r, p, y] = cfg.start_ee_rpy.map(f64::from);
    let start_rot = UnitQuaternion::from_euler_angles(r, p, y);
    let start_ee = Isometry3::from_parts(start_pos.into(), start_rot);
    let spoon_offset = start_rot * arm.spoon_in_ee().translation.vector;
    let mouth_ee = Isometry3::from_parts((mouth.coords - spoon_offset).into(), start_rot);
    let bowl = [
        cfg.bowl[0] as f64 + uniform(rng, cfg.bowl_noise as f64),
        cfg.bowl[1] as f64 + uniform(rng, cfg.bowl_noise as f64),
        cfg.bowl[2] as f64,
    ];
    let mut parts = person.parts.clone();
    parts.extend(scene::furniture(cfg, bowl));
    let obstacles = obstacles(&parts, &person, &head_pose);
    Draw {
        person,
        head_rest,
        head_limits,
        tremor,
        head_pose,
        start_ee,
        mouth_ee,
        bowl,
        parts,
        obstacles,
    }
}

/// The obstacles of the arm's contact solver: every part, then the head (which moves).
fn obstacles(parts: &[Part], person: &Person, head_pose: &Isometry3<f64>) -> Vec<Obstacle> {
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
    obstacles
}

/// A base (the nominal one, or up to `base_tries` random ones) from which IK reaches the
/// mouth and then the start pose on the same branch, the arm touching nothing; `None` when
/// every try failed.
pub(super) fn place_arm(
    cfg: &WorldConfig,
    arm: &Arm,
    spoon: &[SpoonBox],
    draw: &Draw,
    rng: &mut impl Rng,
) -> Option<Placed> {
    let (pos_tol, rot_tol) = (cfg.ik_pos_tol as f64, cfg.ik_rot_tol as f64);
    for _ in 0..cfg.base_tries {
        let base = base_pose(cfg, rng);
        for attempt in 0..cfg.ik_tries {
            let rest = if attempt == 0 {
                NEUTRAL
            } else {
                random_rest(rng, 0.8)
            };
            // NOTE: solve for the mouth first and then for the start pose from there, so
            // that the start posture lies on the same IK branch as the mouth and a smooth
            // reach connects the two.
            let (q_mouth, reach) = arm.ik(&base, &draw.mouth_ee, &rest, pos_tol, rot_tol);
            if !reach {
                continue;
            }
            let (q, ok) = arm.ik(&base, &draw.start_ee, &q_mouth, pos_tol, rot_tol);
            if !ok {
                continue;
            }
            let frames = arm.frames(&base, &q);
            if !arm_touches(spoon, &frames, &draw.obstacles) {
                return Some(Placed { base, q, frames });
            }
        }
        if cfg.base == BasePlacement::Nominal {
            // The nominal base does not change; the rest poses above were its tries.
            break;
        }
    }
    None
}

fn base_pose(cfg: &WorldConfig, rng: &mut impl Rng) -> Isometry3<f64> {
    let [bx, by, bz] = cfg.base_nominal.map(f64::from);
    match cfg.base {
        BasePlacement::Nominal => Isometry3::translation(bx, by, bz),
        BasePlacement::Random => {
            let x = bx + rng.random_range(cfg.base_x_range[0] as f64..=cfg.base_x_range[1] as f64);
            let y = by + rng.random_range(cfg.base_y_range[0] as f64..=cfg.base_y_range[1] as f64);
            let [lo, hi] = cfg.base_yaw_deg_range.map(|d| (d as f64).to_radians());
            let yaw = rng.random_range(lo..=hi);
            Isometry3::from_parts(
                nalgebra::Translation3::new(x, y, bz),
                UnitQuaternion::from_euler_angles(0.0, 0.0, yaw),
            )
        }
    }
}

/// The episode: the physics world (fixed parts, the head, the arm's links, the spoon and
/// the food on it) with the arm where `placed` put it, before the food settles.
pub(super) fn episode(
    cfg: &WorldConfig,
    spoon_boxes: &[SpoonBox],
    seed: u64,
    draw: Draw,
    placed: Placed,
) -> Episode {
    let mut phys = PhysicsWorld::new();
    phys.gravity = Vector::new(0.0, 0.0, -cfg.gravity);
    phys.integration_parameters.dt = cfg.substep_dt;
    phys.integration_parameters.length_unit = 0.01;
    phys.integration_parameters.num_solver_iterations = cfg.solver_iterations as usize;
    let only_food = InteractionGroups::new(Group::GROUP_2, FOOD, InteractionTestMode::And);
    for (part, obstacle) in draw.parts.iter().zip(&draw.obstacles) {
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
    let head_body = insert_head(&mut phys, &draw.person, &draw.head_pose, only_food);
    let links = insert_links(&mut phys, &placed.frames, only_food);
    let spoon = phys
        .bodies
        .insert(RigidBodyBuilder::kinematic_position_based().pose(to_pose(&placed.frames.spoon)));
    let compound: Vec<(Pose, SharedShape)> = spoon_boxes
        .iter()
        .map(|b| (b.pose, b.shape.clone()))
        .collect();
    phys.colliders.insert_with_parent(
        ColliderBuilder::compound(compound)
            .friction(cfg.food_friction)
            .collision_groups(only_food),
        spoon,
        &mut phys.bodies,
    );
    let food = insert_food(cfg, &mut phys, &placed.frames);
    let head_obstacle = draw.obstacles.len() - 1;
    Episode {
        seed,
        base: placed.base,
        person: draw.person,
        bowl: draw.bowl,
        q: placed.q,
        qd: [0.0; NJ],
        q_target: placed.q,
        start_spoon: placed.frames.spoon,
        frames: placed.frames,
        start_q: placed.q,
        head: Head {
            rest: draw.head_rest,
            limits: draw.head_limits,
            angles: draw.head_rest,
            tremor: draw.tremor,
            sign: 1.0,
            body: head_body,
        },
        phys,
        links,
        spoon,
        food,
        obstacles: draw.obstacles,
        head_obstacle,
        steps: 0,
        counts: FoodCounts::default(),
        ate_last_step: false,
    }
}

fn insert_head(
    phys: &mut PhysicsWorld,
    person: &Person,
    head_pose: &Isometry3<f64>,
    groups: InteractionGroups,
) -> RigidBodyHandle {
    let head_body = phys
        .bodies
        .insert(RigidBodyBuilder::kinematic_position_based().pose(to_pose(head_pose)));
    let hc = person.head_centre_local;
    phys.colliders.insert_with_parent(
        ColliderBuilder::ball(person.head_radius as f32)
            .translation(Vector::new(hc.x as f32, hc.y as f32, hc.z as f32))
            .collision_groups(groups)
            .user_data(PERSON_TAG),
        head_body,
        &mut phys.bodies,
    );
    head_body
}

/// One kinematic body per arm link.
// NOTE: only the wrist links, which pass near the spoon, carry colliders the food can
// touch; the upper arm is far from the food and skipping it saves a sixth of the physics
// time. Every link still meets the person and the table in the arm's own contact solver.
fn insert_links(
    phys: &mut PhysicsWorld,
    frames: &ArmFrames,
    groups: InteractionGroups,
) -> [RigidBodyHandle; NJ] {
    let segments = frames.link_segments();
    std::array::from_fn(|i| {
        let body = phys
            .bodies
            .insert(RigidBodyBuilder::kinematic_position_based().pose(to_pose(&frames.joints[i])));
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
                .collision_groups(groups),
                body,
                &mut phys.bodies,
            );
        }
        body
    })
}

/// The food particles, stacked on the spoon.
fn insert_food(cfg: &WorldConfig, phys: &mut PhysicsWorld, frames: &ArmFrames) -> Vec<Food> {
    let spoon_origin = frames.spoon.translation.vector;
    scene::food_offsets(cfg.food_count)
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
        .collect()
}
