//! The Baxter right arm: forward kinematics, Jacobians and damped-least-squares IK.
//!
//! The chain is the table of `shared/feeding.md` (from the Baxter URDF); every joint turns
//! about its local z axis. Computed in f64; the physics takes f32 poses from it.

use nalgebra::{
    Isometry3, Matrix6, OMatrix, Point3, Translation3, UnitQuaternion, Vector3, Vector6, U7,
};
use rand::Rng;

/// Number of arm joints.
pub const NJ: usize = 7;

/// Joint names, base to wrist.
pub const JOINT_NAMES: [&str; NJ] = ["s0", "s1", "e0", "e1", "w0", "w1", "w2"];

/// Joint limits (rad), from the URDF (rounded as in `feeding.md`).
// NOTE: -1.5708 is the URDF's number, not a rounded pi/2.
#[allow(clippy::approx_constant)]
pub const JOINT_LIMITS: [[f64; 2]; NJ] = [
    [-1.7017, 1.7017],
    [-2.147, 1.047],
    [-3.0542, 3.0542],
    [-0.05, 2.618],
    [-3.059, 3.059],
    [-1.5708, 2.094],
    [-3.059, 3.059],
];

/// Baxter's neutral pose, the first rest pose IK starts from.
pub const NEUTRAL: [f64; NJ] = [0.0, -0.55, 0.0, 0.75, 0.0, 1.26, 0.0];

/// A 6 x 7 Jacobian (linear rows first, then angular).
pub type Jacobian = OMatrix<f64, nalgebra::U6, U7>;

fn origin(xyz: [f64; 3], rpy: [f64; 3]) -> Isometry3<f64> {
    Isometry3::from_parts(
        Translation3::new(xyz[0], xyz[1], xyz[2]),
        UnitQuaternion::from_euler_angles(rpy[0], rpy[1], rpy[2]),
    )
}

/// The fixed kinematic chain of the arm.
#[derive(Clone, Debug)]
pub struct Arm {
    /// torso -> arm_mount.
    mount: Isometry3<f64>,
    /// Origin of each joint in its parent frame.
    joints: [Isometry3<f64>; NJ],
    /// wrist (after w2) -> right_gripper (the end effector).
    tool: Isometry3<f64>,
    /// right_gripper -> spoon origin (centre of the bowl floor).
    spoon: Isometry3<f64>,
}

/// Every frame of one arm configuration, in the world.
#[derive(Clone, Debug)]
pub struct ArmFrames {
    /// Frame of each joint after its rotation; its origin lies on the joint axis and its z
    /// axis is the joint axis.
    pub joints: [Isometry3<f64>; NJ],
    /// The end effector (`right_gripper`).
    pub ee: Isometry3<f64>,
    /// The spoon origin.
    pub spoon: Isometry3<f64>,
}

impl ArmFrames {
    /// Linear and angular Jacobian of a point `p` carried by the link after joint `last`
    /// (joints after `last` do not move it).
    pub fn jacobian_at(&self, p: &Point3<f64>, last: usize) -> Jacobian {
        let mut j = Jacobian::zeros();
        for i in 0..=last.min(NJ - 1) {
            let f = &self.joints[i];
            let z = f.rotation * Vector3::z();
            let lin = z.cross(&(p - Point3::from(f.translation.vector)));
            j.fixed_view_mut::<3, 1>(0, i).copy_from(&lin);
            j.fixed_view_mut::<3, 1>(3, i).copy_from(&z);
        }
        j
    }

    /// Jacobian of the spoon origin.
    pub fn spoon_jacobian(&self) -> Jacobian {
        self.jacobian_at(&Point3::from(self.spoon.translation.vector), NJ - 1)
    }

    /// Jacobian of the end effector.
    pub fn ee_jacobian(&self) -> Jacobian {
        self.jacobian_at(&Point3::from(self.ee.translation.vector), NJ - 1)
    }

    /// The segments of the arm's links, each from one joint origin to the next (the last
    /// ends at the end effector), with the index of the joint that moves it.
    pub fn link_segments(&self) -> [(Point3<f64>, Point3<f64>, usize); NJ] {
        std::array::from_fn(|i| {
            let a = Point3::from(self.joints[i].translation.vector);
            let b = if i + 1 < NJ {
                Point3::from(self.joints[i + 1].translation.vector)
            } else {
                Point3::from(self.ee.translation.vector)
            };
            (a, b, i)
        })
    }
}

impl Default for Arm {
    fn default() -> Self {
        Self::baxter()
    }
}

