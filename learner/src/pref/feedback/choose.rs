//! Choosing a session's queries: the sides (segments) of candidate pairs (or, for
//! rankings, of candidate sets of three or four attempts) drawn from the annotation buffer,
//! the session's R_avg, and the sampler's pick within the bound on open queries per
//! trajectory. A set's score is the mean of its pairs'.

use std::collections::HashMap;
use std::sync::Arc;

use anyhow::Result;
use rand::Rng;

use super::{Feedback, Job, JobDone};
use crate::pref::config::SegmentStart;
use crate::pref::query::{
    candidate_pairs, candidate_sets, scores, select, Candidate, Sampler, TrajKey,
};
use crate::pref::reward_model::Segment;

/// One side of a query: a segment of a trajectory in the annotation buffer.
#[derive(Clone, Debug)]
pub struct Side {
    pub trajectory: Arc<Candidate>,
    /// Steps `start .. start + len` of the trajectory.
    pub start: usize,
    pub len: usize,
}

impl Side {
    /// The segment's steps, as the reward model reads them.
    fn segment(&self) -> Segment {
        let c = &self.trajectory;
        let span = (self.start, self.len);
        Segment::of(&c.obs, &c.actions, &c.features, span, c.steps())
    }
}

/// Trajectories whose ground-truth returns make R_avg (the authors' 100 newest).
const R_AVG_EPISODES: usize = 100;

impl Feedback {
    /// Trajectory `c` as one side of a query: its segment drawn as the settings say
    /// (the whole trajectory, and no draw, where the segment would be all of it).
    pub(super) fn side(&mut self, c: &Arc<Candidate>) -> Side {
        let steps = c.steps();
        let len = match self.cfg.segment_len {
            0 => steps,
            n => n.min(steps),
        };
        let start = if len >= steps {
            0
        } else {
            match self.cfg.segment_start {
                SegmentStart::Uniform => self.rng.random_range(0..=steps - len),
                SegmentStart::End => steps - len,
            }
        };
        Side {
            trajectory: c.clone(),
            start,
            len,
        }
    }

    /// R_avg for a session now: the mean ground-truth return of the newest
    /// [`R_AVG_EPISODES`] trajectories in the annotation buffer (the newest training
    /// episodes); None while it is empty.
    pub(super) fn r_avg(&self) -> Option<f32> {
        let n = self.buffer.len().min(R_AVG_EPISODES);
        if n == 0 {
            return None;
        }
        let sum: f64 = (self.buffer.len() - n..self.buffer.len())
            .map(|i| {
                self.buffer
                    .get(i)
                    .truth
                    .iter()
                    .map(|&r| r as f64)
                    .sum::<f64>()
            })
            .sum();
        Some((sum / n as f64) as f32)
    }

    /// The job of choosing a session's queries at `env_steps` (or, `top_up`, those the
    /// current session still owes): candidate pairs drawn from the annotation buffer, the
    /// sampler keeps the best of them that the bound per trajectory allows.
    pub(super) fn choosing(&mut self, env_steps: u64, top_up: bool) -> Result<Job> {
        let session = self.counters.sessions + u64::from(!top_up);
        let spent = self.store.counts()?.spent();
        let quota = if top_up {
            self.owed.min(self.budget_left(spent))
        } else {
            self.cfg.session_queries(session, spent)
        };
        let k = quota.min(self.room()) as usize;
        // NOTE: the first session is uniform: an untrained ensemble's disagreement
        // means nothing (a prior's does).
        let first = session == 1 && self.cfg.prior.is_none();
        let sampler = if first || !self.model.trained() {
            Sampler::Uniform
        } else {
            self.cfg.sampler
        };
        let cap = self.cfg.queries_per_trajectory;
        // NOTE: with a bound per trajectory, uniform draws more pairs than it keeps too,
        // so that the ones the bound refuses leave enough.
        let n = if sampler == Sampler::Uniform && cap == 0 {
            k
        } else {
            k * self.cfg.candidate_factor as usize
        };
        let mut open: HashMap<TrajKey, u64> = HashMap::new();
        if cap > 0 {
            for f in self.in_flight.values() {
                for &key in &f.keys {
                    *open.entry(key).or_default() += 1;
                }
            }
        }
        // NOTE: policy-aligned queries (QPA) draw from the newest trajectories only.
        let held = self.buffer.len();
        let recent = match self.cfg.query_recent {
            0 => held,
            r => r.clamp(2, held.max(2)).min(held),
        };
        let offset = held - recent;
        // NOTE: a ranking shows as many attempts as the newest trajectories allow.
        let attempts = self.cfg.query_attempts.clamp(2, recent.max(2));
        let idx: Vec<Vec<usize>> = if attempts == 2 {
            candidate_pairs(&mut self.rng, recent, n)?
                .into_iter()
                .map(|(i, j)| vec![i, j])
                .collect()
        } else {
            candidate_sets(&mut self.rng, recent, attempts, n)?
        };
        let mut candidates: Vec<Vec<Side>> = Vec::with_capacity(idx.len());
        for set in idx {
            let trajectories: Vec<Arc<Candidate>> = set
                .iter()
                .map(|&i| self.buffer.get(offset + i).clone())
                .collect();
            candidates.push(trajectories.iter().map(|c| self.side(c)).collect());
        }
        if cap > 0 {
            candidates.retain(|sides| {
                sides
                    .iter()
                    .all(|s| open.get(&s.trajectory.key).copied().unwrap_or(0) < cap)
            });
        }
        let r_avg = self.r_avg();
        let model = self.model.clone();
        Ok(Box::new(move || {
            let ranked = if sampler == Sampler::Uniform {
                (0..candidates.len()).collect()
            } else {
                let d = distinct_sets(&candidates);
                let probs = model.preference_probs(&d.pairs())?;
                rank_sets(sampler, &probs, candidates.len(), attempts)
            };
            let chosen = within_cap(&candidates, ranked, k, cap, open);
            Ok(JobDone::Chosen {
                session,
                env_steps,
                sampler,
                sets: chosen.into_iter().map(|i| candidates[i].clone()).collect(),
                r_avg,
                quota,
                top_up,
            })
        }))
    }
}

