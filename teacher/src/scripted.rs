//! The six scripted teachers of B-Pref (paper Table I, `method.md` section 4): each judges a
//! pair of trajectories from their per-step ground-truth rewards, in the order of B-Pref's
//! `get_label`: skip, equal, myopic discount, Bradley-Terry choice, mistake. A seventh,
//! `hurried`, errs as people do rather than uniformly: where a pair's returns are too close
//! for it to tell apart, it takes the attempt that moves more.
//!
//! R_avg, which scales the skip and equal thresholds, is the mean ground-truth return of
//! the last `avg_window` trajectories the teacher was shown, so the teacher needs nothing
//! from the learner but the pairs themselves.

use std::collections::VecDeque;

use anyhow::{ensure, Result};
use pbrl_common::wire::Preference;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

/// The six teachers of Table I.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "kebab-case")]
pub enum TeacherKind {
    /// Perfectly rational: always the larger return.
    Oracle,
    /// Bradley-Terry choice with beta = 1.
    Noisy,
    /// The oracle's answer, flipped with probability 0.1.
    Mistake,
    /// Skips a query whose better trajectory is poor (delta_skip = 0.1).
    Skip,
    /// Answers "equal" when the returns are close (delta_equal = 0.1).
    Equal,
    /// Weighs late steps more (gamma_my = 0.99).
    Myopic,
    /// Not of Table I: errs like a person, on what the pair shows. Two attempts whose
    /// returns differ by less than a fifth of the larger (weber = 0.2) look alike to it,
    /// and it then prefers the one that moves more (the larger mean |action|): drawn to
    /// the livelier attempt, whatever the person's taste for speed.
    Hurried,
}

impl TeacherKind {
    /// The six of Table I, in its order: the first six of [`TeacherKind::EVERY`].
    pub const ALL: &'static [TeacherKind] = Self::EVERY.split_at(6).0;

    /// Table I's six, then the teachers that err like people.
    pub const EVERY: [TeacherKind; 7] = [
        TeacherKind::Oracle,
        TeacherKind::Noisy,
        TeacherKind::Mistake,
        TeacherKind::Skip,
        TeacherKind::Equal,
        TeacherKind::Myopic,
        TeacherKind::Hurried,
    ];

    /// The name used in configs, on the command line and in answers (`oracle`, ...).
    pub fn name(self) -> &'static str {
        match self {
            TeacherKind::Oracle => "oracle",
            TeacherKind::Noisy => "noisy",
            TeacherKind::Mistake => "mistake",
            TeacherKind::Skip => "skip",
            TeacherKind::Equal => "equal",
            TeacherKind::Myopic => "myopic",
            TeacherKind::Hurried => "hurried",
        }
    }
}

/// One scripted teacher. [`ScriptedConfig::of`] gives the values of Table I; every field
/// may be changed, so the teachers can also be combined (say a myopic teacher that errs).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ScriptedConfig {
    /// Which row of Table I this started from (names the teacher in answers and logs).
    pub kind: TeacherKind,
    /// Rationality beta of the Bradley-Terry choice; None = infinity (always the larger sum).
    pub beta: Option<f64>,
    /// Myopic discount gamma_my: step t of T is weighted gamma^(T-1-t) (1 = none).
    pub gamma: f64,
    /// Probability of flipping the answer (a mistake).
    pub eps: f64,
    /// Skip threshold delta_skip, a fraction of R_avg - r_min (0 = never skip).
    pub delta_skip: f64,
    /// Equal threshold delta_equal, a fraction of R_avg - r_min (0 = never equal).
    pub delta_equal: f64,
    /// Lowest possible return (the authors use -350 for feeding).
    pub r_min: f64,
    /// R_avg is the mean ground-truth return of the last this-many trajectories shown.
    pub avg_window: usize,
    /// Seeds the teacher's random draws.
    pub seed: u64,
    /// A pair whose returns differ by less than this share of the larger magnitude looks
    /// alike: the teacher takes the attempt that moves more (where the query shows the
    /// actions; else Equal). 0: never (Table I's six).
    #[serde(default)]
    pub weber: f64,
}

impl ScriptedConfig {
    /// The values of Table I for `kind`, with r_min -350 and avg_window 100.
    pub fn of(kind: TeacherKind, seed: u64) -> Self {
        let oracle = ScriptedConfig {
            kind,
            beta: None,
            gamma: 1.0,
            eps: 0.0,
            delta_skip: 0.0,
            delta_equal: 0.0,
            r_min: -350.0,
            avg_window: 100,
            seed,
            weber: 0.0,
        };
        match kind {
            TeacherKind::Oracle => oracle,
            TeacherKind::Noisy => ScriptedConfig {
                beta: Some(1.0),
                ..oracle
            },
            TeacherKind::Mistake => ScriptedConfig { eps: 0.1, ..oracle },
            TeacherKind::Skip => ScriptedConfig {
                delta_skip: 0.1,
                ..oracle
            },
            TeacherKind::Equal => ScriptedConfig {
                delta_equal: 0.1,
                ..oracle
            },
            TeacherKind::Myopic => ScriptedConfig {
                gamma: 0.99,
                ..oracle
            },
            TeacherKind::Hurried => ScriptedConfig {
                weber: 0.2,
                ..oracle
            },
        }
    }

