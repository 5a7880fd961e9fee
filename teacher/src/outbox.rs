//! The teacher's outbox: every answer a teacher gives, scripted or human, kept on disk
//! before it is sent, and sent again until the learner acknowledges it.
//!
//! A label is a person's time, and a scripted teacher's answer is a draw of its random
//! stream: neither is given twice. So an answer is committed to the outbox's SQLite file
//! (WAL, synced at every commit) before anything sends it; one unacknowledged is sent
//! again every `resend`; a query asked again gets the answer given before; and a teacher
//! restarted on the same file finds its answers as it left them and sends the
//! unacknowledged ones at once. An acknowledged answer stays (marked so): a query asked
//! again after it was stored, by a message that crossed the acknowledgement, still gets the
//! same answer, never a new judgement.
//!
//! "The same query" is the same id asked at the same time (`asked_at_ms`, which the learner
//! keeps when it asks again, and which a learner started over does not repeat): a learner
//! started over on the same run numbers its queries from 1 again, and those are judged
//! anew, never answered with an old run's answers.
//!
//! ```text
//! sqlite3 teacher.sqlite "SELECT query, labeller, repeat, kept_at_ms, acked FROM outbox"
//! ```
//!
//! One file can hold the outboxes of several teachers (rows are keyed by the teacher's id);
//! a teacher reads and sends only its own. The human desk keeps its queue in other tables
//! of the same file, on the same connection ([`crate::file`]): it hands an answer over in
//! one transaction with [`Outbox::keep_with`].

use std::collections::BTreeMap;
use std::time::{Duration, Instant};

use anyhow::{Context, Result};
use pbrl_common::wire::{now_ms, Answer, AnswerAck, Query};
use rusqlite::{params, Transaction};

use crate::file::{code, TeacherFile};

const CREATE: &str = "
CREATE TABLE IF NOT EXISTS outbox (
    teacher TEXT NOT NULL,
    query INTEGER NOT NULL,
    labeller TEXT NOT NULL,
    repeat INTEGER NOT NULL,
    message BLOB NOT NULL,
    asked_at_ms INTEGER NOT NULL,
    kept_at_ms INTEGER NOT NULL,
    acked INTEGER NOT NULL DEFAULT 0,
    PRIMARY KEY (teacher, query, labeller, repeat)
);
";

/// An answer's place in the outbox: the query, who answered (empty for a scripted teacher)
/// and whether it answers a repeat.
pub type Key = (u64, String, bool);

/// The key of `a`.
pub fn key(a: &Answer) -> Key {
    (a.query, a.labeller.clone(), a.repeat)
}

/// An answer in the outbox.
#[derive(Clone, Debug)]
struct Kept {
    answer: Answer,
    /// When the learner asked the query answered.
    asked_at_ms: u64,
    /// Last sent by this process (None: not yet, such as one kept before a restart).
    sent: Option<Instant>,
    acked: bool,
}

/// The answers of one teacher, on disk until acknowledged (and after).
pub struct Outbox {
    file: TeacherFile,
    teacher: String,
    kept: BTreeMap<Key, Kept>,
}

impl Outbox {
    /// Open teacher `teacher`'s outbox in the teacher's `file` (creating its table) and
    /// read back what it holds.
    pub fn open(file: &TeacherFile, teacher: &str) -> Result<Self> {
        let path = file.path().to_path_buf();
        file.lock()
            .execute_batch(CREATE)
            .with_context(|| format!("setting up the teacher's outbox {}", path.display()))?;
        let mut outbox = Self {
            file: file.clone(),
            teacher: teacher.to_string(),
            kept: BTreeMap::new(),
        };
        outbox
            .load()
            .with_context(|| format!("reading the teacher's outbox {}", path.display()))?;
        Ok(outbox)
    }

