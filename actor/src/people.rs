//! A population of simulated people (`docs/people.md`): who pbrl is judged on.
//!
//! A person is a [`Profile`]: the seven preference weights, a body, an impairment, a
//! comfort threshold and a taste that no comfort feature names. The population spreads the
//! weights that make people differ in comfort (speed, force, spills) over two orders of
//! magnitude around the paper's person, on a grid so that every sample of n >= 2 people
//! holds both ends; it fixes one body and one impairment per person (a person does not
//! change body between attempts), and gives a third of the people a taste of where the
//! spoon comes from and a third a taste for fewer, bigger bites.

use rand::seq::SliceRandom;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::config::{BodySize, Impairment, PreferenceWeights, Profile, Taste};

/// How far each comfort family's weights reach: 10^-SPAN to 10^SPAN times the paper's.
pub const SPAN: f64 = 1.0;

/// The taste kinds a population holds, in the order people are dealt them.
pub const TASTES: [&str; 3] = ["none", "approach", "bites"];

/// One sampled person and the draws behind them (what `people.csv` lists).
#[derive(Clone, Debug, PartialEq)]
pub struct Person {
    pub profile: Profile,
    /// Scale of the speed terms (C_v, C_fdv) over the paper's person.
    pub speed: f64,
    /// Scale of the force terms (C_f, C_hf).
    pub force: f64,
    /// Scale of the spill term (C_fd).
    pub spills: f64,
    /// Scale of the task-like terms (C_d, C_e).
    pub task: f64,
    /// The taste no comfort feature names: `none`, `approach` or `bites`.
    pub taste: &'static str,
}

/// `n` people drawn with `seed`, named `{prefix}{i:02}` (i from 1).
pub fn sample(n: usize, seed: u64, prefix: &str) -> Vec<Person> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    // The log-scale of each comfort family: the grid -SPAN..SPAN in n points, dealt out in
    // an order of its own per family (a Latin hypercube on the grid), so that every family
    // holds its two ends and no two families move together.
    let grid: Vec<f64> = (0..n)
        .map(|k| {
            if n == 1 {
                0.0
            } else {
                -SPAN + 2.0 * SPAN * k as f64 / (n - 1) as f64
            }
        })
        .collect();
    let dealt = |rng: &mut ChaCha8Rng| {
        let mut g = grid.clone();
        g.shuffle(rng);
        g
    };
    let (speed, force, spills) = (dealt(&mut rng), dealt(&mut rng), dealt(&mut rng));
    // Tastes dealt in turn over a shuffled order: each kind to a third of the people.
    let mut order: Vec<usize> = (0..n).collect();
    order.shuffle(&mut rng);
    let paper = Profile::paper();
    let w = paper.weights;
    (0..n)
        .map(|i| {
            let ten = |e: f64| 10f64.powf(e);
            let (sp, fo, sl) = (ten(speed[i]), ten(force[i]), ten(spills[i]));
            let task = ten(rng.random_range(-0.3..=0.3));
            // Four decimals, so that a person's file reads as it was drawn.
            let scale = |v: f32, s: f64| round4(v as f64 * s);
            let weights = PreferenceWeights {
                distance: scale(w.distance, task),
                eaten: scale(w.eaten, task),
                velocity: scale(w.velocity, sp),
                force: scale(w.force, fo),
                high_force: scale(w.high_force, fo),
                food_hit: scale(w.food_hit, sl),
                food_velocity: scale(w.food_velocity, sp),
            };
            let body = if rng.random_bool(0.5) {
                BodySize::Large
            } else {
                BodySize::Small
            };
            let impairment = [
                Impairment::None,
                Impairment::Limits,
                Impairment::Weakness,
                Impairment::Tremor,
            ][rng.random_range(0..4)];
            let threshold = round4(rng.random_range(5.0..=15.0));
            let kind = TASTES[order.iter().position(|&o| o == i).unwrap_or(0) % TASTES.len()];
            let mut taste = Taste::default();
            // Drawn for everyone, so that a person's other draws do not depend on the kind.
            let azimuth = rng.random_range(-60.0..=60.0f32).to_radians();
            let elevation = rng.random_range(-60.0..=30.0f32).to_radians();
            let approach_weight = rng.random_range(0.2..=0.6f32);
            let bite_weight = rng.random_range(3.0..=10.0f32);
            match kind {
                "approach" => {
                    // Azimuth about the face's front (-y in the head frame), elevation
                    // above (+z) or below it.
                    taste.approach = [
                        elevation.cos() * azimuth.sin(),
                        -elevation.cos() * azimuth.cos(),
                        elevation.sin(),
                    ]
                    .map(|v| round4(v as f64));
                    taste.approach_weight = round4(approach_weight as f64);
                }
                "bites" => taste.bite_weight = round4(bite_weight as f64),
                _ => {}
            }
            Person {
                profile: Profile {
                    name: format!("{prefix}{:02}", i + 1),
                    weights,
                    body,
                    impairment,
                    high_force_threshold: threshold,
                    taste,
                },
                speed: sp,
                force: fo,
                spills: sl,
                task,
                taste: kind,
            }
        })
        .collect()
}

