//! The one trait every teacher implements, and what the teacher loop does with each event
//! apart from the network ([`Served`]).
//!
//! Two kinds of teacher answer queries: a judge answers each at once ([`AtOnce`], over a
//! scripted teacher of [`crate::scripted`]), people at the desk answer when they can
//! ([`crate::human::Desk`]). Both keep every answer in the [`Outbox`] before it is sent;
//! the outbox, not the teacher, answers a query asked again and sends again what the
//! learner has not acknowledged.

use std::collections::BTreeMap;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::Result;
use pbrl_common::wire::{Answer, AnswerAck, LearnerStatus, Preference, Query};

use crate::outbox::Outbox;
use crate::scripted::Scripted;

/// Whoever answers queries: a judge answering at once, or people at a desk.
pub trait Teacher: Send {
    /// The kind of teacher, as the label store records it.
    fn kind(&self) -> String;
    /// A query asked for the first time: judged at once and kept in `outbox`, its answer
    /// returned to send; or queued for people (None).
    fn receive(&mut self, q: Query, outbox: &mut Outbox) -> Result<Option<Answer>>;
    /// Answers given since the last call (people's, once they can no longer be undone):
    /// kept in `outbox`, returned to send.
    fn due(&mut self, outbox: &mut Outbox) -> Result<Vec<Answer>> {
        let _ = outbox;
        Ok(Vec::new())
    }
    /// The learner's newest status (for people's page).
    fn learner_status(&mut self, status: LearnerStatus) {
        let _ = status;
    }
    /// People labelling here now (each holds a liveliness token).
    fn present(&self) -> Vec<String> {
        Vec::new()
    }
}

/// Whoever judges a pair at once from what the query carries: a scripted teacher (or a
/// test's).
pub trait Judge: Send {
    /// The kind of teacher, as the label store records it.
    fn kind(&self) -> String;
    /// Judge a pair.
    fn judge(&mut self, q: &Query) -> Preference;
    /// Rank a query of three or four attempts: each one's place, 0 the best (None: the
    /// judge cannot tell, an answer of Skip). A judge of pairs only cannot.
    fn rank(&mut self, q: &Query) -> Option<Vec<u8>> {
        let _ = q;
        None
    }
}

/// `judge`'s answer to `q` as teacher `id`, which took `took_ms`: a pair's preference, or
/// a ranking's places.
pub fn judged<J: Judge + ?Sized>(judge: &mut J, q: &Query, id: &str, took_ms: u64) -> Answer {
    let kind = judge.kind();
    if q.more.is_empty() {
        return Answer::scripted(q.id, judge.judge(q), &kind, id, took_ms);
    }
    match judge.rank(q) {
        Some(places) => Answer::ranked(q.id, places, &kind, id, took_ms),
        None => Answer::scripted(q.id, Preference::Skip, &kind, id, took_ms),
    }
}

impl Judge for Scripted {
    fn kind(&self) -> String {
        self.config().kind.name().to_string()
    }

    fn judge(&mut self, q: &Query) -> Preference {
        judge_query(self, q)
    }

    fn rank(&mut self, q: &Query) -> Option<Vec<u8>> {
        let steps = q.first.steps().max(1) as f64;
        let truths: Vec<&[f32]> = q.attempts().map(|s| s.segment_truth()).collect();
        let moves: Option<Vec<f64>> = q.attempts().map(movement).collect();
        let fraction = truths[0].len() as f64 / steps;
        self.rank_returns(
            &truths,
            q.r_avg.map(f64::from),
            if q.r_avg.is_some() { fraction } else { 1.0 },
            moves.as_deref(),
        )
    }
}

/// A scripted teacher's judgement of a query's two segments: with the session's R_avg
/// where the query carries one (the learner's newest training episodes, as the authors'
/// code), else with the teacher's own window of returns shown.
pub fn judge_query(t: &mut Scripted, q: &Query) -> Preference {
    let (a, b) = (q.first.segment_truth(), q.second.segment_truth());
    match q.r_avg {
        Some(r_avg) => {
            let steps = q.first.steps().max(1) as f64;
            let moves = [&q.first, &q.second].map(movement);
            let moves = match moves {
                [Some(m0), Some(m1)] => Some([m0, m1]),
                _ => None,
            };
            t.answer_in_session(a, b, r_avg as f64, a.len() as f64 / steps, moves)
        }
        None => t.answer(a, b),
    }
}

/// How much an attempt moves in its judged steps: the mean |action| (None without actions).
pub fn movement(s: &pbrl_common::wire::Shown) -> Option<f64> {
    let dim = s.act_dim as usize;
    let range = s.segment();
    let rows = s.actions.get(range.start * dim..range.end * dim)?;
    if rows.is_empty() {
        return None;
    }
    Some(rows.iter().map(|a| a.abs() as f64).sum::<f64>() / rows.len() as f64)
}

/// A teacher that judges each query at once with its judge, as teacher `id`.
pub struct AtOnce<J> {
    judge: J,
    id: String,
}

impl<J: Judge> AtOnce<J> {
    pub fn new(judge: J, id: &str) -> Self {
        Self {
            judge,
            id: id.to_string(),
        }
    }
}

impl<J: Judge> Teacher for AtOnce<J> {
    fn kind(&self) -> String {
        self.judge.kind()
    }

    fn receive(&mut self, q: Query, outbox: &mut Outbox) -> Result<Option<Answer>> {
        let start = Instant::now();
        let mut answer = judged(&mut self.judge, &q, &self.id, 0);
        answer.took_ms = start.elapsed().as_millis() as u64;
        tracing::debug!(
            query = q.id,
            preference = answer.preference.name(),
            places = ?answer.ranks,
            "judged a query"
        );
        outbox.keep(&answer, q.asked_at_ms)?;
        Ok(Some(answer))
    }
}