impl Arm {
    /// Baxter's right arm holding the feeding spoon.
    pub fn baxter() -> Self {
        use std::f64::consts::FRAC_PI_2 as H;
        let joints = [
            origin([0.055695, 0.0, 0.011038], [0.0, 0.0, 0.0]),
            origin([0.069, 0.0, 0.27035], [-H, 0.0, 0.0]),
            origin([0.102, 0.0, 0.0], [H, 0.0, H]),
            origin([0.069, 0.0, 0.26242], [-H, -H, 0.0]),
            origin([0.10359, 0.0, 0.0], [H, 0.0, H]),
            origin([0.01, 0.0, 0.2707], [-H, -H, 0.0]),
            origin([0.115975, 0.0, 0.0], [H, 0.0, H]),
        ];
        // wrist -> hand -> gripper_base -> right_gripper, all pure z offsets.
        let tool = origin([0.0, 0.0, 0.11355 + 0.025 + 0.1327], [0.0; 3]);
        // NOTE: the spoon's rotation in the EE frame is given as rows in feeding.md; the
        // matrix is orthonormal to 1e-4, so it is re-orthonormalised here.
        let rows = nalgebra::Matrix3::new(0.0, 0.0998, -0.995, 0.0, 0.995, 0.0998, 1.0, 0.0, 0.0);
        let rot = UnitQuaternion::from_matrix(&rows);
        let spoon = Isometry3::from_parts(Translation3::new(0.1, -0.02, -0.0127), rot);
        // NOTE: the mount's -0.7854 is the URDF's number, not a rounded pi/4.
        #[allow(clippy::approx_constant)]
        let mount = origin([0.024645, -0.219645, 0.118588], [0.0, 0.0, -0.7854]);
        Self {
            mount,
            joints,
            tool,
            spoon,
        }
    }

    /// The spoon origin in the end-effector frame.
    pub fn spoon_in_ee(&self) -> &Isometry3<f64> {
        &self.spoon
    }

    /// Forward kinematics from the base pose (the torso frame) and joint angles.
    pub fn frames(&self, base: &Isometry3<f64>, q: &[f64; NJ]) -> ArmFrames {
        let mut t = base * self.mount;
        let joints = std::array::from_fn(|i| {
            t = t * self.joints[i] * UnitQuaternion::from_axis_angle(&Vector3::z_axis(), q[i]);
            t
        });
        let ee = t * self.tool;
        ArmFrames {
            joints,
            ee,
            spoon: ee * self.spoon,
        }
    }

    /// Damped-least-squares IK for the end-effector pose `target`, starting from `q0`.
    /// Returns the joint angles (within limits) and whether the pose was reached within
    /// `pos_tol` (m) and `rot_tol` (quaternion difference norm).
    pub fn ik(
        &self,
        base: &Isometry3<f64>,
        target: &Isometry3<f64>,
        q0: &[f64; NJ],
        pos_tol: f64,
        rot_tol: f64,
    ) -> ([f64; NJ], bool) {
        const ITERS: usize = 200;
        const DAMPING: f64 = 0.05;
        let mut q = *q0;
        for _ in 0..ITERS {
            let f = self.frames(base, &q);
            let (e, pos_err, rot_err) = pose_error(target, &f.ee);
            if pos_err < pos_tol * 0.1 && rot_err < rot_tol * 0.1 {
                break;
            }
            // NOTE: the null-space pull towards the rest pose keeps solutions away from the
            // joint limits, where a feeder could not move on.
            let pull = posture_pull(&q, q0, 0.1, 0.2);
            let dq = dls_velocity(&f.ee_jacobian(), &e, DAMPING, &pull);
            let dq = nalgebra::SVector::<f64, NJ>::from(dq);
            // Cap the step so the linearisation holds.
            let scale = (0.3 / dq.amax()).min(1.0);
            for i in 0..NJ {
                q[i] = (q[i] + scale * dq[i]).clamp(JOINT_LIMITS[i][0], JOINT_LIMITS[i][1]);
            }
        }
        let f = self.frames(base, &q);
        let (_, pos_err, rot_err) = pose_error(target, &f.ee);
        (q, pos_err < pos_tol && rot_err < rot_tol)
    }
}

/// The 6-vector error (position, rotation vector) taking `current` to `target`, the
/// position error norm and the quaternion difference norm (sign-aligned).
pub fn pose_error(target: &Isometry3<f64>, current: &Isometry3<f64>) -> (Vector6<f64>, f64, f64) {
    let dp = target.translation.vector - current.translation.vector;
    let dr = (target.rotation * current.rotation.inverse()).scaled_axis();
    let (a, b) = (target.rotation.coords, current.rotation.coords);
    let qdiff = (a - b).norm().min((a + b).norm());
    let mut e = Vector6::zeros();
    e.fixed_rows_mut::<3>(0).copy_from(&dp);
    e.fixed_rows_mut::<3>(3).copy_from(&dr);
    (e, dp.norm(), qdiff)
}