    /// Check every field; the error names the field and its value.
    pub fn validate(&self) -> Result<()> {
        if let Some(beta) = self.beta {
            ensure!(
                beta.is_finite() && beta > 0.0,
                "teacher beta = {beta}: must be a finite number > 0 (leave it out for a \
                 perfectly rational teacher)"
            );
        }
        ensure!(
            self.gamma > 0.0 && self.gamma <= 1.0,
            "teacher gamma = {}: must be in (0, 1]",
            self.gamma
        );
        ensure!(
            (0.0..=1.0).contains(&self.eps),
            "teacher eps = {}: must be in [0, 1]",
            self.eps
        );
        ensure!(
            self.delta_skip.is_finite() && self.delta_skip >= 0.0,
            "teacher delta_skip = {}: must be a finite number >= 0",
            self.delta_skip
        );
        ensure!(
            self.delta_equal.is_finite() && self.delta_equal >= 0.0,
            "teacher delta_equal = {}: must be a finite number >= 0",
            self.delta_equal
        );
        ensure!(
            self.r_min.is_finite(),
            "teacher r_min = {}: must be finite",
            self.r_min
        );
        ensure!(
            self.weber.is_finite() && (0.0..1.0).contains(&self.weber),
            "teacher weber = {}: must be in [0, 1)",
            self.weber
        );
        ensure!(
            self.avg_window >= 1,
            "teacher avg_window = {}: must be at least 1",
            self.avg_window
        );
        Ok(())
    }
}

/// A scripted teacher: its config, its random source and the returns it was shown.
///
/// Random draws, from a ChaCha8 stream seeded with `cfg.seed`: one uniform f64 for the
/// Bradley-Terry choice when beta is finite, then one uniform f64 for the mistake when
/// eps > 0; none for a query answered Skip or Equal. So a teacher's answers are a function
/// of its seed and the queries it saw, in order.
#[derive(Clone, Debug)]
pub struct Scripted {
    cfg: ScriptedConfig,
    rng: ChaCha8Rng,
    /// Ground-truth returns of the last `cfg.avg_window` trajectories shown, oldest first.
    shown: VecDeque<f64>,
}

impl Scripted {
    /// A teacher with a validated config.
    pub fn new(cfg: ScriptedConfig) -> Result<Self> {
        cfg.validate()?;
        Ok(Scripted {
            rng: ChaCha8Rng::seed_from_u64(cfg.seed),
            shown: VecDeque::with_capacity(cfg.avg_window),
            cfg,
        })
    }

    /// The config this teacher runs with.
    pub fn config(&self) -> &ScriptedConfig {
        &self.cfg
    }

    /// Judge a pair from each trajectory's per-step ground-truth reward r. The two may
    /// differ in length (returns are sums). An empty trajectory, or one with a non-finite
    /// reward, cannot be judged: the answer is Skip, and neither return is remembered.
    pub fn answer(&mut self, first: &[f32], second: &[f32]) -> Preference {
        let (r0, r1) = (sum(first), sum(second));
        if first.is_empty() || second.is_empty() || !r0.is_finite() || !r1.is_finite() {
            return Preference::Skip;
        }
        // NOTE: both returns join the window before judging, so R_avg includes this pair.
        self.remember(r0);
        self.remember(r1);
        // `remember` just pushed two returns and avg_window >= 1, so the window is not empty.
        let r_avg = self.r_avg().expect("the window holds this pair's returns");
        self.judge_returns(first, second, r_avg, 1.0, None)
    }

    /// Judge two segments with the session's R_avg, as the authors' code does: R_avg is
    /// the mean ground-truth return of the newest training episodes when the session was
    /// asked (the learner's, carried by the query), and `fraction` is the segments' share
    /// of an episode (segment length over episode length): the thresholds compare
    /// segment returns with `(R_avg - r_min) * fraction * delta`, the skip threshold's
    /// floor is `r_min * fraction`. With whole trajectories (`fraction` 1) this is
    /// [`Scripted::answer`] with R_avg fixed for the session instead of the window.
    /// `moves` is how much each attempt moves (its mean |action|), where the query shows it.
    pub fn answer_in_session(
        &mut self,
        first: &[f32],
        second: &[f32],
        r_avg: f64,
        fraction: f64,
        moves: Option<[f64; 2]>,
    ) -> Preference {
        let (r0, r1) = (sum(first), sum(second));
        if first.is_empty()
            || second.is_empty()
            || !r0.is_finite()
            || !r1.is_finite()
            || !r_avg.is_finite()
            || fraction <= 0.0
            || fraction > 1.0
            || fraction.is_nan()
        {
            return Preference::Skip;
        }
        self.judge_returns(first, second, r_avg, fraction, moves)
    }

