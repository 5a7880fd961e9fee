use pbrl_actor::controller::{Controller, ControllerKind};
use pbrl_actor::*;
fn main() {
    let args: Vec<String> = std::env::args().collect();
    let kind = if args[1] == "random" {
        ControllerKind::Random
    } else {
        ControllerKind::Scripted
    };
    let seed: u64 = args[2].parse().unwrap();
    let mut cfg = WorldConfig::default();
    if args.len() > 3 {
        cfg.base = config::BasePlacement::Nominal;
    }
    let mut w = FeedingWorld::new(cfg).unwrap();
    let mut c = Controller::new(kind, seed);
    w.reset(seed).unwrap();
    println!(
        "base {:?} q {:?}",
        w.base().unwrap().translation.vector,
        w.joints().unwrap()
    );
    for t in 0..200 {
        let a = c.act(&w).unwrap();
        let s = w.step(&a).unwrap();
        if t % 10 == 0 || s.food.eaten > 0 {
            let sp = w.frames().unwrap().spoon.translation.vector;
            let m = w.mouth().unwrap();
            let f = w.food_positions().unwrap();
            println!("t {t} spoon {:.3} {:.3} {:.3} mouth {:.3} {:.3} {:.3} d {:.3} eaten {} F {:.2} {:.2} food0 {:.3} {:.3} {:.3} a {:?}", sp.x, sp.y, sp.z, m.x, m.y, m.z, -s.rewards.task, s.food.eaten_total, s.spoon_force, s.robot_force, f[0].x, f[0].y, f[0].z, a.map(|x| (x*100.0).round()/100.0));
        }
    }
}
