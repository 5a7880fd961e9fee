//! The queries in flight and their answers: each query committed to the label store before
//! it is sent, each answer committed before it is acknowledged and added to D, queries asked
//! again, expired or withdrawn.

use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{Context, Result};
use pbrl_common::wire::{self, now_ms, Answer, AnswerAck, Body, Preference, Query, Shown};

use super::{Answered, Feedback, Side};
use crate::pref::labels::{Stored, StoredTrajectory};
use crate::pref::query::{Candidate, Sampler, TrajKey};
use crate::pref::reward_model::{Labelled, Segment};

/// The newest answers whose agreement with the ensemble is kept ([`Feedback::agreement`]).
pub const AGREEMENT_WINDOW: usize = 20;

/// A query to send, encoded once: the message the label store keeps is the message sent
/// (and sent again). It reads as its query.
#[derive(Clone, Debug)]
pub struct Outgoing {
    pub query: Query,
    pub message: Arc<Vec<u8>>,
}

impl Outgoing {
    /// `query` of run `run`, encoded.
    pub fn encode(run: &str, query: Query) -> Self {
        let message = Arc::new(wire::encode(run, &Body::Query(Box::new(query.clone()))));
        Self { query, message }
    }
}

impl std::ops::Deref for Outgoing {
    type Target = Query;
    fn deref(&self) -> &Query {
        &self.query
    }
}

pub(super) struct InFlight {
    pub(super) query: Outgoing,
    pub(super) sent: Instant,
    /// Its trajectories (for the bound on open queries per trajectory).
    pub(super) keys: Vec<TrajKey>,
    /// When it was asked: env steps and wall time (to keep time with the teacher).
    pub(super) asked: AskedAt,
}

/// When a query was asked, in env steps and in wall time.
pub(super) type AskedAt = (u64, Instant);

impl Feedback {
    pub(super) fn segment(&self, id: u64) -> Result<Arc<Segment>> {
        if let Some(s) = self.segments.get(&id) {
            return Ok(s.clone());
        }
        let s = self.store.steps(id)?;
        Ok(Arc::new(Segment {
            obs: s.obs,
            actions: s.actions,
            features: s.features,
        }))
    }

    /// Steps `start .. start + len` of stored trajectory `id`, for D (the whole
    /// trajectory's segment, shared, when the query compared whole trajectories).
    pub(super) fn labelled_side(
        &mut self,
        id: u64,
        (start, len): (usize, usize),
    ) -> Result<Arc<Segment>> {
        let whole = self.segment(id)?;
        let a = self.model.act_dim();
        let steps = whole.actions.len() / a.max(1);
        if start == 0 && len == steps {
            // Shared by every label of this trajectory (kept while D holds it).
            self.segments.insert(id, whole.clone());
            return Ok(whole);
        }
        if len == 0 || start + len > steps {
            anyhow::bail!(
                "label store {}: segment start {start}, length {len} of trajectory {id} is not within its {steps} steps",
                self.store.path().display()
            );
        }
        Ok(Arc::new(whole.cut(start, len, steps)))
    }

    /// What one answer adds to D: a pair's label, or every pair of a ranking's attempts
    /// (`attempts` as trajectory ids and segments), each with the target its places give.
    pub(super) fn labelled(
        &mut self,
        attempts: &[(u64, (usize, usize))],
        preference: Preference,
        ranks: &[u8],
    ) -> Result<Vec<Labelled>> {
        let sides = attempts
            .iter()
            .map(|&(id, seg)| self.labelled_side(id, seg))
            .collect::<Result<Vec<_>>>()?;
        Ok(labelled(&sides, preference, ranks))
    }

    /// Record the chosen pairs (or sets to rank) in the label store (each query committed
    /// before it is sent) and return the queries.
    pub(super) fn ask(
        &mut self,
        session: u64,
        env_steps: u64,
        sampler: Sampler,
        sets: &[Vec<Side>],
        r_avg: Option<f32>,
    ) -> Result<Vec<Outgoing>> {
        let mut out = Vec::with_capacity(sets.len());
        let sampler_name = match sampler {
            Sampler::Uniform => "uniform",
            Sampler::Disagreement => "disagreement",
            Sampler::Entropy => "entropy",
        };
        for set in sets {
            let asked_at_ms = now_ms();
            let mut built = None;
            let run = self.run.clone();
            let expires_at_ms = match self.cfg.query_expiry_s {
                0 => 0,
                s => asked_at_ms + s * 1000,
            };
            let withdraw_at_steps = match self.cfg.query_stale_steps {
                0 => 0,
                s => env_steps + s,
            };
            let attempts: Vec<StoredTrajectory<'_>> = set.iter().map(stored).collect();
            let attempts: Vec<&StoredTrajectory<'_>> = attempts.iter().collect();
            let asked = self.store.ask_attempts(
                session,
                sampler_name,
                env_steps,
                asked_at_ms,
                &attempts,
                |id, ids| {
                    let q = Query {
                        id,
                        session,
                        asked_at_ms,
                        expires_at_ms,
                        first: shown(&set[0], ids[0]),
                        second: shown(&set[1], ids[1]),
                        r_avg,
                        withdraw_at_steps,
                        more: set[2..]
                            .iter()
                            .zip(&ids[2..])
                            .map(|(s, &id)| shown(s, id))
                            .collect(),
                    };
                    let out = Outgoing::encode(&run, q);
                    let bytes = out.message.to_vec();
                    built = Some(out);
                    bytes
                },
            )?;
            let q = built.context("the label store did not build the query")?;
            let ids = [asked.first, asked.second].into_iter().chain(asked.more);
            for (id, side) in ids.zip(set) {
                self.segments.insert(id, Arc::new(seg_of(&side.trajectory)));
            }
            self.in_flight.insert(
                asked.query,
                InFlight {
                    query: q.clone(),
                    sent: Instant::now(),
                    keys: set.iter().map(|s| s.trajectory.key).collect(),
                    asked: (env_steps, Instant::now()),
                },
            );
            out.push(q);
        }
        Ok(out)
    }

