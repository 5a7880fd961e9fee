use nalgebra::*;
use pbrl_actor::kinematics::*;
fn main() {
    let arm = Arm::baxter();
    let base = Isometry3::translation(-0.85, -0.2, 0.925);
    let rot = UnitQuaternion::from_euler_angles(
        std::f64::consts::FRAC_PI_2,
        0.0,
        std::f64::consts::FRAC_PI_2,
    );
    for (x, y, z) in [
        (-0.15, -0.65, 1.15),
        (-0.1, -0.6, 1.1),
        (-0.2, -0.7, 1.2),
        (-0.1, -0.7, 1.1),
    ] {
        let target = Isometry3::from_parts(Translation3::new(x, y, z), rot);
        let (q, ok) = arm.ik(&base, &target, &NEUTRAL, 0.03, 0.03);
        let f = arm.frames(&base, &q);
        let (_, pe, re) = pose_error(&target, &f.ee);
        println!(
            "{x} {y} {z}: ok {ok} pe {pe:.4} re {re:.4} q {:?}",
            q.map(|v| (v * 100.0).round() / 100.0)
        );
    }
    // mouth
    let spoff = rot * arm.spoon_in_ee().translation.vector;
    let m = Vector3::new(0.0, -0.08, 1.2085) - spoff;
    let target = Isometry3::from_parts(m.into(), rot);
    let (q, ok) = arm.ik(&base, &target, &NEUTRAL, 0.03, 0.03);
    println!(
        "mouth ok {ok} q {:?}",
        q.map(|v| (v * 100.0).round() / 100.0)
    );
}
