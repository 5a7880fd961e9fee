//! The feeding world: determinism, physics sanity, the scripted feeder, bad input.

use pbrl_actor::config::WorldConfig;
use pbrl_actor::controller::{Controller, ControllerKind, Scripted};
use pbrl_actor::kinematics::{JOINT_LIMITS, NJ};
use pbrl_actor::rollout::run_episode;
use pbrl_actor::{FeedingWorld, WorldError, OBS_DIM};
use pbrl_common::Trajectory;

fn fixed_world() -> FeedingWorld {
    FeedingWorld::new(WorldConfig::fixed()).expect("the fixed test world is valid")
}

/// Distance of every food particle from the spoon origin.
fn food_to_spoon(world: &FeedingWorld) -> Vec<f64> {
    let spoon = world.frames().unwrap().spoon.translation.vector;
    world
        .food_positions()
        .unwrap()
        .iter()
        .map(|p| (p.coords - spoon).norm())
        .collect()
}

#[test]
fn same_seed_and_actions_give_bit_identical_trajectories() {
    let mut world = FeedingWorld::new(WorldConfig::default()).unwrap();
    let run = |world: &mut FeedingWorld, seed| {
        let mut c = Controller::new(ControllerKind::Random);
        run_episode(world, &mut c, seed).unwrap()
    };
    let a = run(&mut world, 7);
    // Another episode in between must leave no trace in the next one.
    let other = run(&mut world, 8);
    let b = run(&mut world, 7);
    assert_eq!(
        a.encode(),
        b.encode(),
        "same seed and actions, different bytes"
    );
    assert_ne!(a.encode(), other.encode());
    // A fresh world gives the same bytes too.
    let c = run(&mut FeedingWorld::new(WorldConfig::default()).unwrap(), 7);
    assert_eq!(a.encode(), c.encode());
}

#[test]
fn zero_action_keeps_the_food_in_the_spoon_for_a_whole_episode() {
    let mut world = FeedingWorld::new(WorldConfig::default()).unwrap();
    for seed in 0..4 {
        world.reset(seed).unwrap();
        let start = world.joints().unwrap();
        for _ in 0..200 {
            let s = world.step(&[0.0; 7]).unwrap();
            assert_eq!(s.food.spilled_total, 0, "seed {seed}: food spilled");
            assert_eq!(s.food.hits_total, 0, "seed {seed}: food on the person");
        }
        for d in food_to_spoon(&world) {
            assert!(
                d < 0.03,
                "seed {seed}: a particle is {d:.3} m from the spoon origin"
            );
        }
        // The arm holds still: the original drifts by 5e-10 rad.
        let end = world.joints().unwrap();
        for i in 0..NJ {
            assert!(
                (end[i] - start[i]).abs() < 1e-6,
                "seed {seed}: joint {i} drifted"
            );
        }
    }
}

#[test]
fn a_spoon_turned_over_spills_each_particle_once() {
    let mut world = fixed_world();
    let n = world.config().food_count;
    world.reset(1).unwrap();
    // Turn the last wrist joint (its axis runs along the gripper) as far as it goes.
    let dir = if world.joints().unwrap()[6] > 0.0 {
        -1.0
    } else {
        1.0
    };
    let mut last = None;
    for _ in 0..200 {
        let s = world.step(&[0.0, 0.0, 0.0, 0.0, 0.0, 0.0, dir]).unwrap();
        // Spilling costs 5 in r_R, in the step it happens.
        if s.food.spilled > 0 {
            assert!(s.rewards.robot < -5.0 * s.food.spilled as f32 + 0.01);
        }
        last = Some(s);
    }
    let last = last.unwrap();
    // Spilled particles fall far from the spoon and stay there, yet count once each.
    assert_eq!(
        last.food.spilled_total, n,
        "every particle spills, each once"
    );
    assert_eq!(last.food.eaten_total, 0);
}

#[test]
fn the_scripted_feeder_eats_the_food() {
    let mut world = FeedingWorld::new(WorldConfig::default()).unwrap();
    let mut c = Controller::new(ControllerKind::Scripted);
    let mut successes = 0;
    for seed in 0..8 {
        let t = run_episode(&mut world, &mut c, seed).unwrap();
        successes += t.outcome.success as u32;
        if t.outcome.success {
            assert!(
                t.rewards.iter().any(|r| r.terms[1] > 0.0),
                "C_e counts the eating"
            );
            assert!(t.outcome.eaten >= 6);
            // Eating pays: 20 per particle in r_R.
            assert!(t.outcome.return_robot > 0.0, "seed {seed}: {:?}", t.outcome);
        }
    }
    assert!(
        successes >= 6,
        "the scripted feeder succeeded {successes} times in 8"
    );
}