    /// Store a teacher's answer (committed before this returns) and say whether to
    /// acknowledge it.
    pub fn answer(&mut self, a: &Answer) -> Result<Answered> {
        if a.repeat {
            return Ok(match self.store.repeat(a, now_ms())? {
                Stored::Unknown => {
                    self.counters.unknown_answers += 1;
                    tracing::warn!(
                        query = a.query,
                        teacher = %a.teacher_id,
                        "dropped a repeated answer to a query this run never asked"
                    );
                    Answered::Dropped
                }
                _ => Answered::Ack(AnswerAck {
                    teacher_id: a.teacher_id.clone(),
                    queries: Vec::new(),
                    repeats: vec![(a.query, a.labeller.clone())],
                }),
            });
        }
        let stored = self.store.answer(a, now_ms())?;
        match stored {
            Stored::New | Stored::Late => {
                let open = self.in_flight.remove(&a.query);
                if a.preference != Preference::Skip {
                    if let Some(f) = &open {
                        // NOTE: the learner keeps time with this answer until it is trained on.
                        self.untrained_from = Some(match self.untrained_from {
                            Some(u) if u.0 <= f.asked.0 => u,
                            _ => f.asked,
                        });
                    }
                    let bounds = |s: &Shown| (s.id, (s.start as usize, s.len as usize));
                    let attempts = match &open {
                        Some(f) => f.query.attempts().map(bounds).collect(),
                        None => {
                            // NOTE: a late answer to an expired query: its ids are in D.
                            self.store
                                .labels_since(0)?
                                .into_iter()
                                .find(|r| r.query == a.query)
                                .context("a stored answer is not in D")?
                                .attempts()
                        }
                    };
                    let labels = self.labelled(&attempts, a.preference, &a.ranks)?;
                    self.agree(&labels)?;
                    self.data.extend(labels);
                }
            }
            Stored::Repeated => {
                self.counters.repeated_answers += 1;
                tracing::debug!(query = a.query, teacher = %a.teacher_id, "an answer came again; the first stands");
            }
            Stored::Unknown => {
                self.counters.unknown_answers += 1;
                tracing::warn!(
                    query = a.query,
                    teacher = %a.teacher_id,
                    "dropped an answer to a query this run never asked"
                );
                return Ok(Answered::Dropped);
            }
            Stored::Misfit => {
                self.counters.unknown_answers += 1;
                tracing::warn!(
                    query = a.query,
                    teacher = %a.teacher_id,
                    places = ?a.ranks,
                    "dropped an answer that does not fit its query (a pair's answer to a ranking, or places for another number of attempts)"
                );
                return Ok(Answered::Dropped);
            }
        }
        self.prune_segments();
        Ok(Answered::Ack(AnswerAck {
            teacher_id: a.teacher_id.clone(),
            queries: vec![a.query],
            repeats: Vec::new(),
        }))
    }

    /// How far the reward ensemble as it stands (not yet trained on these `labels`, one
    /// answer's) agrees with them: the share of their pairs it orders as the teacher did
    /// (pairs the teacher called equal left out), kept for the newest [`AGREEMENT_WINDOW`]
    /// answers. Nothing before the ensemble is trained.
    fn agree(&mut self, labels: &[Labelled]) -> Result<()> {
        let hard: Vec<&Labelled> = labels.iter().filter(|l| !l.is_equal()).collect();
        if !self.model.trained() || hard.is_empty() {
            return Ok(());
        }
        let pairs: Vec<(&Segment, &Segment)> =
            hard.iter().map(|l| (&*l.first, &*l.second)).collect();
        let probs = self.model.preference_probs(&pairs)?;
        let members = probs.len().max(1) as f32;
        let right = hard
            .iter()
            .enumerate()
            .filter(|(k, l)| {
                let p = probs.iter().map(|m| m[*k]).sum::<f32>() / members;
                (p > 0.5) == (l.target > 0.5)
            })
            .count();
        if self.agreement.len() == AGREEMENT_WINDOW {
            self.agreement.pop_front();
        }
        self.agreement.push_back(right as f64 / hard.len() as f64);
        Ok(())
    }