    fn load(&mut self) -> Result<()> {
        let rows = {
            let db = self.file.lock();
            let mut select = db.prepare(
                "SELECT query, message, asked_at_ms, acked FROM outbox WHERE teacher = ?1",
            )?;
            let rows = select
                .query_map([&self.teacher], |r| {
                    Ok((r.get(0)?, r.get(1)?, r.get(2)?, r.get(3)?))
                })?
                .collect::<rusqlite::Result<Vec<(i64, Vec<u8>, i64, bool)>>>()?;
            rows
        };
        for (query, bytes, asked_at_ms, acked) in rows {
            let answer = crate::file::stored_answer(&bytes)
                .with_context(|| format!("the answer to query {query} does not decode"))?;
            let kept = Kept {
                answer,
                asked_at_ms: asked_at_ms as u64,
                sent: None,
                acked,
            };
            self.kept.insert(key(&kept.answer), kept);
        }
        let open = self.unacknowledged();
        if open > 0 {
            tracing::info!(
                teacher = %self.teacher,
                unacknowledged = open,
                outbox = %self.file.path().display(),
                "the teacher's outbox is back: sending its unacknowledged answers again"
            );
        }
        Ok(())
    }

    /// Keep `a`, the answer to a query asked at `asked_at_ms`, committed to disk before
    /// this returns; it counts as sent now (the caller sends it next). False when the
    /// outbox holds it already (then it is not changed); an answer to an older query of the
    /// same id (a learner started over) is replaced.
    pub fn keep(&mut self, a: &Answer, asked_at_ms: u64) -> Result<bool> {
        if self.holds_asked(a, asked_at_ms) {
            return Ok(false);
        }
        self.keep_with(a, asked_at_ms, |_| Ok(()))
    }

    /// Whether the outbox holds `a` as the answer to the query asked at `asked_at_ms`.
    fn holds_asked(&self, a: &Answer, asked_at_ms: u64) -> bool {
        self.kept
            .get(&key(a))
            .is_some_and(|k| k.asked_at_ms == asked_at_ms)
    }

    /// [`Outbox::keep`], with `also` done in the same transaction (the desk takes the
    /// answer off its own tables there); `also` is done, alone, when the outbox holds the
    /// answer already.
    pub fn keep_with(
        &mut self,
        a: &Answer,
        asked_at_ms: u64,
        also: impl FnOnce(&Transaction<'_>) -> Result<()>,
    ) -> Result<bool> {
        let k = key(a);
        let held = self.holds_asked(a, asked_at_ms);
        let context = || {
            format!(
                "keeping the answer to query {} in the outbox {}",
                a.query,
                self.file.path().display()
            )
        };
        let bytes = bincode::serde::encode_to_vec(a, code())?;
        {
            let db = self.file.lock();
            let tx = db.unchecked_transaction().with_context(context)?;
            if !held {
                tx.execute(
                    "INSERT OR REPLACE INTO outbox
                     (teacher, query, labeller, repeat, message, asked_at_ms, kept_at_ms)
                     VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7)",
                    params![
                        self.teacher,
                        a.query as i64,
                        a.labeller,
                        a.repeat,
                        bytes,
                        asked_at_ms as i64,
                        now_ms() as i64
                    ],
                )
                .with_context(context)?;
            }
            also(&tx)?;
            tx.commit().with_context(context)?;
        }
        if held {
            return Ok(false);
        }
        let kept = Kept {
            answer: a.clone(),
            asked_at_ms,
            sent: Some(Instant::now()),
            acked: false,
        };
        self.kept.insert(k, kept);
        Ok(true)
    }

    /// The key of the answer to `query` that is not a repeat's.
    fn first_key(&self, query: u64) -> Option<Key> {
        // NOTE: a person's answer is keyed by who gave it; a query has one answer that is
        // not a repeat, whoever gave it.
        self.kept
            .range((query, String::new(), false)..)
            .take_while(|((q, _, _), _)| *q == query)
            .find(|((_, _, repeat), _)| !repeat)
            .map(|(k, _)| k.clone())
    }