fn round4(v: f64) -> f32 {
    ((v * 1e4).round() / 1e4) as f32
}

/// The header of `people.csv`.
pub const CSV_HEADER: &str = "name,speed_x,force_x,spills_x,task_x,body,impairment,\
high_force_threshold,taste,approach_x,approach_y,approach_z,approach_weight,bite_weight";

impl Person {
    /// This person's row of `people.csv`.
    pub fn csv_row(&self) -> String {
        let p = &self.profile;
        let t = &p.taste;
        format!(
            "{},{:.3},{:.3},{:.3},{:.3},{},{},{:.2},{},{:.3},{:.3},{:.3},{:.3},{:.3}",
            p.name,
            self.speed,
            self.force,
            self.spills,
            self.task,
            config_name(&p.body),
            config_name(&p.impairment),
            p.high_force_threshold,
            self.taste,
            t.approach[0],
            t.approach[1],
            t.approach[2],
            t.approach_weight,
            t.bite_weight,
        )
    }
}

/// A unit enum's name in configs (its serde name: `large`, `tremor`).
fn config_name<T: serde::Serialize>(v: &T) -> String {
    serde_json::to_value(v)
        .ok()
        .and_then(|v| v.as_str().map(str::to_owned))
        .unwrap_or_default()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::WorldConfig;

    #[test]
    fn a_sample_spans_both_ends_of_every_family_and_every_taste() {
        let people = sample(6, 1, "p");
        assert_eq!(people.len(), 6);
        for scale in [
            |p: &Person| p.speed,
            |p: &Person| p.force,
            |p: &Person| p.spills,
        ] {
            let lo = people.iter().map(scale).fold(f64::INFINITY, f64::min);
            let hi = people.iter().map(scale).fold(0.0, f64::max);
            assert!(
                (lo - 0.1).abs() < 1e-9 && (hi - 10.0).abs() < 1e-9,
                "{lo} {hi}"
            );
        }
        for kind in TASTES {
            let n = people.iter().filter(|p| p.taste == kind).count();
            assert_eq!(n, 2, "{kind}");
        }
        for p in &people {
            let cfg = WorldConfig {
                profile: p.profile.clone(),
                ..WorldConfig::default()
            };
            cfg.validate().unwrap();
            let kinds = p.profile.taste.kinds();
            match p.taste {
                "none" => assert!(kinds.is_empty()),
                k => assert_eq!(
                    kinds,
                    vec![if k == "approach" { "approach" } else { "bites" }]
                ),
            }
            assert_ne!(p.profile.body, BodySize::Random);
            assert_ne!(p.profile.impairment, Impairment::Random);
            // The paper's speed weights scaled together.
            let w = &p.profile.weights;
            assert!((w.food_velocity / w.velocity / 40.0 - 1.0).abs() < 1e-3);
        }
        // Names, seeds.
        assert_eq!(people[0].profile.name, "p01");
        assert_eq!(sample(6, 1, "p"), people);
        assert_ne!(sample(6, 2, "p"), people);
        assert_eq!(sample(1, 1, "p")[0].speed, 1.0);
        assert!(sample(0, 1, "p").is_empty());
    }
}
