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
mod tests;