/// Joint velocities that give the 6D twist `twist` (linear, angular) by damped least
/// squares, plus `secondary` projected into the Jacobian's null space (a motion that does
/// not disturb the twist, such as drifting back towards a comfortable posture).
pub fn dls_velocity(
    j: &Jacobian,
    twist: &Vector6<f64>,
    damping: f64,
    secondary: &[f64; NJ],
) -> [f64; NJ] {
    let jj = j * j.transpose() + Matrix6::identity() * (damping * damping);
    let Some(inv) = jj.try_inverse() else {
        return [0.0; NJ];
    };
    let pinv = j.transpose() * inv;
    let z = nalgebra::SVector::<f64, NJ>::from_column_slice(secondary);
    let dq = pinv * twist + (z - pinv * (j * z));
    std::array::from_fn(|i| dq[i])
}

/// Like [`dls_velocity`], but a joint at (or within `margin` of) a limit that the motion
/// would push further in is locked and the rest re-solved, so the twist is not lost on a
/// joint that cannot move.
pub fn dls_velocity_within_limits(
    j: &Jacobian,
    twist: &Vector6<f64>,
    damping: f64,
    secondary: &[f64; NJ],
    q: &[f64; NJ],
    margin: f64,
) -> [f64; NJ] {
    let mut j = *j;
    let mut secondary = *secondary;
    let mut locked = [false; NJ];
    loop {
        let dq = dls_velocity(&j, twist, damping, &secondary);
        let mut changed = false;
        for i in 0..NJ {
            let [lo, hi] = JOINT_LIMITS[i];
            let blocked =
                (q[i] - lo < margin && dq[i] < 0.0) || (hi - q[i] < margin && dq[i] > 0.0);
            if blocked && !locked[i] {
                locked[i] = true;
                changed = true;
                j.column_mut(i).fill(0.0);
                secondary[i] = 0.0;
            }
        }
        if !changed {
            return std::array::from_fn(|i| if locked[i] { 0.0 } else { dq[i] });
        }
    }
}

/// A pull towards `rest` plus a push away from any limit closer than `margin`.
pub fn posture_pull(q: &[f64; NJ], rest: &[f64; NJ], gain: f64, margin: f64) -> [f64; NJ] {
    std::array::from_fn(|i| {
        let [lo, hi] = JOINT_LIMITS[i];
        let push = (margin - (q[i] - lo)).max(0.0) - (margin - (hi - q[i])).max(0.0);
        gain * (rest[i] - q[i]) + 5.0 * gain * push
    })
}

/// A random rest pose: the neutral pose plus U(-spread, spread) per joint, within limits.
pub fn random_rest(rng: &mut impl Rng, spread: f64) -> [f64; NJ] {
    std::array::from_fn(|i| {
        (NEUTRAL[i] + rng.random_range(-spread..=spread))
            .clamp(JOINT_LIMITS[i][0], JOINT_LIMITS[i][1])
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn jacobian_matches_finite_differences() {
        let arm = Arm::baxter();
        let base = Isometry3::translation(-0.85, -0.2, 0.925);
        let q = [0.1, -0.4, 0.2, 1.0, -0.3, 1.1, 0.2];
        let f = arm.frames(&base, &q);
        let j = f.spoon_jacobian();
        let h = 1e-6;
        for i in 0..NJ {
            let mut q2 = q;
            q2[i] += h;
            let f2 = arm.frames(&base, &q2);
            let dp = (f2.spoon.translation.vector - f.spoon.translation.vector) / h;
            let dr = (f2.spoon.rotation * f.spoon.rotation.inverse()).scaled_axis() / h;
            for k in 0..3 {
                assert!((dp[k] - j[(k, i)]).abs() < 1e-4, "lin {i},{k}");
                assert!((dr[k] - j[(3 + k, i)]).abs() < 1e-4, "ang {i},{k}");
            }
        }
    }

    #[test]
    fn ik_reaches_the_start_pose_and_spoon_sits_where_the_spec_says() {
        let arm = Arm::baxter();
        let base = Isometry3::translation(-0.85, -0.2, 0.925);
        let rot = UnitQuaternion::from_euler_angles(
            std::f64::consts::FRAC_PI_2,
            0.0,
            std::f64::consts::FRAC_PI_2,
        );
        let target = Isometry3::from_parts(Translation3::new(-0.15, -0.65, 1.15), rot);
        let (q, ok) = arm.ik(&base, &target, &NEUTRAL, 0.03, 0.03);
        assert!(ok, "IK failed: {q:?}");
        let f = arm.frames(&base, &q);
        let s = f.spoon.translation.vector;
        // feeding.md: the spoon origin then sits near (-0.163, -0.55, 1.13).
        assert!(
            (s - Vector3::new(-0.1627, -0.55, 1.13)).norm() < 0.03,
            "{s:?}"
        );
        for (i, qi) in q.iter().enumerate() {
            assert!(*qi >= JOINT_LIMITS[i][0] && *qi <= JOINT_LIMITS[i][1]);
        }
    }
}
