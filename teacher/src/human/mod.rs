//! The human teacher's desk: the queue of open queries that people answer from a page (or
//! any client of the HTTP API in [`crate::web`]), kept on disk.
//!
//! A label is a person's time, so the desk writes each query it receives and each answer a
//! person gives to the teacher's SQLite file (WAL, synced at every commit) before anything
//! else sees it. An answer stays on the desk while it can be undone; then the desk hands it
//! to the teacher's [`Outbox`] (in the same file), which sends it until the learner
//! acknowledges it, as it does a scripted teacher's. A teacher restarted finds its queue,
//! the answers in their undo window and its repeats as they were.
//!
//! - An answer can be undone for `undo_s` seconds; then it goes to the outbox.
//! - Each query is leased to the person it is shown to for `lease_s` seconds, so two people
//!   are not shown the same pair; a person may hold two (the page fetches the next pair
//!   while the person judges the current one).
//! - A share `repeat_share` of answered queries is asked again later: of the same person
//!   (sides swapped at random again), and of another when someone else is labelling. Those
//!   answers are repeats: stored apart from D, they measure consistency and agreement.
//! - With `shadow`, the oracle also judges every query a person answers, on the ground
//!   truth the query carries; its answer is recorded beside the person's, never shown and
//!   never trained on.
//! - Sides are shuffled per query and person, so neither side says which attempt is newer;
//!   a person never sees the ground truth.

use std::collections::{BTreeMap, HashMap};
use std::sync::Arc;

use anyhow::{bail, Result};
use pbrl_common::wire::{check_labeller, now_ms, Answer, LearnerStatus, Preference, Query};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use crate::file::TeacherFile;
use crate::outbox::{self, Outbox};
use store::DeskStore;

mod store;
#[cfg(test)]
pub(crate) mod tests;
use crate::scripted::{Scripted, ScriptedConfig, TeacherKind};
use crate::teacher::Teacher;

/// Whose answer is recorded beside each person's (`--shadow`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum Shadow {
    /// The oracle judges each query a person answers, on the ground truth; recorded
    /// beside the person's answer, never shown and never trained on.
    Oracle,
}

/// The desk's settings (its file is the teacher's: `TeacherConfig::state`). Each default is
/// its flag's.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, clap::Args)]
pub struct HumanConfig {
    /// Human teacher: seconds an answer can be undone before it goes to the learner.
    #[arg(long, default_value_t = 10)]
    pub undo_s: u64,
    /// Human teacher: seconds a pair shown to a person stays theirs (nobody else is shown
    /// it meanwhile).
    #[arg(long, default_value_t = 300)]
    pub lease_s: u64,
    /// Human teacher: share of answered queries asked again (of the same person, and of
    /// another when two are labelling), to measure consistency and agreement.
    #[arg(long, default_value_t = 0.1)]
    pub repeat_share: f64,
    /// Human teacher: record a scripted teacher's answer beside each person's.
    #[arg(long, value_enum)]
    pub shadow: Option<Shadow>,
    /// Seed of the repeats' draws and the sides' shuffles (the run's).
    #[arg(skip)]
    pub seed: u64,
}

impl Default for HumanConfig {
    fn default() -> Self {
        pbrl_common::flags::defaults()
    }
}

impl HumanConfig {
    pub fn validate(&self) -> Result<()> {
        if !(0.0..=1.0).contains(&self.repeat_share) {
            bail!("repeat_share is {}: must be in [0, 1]", self.repeat_share);
        }
        if self.lease_s == 0 {
            bail!("lease_s is 0: must be at least 1");
        }
        Ok(())
    }
}

/// A person's choice as the page gives it.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Choice {
    Left,
    Right,
    Equal,
    Skip,
}

/// A person's answer as given on the page: a choice on a pair, or each attempt's place in
/// a ranking (in the order shown, 0 the best, ties sharing a place).
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Verdict {
    Choice(Choice),
    Places(Vec<u8>),
}