#[test]
fn scripted_beats_random_on_the_ground_truth() {
    let mut world = FeedingWorld::new(WorldConfig::default()).unwrap();
    let mean = |world: &mut FeedingWorld, kind| {
        let mut c = Controller::new(kind);
        (100..104)
            .map(|s| run_episode(world, &mut c, s).unwrap().outcome.return_truth)
            .sum::<f32>()
            / 4.0
    };
    let scripted = mean(&mut world, ControllerKind::Scripted);
    let random = mean(&mut world, ControllerKind::Random);
    assert!(
        scripted > random + 100.0,
        "scripted {scripted}, random {random}"
    );
    assert!(random < -50.0, "a random policy eats nothing: {random}");
}

#[test]
fn food_dropped_on_the_person_is_a_hit_once_per_particle() {
    let mut world = fixed_world();
    let n = world.config().food_count;
    let mut all_hits = 0;
    for seed in [0, 2] {
        world.reset(seed).unwrap();
        assert_eq!(
            world.food_counts().unwrap().hits_total,
            0,
            "no hits at reset"
        );
        // Hold the spoon 20 cm in front of the face, then turn it over above the lap.
        let mut c = Scripted::reaching(0.2, 0.05);
        let (mut hits, mut c_fd, mut dir) = (0, 0.0, 0.0);
        for t in 0..200 {
            if t == 100 {
                dir = if world.joints().unwrap()[6] > 0.0 {
                    -1.0
                } else {
                    1.0
                };
            }
            let a = if t < 100 {
                c.act(&world).unwrap()
            } else {
                [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, dir]
            };
            let s = world.step(&a).unwrap();
            hits += s.food.hits;
            c_fd += s.rewards.terms[5];
        }
        let counts = world.food_counts().unwrap();
        // The particles lie on the person for dozens of steps; each counts once.
        assert!(
            counts.hits_total <= n,
            "seed {seed}: {} hits from {n} particles",
            counts.hits_total
        );
        assert_eq!(hits, counts.hits_total);
        assert_eq!(c_fd, -(counts.hits_total as f32), "C_fd = -(new hits)");
        all_hits += counts.hits_total;
    }
    assert!(
        all_hits >= 8,
        "food dropped on the lap: only {all_hits} hits"
    );
}

#[test]
fn the_observation_is_in_the_robot_base_frame() {
    let mut world = FeedingWorld::new(WorldConfig::default()).unwrap();
    let mut checked = 0;
    for seed in 0..6 {
        let obs = world.reset(seed).unwrap();
        let base = world.base().unwrap();
        if base.rotation.angle() < 0.05 {
            continue; // a frame mix-up only shows with a turned base
        }
        checked += 1;
        let inv = base.inverse();
        let spoon = inv * world.frames().unwrap().spoon;
        let head = inv * world.head().unwrap();
        let rel = inv.rotation
            * (world.frames().unwrap().spoon.translation.vector - world.mouth().unwrap().coords);
        let close =
            |o: &[f32], x: &[f64]| o.iter().zip(x).all(|(a, b)| (*a as f64 - b).abs() < 1e-5);
        assert!(
            close(&obs[0..3], spoon.translation.vector.as_slice()),
            "spoon position"
        );
        assert!(
            close(&obs[3..7], spoon.rotation.coords.as_slice()),
            "spoon quaternion x, y, z, w"
        );
        assert!(close(&obs[7..10], rel.as_slice()), "spoon minus mouth");
        assert!(
            close(&obs[10..17], &world.joints().unwrap()),
            "joint angles"
        );
        assert!(
            close(&obs[17..20], head.translation.vector.as_slice()),
            "head position"
        );
        assert!(
            close(&obs[20..24], head.rotation.coords.as_slice()),
            "head quaternion"
        );
        assert_eq!(obs[24], 0.0, "no force at reset");
    }
    assert!(checked >= 3, "too few turned bases to check ({checked})");
}