/// Candidate sets of `attempts` each in the sampler's order, best first: for pairs, as
/// [`select`]; for larger sets, by the mean of their pairs' scores (a NaN last; equal
/// scores keep the lower index first). `probs[m]` holds member m's predictions on every
/// set's pairs, set by set, in [`distinct_sets`]' order.
pub(super) fn rank_sets(
    sampler: Sampler,
    probs: &[Vec<f32>],
    n_sets: usize,
    attempts: usize,
) -> Vec<usize> {
    if attempts == 2 {
        return select(sampler, probs, n_sets, n_sets);
    }
    let per = attempts * (attempts - 1) / 2;
    let pair_scores = scores(sampler, probs, n_sets * per);
    let s: Vec<f64> = pair_scores
        .chunks(per)
        .map(|c| c.iter().sum::<f64>() / per as f64)
        .map(|x| if x.is_nan() { f64::NEG_INFINITY } else { x })
        .collect();
    let mut order: Vec<usize> = (0..n_sets).collect();
    order.sort_by(|&a, &b| s[b].total_cmp(&s[a]));
    order
}

/// The candidates to keep, `k` at most, in the order `ranked`, such that no trajectory is in
/// more than `cap` open queries (0: no bound), `open` counting those open already.
pub(super) fn within_cap(
    candidates: &[Vec<Side>],
    ranked: Vec<usize>,
    k: usize,
    cap: u64,
    mut open: HashMap<TrajKey, u64>,
) -> Vec<usize> {
    if cap == 0 {
        return ranked.into_iter().take(k).collect();
    }
    let mut out = Vec::with_capacity(k);
    for i in ranked {
        if out.len() >= k {
            break;
        }
        let keys: Vec<TrajKey> = candidates[i].iter().map(|s| s.trajectory.key).collect();
        let n = |key: &TrajKey| open.get(key).copied().unwrap_or(0);
        let repeats = (1..keys.len()).any(|k| keys[..k].contains(&keys[k]));
        if repeats || keys.iter().any(|key| n(key) >= cap) {
            continue;
        }
        for key in keys {
            *open.entry(key).or_default() += 1;
        }
        out.push(i);
    }
    out
}

/// Candidate pairs as the ensemble judges them: one segment per distinct trajectory, and
/// each pair as two indices into them.
pub(super) struct Distinct {
    pub(super) segs: Vec<Segment>,
    pub(super) sides: Vec<(usize, usize)>,
}

impl Distinct {
    pub(super) fn pairs(&self) -> Vec<(&Segment, &Segment)> {
        self.sides
            .iter()
            .map(|&(a, b)| (&self.segs[a], &self.segs[b]))
            .collect()
    }
}

/// One segment per distinct side of `candidates`: the ensemble judges each once.
pub(super) fn distinct_pairs(candidates: &[(Side, Side)]) -> Distinct {
    distinct(candidates.iter().map(|(a, b)| (a, b)))
}

/// Every pair of every set of `sets` (set by set, `(i, j)` with `i < j`), one segment per
/// distinct side.
pub(super) fn distinct_sets(sets: &[Vec<Side>]) -> Distinct {
    distinct(sets.iter().flat_map(|set| {
        (0..set.len()).flat_map(move |i| (i + 1..set.len()).map(move |j| (&set[i], &set[j])))
    }))
}

fn distinct<'a>(pairs: impl Iterator<Item = (&'a Side, &'a Side)>) -> Distinct {
    let mut index: HashMap<(*const Candidate, usize, usize), usize> = HashMap::new();
    let mut segs: Vec<Segment> = Vec::new();
    let mut sides = Vec::new();
    for (a, b) in pairs {
        let mut at = |s: &Side| {
            let key = (Arc::as_ptr(&s.trajectory), s.start, s.len);
            *index.entry(key).or_insert_with(|| {
                segs.push(s.segment());
                segs.len() - 1
            })
        };
        sides.push((at(a), at(b)));
    }
    Distinct { segs, sides }
}