/// Why the desk refused a request (the HTTP side's 4xx).
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum Refused {
    #[error("no open query {0}")]
    Unknown(u64),
    #[error("query {0} is answered already")]
    Answered(u64),
    #[error("query {0} was answered by another labeller first; this answer is not recorded")]
    AnsweredByOther(u64),
    #[error("nothing to undo")]
    NothingToUndo,
    #[error("{0}")]
    Invalid(String),
    /// The desk's file failed (the answer is not stored, or stored and its repeats not
    /// planned): the HTTP side's 500.
    #[error("{0}")]
    Failed(String),
}

/// A pair to show: the query and which side goes left.
#[derive(Clone, Debug)]
pub struct Showing {
    pub query: Arc<Query>,
    /// The query's second trajectory is shown on the left.
    pub swapped: bool,
    pub repeat: bool,
    /// The number the page shows for this pair (1000-9999): the same on a reload, another
    /// for a repeat, so that a person cannot tell a consistency check by its number.
    pub display: u32,
    /// A ranking's attempts in the order shown: position k shows the query's attempt
    /// `order[k]` (for a pair, `swapped` says).
    pub order: Vec<usize>,
}

/// An answer a person gave that is still on the desk (in its undo window, or past it and
/// not yet handed to the outbox).
#[derive(Clone, Debug)]
struct Given {
    answer: Answer,
    given_at_ms: u64,
}

/// A query to ask a person again.
#[derive(Clone, Debug)]
struct Check {
    query: u64,
    labeller: String,
    /// Shown once the person has answered this many (not at once after the first time).
    due_after: u64,
}

/// What a person did at this desk.
#[derive(Clone, Debug, Default)]
struct Person {
    /// Answers since the desk started (the page's count for this sitting).
    answered: u64,
    /// Answers ever given here, kept on disk: repeats are due after a count of these, so
    /// a restart neither brings them forward nor puts them off.
    total: u64,
    last_seen_ms: u64,
    /// The query of an undone answer, given back first.
    undone: Option<(u64, bool)>,
}

/// The queue, the answers that can still be undone and the repeats.
pub struct Desk {
    cfg: HumanConfig,
    run: String,
    teacher_id: String,
    store: DeskStore,
    /// Every query still needed: open, answered and still on the desk, or to be repeated.
    queries: BTreeMap<u64, Arc<Query>>,
    /// Queries answered (by anyone), so not open.
    answered: std::collections::BTreeSet<u64>,
    leases: HashMap<u64, (String, u64)>,
    /// Answers still on the desk.
    given: BTreeMap<outbox::Key, Given>,
    checks: Vec<Check>,
    people: HashMap<String, Person>,
    oracle: Scripted,
    rng: ChaCha8Rng,
    status: Option<(LearnerStatus, u64)>,
    /// The learner's env steps grew at the last status.
    training: bool,
}

/// A labeller's name as the wire checks it, and not blank.
fn check_name(labeller: &str) -> Result<(), Refused> {
    check_labeller("labeller", labeller).map_err(|e| Refused::Invalid(e.to_string()))?;
    if labeller.trim().is_empty() {
        return Err(Refused::Invalid("labeller: a name is needed".into()));
    }
    Ok(())
}

impl Desk {
    /// Open the desk in the teacher's `file` (making its tables) and read back what it
    /// holds.
    pub fn open(cfg: HumanConfig, file: &TeacherFile, run: &str, teacher_id: &str) -> Result<Self> {
        cfg.validate()?;
        let (store, loaded) = DeskStore::open(file)?;
        let mut desk = Self {
            run: run.into(),
            teacher_id: teacher_id.into(),
            store,
            queries: BTreeMap::new(),
            answered: Default::default(),
            leases: HashMap::new(),
            given: BTreeMap::new(),
            checks: Vec::new(),
            people: HashMap::new(),
            oracle: Scripted::new(ScriptedConfig::of(TeacherKind::Oracle, cfg.seed))?,
            rng: ChaCha8Rng::seed_from_u64(cfg.seed ^ 0xdeb5_0000_0000_0001),
            status: None,
            training: false,
            cfg,
        };
        desk.load(loaded);
        Ok(desk)
    }