    /// The share of the newest answers (at most [`AGREEMENT_WINDOW`]) the ensemble agreed
    /// with before it trained on them, and how many answers that is (None before any).
    pub fn agreement(&self) -> Option<(f64, usize)> {
        let n = self.agreement.len();
        (n > 0).then(|| (self.agreement.iter().sum::<f64>() / n as f64, n))
    }

    /// Forget the whole trajectories no query in flight compares and D does not share:
    /// a label of a segment holds its own cut, so keeping the whole trajectory of every
    /// query ever asked would grow the learner by two trajectories a label.
    pub(super) fn prune_segments(&mut self) {
        let open: std::collections::HashSet<u64> = self
            .in_flight
            .values()
            .flat_map(|f| [f.query.first.id, f.query.second.id])
            .collect();
        self.segments
            .retain(|id, s| Arc::strong_count(s) > 1 || open.contains(id));
    }

    /// Queries to ask again (unanswered for `query_retry_s`) at `env_steps`; queries past
    /// `query_expiry_s` expire instead, and those grown stale (`query_stale_steps`) are
    /// withdrawn, a fresh one owed in each one's place.
    pub fn retry(&mut self, env_steps: u64) -> Result<Vec<Outgoing>> {
        let retry = Duration::from_secs(self.cfg.query_retry_s);
        let now = now_ms();
        let mut again = Vec::new();
        let mut expired = Vec::new();
        let mut stale = Vec::new();
        for (id, f) in self.in_flight.iter_mut() {
            let age_ms = now.saturating_sub(f.query.asked_at_ms);
            if self.cfg.query_expiry_s > 0 && age_ms >= self.cfg.query_expiry_s * 1000 {
                expired.push(*id);
            } else if f.query.stale_at(env_steps) {
                stale.push(*id);
            } else if f.sent.elapsed() >= retry {
                f.sent = Instant::now();
                again.push(f.query.clone());
            }
        }
        for id in expired {
            self.store.expire(id, now)?;
            self.in_flight.remove(&id);
            tracing::warn!(query = id, "a query went unanswered too long: expired");
        }
        for id in stale {
            // NOTE: the store says it was withdrawn; an answer that still comes (a person
            // held the pair) is stored as late, exactly once.
            if self.store.withdraw(id, now, env_steps)? {
                self.owed += 1;
                self.counters.withdrawn_queries += 1;
            }
            self.in_flight.remove(&id);
            tracing::debug!(
                query = id,
                env_steps,
                "a stale query withdrawn; a fresh one owed"
            );
        }
        self.counters.retried_queries += again.len() as u64;
        Ok(again)
    }
}

/// The soft target of a preference: P[second preferred].
/// The labels of D one answer gives over its attempts' segments `sides`: a pair's one
/// (`preference`), or every pair of a ranking's attempts with the target their places give.
pub(crate) fn labelled(
    sides: &[Arc<Segment>],
    preference: Preference,
    ranks: &[u8],
) -> Vec<Labelled> {
    if ranks.is_empty() {
        return vec![Labelled {
            first: sides[0].clone(),
            second: sides[1].clone(),
            target: target(preference),
        }];
    }
    let mut out = Vec::with_capacity(sides.len() * (sides.len() - 1) / 2);
    for i in 0..sides.len() {
        for j in i + 1..sides.len() {
            out.push(Labelled {
                first: sides[i].clone(),
                second: sides[j].clone(),
                target: target(Preference::of_places(ranks[i], ranks[j])),
            });
        }
    }
    out
}

pub(crate) fn target(p: Preference) -> f32 {
    match p {
        Preference::First => 0.0,
        Preference::Second => 1.0,
        Preference::Equal | Preference::Skip => 0.5,
    }
}

pub(super) fn seg_of(c: &Candidate) -> Segment {
    Segment {
        obs: c.obs.clone(),
        actions: c.actions.clone(),
        features: c.features.clone(),
    }
}

pub(super) fn stored(side: &Side) -> StoredTrajectory<'_> {
    let c = &*side.trajectory;
    StoredTrajectory {
        actor: c.key.actor,
        incarnation: c.key.incarnation,
        seq: c.key.seq,
        seed: c.seed,
        policy_version: c.policy_version,
        obs_dim: c.obs_dim as usize,
        act_dim: c.act_dim as usize,
        obs: &c.obs,
        actions: &c.actions,
        features: &c.features,
        segment: (side.start, side.len),
    }
}

pub(super) fn shown(side: &Side, id: u64) -> Shown {
    let c = &*side.trajectory;
    Shown {
        id,
        seed: c.seed,
        policy_version: c.policy_version,
        act_dim: c.act_dim,
        actions: c.actions.clone(),
        truth: c.truth.clone(),
        replay: None,
        start: side.start as u32,
        len: side.len as u32,
    }
}