#[test]
fn an_episode_depends_on_its_seed_alone() {
    // The random controller restarts its stream from each episode's seed, so episode 5 of
    // a demo is the same as a record of seed 5.
    let mut world = FeedingWorld::new(WorldConfig::default()).unwrap();
    let mut c = Controller::new(ControllerKind::Random);
    for s in 0..5 {
        run_episode(&mut world, &mut c, s).unwrap();
    }
    let in_a_run = run_episode(&mut world, &mut c, 5).unwrap();
    let alone = run_episode(
        &mut FeedingWorld::new(WorldConfig::default()).unwrap(),
        &mut Controller::new(ControllerKind::Random),
        5,
    )
    .unwrap();
    assert_eq!(in_a_run.encode(), alone.encode());
}

#[test]
fn a_failed_reset_leaves_no_episode_behind() {
    let mut world = FeedingWorld::new(WorldConfig {
        // No start pose within 1 mm and 1e-6 exists from these few tries.
        ik_pos_tol: 1e-9,
        ik_rot_tol: 1e-9,
        ik_tries: 1,
        ..WorldConfig::fixed()
    })
    .unwrap();
    let e = world.reset(0).unwrap_err();
    assert!(
        matches!(e, WorldError::ResetFailed { seed: 0, tries: 1 }),
        "{e}"
    );
    assert!(matches!(world.step(&[0.0; 7]), Err(WorldError::NotReset)));
}

/// The largest spoon force and the smallest C_hf over an episode of the scripted feeder
/// stopping `stop` m in front of the mouth.
fn press(stop: f64, final_speed: f64, gain: f64) -> (f32, f32) {
    let mut world = fixed_world();
    let (mut force, mut c_hf) = (0.0f32, 0.0f32);
    for seed in 0..2 {
        world.reset(seed).unwrap();
        let mut c = Scripted::reaching(stop, final_speed);
        c.gain = gain;
        for _ in 0..200 {
            let s = world.step(&c.act(&world).unwrap()).unwrap();
            force = force.max(s.spoon_force);
            c_hf = c_hf.min(s.rewards.terms[4]);
            assert_eq!(
                s.obs[24], s.spoon_force,
                "observation 24 is the spoon force"
            );
        }
    }
    (force, c_hf)
}

#[test]
fn a_spoon_pressed_into_the_face_is_a_hard_force_and_a_gentle_touch_is_not() {
    // Rammed 8 cm past the mouth target, into the face.
    let (force, c_hf) = press(-0.08, 0.5, 20.0);
    assert!(force >= 10.0, "pressing gave only {force} N");
    assert!(c_hf < 0.0, "C_hf stayed {c_hf}");
    // Slowly up to the lips and 5 mm on.
    let (force, c_hf) = press(-0.005, 0.02, 1.5);
    assert!(force > 0.0, "the gentle approach never touched the face");
    assert!(force < 10.0, "a gentle touch gave {force} N");
    assert_eq!(c_hf, 0.0);
}

#[test]
fn joint_limits_are_never_exceeded() {
    let mut world = FeedingWorld::new(WorldConfig::default()).unwrap();
    let mut c = Controller::new(ControllerKind::Random);
    for seed in 0..3 {
        world.reset(seed).unwrap();
        for t in 0..200 {
            // Random actions, then pushes against every limit at once.
            let a = if t < 100 {
                c.act(&world).unwrap()
            } else if t < 150 {
                [1.0; 7]
            } else {
                [-1.0; 7]
            };
            world.step(&a).unwrap();
            let q = world.joints().unwrap();
            for i in 0..NJ {
                let [lo, hi] = JOINT_LIMITS[i];
                assert!(
                    q[i] >= lo && q[i] <= hi,
                    "seed {seed} step {t}: joint {i} at {}",
                    q[i]
                );
            }
        }
    }
}

#[test]
fn the_arm_responds_as_the_original_does() {
    // feeding.md: under a full action s0-e1 move about 0.005 rad in the first step and ramp
    // up to about 0.029 rad per step within about 5 steps; w0-w2 move 0.027-0.030 at once.
    let mut world = fixed_world();
    for seed in 0..2 {
        world.reset(seed).unwrap();
        let q0 = world.joints().unwrap();
        let a: [f32; 7] = std::array::from_fn(|i| if q0[i] > 0.0 { -1.0 } else { 1.0 });
        let mut moves = Vec::new();
        let mut prev = q0;
        for _ in 0..6 {
            world.step(&a).unwrap();
            let q = world.joints().unwrap();
            moves.push(std::array::from_fn::<f64, NJ, _>(|i| {
                (q[i] - prev[i]).abs()
            }));
            prev = q;
        }
        let (first, sixth) = (&moves[0], &moves[5]);
        for i in 0..4 {
            assert!(
                first[i] > 0.001 && first[i] < 0.01,
                "seed {seed} joint {i} first step {}",
                first[i]
            );
            assert!(
                sixth[i] > 0.027 && sixth[i] < 0.031,
                "seed {seed} joint {i} step 6 {}",
                sixth[i]
            );
        }
        for (i, m) in first.iter().enumerate().skip(4) {
            assert!(
                *m > 0.022 && *m < 0.031,
                "seed {seed} joint {i} first step {m}"
            );
        }
    }
}