    fn load(&mut self, loaded: store::Loaded) {
        for q in loaded.queries {
            self.queries.insert(q.id, Arc::new(q));
        }
        for (a, given_at_ms) in loaded.answers {
            if !a.repeat {
                self.answered.insert(a.query);
            }
            self.given.insert(
                outbox::key(&a),
                Given {
                    answer: a,
                    given_at_ms,
                },
            );
        }
        // NOTE: a pair on someone's open page stays theirs across a restart.
        self.leases = (loaded.leases.into_iter())
            .map(|(q, who, at)| (q, (who, at)))
            .collect();
        self.checks = (loaded.checks.into_iter())
            .map(|(query, labeller, due_after)| Check {
                query,
                labeller,
                due_after,
            })
            .collect();
        // NOTE: a repeat is planned only on a query's answer (and withdrawn with it), so a
        // query with repeats to ask is answered, even once that answer has left the disk.
        self.answered.extend(self.checks.iter().map(|c| c.query));
        for (name, total) in loaded.labellers {
            self.people.entry(name).or_default().total = total;
        }
        if !self.queries.is_empty() || !self.given.is_empty() {
            tracing::info!(
                open = self.open_queries(),
                on_the_desk = self.given.len(),
                repeats = self.checks.len(),
                "the teacher's queue is back"
            );
        }
    }

    /// Queries waiting for a person's answer.
    pub fn open_queries(&self) -> usize {
        self.queries
            .keys()
            .filter(|id| !self.answered.contains(id))
            .count()
    }

    /// A query from the learner: queued (written to disk first), unless it is queued,
    /// answered or expired already. (A query asked again after its answer left the desk is
    /// answered by the outbox and never comes here.)
    pub fn queue(&mut self, q: Query) -> Result<()> {
        if self.answered.contains(&q.id) || self.queries.contains_key(&q.id) {
            return Ok(());
        }
        if q.expired_at(now_ms()) || q.stale_at(self.learner_steps()) {
            return Ok(());
        }
        self.store.queue(&q)?;
        self.queries.insert(q.id, Arc::new(q));
        Ok(())
    }

    /// Answers past their undo window: kept in `outbox` (committed there first), then
    /// taken off the desk; returned to send. One the outbox holds already (the desk was
    /// stopped between the two) is only taken off.
    pub fn hand_over(&mut self, outbox: &mut Outbox) -> Result<Vec<Answer>> {
        let now = now_ms();
        let undo_ms = self.cfg.undo_s * 1000;
        let settled: Vec<outbox::Key> = self
            .given
            .iter()
            .filter(|(_, g)| now >= g.given_at_ms + undo_ms)
            .map(|(k, _)| k.clone())
            .collect();
        let mut out = Vec::new();
        for k in settled {
            let answer = self.given[&k].answer.clone();
            // NOTE: the desk keeps a query while an answer to it is on the desk.
            let asked_at_ms = self.queries.get(&k.0).map_or(0, |q| q.asked_at_ms);
            // NOTE: one transaction: the answer is on exactly one of the desk and the outbox.
            if outbox.keep_with(&answer, asked_at_ms, |tx| store::take_off(tx, &k))? {
                out.push(answer);
            }
            self.given.remove(&k);
            self.forget_if_done(k.0)?;
        }
        Ok(out)
    }

    fn forget_if_done(&mut self, query: u64) -> Result<()> {
        let needed = !self.answered.contains(&query)
            || self.given.keys().any(|(q, _, _)| *q == query)
            || self.checks.iter().any(|c| c.query == query);
        if !needed {
            self.store.forget(query)?;
            self.queries.remove(&query);
        }
        Ok(())
    }

