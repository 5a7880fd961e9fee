//! The arm's joint-space dynamics: its mass matrix, its position motors and its contacts
//! with the person and the furniture, solved together by projected Gauss-Seidel.

use nalgebra::{Point3, Vector3};
use rapier3d::parry::query;
use rapier3d::parry::shape::Capsule;
use rapier3d::prelude::*;

use super::{to_point, to_pose, Obstacle};
use crate::config::WorldConfig;
use crate::kinematics::{ArmFrames, NJ};
use crate::scene::{self, Owner};

pub(super) type Matrix7 = nalgebra::SMatrix<f64, NJ, NJ>;
pub(super) type Vector7 = nalgebra::SVector<f64, NJ>;
/// Projected Gauss-Seidel passes of the arm's motor and contact solver.
const SOLVER_ITERATIONS: usize = 10;

/// One box of the spoon, in the spoon's frame, with its bounding sphere.
pub(super) struct SpoonBox {
    pub pose: Pose,
    pub shape: SharedShape,
    pub sphere: (Point3<f64>, f64),
}

/// One non-penetration constraint of the arm's contact solver.
pub(super) struct ContactRow {
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

/// Whether any arm link or the spoon penetrates an obstacle.
pub(super) fn arm_touches(spoon: &[SpoonBox], frames: &ArmFrames, obstacles: &[Obstacle]) -> bool {
    let mut touching = false;
    for_each_contact(spoon, frames, obstacles, 0.0, |c| {
        if c.dist < 0.0 {
            touching = true;
        }
    });
    touching
}

/// Calls `f` for every contact (within `prediction`) of the arm and spoon with the
/// obstacles.
fn for_each_contact(
    spoon: &[SpoonBox],
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
    let spoon_spheres: Vec<(Point3<f64>, f64)> = spoon
        .iter()
        .map(|b| (frames.spoon * b.sphere.0, b.sphere.1))
        .collect();
    for (oi, o) in obstacles.iter().enumerate() {
        let apart = |sphere: &(Point3<f64>, f64)| {
            (sphere.0 - o.sphere.0).norm() > sphere.1 + o.sphere.1 + margin
        };
        let contact = |ct: query::Contact, link: usize, spoon: bool| ArmContact {
            obstacle: oi,
            link,
            spoon,
            point: to_point(ct.point1),
            normal: -to_point(ct.normal1).coords,
            dist: ct.dist,
        };
        for (cap, sphere, link) in &links {
            if apart(sphere) {
                continue;
            }
            if let Ok(Some(ct)) =
                query::contact(&Pose::identity(), cap, &o.pose, &*o.shape, prediction)
            {
                f(contact(ct, *link, false));
            }
        }
        for (b, sphere) in spoon.iter().zip(&spoon_spheres) {
            if apart(sphere) {
                continue;
            }
            let pose = spoon_pose * b.pose;
            if let Ok(Some(ct)) = query::contact(&pose, &*b.shape, &o.pose, &*o.shape, prediction) {
                f(contact(ct, NJ - 1, true));
            }
        }
    }
}

/// The arm's joint-space mass matrix's inverse, and the joint velocities after the
/// (implicit) joint damping.
pub(super) fn dynamics(
    cfg: &WorldConfig,
    frames: &ArmFrames,
    qd: &[f64; NJ],
) -> (Matrix7, Vector7) {
    let dt = cfg.substep_dt as f64;
    // The fitted joint inertias plus the spoon (a 1 kg body at the end of the chain, which
    // couples the joints).
    let js = frames.spoon_jacobian();
    let (jv, jw) = (js.fixed_rows::<3>(0), js.fixed_rows::<3>(3));
    let mut mass = Matrix7::from_diagonal(&Vector7::from(cfg.joint_inertia.map(f64::from)));
    mass += (jv.transpose() * jv) * cfg.spoon_mass as f64
        + (jw.transpose() * jw) * cfg.spoon_inertia as f64;
    // Joint damping, implicit so that light joints stay stable: (M + c dt) qd' = M qd.
    let damped = mass + Matrix7::identity() * (cfg.joint_damping as f64 * dt);
    // NOTE: cannot fail: the config bounds the inertias to [1e-4, 1e3] and the spoon's
    // terms are Gram matrices, so both matrices are symmetric positive definite.
    let (Some(m_inv), Some(d_inv)) = (mass.cholesky(), damped.cholesky()) else {
        unreachable!("a diagonal of positive inertias plus Gram matrices is positive definite");
    };
    let qd = d_inv.solve(&(mass * Vector7::from(*qd)));
    (m_inv.inverse(), qd)
}

/// One non-penetration constraint per contact point along its normal, into `rows`.
pub(super) fn contact_rows(
    cfg: &WorldConfig,
    spoon: &[SpoonBox],
    frames: &ArmFrames,
    obstacles: &[Obstacle],
    m_inv: &Matrix7,
    rows: &mut Vec<ContactRow>,
) {
    rows.clear();
    let dt = cfg.substep_dt as f64;
    let erp = cfg.contact_erp as f64;
    let slop = cfg.contact_slop as f64;
    for_each_contact(spoon, frames, obstacles, 0.005, |c| {
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
        rows.push(ContactRow {
            jc,
            w,
            target,
            m_eff: 1.0 / m_inv_n,
            lambda: 0.0,
            person: obstacles[c.obstacle].owner == Owner::Person,
            spoon: c.spoon,
        });
    });
}

/// Position motors as PyBullet makes them (a velocity constraint asking for
/// gain * error / dt, its impulse capped by the force limit) solved together with the
/// contacts, so that a blocked joint pushes with its whole force limit. Returns the joint
/// velocities and the spoon's and the whole robot's normal force on the person (N).
pub(super) fn solve(
    cfg: &WorldConfig,
    error: &[f64; NJ],
    m_inv: &Matrix7,
    mut qd: Vector7,
    rows: &mut [ContactRow],
) -> (Vector7, f64, f64) {
    let dt = cfg.substep_dt as f64;
    let (kp, cap) = (cfg.motor_gain as f64, cfg.motor_max_force as f64);
    let v_motor: [f64; NJ] = std::array::from_fn(|i| kp * error[i] / dt);
    let mut motor_impulse = [0.0f64; NJ];
    for _ in 0..SOLVER_ITERATIONS {
        for i in 0..NJ {
            let m_eff = 1.0 / m_inv[(i, i)];
            let new = (motor_impulse[i] + m_eff * (v_motor[i] - qd[i])).clamp(-cap * dt, cap * dt);
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
    let (mut f_spoon, mut f_robot) = (0.0, 0.0);
    for row in rows.iter().filter(|r| r.person) {
        f_robot += row.lambda / dt;
        if row.spoon {
            f_spoon += row.lambda / dt;
        }
    }
    (qd, f_spoon, f_robot)
}