#[test]
fn the_observation_and_rewards_agree() {
    let mut world = FeedingWorld::new(WorldConfig::default()).unwrap();
    let mut c = Controller::new(ControllerKind::Random);
    let t = run_episode(&mut world, &mut c, 42).unwrap();
    assert_eq!(t.obs_dim as usize, OBS_DIM);
    for (k, r) in t.rewards.iter().enumerate() {
        let o = t.obs_at(k + 1);
        // Spoon minus mouth (in the base frame) has the length d, and r_task = -d.
        let d = (o[7] * o[7] + o[8] * o[8] + o[9] * o[9]).sqrt();
        assert!(
            (d + r.task).abs() < 1e-4,
            "step {k}: |spoon - mouth| {d} vs r_task {}",
            r.task
        );
        assert_eq!(r.terms[0], r.task, "C_d = -d");
        // Quaternions are unit length.
        let q = (o[3] * o[3] + o[4] * o[4] + o[5] * o[5] + o[6] * o[6]).sqrt();
        assert!((q - 1.0).abs() < 1e-4);
        // Ground truth is r_R + r_H, r_H the weighted terms.
        let w = WorldConfig::default().profile.weights.as_array();
        let h: f32 = r.terms.iter().zip(w).map(|(t, w)| t * w).sum();
        assert!((h - r.human).abs() < 1e-3);
        assert!((r.robot + r.human - r.truth).abs() < 1e-3);
    }
    assert!(t.outcome.truncated && !t.outcome.terminated);
    assert_eq!(t.outcome.steps, 200);
}

#[test]
fn the_trajectory_record_is_compact_and_decodes() {
    let mut world = fixed_world();
    let mut c = Controller::new(ControllerKind::Scripted);
    let t = run_episode(&mut world, &mut c, 3).unwrap();
    let bytes = t.encode();
    assert!(
        bytes.len() < 100_000,
        "a 200-step record takes {} bytes",
        bytes.len()
    );
    let back = Trajectory::decode(&bytes).unwrap();
    assert_eq!(back, t);
    let rp = back.replay.as_ref().unwrap();
    assert_eq!(rp.spoon.len(), 201);
    assert_eq!(rp.food.len(), 201 * 8);
    assert_eq!(
        rp.food_outcome.iter().filter(|&&s| s == 1).count() as u32,
        back.outcome.eaten
    );
}

#[test]
fn bad_actions_are_refused_with_the_value_named() {
    let mut world = fixed_world();
    assert!(matches!(world.step(&[0.0; 7]), Err(WorldError::NotReset)));
    world.reset(0).unwrap();
    let e = world.step(&[0.0; 6]).unwrap_err();
    assert!(
        matches!(
            e,
            WorldError::ActionLength {
                found: 6,
                expected: 7
            }
        ),
        "{e}"
    );
    let mut a = [0.0f32; 7];
    a[3] = f32::NAN;
    let e = world.step(&a).unwrap_err();
    assert!(e.to_string().contains("action[3] = NaN"), "{e}");
    a[3] = f32::INFINITY;
    let e = world.step(&a).unwrap_err();
    assert!(e.to_string().contains("action[3] = inf"), "{e}");
    // A refused action leaves the episode where it was.
    assert_eq!(world.steps().unwrap(), 0);
    for _ in 0..200 {
        world.step(&[0.0; 7]).unwrap();
    }
    assert!(matches!(
        world.step(&[0.0; 7]),
        Err(WorldError::EpisodeOver { steps: 200 })
    ));
}

#[test]
fn bad_configs_are_refused_with_the_field_named() {
    let cfg = WorldConfig {
        food_count: 0,
        ..WorldConfig::default()
    };
    let e = FeedingWorld::new(cfg).err().unwrap();
    assert!(e.to_string().contains("food_count = 0"), "{e}");
    let cfg = WorldConfig {
        food_radius: -0.005,
        ..WorldConfig::default()
    };
    let e = FeedingWorld::new(cfg).err().unwrap();
    assert!(e.to_string().contains("food_radius = -0.005"), "{e}");
}