    /// Open queries past their expiry leave the queue, and so do those the learner has
    /// withdrawn as stale, unless a person holds one on their page (they may still answer
    /// it; the learner stores that answer as late).
    pub fn expire(&mut self) -> Result<()> {
        let now = now_ms();
        let steps = self.learner_steps();
        let lease_ms = self.cfg.lease_s * 1000;
        let expired: Vec<u64> = self
            .queries
            .values()
            .filter(|q| {
                let held = self
                    .leases
                    .get(&q.id)
                    .is_some_and(|(_, at)| now < at + lease_ms);
                !self.answered.contains(&q.id)
                    && (q.expired_at(now) || (q.stale_at(steps) && !held))
            })
            .map(|q| q.id)
            .collect();
        for id in expired {
            self.store.forget(id)?;
            self.queries.remove(&id);
            self.leases.remove(&id);
        }
        Ok(())
    }

    fn swapped(&self, query: u64, labeller: &str, repeat: bool) -> bool {
        self.showing_hash(query, labeller, repeat) & 1 == 1
    }

    /// The order a ranking's attempts show in for `labeller`: shown position k holds the
    /// query's attempt `order[k]` (the same on a reload, drawn afresh for a repeat).
    pub fn order(&self, query: u64, labeller: &str, repeat: bool, attempts: usize) -> Vec<usize> {
        let h = self.showing_hash(query, labeller, repeat);
        let mut order: Vec<usize> = (0..attempts).collect();
        order.sort_by_key(|&k| {
            (h ^ (k as u64 + 1).wrapping_mul(0x9e37_79b9_7f4a_7c15))
                .wrapping_mul(0xff51_afd7_ed55_8ccd)
        });
        order
    }

    /// The pair's number on the page: a repeat's is never its first showing's.
    fn display(&self, query: u64, labeller: &str, repeat: bool) -> u32 {
        let number =
            |repeat| 1000 + ((self.showing_hash(query, labeller, repeat) >> 1) % 9000) as u32;
        let shown = number(repeat);
        if repeat && shown == number(false) {
            1000 + (shown - 1000 + 1) % 9000
        } else {
            shown
        }
    }

    fn showing_hash(&self, query: u64, labeller: &str, repeat: bool) -> u64 {
        // NOTE: a hash of the query, the person and the round, mixed with the desk's seed:
        // the same pair shows the same way on a reload, and a repeat is drawn afresh.
        let mut h: u64 = self.cfg.seed ^ 0x9e37_79b9_7f4a_7c15;
        for b in labeller
            .bytes()
            .chain(query.to_le_bytes())
            .chain([repeat as u8])
        {
            h = (h ^ b as u64).wrapping_mul(0x0000_0100_0000_01b3);
        }
        // NOTE: FNV alone leaves the high bits nearly unmoved by the last byte (the round):
        // mixed, a repeat's sides are a fresh draw.
        h ^= h >> 33;
        h = h.wrapping_mul(0xff51_afd7_ed55_8ccd);
        h ^= h >> 33;
        h
    }