/// A teacher shared with others (the desk, with the page's handlers).
impl<T: Teacher> Teacher for Arc<Mutex<T>> {
    fn kind(&self) -> String {
        lock(self).kind()
    }

    fn receive(&mut self, q: Query, outbox: &mut Outbox) -> Result<Option<Answer>> {
        lock(self).receive(q, outbox)
    }

    fn due(&mut self, outbox: &mut Outbox) -> Result<Vec<Answer>> {
        lock(self).due(outbox)
    }

    fn learner_status(&mut self, status: LearnerStatus) {
        lock(self).learner_status(status)
    }

    fn present(&self) -> Vec<String> {
        lock(self).present()
    }
}

/// `m`'s guard, even if a holder panicked (what it guards is written to disk first).
pub fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

/// What a teacher did.
#[derive(Clone, Debug, Default)]
pub struct TeacherSummary {
    /// Answers given by this process (queries judged, each once; people's answers).
    pub judged: u64,
    /// Answers by kind: first, second, equal, skip.
    pub by_kind: BTreeMap<&'static str, u64>,
    /// Answers sent again (asked again, unacknowledged for a while, or kept before a
    /// restart).
    pub resent: u64,
    /// Answers the learner acknowledged.
    pub acknowledged: u64,
    /// Malformed messages, or another run's, dropped.
    pub dropped: u64,
}

impl TeacherSummary {
    fn given(&mut self, a: &Answer) {
        self.judged += 1;
        *self.by_kind.entry(a.preference.name()).or_default() += 1;
    }
}

/// A teacher and its outbox: what the teacher loop does with each event, before it sends
/// what comes back.
pub struct Served<T> {
    pub teacher: T,
    pub outbox: Outbox,
    pub summary: TeacherSummary,
}

impl<T: Teacher> Served<T> {
    pub fn new(teacher: T, outbox: Outbox) -> Self {
        Self {
            teacher,
            outbox,
            summary: TeacherSummary::default(),
        }
    }

    /// A query from the learner: the answer to send now (the one given before, or a judge's
    /// new one), or None (queued for people).
    pub fn receive(&mut self, q: Query) -> Result<Option<Answer>> {
        // NOTE: asked again: the learner has not stored it (or its acknowledgement crossed
        // this query); the same answer, never a new judgement.
        if let Some(a) = self.outbox.again(&q) {
            self.summary.resent += 1;
            return Ok(Some(a));
        }
        let answer = self.teacher.receive(q, &mut self.outbox)?;
        if let Some(a) = &answer {
            self.summary.given(a);
        }
        Ok(answer)
    }

    /// Answers to send now: those given since (people's), then those unacknowledged and
    /// not sent within `resend`.
    pub fn due(&mut self, resend: Duration) -> Result<Vec<Answer>> {
        let mut out = self.teacher.due(&mut self.outbox)?;
        for a in &out {
            self.summary.given(a);
        }
        let again = self.outbox.due(resend);
        self.summary.resent += again.len() as u64;
        out.extend(again);
        Ok(out)
    }

    /// The learner stored these answers.
    pub fn acknowledged(&mut self, ack: &AnswerAck) -> Result<u64> {
        let n = self.outbox.acknowledged(ack)?;
        self.summary.acknowledged += n;
        Ok(n)
    }

    /// Answers the learner has not acknowledged.
    pub fn unacknowledged(&self) -> usize {
        self.outbox.unacknowledged()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scripted::{ScriptedConfig, TeacherKind};

    /// A judge that counts its judgements.
    struct Counting(Scripted, u64);

    impl Judge for Counting {
        fn kind(&self) -> String {
            self.0.kind()
        }

        fn judge(&mut self, q: &Query) -> Preference {
            self.1 += 1;
            self.0.judge(q)
        }
    }

    /// A query whose first side's truth is `id` and second's 1.5 (the desk's test query).
    fn query(id: u64) -> Query {
        crate::human::tests::query(id, id as f32, 1.5)
    }

    fn served(path: &std::path::Path) -> Served<AtOnce<Counting>> {
        let oracle = Scripted::new(ScriptedConfig::of(TeacherKind::Oracle, 0)).unwrap();
        Served::new(
            AtOnce::new(Counting(oracle, 0), "oracle-0"),
            Outbox::open(&crate::file::TeacherFile::open(path).unwrap(), "oracle-0").unwrap(),
        )
    }

    #[test]
    fn a_judge_restarted_sends_its_answers_again_and_judges_nothing_twice() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("t.sqlite");
        let mut s = served(&path);
        let one = s.receive(query(1)).unwrap().unwrap();
        let two = s.receive(query(2)).unwrap().unwrap();
        assert_eq!(
            (one.preference, two.preference),
            (Preference::Second, Preference::First)
        );
        assert_eq!(s.receive(query(1)).unwrap(), Some(one.clone()));
        assert_eq!(s.teacher.judge.1, 2, "asked again: not judged again");
        s.acknowledged(&AnswerAck {
            teacher_id: "oracle-0".into(),
            queries: vec![2],
            repeats: vec![],
        })
        .unwrap();
        drop(s);
        // Restarted: 1 (unacknowledged) goes at once; both are answered as before.
        let mut s = served(&path);
        assert_eq!(s.due(Duration::from_secs(60)).unwrap(), vec![one.clone()]);
        assert_eq!(s.receive(query(1)).unwrap(), Some(one));
        assert_eq!(s.receive(query(2)).unwrap(), Some(two));
        assert!(s.receive(query(3)).unwrap().is_some());
        assert_eq!(s.teacher.judge.1, 1, "only the new query judged");
        assert_eq!((s.summary.judged, s.summary.resent), (1, 3));
    }
}