/// The taste terms of a person (`Taste`) on the scripted feeder's episode, which comes in
/// from in front of the face: what they add to r_H, step by step.
fn taste_cost(taste: pbrl_actor::config::Taste) -> (Trajectory, Vec<f32>) {
    let plain = WorldConfig::fixed();
    let mut with = plain.clone();
    with.profile.taste = taste;
    let run = |cfg: WorldConfig| {
        let mut world = FeedingWorld::new(cfg).unwrap();
        run_episode(
            &mut world,
            &mut Controller::new(ControllerKind::Scripted),
            3,
        )
        .unwrap()
    };
    let (a, b) = (run(plain), run(with));
    // The taste changes what the person feels, not what happens.
    assert_eq!(a.obs, b.obs);
    let diff = a.rewards.iter().zip(&b.rewards);
    let added = diff
        .map(|(a, b)| {
            assert_eq!(a.terms, b.terms);
            assert_eq!(a.robot, b.robot);
            assert!((b.truth - b.robot - b.human).abs() < 1e-4);
            b.human - a.human
        })
        .collect();
    (b, added)
}

#[test]
fn a_taste_for_where_the_spoon_comes_from_costs_only_near_the_mouth() {
    use pbrl_actor::config::Taste;
    let front = Taste {
        approach_weight: 2.0,
        ..Taste::default()
    };
    let side = Taste {
        approach: [1.0, 0.0, 0.0],
        ..front
    };
    let (t, from_front) = taste_cost(front);
    let (_, from_side) = taste_cost(side);
    assert!(t.outcome.success, "{:?}", t.outcome);
    let near: Vec<bool> = t
        .rewards
        .iter()
        .map(|r| (0.04..0.15).contains(&-r.task))
        .collect();
    assert!(near.iter().filter(|n| **n).count() > 5);
    for ((f, s), near) in from_front.iter().zip(&from_side).zip(&near) {
        // -(1 - cos) in [-2, 0], times the weight; nothing far from the mouth.
        assert!(*f <= 1e-6 && *s <= 1e-6 && *f >= -4.0 - 1e-4 && *s >= -4.0 - 1e-4);
        if !near {
            assert_eq!((*f, *s), (0.0, 0.0));
        }
    }
    let (sf, ss): (f32, f32) = (from_front.iter().sum(), from_side.iter().sum());
    // The feeder comes in from the front: the person who wants that is nearly content,
    // the one who wants the spoon from the side is not.
    assert!(ss < 3.0 * sf - 5.0, "front {sf}, side {ss}");
    let off = Taste {
        approach_weight: 0.0,
        ..side
    };
    assert!(taste_cost(off).1.iter().all(|d| *d == 0.0));
}

#[test]
fn a_taste_for_fewer_bites_costs_each_new_bite() {
    use pbrl_actor::config::Taste;
    let (t, added) = taste_cost(Taste {
        bite_weight: 5.0,
        ..Taste::default()
    });
    let ate: Vec<bool> = t.rewards.iter().map(|r| r.terms[1] > 0.0).collect();
    let bites = (0..ate.len())
        .filter(|&i| ate[i] && (i == 0 || !ate[i - 1]))
        .count();
    assert!(bites >= 1);
    let cost: f32 = added.iter().sum();
    assert!(
        (cost + 5.0 * bites as f32).abs() < 1e-3,
        "{cost} for {bites} bites"
    );
    for (i, d) in added.iter().enumerate() {
        let new_bite = ate[i] && (i == 0 || !ate[i - 1]);
        assert_eq!(*d != 0.0, new_bite, "step {i}");
    }
}

#[test]
fn a_taste_without_a_direction_is_refused_by_name() {
    let mut cfg = WorldConfig::default();
    cfg.profile.taste.approach = [0.0; 3];
    cfg.profile.taste.approach_weight = 1.0;
    let e = cfg.validate().unwrap_err();
    assert_eq!(e.field, "profile.taste.approach");
    let e = WorldConfig::from_json(r#"{"profile": {"name": "x", "weights": {"distance": 0.5, "eaten": 0.5, "velocity": 0.25, "force": 0.3, "high_force": 0.1, "food_hit": 2.5, "food_velocity": 10.0}, "body": "large", "impairment": "none", "high_force_threshold": 10, "taste": {"bites": 1}}}"#).unwrap_err();
    assert!(e.reason.contains("bites"), "{e}");
}