    /// The next pair for `labeller` (none open: `None`), not `exclude`: an undone answer's
    /// query first, then a repeat that is due, then the oldest open query nobody else holds.
    pub fn next(
        &mut self,
        labeller: &str,
        exclude: Option<u64>,
    ) -> Result<Option<Showing>, Refused> {
        check_name(labeller)?;
        let now = now_ms();
        let lease_ms = self.cfg.lease_s * 1000;
        let person = self.people.entry(labeller.to_string()).or_default();
        person.last_seen_ms = now;
        let answered_by_them = person.total;
        let undone = person.undone;
        let pick = |id: u64, repeat: bool| Some((id, repeat));
        let mut chosen = None;
        if let Some((id, repeat)) = undone {
            if Some(id) != exclude && self.queries.contains_key(&id) {
                chosen = pick(id, repeat);
            }
        }
        if chosen.is_none() {
            chosen = self
                .checks
                .iter()
                .find(|c| {
                    c.labeller == labeller
                        && c.due_after <= answered_by_them
                        && Some(c.query) != exclude
                        && self.queries.contains_key(&c.query)
                })
                .map(|c| (c.query, true));
        }
        if chosen.is_none() {
            // NOTE: a query withdrawn as stale is offered to nobody new; who holds it may
            // see it again (a reload) and answer it.
            let steps = self.learner_steps();
            chosen = self
                .queries
                .values()
                .find(|q| {
                    !self.answered.contains(&q.id)
                        && Some(q.id) != exclude
                        && match self.leases.get(&q.id) {
                            Some((who, _)) if who == labeller => true,
                            Some((_, at)) => now >= at + lease_ms && !q.stale_at(steps),
                            None => !q.stale_at(steps),
                        }
                })
                .map(|q| (q.id, false));
        }
        let Some((id, repeat)) = chosen else {
            return Ok(None);
        };
        if !repeat && self.leases.get(&id).is_none_or(|(who, _)| who != labeller) {
            self.store
                .lease(id, labeller, now, self.learner_steps())
                .map_err(|e| Refused::Failed(format!("keeping the lease failed: {e:#}")))?;
            self.leases.insert(id, (labeller.to_string(), now));
        }
        let attempts = self.queries[&id].len();
        Ok(Some(Showing {
            query: self.queries[&id].clone(),
            order: self.order(id, labeller, repeat, attempts),
            swapped: self.swapped(id, labeller, repeat),
            repeat,
            display: self.display(id, labeller, repeat),
        }))
    }

    /// A person's answer: written to disk before this returns; it can be undone for
    /// `undo_s` seconds. Returns what this person has answered since the desk started.
    pub fn answer(
        &mut self,
        labeller: &str,
        query: u64,
        choice: Choice,
        took_ms: u64,
        replays: [u32; 2],
    ) -> Result<u64, Refused> {
        self.give(labeller, query, Verdict::Choice(choice), took_ms, replays)
    }

    /// A person's answer, a choice on a pair or places in a ranking ([`Desk::answer`]).
    pub fn give(
        &mut self,
        labeller: &str,
        query: u64,
        verdict: Verdict,
        took_ms: u64,
        replays: [u32; 2],
    ) -> Result<u64, Refused> {
        check_name(labeller)?;
        let check = self.answerable(labeller, query)?;
        let repeat = check.is_some();
        let skip = verdict == Verdict::Choice(Choice::Skip);
        let a = self.person_answer(labeller, query, repeat, verdict, took_ms, replays)?;
        let now = now_ms();
        self.store
            .answer(&a, now)
            .map_err(|e| Refused::Failed(format!("storing the answer failed: {e:#}")))?;
        if let Some(k) = check {
            self.checks.remove(k);
        } else {
            self.answered.insert(query);
            self.leases.remove(&query);
        }
        let key = outbox::key(&a);
        self.given.insert(
            key,
            Given {
                answer: a,
                given_at_ms: now,
            },
        );
        let person = self.people.entry(labeller.to_string()).or_default();
        person.answered += 1;
        person.total += 1;
        person.undone = None;
        let answered = person.total;
        if !repeat && !skip {
            self.plan_repeats(query, labeller, answered)
                .map_err(|e| Refused::Failed(format!("planning a repeat failed: {e:#}")))?;
        }
        Ok(answered)
    }

    /// Whether `labeller` may answer `query` now: as its repeat (the index of the check),
    /// or as its first answer (None).
    fn answerable(&self, labeller: &str, query: u64) -> Result<Option<usize>, Refused> {
        let check = self
            .checks
            .iter()
            .position(|c| c.query == query && c.labeller == labeller);
        if check.is_some() {
            return Ok(check);
        }
        if self.answered.contains(&query) {
            let mine = self
                .given
                .contains_key(&(query, labeller.to_string(), false));
            return Err(if mine {
                Refused::Answered(query)
            } else {
                Refused::AnsweredByOther(query)
            });
        }
        if !self.queries.contains_key(&query) {
            return Err(Refused::Unknown(query));
        }
        Ok(None)
    }