    /// The answer given to `q` (not a repeat's), to send again: the learner asks once
    /// more because it has not heard it. None for a query not answered here, or only one
    /// of the same id asked at another time (by a learner since started over).
    pub fn again(&mut self, q: &Query) -> Option<Answer> {
        let k = self.first_key(q.id)?;
        let kept = self.kept.get_mut(&k)?;
        if kept.asked_at_ms != q.asked_at_ms {
            return None;
        }
        kept.sent = Some(Instant::now());
        Some(kept.answer.clone())
    }

    /// Unacknowledged answers not sent within `resend` (or not yet by this process): to
    /// send now.
    pub fn due(&mut self, resend: Duration) -> Vec<Answer> {
        let now = Instant::now();
        self.kept
            .values_mut()
            .filter(|k| !k.acked && k.sent.is_none_or(|at| now >= at + resend))
            .map(|k| {
                k.sent = Some(now);
                k.answer.clone()
            })
            .collect()
    }

    /// The learner stored these answers (written to disk): they are not sent again.
    /// Returns how many were waiting for it.
    pub fn acknowledged(&mut self, ack: &AnswerAck) -> Result<u64> {
        // NOTE: the learner names the query of an answer that is not a repeat, not who
        // gave it; a repeat's by the query and the person.
        let firsts = ack.queries.iter().filter_map(|q| self.first_key(*q));
        let repeats = (ack.repeats.iter()).map(|(q, l)| (*q, l.clone(), true));
        let keys: Vec<Key> = firsts
            .chain(repeats)
            .filter(|k| self.kept.get(k).is_some_and(|kept| !kept.acked))
            .collect();
        if keys.is_empty() {
            return Ok(0);
        }
        let db = self.file.lock();
        let tx = db.unchecked_transaction()?;
        for (query, labeller, repeat) in &keys {
            tx.execute(
                "UPDATE outbox SET acked = 1
                 WHERE teacher = ?1 AND query = ?2 AND labeller = ?3 AND repeat = ?4",
                params![self.teacher, *query as i64, labeller, repeat],
            )?;
        }
        tx.commit().with_context(|| {
            format!(
                "marking {} answers acknowledged in the outbox {}",
                keys.len(),
                self.file.path().display()
            )
        })?;
        drop(db);
        for k in &keys {
            if let Some(kept) = self.kept.get_mut(k) {
                kept.acked = true;
            }
        }
        Ok(keys.len() as u64)
    }

    /// Whether the outbox holds the answer of `k`.
    pub fn holds(&self, k: &Key) -> bool {
        self.kept.contains_key(k)
    }

    /// Answers the learner has not acknowledged.
    pub fn unacknowledged(&self) -> usize {
        self.kept.values().filter(|k| !k.acked).count()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use pbrl_common::wire::{Preference, Shown};

    #[test]
    fn an_outbox_in_a_folder_not_made_yet_is_opened() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("run-not-made-yet").join("teacher.sqlite");
        Outbox::open(&TeacherFile::open(&path).unwrap(), "t-0").unwrap();
        assert!(path.exists());
    }

    fn ack(queries: &[u64], repeats: &[(u64, &str)]) -> AnswerAck {
        AnswerAck {
            teacher_id: "t-0".into(),
            queries: queries.to_vec(),
            repeats: repeats.iter().map(|(q, l)| (*q, l.to_string())).collect(),
        }
    }

    /// Query `id` as asked at `asked_at_ms` (its pair does not matter here).
    fn asked(id: u64, asked_at_ms: u64) -> Query {
        let side = Shown {
            id,
            seed: id,
            policy_version: 1,
            act_dim: 1,
            actions: vec![0.0],
            truth: vec![0.0],
            replay: None,
            start: 0,
            len: 1,
        };
        Query {
            id,
            session: 1,
            asked_at_ms,
            expires_at_ms: 0,
            first: side.clone(),
            second: side,
            r_avg: None,
            withdraw_at_steps: 0,
            more: Vec::new(),
        }
    }