    fn judge_returns(
        &mut self,
        first: &[f32],
        second: &[f32],
        r_avg: f64,
        fraction: f64,
        moves: Option<[f64; 2]>,
    ) -> Preference {
        let (r0, r1) = (sum(first), sum(second));
        let cfg = &self.cfg;
        let r_min = cfg.r_min * fraction;
        let scale = (r_avg - cfg.r_min) * fraction;

        // 1. Skip when even the better trajectory is poor.
        if cfg.delta_skip > 0.0 && r0.max(r1) - r_min < scale * cfg.delta_skip {
            return Preference::Skip;
        }
        // 2. Equal when the (undiscounted) returns are close.
        // NOTE: Equal overrides the noisy choice and a mistake, so it draws nothing.
        if cfg.delta_equal > 0.0 && (r0 - r1).abs() < scale * cfg.delta_equal {
            return Preference::Equal;
        }
        // 2b. Hurried: too close to tell apart, so the livelier attempt (draws nothing).
        if cfg.weber > 0.0 && (r0 - r1).abs() < cfg.weber * r0.abs().max(r1.abs()) {
            return match moves {
                Some([m0, m1]) if m1 > m0 => Preference::Second,
                Some(_) => Preference::First,
                None => Preference::Equal,
            };
        }
        // 3. Myopic: step t of T weighted gamma^(T-1-t).
        let (d0, d1) = if cfg.gamma < 1.0 {
            (discounted(first, cfg.gamma), discounted(second, cfg.gamma))
        } else {
            (r0, r1)
        };
        // 4. Bradley-Terry choice, or the larger sum (a tie is First, as B-Pref's
        //    `1 * (sum1 < sum2)`).
        let mut second_better = match cfg.beta {
            Some(beta) => self.rng.random::<f64>() < sigmoid(beta * (d1 - d0)),
            None => d1 > d0,
        };
        // 5. Mistake: flip with probability eps.
        if cfg.eps > 0.0 && self.rng.random::<f64>() < cfg.eps {
            second_better = !second_better;
        }
        if second_better {
            Preference::Second
        } else {
            Preference::First
        }
    }

    /// Rank three or four attempts (their per-step ground-truth rewards), as a pair is
    /// judged but over all of them: Skip (None) when even the best is poor; the order by
    /// return (myopic: discounted), drawn by Plackett-Luce with rationality beta where it is
    /// finite (for two attempts, the Bradley-Terry choice); a mistake swaps one adjacent
    /// pair of the order with probability eps; the hurried teacher puts the livelier of two
    /// neighbours too close to tell first; attempts whose returns are within the equal
    /// threshold of their neighbour in the order share its place. `r_avg` None: the
    /// teacher's own window of returns shown. Returns each attempt's place, 0 the best.
    pub fn rank_returns(
        &mut self,
        attempts: &[&[f32]],
        r_avg: Option<f64>,
        fraction: f64,
        moves: Option<&[f64]>,
    ) -> Option<Vec<u8>> {
        let returns: Vec<f64> = attempts.iter().map(|r| sum(r)).collect();
        let judgeable = attempts.len() >= 2
            && attempts.iter().all(|r| !r.is_empty())
            && returns.iter().all(|r| r.is_finite())
            && fraction > 0.0
            && fraction <= 1.0;
        if !judgeable {
            return None;
        }
        let r_avg = match r_avg {
            Some(r) if r.is_finite() => r,
            Some(_) => return None,
            None => {
                for &r in &returns {
                    self.remember(r);
                }
                self.r_avg().expect("the window holds this query's returns")
            }
        };
        let cfg = self.cfg.clone();
        let r_min = cfg.r_min * fraction;
        let scale = (r_avg - cfg.r_min) * fraction;
        let best = returns.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        if cfg.delta_skip > 0.0 && best - r_min < scale * cfg.delta_skip {
            return None;
        }
        let utility: Vec<f64> = if cfg.gamma < 1.0 {
            attempts.iter().map(|r| discounted(r, cfg.gamma)).collect()
        } else {
            returns.clone()
        };
        // The order, best first.
        let mut order: Vec<usize> = (0..attempts.len()).collect();
        match cfg.beta {
            None => order.sort_by(|&a, &b| utility[b].total_cmp(&utility[a])),
            Some(beta) => {
                let mut left = order.clone();
                order.clear();
                while left.len() > 1 {
                    let top = left
                        .iter()
                        .map(|&i| beta * utility[i])
                        .fold(f64::NEG_INFINITY, f64::max);
                    let w: Vec<f64> = left
                        .iter()
                        .map(|&i| (beta * utility[i] - top).exp())
                        .collect();
                    let mut u = self.rng.random::<f64>() * w.iter().sum::<f64>();
                    let mut pick = left.len() - 1;
                    for (k, wk) in w.iter().enumerate() {
                        if u < *wk {
                            pick = k;
                            break;
                        }
                        u -= wk;
                    }
                    order.push(left.remove(pick));
                }
                order.extend(left);
            }
        }
        if cfg.weber > 0.0 {
            if let Some(m) = moves {
                for k in 1..order.len() {
                    let (a, b) = (order[k - 1], order[k]);
                    let close = (returns[a] - returns[b]).abs()
                        < cfg.weber * returns[a].abs().max(returns[b].abs());
                    if close && m[b] > m[a] {
                        order.swap(k - 1, k);
                    }
                }
            }
        }
        if cfg.eps > 0.0 && self.rng.random::<f64>() < cfg.eps {
            let k = self.rng.random_range(1..order.len());
            order.swap(k - 1, k);
        }
        let mut places = vec![0u8; attempts.len()];
        let mut place = 0u8;
        for k in 0..order.len() {
            let tied = k > 0
                && cfg.delta_equal > 0.0
                && (returns[order[k]] - returns[order[k - 1]]).abs() < scale * cfg.delta_equal;
            if k > 0 && !tied {
                place = k as u8;
            }
            places[order[k]] = place;
        }
        Some(places)
    }