    /// The answer a verdict on the query as shown means (sides or attempts put back in the
    /// query's order, the oracle's shadow beside it when asked for); a verdict that does not
    /// fit the query is refused.
    fn person_answer(
        &mut self,
        labeller: &str,
        query: u64,
        repeat: bool,
        verdict: Verdict,
        took_ms: u64,
        replays: [u32; 2],
    ) -> Result<Answer, Refused> {
        let q = self.queries[&query].clone();
        let swapped = self.swapped(query, labeller, repeat);
        let n = q.len();
        let (preference, ranks) = match verdict {
            Verdict::Choice(Choice::Skip) => (Preference::Skip, Vec::new()),
            Verdict::Choice(_) if n > 2 => {
                return Err(Refused::Invalid(format!(
                    "query {query} asks to rank {n} attempts: send \"places\", one per attempt as shown (or the choice skip)"
                )))
            }
            Verdict::Choice(choice) => (
                match (choice, swapped) {
                    (Choice::Left, false) | (Choice::Right, true) => Preference::First,
                    (Choice::Right, false) | (Choice::Left, true) => Preference::Second,
                    _ => Preference::Equal,
                },
                Vec::new(),
            ),
            Verdict::Places(shown) => {
                if n == 2 || shown.len() != n || shown.iter().any(|&p| p as usize >= n) {
                    return Err(Refused::Invalid(format!(
                        "places {shown:?}: query {query} shows {n} attempts{}",
                        if n == 2 {
                            ", a pair: send a choice"
                        } else {
                            "; send one place each, in the order shown, 0 the best"
                        }
                    )));
                }
                let mut ranks = vec![0u8; n];
                for (k, &attempt) in self.order(query, labeller, repeat, n).iter().enumerate() {
                    ranks[attempt] = shown[k];
                }
                (Preference::of_places(ranks[0], ranks[1]), ranks)
            }
        };
        let replays = if swapped {
            [replays[1], replays[0]]
        } else {
            replays
        };
        let shadow = self
            .cfg
            .shadow
            .is_some()
            .then(|| crate::teacher::judge_query(&mut self.oracle, &q));
        Ok(Answer {
            query,
            preference,
            teacher: "human".into(),
            teacher_id: self.teacher_id.clone(),
            took_ms,
            labeller: labeller.to_string(),
            replays,
            shadow,
            repeat,
            ranks,
        })
    }

    fn plan_repeats(&mut self, query: u64, labeller: &str, answered: u64) -> Result<()> {
        if self.cfg.repeat_share <= 0.0 || !self.rng.random_bool(self.cfg.repeat_share) {
            return Ok(());
        }
        let now = now_ms();
        // NOTE: the same person a few pairs later (not the very next: memory is not
        // consistency); another person active in the last minute, at their next pair.
        let mut plan = vec![(labeller.to_string(), answered + 3)];
        if let Some((other, p)) = self
            .people
            .iter()
            .filter(|(name, p)| name.as_str() != labeller && now < p.last_seen_ms + 60_000)
            .min_by_key(|(name, _)| name.as_str())
        {
            plan.push((other.clone(), p.total));
        }
        for (who, due_after) in plan {
            self.store.plan_check(query, &who, due_after)?;
            self.checks.push(Check {
                query,
                labeller: who,
                due_after,
            });
        }
        Ok(())
    }