    fn person(query: u64, labeller: &str, repeat: bool) -> Answer {
        Answer {
            labeller: labeller.into(),
            repeat,
            ..Answer::scripted(query, Preference::Equal, "human", "t-0", 900)
        }
    }

    #[test]
    fn an_answer_is_kept_together_with_its_companion_change_or_not_at_all() {
        let dir = tempfile::tempdir().unwrap();
        let file = TeacherFile::open(&dir.path().join("t.sqlite")).unwrap();
        file.lock()
            .execute_batch("CREATE TABLE desk (query INTEGER)")
            .unwrap();
        let mut o = Outbox::open(&file, "t-0").unwrap();
        let a = person(1, "ada", false);
        // The companion (the desk taking the answer off) fails: nothing is kept.
        let err = o
            .keep_with(&a, 10, |tx| {
                tx.execute("INSERT INTO desk (query) VALUES (1)", [])?;
                anyhow::bail!("the desk failed")
            })
            .unwrap_err();
        assert!(err.to_string().contains("the desk failed"), "{err:#}");
        assert!(!o.holds(&key(&a)));
        let o = Outbox::open(&file, "t-0").unwrap();
        assert!(!o.holds(&key(&a)), "nothing of it reached the disk");
        let rows: i64 = file
            .lock()
            .query_row("SELECT count(*) FROM desk", [], |r| r.get(0))
            .unwrap();
        assert_eq!(rows, 0, "nor of its companion");
        // Both succeed: both are on disk.
        let mut o = o;
        assert!(o
            .keep_with(&a, 10, |tx| {
                tx.execute("INSERT INTO desk (query) VALUES (1)", [])?;
                Ok(())
            })
            .unwrap());
        let o = Outbox::open(&file, "t-0").unwrap();
        assert!(o.holds(&key(&a)));
        let rows: i64 = file
            .lock()
            .query_row("SELECT count(*) FROM desk", [], |r| r.get(0))
            .unwrap();
        assert_eq!(rows, 1);
    }