    /// Mean ground-truth return of the last `avg_window` trajectories shown; None before
    /// the first pair.
    pub fn r_avg(&self) -> Option<f64> {
        if self.shown.is_empty() {
            None
        } else {
            Some(self.shown.iter().sum::<f64>() / self.shown.len() as f64)
        }
    }

    fn remember(&mut self, ret: f64) {
        if self.shown.len() == self.cfg.avg_window {
            self.shown.pop_front();
        }
        self.shown.push_back(ret);
    }
}

/// Undiscounted return, summed in f64.
fn sum(r: &[f32]) -> f64 {
    r.iter().map(|&x| f64::from(x)).sum()
}

/// sum_t gamma^(T-1-t) r_t, by Horner's rule (the last step has weight 1).
fn discounted(r: &[f32], gamma: f64) -> f64 {
    r.iter().fold(0.0, |acc, &x| acc * gamma + f64::from(x))
}

/// 1 / (1 + e^-x), without overflow for large |x|.
fn sigmoid(x: f64) -> f64 {
    if x >= 0.0 {
        1.0 / (1.0 + (-x).exp())
    } else {
        let e = x.exp();
        e / (1.0 + e)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::ValueEnum;
    use Preference::{Equal, First, Second, Skip};

    fn teacher(cfg: ScriptedConfig) -> Scripted {
        Scripted::new(cfg).unwrap() // the configs here are valid
    }

    fn table(kind: TeacherKind) -> Scripted {
        teacher(ScriptedConfig::of(kind, 7))
    }

    /// Fraction of `n` answers to the same pair that are `Second`.
    fn second_rate(t: &mut Scripted, first: &[f32], second: &[f32], n: usize) -> f64 {
        let k = (0..n).filter(|_| t.answer(first, second) == Second).count();
        k as f64 / n as f64
    }

    #[test]
    fn table_one_values_and_names() {
        // (kind, beta, gamma, eps, delta_skip, delta_equal) from method.md section 4.
        let rows = [
            (TeacherKind::Oracle, None, 1.0, 0.0, 0.0, 0.0),
            (TeacherKind::Noisy, Some(1.0), 1.0, 0.0, 0.0, 0.0),
            (TeacherKind::Mistake, None, 1.0, 0.1, 0.0, 0.0),
            (TeacherKind::Skip, None, 1.0, 0.0, 0.1, 0.0),
            (TeacherKind::Equal, None, 1.0, 0.0, 0.0, 0.1),
            (TeacherKind::Myopic, None, 0.99, 0.0, 0.0, 0.0),
        ];
        for (kind, beta, gamma, eps, delta_skip, delta_equal) in rows {
            let c = ScriptedConfig::of(kind, 3);
            let want = ScriptedConfig {
                kind,
                beta,
                gamma,
                eps,
                delta_skip,
                delta_equal,
                r_min: -350.0,
                avg_window: 100,
                seed: 3,
                weber: 0.0,
            };
            assert_eq!(c, want);
            c.validate().unwrap();
            // One name for the config file, the command line and answers.
            let serde_name = serde_json::to_string(&kind).unwrap();
            assert_eq!(serde_name, format!("\"{}\"", kind.name()));
            let clap_name = kind.to_possible_value().unwrap();
            assert_eq!(clap_name.get_name(), kind.name());
            let back: ScriptedConfig =
                serde_json::from_str(&serde_json::to_string(&c).unwrap()).unwrap();
            assert_eq!(back, c);
        }
        assert_eq!(TeacherKind::ALL.len(), rows.len());
    }

    #[test]
    fn oracle_prefers_the_larger_sum_and_a_tie_is_first() {
        let mut t = table(TeacherKind::Oracle);
        // sums: 3 vs 4 -> Second; 4 vs 3 -> First
        assert_eq!(t.answer(&[1.0, 2.0], &[0.0, 4.0]), Second);
        assert_eq!(t.answer(&[0.0, 4.0], &[1.0, 2.0]), First);
        // Different lengths: 1 + 1 + 1 = 3 > 2.
        assert_eq!(t.answer(&[1.0, 1.0, 1.0], &[2.0]), First);
        // A tie is First (B-Pref: label = 1 * (sum1 < sum2) = 0).
        assert_eq!(t.answer(&[1.0, 2.0], &[3.0]), First);
        // Feeding-like negative returns: -120 vs -80.
        assert_eq!(t.answer(&[-60.0, -60.0], &[-40.0, -40.0]), Second);
    }

    #[test]
    fn mistake_flips_at_rate_eps_and_is_deterministic_per_seed() {
        // Oracle answer First (5 > 1); a mistake teacher answers Second with rate 0.1.
        let (a, b) = ([5.0f32], [1.0f32]);
        let n = 4000;
        let rate = second_rate(&mut table(TeacherKind::Mistake), &a, &b, n);
        // std of the rate: sqrt(0.1 * 0.9 / 4000) = 0.0047; allow about 4 std.
        assert!((rate - 0.1).abs() < 0.02, "flip rate {rate}");
        let answers = |seed| {
            let mut t = teacher(ScriptedConfig::of(TeacherKind::Mistake, seed));
            (0..200).map(|_| t.answer(&a, &b)).collect::<Vec<_>>()
        };
        assert_eq!(answers(11), answers(11));
        assert_ne!(answers(11), answers(12));
    }

    #[test]
    fn skip_happens_below_the_threshold_and_not_above() {
        // Both teachers first see two pairs of return -50, then one pair whose returns sum
        // to -670, so the window holds the same six returns:
        //   R_avg = (4 * -50 + -670) / 6 = -145.0
        //   threshold = (R_avg - r_min) * delta_skip = (-145 + 350) * 0.1 = 20.5
        // Pair (-330, -340): max - r_min = -330 + 350 = 20 < 20.5 -> Skip.
        // Pair (-329, -341): max - r_min = -329 + 350 = 21 > 20.5 -> judged, First.
        let warm = |t: &mut Scripted| {
            for _ in 0..2 {
                // max - r_min = 300 > (-50 + 350) * 0.1 = 30: judged (a tie, First)
                assert_eq!(t.answer(&[-25.0, -25.0], &[-50.0]), First);
            }
        };
        let mut below = table(TeacherKind::Skip);
        warm(&mut below);
        assert_eq!(below.answer(&[-165.0, -165.0], &[-340.0]), Skip);
        assert_eq!(below.r_avg(), Some(-145.0));

        let mut above = table(TeacherKind::Skip);
        warm(&mut above);
        assert_eq!(above.answer(&[-329.0], &[-341.0]), First);
        assert_eq!(above.r_avg(), Some(-145.0));

        // The oracle never skips the same pair.
        let mut oracle = table(TeacherKind::Oracle);
        warm(&mut oracle);
        assert_eq!(oracle.answer(&[-165.0, -165.0], &[-340.0]), First);
    }

    #[test]
    fn equal_answers_close_pairs_and_overrides_a_mistake() {
        // First pair: window [-100, -101], R_avg = -100.5,
        //   threshold = (-100.5 + 350) * 0.1 = 24.95; |(-100) - (-101)| = 1 < 24.95 -> Equal.
        // Second pair: window [-100, -101, -50, -250], R_avg = -125.25,
        //   threshold = (-125.25 + 350) * 0.1 = 22.475; |-50 - -250| = 200 -> not equal,
        //   the oracle says First.
        let near = ([-50.0f32, -50.0], [-101.0f32]);
        let far = ([-50.0f32], [-125.0f32, -125.0]);

        let mut equal = table(TeacherKind::Equal);
        assert_eq!(equal.answer(&near.0, &near.1), Equal);
        assert_eq!(equal.answer(&far.0, &far.1), First);

        // With eps = 1 every answer is flipped, except Equal, which overrides the mistake.
        let mut erring = teacher(ScriptedConfig {
            eps: 1.0,
            ..ScriptedConfig::of(TeacherKind::Equal, 7)
        });
        assert_eq!(erring.answer(&near.0, &near.1), Equal);
        assert_eq!(erring.answer(&far.0, &far.1), Second);
        assert_eq!(erring.r_avg(), Some(-125.25));
    }

    #[test]
    fn equal_is_judged_on_undiscounted_sums() {
        // gamma = 0.5: first [-100, -100]: R = -200, R' = 0.5 * -100 + -100 = -150
        //              second [-200, 0]:   R = -200, R' = 0.5 * -200 + 0    = -100
        // Undiscounted the two are equal (|R0 - R1| = 0 < threshold) -> Equal, although
        // the myopic sums alone would pick Second.
        let cfg = ScriptedConfig {
            gamma: 0.5,
            ..ScriptedConfig::of(TeacherKind::Equal, 7)
        };
        assert_eq!(
            teacher(cfg).answer(&[-100.0, -100.0], &[-200.0, 0.0]),
            Equal
        );
        let cfg = ScriptedConfig {
            gamma: 0.5,
            ..ScriptedConfig::of(TeacherKind::Oracle, 7)
        };
        assert_eq!(
            teacher(cfg).answer(&[-100.0, -100.0], &[-200.0, 0.0]),
            Second
        );
    }

    #[test]
    fn myopic_weighs_late_steps_and_can_reverse_the_oracle() {
        // Reference (Python):
        //   first = [10] + [0] * 99;  second = [0] * 99 + [9]
        //   sum(first), sum(second)                                   # 10, 9: oracle First
        //   sum(r * 0.99 ** (99 - t) for t, r in enumerate(first))   # 3.697296376497264
        //   sum(r * 0.99 ** (99 - t) for t, r in enumerate(second))  # 9.0: myopic Second
        let mut first = vec![0.0f32; 100];
        first[0] = 10.0;
        let mut second = vec![0.0f32; 100];
        second[99] = 9.0;
        assert!((discounted(&first, 0.99) - 3.697296376497264).abs() < 1e-12);
        assert_eq!(discounted(&second, 0.99), 9.0);
        assert_eq!(table(TeacherKind::Oracle).answer(&first, &second), First);
        assert_eq!(table(TeacherKind::Myopic).answer(&first, &second), Second);

        // Each trajectory is weighted from its own last step:
        //   [1, 2, 3] at 0.5: 1 * 0.25 + 2 * 0.5 + 3 = 4.25;  [4.5]: 4.5
        assert_eq!(discounted(&[1.0, 2.0, 3.0], 0.5), 4.25);
        assert_eq!(discounted(&[], 0.5), 0.0);
        let mut t = teacher(ScriptedConfig {
            gamma: 0.5,
            ..ScriptedConfig::of(TeacherKind::Myopic, 7)
        });
        assert_eq!(t.answer(&[1.0, 2.0, 3.0], &[4.5]), Second); // undiscounted: 6 > 4.5
    }

    #[test]
    fn noisy_matches_the_sigmoid_and_is_deterministic_per_seed() {
        // Reference (Python): 1 / (1 + math.exp(-0.5)) = 0.6224593312018546
        assert!((sigmoid(0.5) - 0.6224593312018546).abs() < 1e-15);
        assert_eq!(sigmoid(0.0), 0.5);
        // Stable at the extremes: no NaN, no overflow.
        assert_eq!(sigmoid(1000.0), 1.0);
        assert_eq!(sigmoid(-1000.0), 0.0);
        assert!((sigmoid(-0.5) - (1.0 - 0.6224593312018546)).abs() < 1e-15);

        // R0 = 1, R1 = 1.5: P[Second] = sigmoid(1 * 0.5) = 0.6225.
        let (a, b) = ([0.5f32, 0.5], [1.5f32]);
        let n = 4000;
        let rate = second_rate(&mut table(TeacherKind::Noisy), &a, &b, n);
        // std of the rate: sqrt(0.6225 * 0.3775 / 4000) = 0.0077; allow about 4 std.
        assert!((rate - 0.6224593312018546).abs() < 0.03, "rate {rate}");
        // Swapped, P[Second] = sigmoid(-0.5) = 0.3775.
        let rate = second_rate(&mut table(TeacherKind::Noisy), &b, &a, n);
        assert!(
            (rate - 0.3775406687981454).abs() < 0.03,
            "swapped rate {rate}"
        );
        // Far apart the choice is certain.
        let mut t = table(TeacherKind::Noisy);
        assert_eq!(second_rate(&mut t, &[-1000.0], &[0.0], 100), 1.0);
        assert_eq!(second_rate(&mut t, &[0.0], &[-1000.0], 100), 0.0);

        let answers = |seed| {
            let mut t = teacher(ScriptedConfig::of(TeacherKind::Noisy, seed));
            (0..200).map(|_| t.answer(&a, &b)).collect::<Vec<_>>()
        };
        assert_eq!(answers(5), answers(5));
        assert_ne!(answers(5), answers(6));
    }

    #[test]
    fn draws_happen_only_where_documented() {
        // One f64 draw takes one u64, two 32-bit words of the ChaCha stream.
        let words = |t: &Scripted| t.rng.get_word_pos();
        for kind in [
            TeacherKind::Oracle,
            TeacherKind::Skip,
            TeacherKind::Equal,
            TeacherKind::Myopic,
        ] {
            let mut t = table(kind);
            for _ in 0..10 {
                t.answer(&[1.0, 2.0], &[3.0, -1.0]);
            }
            assert_eq!(words(&t), 0, "{kind:?} drew");
        }
        // Noisy: one draw per judged query; mistake: one per query.
        let mut t = table(TeacherKind::Noisy);
        t.answer(&[1.0], &[2.0]);
        assert_eq!(words(&t), 2);
        let mut t = table(TeacherKind::Mistake);
        t.answer(&[1.0], &[2.0]);
        assert_eq!(words(&t), 2);
        // Both: two draws. Skip and Equal answers draw nothing.
        let mut t = teacher(ScriptedConfig {
            eps: 0.1,
            delta_equal: 0.1,
            ..ScriptedConfig::of(TeacherKind::Noisy, 7)
        });
        t.answer(&[-10.0], &[-200.0]);
        assert_eq!(words(&t), 4);
        assert_eq!(t.answer(&[-10.0], &[-10.5]), Equal);
        assert_eq!(words(&t), 4);
    }

    #[test]
    fn in_a_session_the_thresholds_scale_the_sessions_r_avg_to_the_segment() {
        // The authors' thresholds: R_avg of the session (the newest training episodes,
        // -100 a whole episode), scaled by the segment's share of an episode (50 of 200);
        // with r_min -350: floor -87.5, scale 62.5, so skip below -87.5 + 6.25 = -81.25
        // and equal within 6.25.
        let mut skip = table(TeacherKind::Skip);
        assert_eq!(
            skip.answer_in_session(&[-82.0], &[-85.0], -100.0, 0.25, None),
            Preference::Skip
        );
        assert_eq!(
            skip.answer_in_session(&[-81.0], &[-85.0], -100.0, 0.25, None),
            Preference::First
        );
        let mut equal = table(TeacherKind::Equal);
        assert_eq!(
            equal.answer_in_session(&[-50.0], &[-56.2], -100.0, 0.25, None),
            Preference::Equal
        );
        assert_eq!(
            equal.answer_in_session(&[-50.0], &[-56.3], -100.0, 0.25, None),
            Preference::First
        );
        // Whole trajectories (fraction 1): the window's rule with R_avg fixed. The window
        // is not touched by a session's answers.
        assert_eq!(
            equal.answer_in_session(&[-100.0], &[-124.0], -100.0, 1.0, None),
            Preference::Equal
        );
        assert_eq!(equal.r_avg(), None);
        // Nothing to judge by: skipped.
        assert_eq!(
            equal.answer_in_session(&[-1.0], &[-2.0], f64::NAN, 1.0, None),
            Preference::Skip
        );
        assert_eq!(
            equal.answer_in_session(&[-1.0], &[-2.0], -100.0, 0.0, None),
            Preference::Skip
        );
    }

    #[test]
    fn r_avg_is_the_mean_of_the_last_window_returns_shown() {
        let mut t = teacher(ScriptedConfig {
            avg_window: 3,
            ..ScriptedConfig::of(TeacherKind::Oracle, 7)
        });
        assert_eq!(t.r_avg(), None);
        t.answer(&[1.0], &[2.0]); // window [1, 2]
        assert_eq!(t.r_avg(), Some(1.5));
        t.answer(&[1.0, 2.0], &[4.0]); // window [2, 3, 4]
        assert_eq!(t.r_avg(), Some(3.0));
        t.answer(&[10.0], &[15.0, 5.0]); // window [4, 10, 20]
        assert_eq!(t.r_avg(), Some(34.0 / 3.0));
    }

    #[test]
    fn empty_or_non_finite_trajectories_are_skipped_and_not_remembered() {
        let mut t = table(TeacherKind::Noisy);
        assert_eq!(t.answer(&[], &[1.0]), Skip);
        assert_eq!(t.answer(&[1.0], &[]), Skip);
        assert_eq!(t.answer(&[], &[]), Skip);
        assert_eq!(t.answer(&[f32::NAN], &[1.0]), Skip);
        assert_eq!(t.answer(&[1.0], &[2.0, f32::INFINITY]), Skip);
        assert_eq!(t.r_avg(), None);
        assert_eq!(t.rng.get_word_pos(), 0);
    }

    #[test]
    fn validate_names_the_field_and_its_value() {
        let base = || ScriptedConfig::of(TeacherKind::Oracle, 7);
        let cases = [
            (
                ScriptedConfig {
                    beta: Some(0.0),
                    ..base()
                },
                "beta = 0",
            ),
            (
                ScriptedConfig {
                    beta: Some(f64::INFINITY),
                    ..base()
                },
                "beta = inf",
            ),
            (
                ScriptedConfig {
                    gamma: 0.0,
                    ..base()
                },
                "gamma = 0",
            ),
            (
                ScriptedConfig {
                    gamma: 1.5,
                    ..base()
                },
                "gamma = 1.5",
            ),
            (
                ScriptedConfig {
                    eps: -0.1,
                    ..base()
                },
                "eps = -0.1",
            ),
            (ScriptedConfig { eps: 1.1, ..base() }, "eps = 1.1"),
            (
                ScriptedConfig {
                    eps: f64::NAN,
                    ..base()
                },
                "eps = NaN",
            ),
            (
                ScriptedConfig {
                    delta_skip: -1.0,
                    ..base()
                },
                "delta_skip = -1",
            ),
            (
                ScriptedConfig {
                    delta_equal: f64::NAN,
                    ..base()
                },
                "delta_equal = NaN",
            ),
            (
                ScriptedConfig {
                    r_min: f64::NEG_INFINITY,
                    ..base()
                },
                "r_min = -inf",
            ),
            (
                ScriptedConfig {
                    avg_window: 0,
                    ..base()
                },
                "avg_window = 0",
            ),
        ];
        for (cfg, want) in cases {
            let err = cfg.validate().unwrap_err().to_string();
            assert!(err.contains(want), "{err:?} should contain {want:?}");
            let err = Scripted::new(cfg).unwrap_err().to_string();
            assert!(err.contains(want), "{err:?} should contain {want:?}");
        }
        ScriptedConfig {
            eps: 1.0,
            gamma: 1e-3,
            beta: Some(1e-3),
            ..base()
        }
        .validate()
        .unwrap();
    }

    #[test]
    fn hurried_takes_the_livelier_of_two_close_attempts_and_the_better_of_two_far_ones() {
        let c = ScriptedConfig::of(TeacherKind::Hurried, 1);
        assert_eq!(c.weber, 0.2);
        assert_eq!(
            ScriptedConfig {
                weber: 0.0,
                ..c.clone()
            },
            ScriptedConfig {
                kind: TeacherKind::Hurried,
                ..ScriptedConfig::of(TeacherKind::Oracle, 1)
            }
        );
        assert_eq!(TeacherKind::Hurried.name(), "hurried");
        let mut t = teacher(c);
        // -30 against -34: 4 < 0.2 * 34, too close. The second moves more: Second, though
        // the first is better.
        let (a, b) = ([-15.0f32, -15.0], [-17.0f32, -17.0]);
        let lively = Some([0.1, 0.5]);
        assert_eq!(t.answer_in_session(&a, &b, -100.0, 0.25, lively), Second);
        assert_eq!(
            t.answer_in_session(&a, &b, -100.0, 0.25, Some([0.5, 0.1])),
            First
        );
        // Without the actions it cannot tell: Equal.
        assert_eq!(t.answer_in_session(&a, &b, -100.0, 0.25, None), Equal);
        // -30 against -50: far enough, the better one whatever moves more.
        let far = [-25.0f32, -25.0];
        assert_eq!(
            t.answer_in_session(&a, &far, -100.0, 0.25, Some([0.1, 0.9])),
            First
        );
        // The oracle is never drawn to the livelier one.
        let mut oracle = table(TeacherKind::Oracle);
        assert_eq!(
            oracle.answer_in_session(&a, &b, -100.0, 0.25, lively),
            First
        );
        // Out of range: refused by name.
        let bad = ScriptedConfig {
            weber: 1.5,
            ..ScriptedConfig::of(TeacherKind::Hurried, 1)
        };
        assert!(Scripted::new(bad)
            .unwrap_err()
            .to_string()
            .contains("weber = 1.5"));
    }

    #[test]
    fn a_ranking_orders_by_return_ties_the_close_and_errs_as_each_teacher_does() {
        let (a, b, c, d) = ([1.0f32, 1.0], [3.0f32, 3.0], [2.0f32, 2.0], [2.05f32, 2.0]);
        let four: [&[f32]; 4] = [&a, &b, &c, &d];
        let mut oracle = table(TeacherKind::Oracle);
        assert_eq!(
            oracle.rank_returns(&four, Some(0.0), 1.0, None),
            Some(vec![3, 0, 2, 1])
        );
        // Equal: returns 4.0 and 4.05 are within 0.1 of (R_avg - r_min) = 10.
        let mut equal = teacher(ScriptedConfig {
            r_min: -10.0,
            ..ScriptedConfig::of(TeacherKind::Equal, 1)
        });
        assert_eq!(
            equal.rank_returns(&four, Some(0.0), 1.0, None),
            Some(vec![3, 0, 1, 1])
        );
        // Skip: even the best is poor.
        let mut skip = teacher(ScriptedConfig {
            r_min: -10.0,
            delta_skip: 2.0,
            ..ScriptedConfig::of(TeacherKind::Skip, 1)
        });
        assert_eq!(skip.rank_returns(&four, Some(0.0), 1.0, None), None);
        // Noisy: Plackett-Luce; a wide gap is ranked as the oracle does nearly always, a
        // narrow one about half the time.
        let mut noisy = table(TeacherKind::Noisy);
        let (lo, hi) = ([0.0f32], [10.0f32]);
        let (x, y) = ([5.0f32], [5.1f32]);
        let wide: [&[f32]; 3] = [&lo, &hi, &x];
        let n = 2000;
        let best_first = (0..n)
            .filter(|_| noisy.rank_returns(&wide, Some(0.0), 1.0, None).unwrap()[1] == 0)
            .count() as f64
            / n as f64;
        assert!(best_first > 0.98, "{best_first}");
        let narrow: [&[f32]; 3] = [&x, &y, &lo];
        let first_ahead = (0..n)
            .filter(|_| {
                let p = noisy.rank_returns(&narrow, Some(0.0), 1.0, None).unwrap();
                p[0] < p[1]
            })
            .count() as f64
            / n as f64;
        assert!((first_ahead - sigmoid(-0.1)).abs() < 0.05, "{first_ahead}");
        // Mistake: one adjacent pair swapped in about eps of the rankings.
        let mut mistake = table(TeacherKind::Mistake);
        let wrong = (0..n)
            .filter(|_| mistake.rank_returns(&four, Some(0.0), 1.0, None).unwrap() != [3, 0, 2, 1])
            .count() as f64
            / n as f64;
        assert!((wrong - 0.1).abs() < 0.03, "{wrong}");
        // Hurried: of two too close to tell apart, the livelier goes first.
        let mut hurried = table(TeacherKind::Hurried);
        let moves = [0.1, 0.1, 0.9, 0.1];
        assert_eq!(
            hurried.rank_returns(&four, Some(0.0), 1.0, Some(&moves)),
            Some(vec![3, 0, 1, 2])
        );
    }
}