    /// Withdraw `labeller`'s newest answer still in its undo window; its pair is given back
    /// to them next.
    pub fn undo(&mut self, labeller: &str) -> Result<u64, Refused> {
        let newest = self
            .given
            .iter()
            .filter(|((_, l, _), _)| l == labeller)
            .max_by_key(|(_, g)| g.given_at_ms)
            .map(|(k, _)| k.clone());
        let Some(k) = newest else {
            return Err(Refused::NothingToUndo);
        };
        if now_ms() >= self.given[&k].given_at_ms + self.cfg.undo_s * 1000 {
            return Err(Refused::NothingToUndo);
        }
        let (query, _, repeat) = k.clone();
        let undone = self.store.undo(query, labeller, repeat);
        undone.map_err(|e| Refused::Failed(format!("undoing failed: {e:#}")))?;
        self.given.remove(&k);
        if repeat {
            self.checks.push(Check {
                query,
                labeller: labeller.to_string(),
                due_after: 0,
            });
        } else {
            self.answered.remove(&query);
            self.checks.retain(|c| c.query != query);
            self.leases.insert(query, (labeller.to_string(), now_ms()));
        }
        let person = self.people.entry(labeller.to_string()).or_default();
        person.answered = person.answered.saturating_sub(1);
        person.total = person.total.saturating_sub(1);
        person.undone = Some((query, repeat));
        Ok(query)
    }

    /// The learner's newest status.
    pub fn learner_status(&mut self, s: LearnerStatus) {
        let grew = self
            .status
            .as_ref()
            .is_some_and(|(old, _)| s.env_steps > old.env_steps);
        if grew || self.status.is_none() {
            self.training = grew;
        }
        self.status = Some((s, now_ms()));
    }

    /// The learner's env steps at its newest status (0 before any).
    fn learner_steps(&self) -> u64 {
        self.status.as_ref().map_or(0, |(s, _)| s.env_steps)
    }

    /// The learner's status if heard in the last 5 seconds, and whether its env steps
    /// grew at the last one (it trains).
    pub fn learner(&self) -> Option<(&LearnerStatus, bool)> {
        let now = now_ms();
        self.status
            .as_ref()
            .filter(|(_, at)| now < at + 5_000)
            .map(|(s, _)| (s, self.training))
    }

    /// What `labeller` has answered since the desk started.
    pub fn answered_by(&self, labeller: &str) -> u64 {
        self.people.get(labeller).map_or(0, |p| p.answered)
    }

    /// The run and this teacher's id.
    pub fn names(&self) -> (&str, &str) {
        (&self.run, &self.teacher_id)
    }

    /// A person whose page asks for the status is present, answering or not (the page
    /// polls it every 2 s while it is open). A name that is not usable changes nothing.
    pub fn seen(&mut self, labeller: &str) {
        if check_name(labeller).is_ok() {
            self.people
                .entry(labeller.to_string())
                .or_default()
                .last_seen_ms = now_ms();
        }
    }

    /// People seen in the last 30 seconds (their liveliness tokens).
    pub fn present(&self) -> Vec<String> {
        let now = now_ms();
        self.people
            .iter()
            .filter(|(_, p)| now < p.last_seen_ms + 30_000)
            .map(|(n, _)| n.clone())
            .collect()
    }

    /// Answers still on the desk (in their undo window, or not yet handed to the outbox).
    pub fn on_the_desk(&self) -> usize {
        self.given.len()
    }
}

/// People's desk as a teacher: a query is queued for them; their answers go to the outbox
/// once they can no longer be undone.
impl Teacher for Desk {
    fn kind(&self) -> String {
        "human".into()
    }

    fn receive(&mut self, q: Query, _outbox: &mut Outbox) -> Result<Option<Answer>> {
        self.queue(q)?;
        Ok(None)
    }

    fn due(&mut self, outbox: &mut Outbox) -> Result<Vec<Answer>> {
        self.expire()?;
        self.hand_over(outbox)
    }

    fn learner_status(&mut self, status: LearnerStatus) {
        Desk::learner_status(self, status)
    }

    fn present(&self) -> Vec<String> {
        Desk::present(self)
    }
}