    #[test]
    fn answers_are_sent_until_acknowledged_and_survive_a_restart() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("t.sqlite");
        let first = Answer::scripted(1, Preference::First, "oracle", "t-0", 3);
        {
            let mut o = Outbox::open(&TeacherFile::open(&path).unwrap(), "t-0").unwrap();
            assert!(o.keep(&first, 10).unwrap());
            assert!(!o.keep(&first, 10).unwrap(), "kept once");
            let second = Answer::scripted(2, Preference::Second, "oracle", "t-0", 3);
            assert!(o.keep(&second, 20).unwrap());
            // Just kept counts as just sent: not due before the resend interval.
            assert!(o.due(Duration::from_secs(60)).is_empty());
            assert_eq!(o.due(Duration::ZERO).len(), 2);
            assert_eq!(o.again(&asked(1, 10)), Some(first.clone()));
            assert_eq!(o.again(&asked(3, 30)), None);
            assert_eq!(o.acknowledged(&ack(&[2, 9], &[])).unwrap(), 1);
            assert_eq!(o.acknowledged(&ack(&[2], &[])).unwrap(), 0, "once");
            // NOTE: dropped with query 1 unacknowledged: a teacher killed.
        }
        // Another teacher's outbox in the same file is apart.
        let mut other = Outbox::open(&TeacherFile::open(&path).unwrap(), "t-1").unwrap();
        assert_eq!(other.unacknowledged(), 0);
        assert_eq!(other.again(&asked(1, 10)), None);
        let mut o = Outbox::open(&TeacherFile::open(&path).unwrap(), "t-0").unwrap();
        assert_eq!(o.unacknowledged(), 1);
        // Sent at once after a restart, then every resend interval.
        assert_eq!(o.due(Duration::from_secs(60)), vec![first.clone()]);
        assert!(o.due(Duration::from_secs(60)).is_empty());
        // An acknowledged answer is given again to the same query, never judged anew.
        let second = o.again(&asked(2, 20)).unwrap();
        assert_eq!((second.query, second.preference), (2, Preference::Second));
        assert_eq!(o.acknowledged(&ack(&[1], &[])).unwrap(), 1);
        assert_eq!(o.unacknowledged(), 0);
        assert!(o.due(Duration::ZERO).is_empty());
    }

    #[test]
    fn a_learner_started_over_gets_new_answers_to_its_new_queries() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("t.sqlite");
        let old = Answer::scripted(1, Preference::First, "oracle", "t-0", 3);
        let mut o = Outbox::open(&TeacherFile::open(&path).unwrap(), "t-0").unwrap();
        o.keep(&old, 10).unwrap();
        o.acknowledged(&ack(&[1], &[])).unwrap();
        // Query 1 of a learner started over (asked later): not the old answer.
        let q = asked(1, 5_000);
        assert_eq!(o.again(&q), None);
        let new = Answer::scripted(1, Preference::Second, "oracle", "t-0", 3);
        assert!(o.keep(&new, q.asked_at_ms).unwrap());
        drop(o);
        let mut o = Outbox::open(&TeacherFile::open(&path).unwrap(), "t-0").unwrap();
        assert_eq!(o.again(&q), Some(new));
        assert_eq!(o.again(&asked(1, 10)), None);
    }

    #[test]
    fn a_persons_answer_and_repeats_are_acknowledged_apart() {
        let dir = tempfile::tempdir().unwrap();
        let mut o = Outbox::open(
            &TeacherFile::open(&dir.path().join("t.sqlite")).unwrap(),
            "t-0",
        )
        .unwrap();
        for a in [
            person(5, "ann", false),
            person(5, "bob", true),
            person(5, "ann", true),
        ] {
            assert!(o.keep(&a, 50).unwrap());
        }
        // The query's answer is ann's first, whoever asks.
        assert_eq!(o.again(&asked(5, 50)), Some(person(5, "ann", false)));
        assert_eq!(o.acknowledged(&ack(&[], &[(5, "bob")])).unwrap(), 1);
        assert!(o.holds(&(5, "ann".into(), true)));
        assert_eq!(o.unacknowledged(), 2);
        assert_eq!(o.acknowledged(&ack(&[5], &[])).unwrap(), 1);
        let left: Vec<Key> = o.due(Duration::ZERO).iter().map(key).collect();
        assert_eq!(left, vec![(5, "ann".to_string(), true)]);
    }

    #[test]
    fn an_answer_an_older_build_kept_is_read_as_a_pairs_and_sent() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("t.sqlite");
        let file = TeacherFile::open(&path).unwrap();
        drop(Outbox::open(&file, "t-0").unwrap());
        let a = person(7, "ada", false);
        let old = pbrl_common::wire::v9::Answer {
            query: a.query,
            preference: a.preference,
            teacher: a.teacher.clone(),
            teacher_id: a.teacher_id.clone(),
            took_ms: a.took_ms,
            labeller: a.labeller.clone(),
            replays: a.replays,
            shadow: a.shadow,
            repeat: a.repeat,
        };
        let bytes = bincode::serde::encode_to_vec(&old, code()).unwrap();
        file.lock()
            .execute(
                "INSERT INTO outbox (teacher, query, labeller, repeat, message, asked_at_ms, kept_at_ms)
                 VALUES ('t-0', 7, 'ada', 0, ?1, 5, 6)",
                [bytes],
            )
            .unwrap();
        let mut o = Outbox::open(&file, "t-0").unwrap();
        assert_eq!(o.unacknowledged(), 1);
        assert_eq!(o.due(Duration::from_secs(60)), vec![a]);
    }
}
