//! The desk's storage: its tables in the teacher's file, on the connection it shares with
//! the outbox. Every change a person makes is one transaction, committed (and synced)
//! before the desk changes what it holds in memory.

use anyhow::{Context, Result};
use pbrl_common::wire::{Answer, Query};
use rusqlite::{params, Connection, Transaction};

use crate::file::{code, TeacherFile};
use crate::outbox;

const CREATE: &str = "
CREATE TABLE IF NOT EXISTS queries (id INTEGER PRIMARY KEY, message BLOB NOT NULL);
CREATE TABLE IF NOT EXISTS answers (
    query INTEGER NOT NULL,
    labeller TEXT NOT NULL,
    repeat INTEGER NOT NULL,
    message BLOB NOT NULL,
    given_at_ms INTEGER NOT NULL,
    PRIMARY KEY (query, labeller, repeat)
);
CREATE TABLE IF NOT EXISTS leases (
    query INTEGER PRIMARY KEY,
    labeller TEXT NOT NULL,
    at_ms INTEGER NOT NULL
);
CREATE TABLE IF NOT EXISTS checks (
    query INTEGER NOT NULL,
    labeller TEXT NOT NULL,
    due_after INTEGER NOT NULL,
    PRIMARY KEY (query, labeller)
);
CREATE TABLE IF NOT EXISTS labellers (name TEXT PRIMARY KEY, answered INTEGER NOT NULL);
CREATE TABLE IF NOT EXISTS shown (
    query INTEGER NOT NULL,
    labeller TEXT NOT NULL,
    env_steps INTEGER NOT NULL,
    at_ms INTEGER NOT NULL,
    PRIMARY KEY (query, labeller)
);
";

/// What the desk's tables hold, read back on opening.
#[derive(Default)]
pub(super) struct Loaded {
    pub queries: Vec<Query>,
    /// Answers still on the desk, each with when it was given.
    pub answers: Vec<(Answer, u64)>,
    /// query, labeller, when it was leased.
    pub leases: Vec<(u64, String, u64)>,
    /// query, labeller, due after this many of their answers.
    pub checks: Vec<(u64, String, u64)>,
    /// Every person's answers ever given here.
    pub labellers: Vec<(String, u64)>,
}

/// The desk's tables.
pub(super) struct DeskStore {
    file: TeacherFile,
}

/// A query as the desk keeps it: this build's layout; the layout before rankings, read as
/// a pair; or the layout before the withdrawal step (which an older build wrote), read as
/// never withdrawn.
pub(super) fn stored_query(bytes: &[u8]) -> Result<Query> {
    if let Ok((q, n)) = bincode::serde::decode_from_slice::<Query, _>(bytes, code()) {
        if n == bytes.len() {
            return Ok(q);
        }
    }
    if let Ok((q, n)) =
        bincode::serde::decode_from_slice::<pbrl_common::wire::v9::Query, _>(bytes, code())
    {
        if n == bytes.len() {
            return Ok(q.upgrade());
        }
    }
    let (q, _): (pbrl_common::wire::v8::Query, usize) =
        bincode::serde::decode_from_slice(bytes, code())?;
    Ok(q.upgrade())
}

/// Every row of `sql`, each as a tuple of its columns.
fn all_rows<T>(db: &Connection, sql: &str) -> rusqlite::Result<Vec<T>>
where
    T: for<'a> TryFrom<&'a rusqlite::Row<'a>, Error = rusqlite::Error>,
{
    db.prepare(sql)?
        .query_map([], |r| T::try_from(r))?
        .collect()
}

impl DeskStore {
    /// Every row of `sql` (for tests that read the tables).
    #[cfg(test)]
    pub fn rows<T>(&self, sql: &str) -> rusqlite::Result<Vec<T>>
    where
        T: for<'a> TryFrom<&'a rusqlite::Row<'a>, Error = rusqlite::Error>,
    {
        all_rows(&self.file.lock(), sql)
    }

    /// The desk's tables in `file` (made if new) and what they hold.
    pub fn open(file: &TeacherFile) -> Result<(Self, Loaded)> {
        let path = file.path().display().to_string();
        let store = Self { file: file.clone() };
        store
            .file
            .lock()
            .execute_batch(CREATE)
            .with_context(|| format!("setting up the teacher's queue {path}"))?;
        let loaded = store
            .load()
            .with_context(|| format!("reading the teacher's queue {path}"))?;
        Ok((store, loaded))
    }

    fn load(&self) -> Result<Loaded> {
        let db = self.file.lock();
        let mut out = Loaded::default();
        let rows: Vec<(i64, Vec<u8>)> =
            all_rows(&db, "SELECT id, message FROM queries ORDER BY id")?;
        for (id, bytes) in rows {
            let q = stored_query(&bytes).with_context(|| format!("query {id} does not decode"))?;
            out.queries.push(q);
        }
        let rows: Vec<(Vec<u8>, i64)> = all_rows(&db, "SELECT message, given_at_ms FROM answers")?;
        for (bytes, at) in rows {
            let a = crate::file::stored_answer(&bytes).context("an answer does not decode")?;
            out.answers.push((a, at as u64));
        }
        let rows: Vec<(i64, String, i64)> =
            all_rows(&db, "SELECT query, labeller, at_ms FROM leases")?;
        out.leases = (rows.into_iter())
            .map(|(q, who, at)| (q as u64, who, at as u64))
            .collect();
        let rows: Vec<(i64, String, i64)> =
            all_rows(&db, "SELECT query, labeller, due_after FROM checks")?;
        out.checks = (rows.into_iter())
            .map(|(q, who, due)| (q as u64, who, due as u64))
            .collect();
        let rows: Vec<(String, i64)> = all_rows(&db, "SELECT name, answered FROM labellers")?;
        out.labellers = (rows.into_iter())
            .map(|(name, n)| (name, n as u64))
            .collect();
        Ok(out)
    }

    /// Queue a query from the learner.
    pub fn queue(&self, q: &Query) -> Result<()> {
        let bytes = bincode::serde::encode_to_vec(q, code())?;
        self.file
            .lock()
            .execute(
                "INSERT OR IGNORE INTO queries (id, message) VALUES (?1, ?2)",
                params![q.id as i64, bytes],
            )
            .with_context(|| format!("queueing query {}", q.id))?;
        Ok(())
    }

    /// A query no longer needed, or expired: it leaves the queue with its lease.
    pub fn forget(&self, query: u64) -> Result<()> {
        let db = self.file.lock();
        let tx = db.unchecked_transaction()?;
        tx.execute("DELETE FROM queries WHERE id = ?1", [query as i64])?;
        tx.execute("DELETE FROM leases WHERE query = ?1", [query as i64])?;
        tx.commit()
            .with_context(|| format!("taking query {query} off the queue"))
    }

    /// `query` is leased to `labeller` from `now`, and its first showing to them noted with
    /// where the learner stood (provenance: how old the pair was when the person saw it).
    pub fn lease(&self, query: u64, labeller: &str, now: u64, env_steps: u64) -> Result<()> {
        let db = self.file.lock();
        let tx = db.unchecked_transaction()?;
        tx.execute(
            "INSERT OR REPLACE INTO leases (query, labeller, at_ms) VALUES (?1, ?2, ?3)",
            params![query as i64, labeller, now as i64],
        )?;
        tx.execute(
            "INSERT OR IGNORE INTO shown (query, labeller, env_steps, at_ms)
             VALUES (?1, ?2, ?3, ?4)",
            params![query as i64, labeller, env_steps as i64, now as i64],
        )?;
        tx.commit()?;
        Ok(())
    }

    /// A person's answer, in one transaction: the answer, its lease or its check gone,
    /// their count one up.
    pub fn answer(&self, a: &Answer, now: u64) -> Result<()> {
        let (query, labeller) = (a.query as i64, a.labeller.as_str());
        let db = self.file.lock();
        let tx = db.unchecked_transaction()?;
        tx.execute(
            "INSERT INTO answers (query, labeller, repeat, message, given_at_ms)
             VALUES (?1, ?2, ?3, ?4, ?5)",
            params![
                query,
                labeller,
                a.repeat,
                bincode::serde::encode_to_vec(a, code())?,
                now as i64
            ],
        )?;
        if a.repeat {
            tx.execute(
                "DELETE FROM checks WHERE query = ?1 AND labeller = ?2",
                params![query, labeller],
            )?;
        } else {
            tx.execute("DELETE FROM leases WHERE query = ?1", [query])?;
        }
        tx.execute(
            "INSERT INTO labellers (name, answered) VALUES (?1, 1)
             ON CONFLICT (name) DO UPDATE SET answered = answered + 1",
            [labeller],
        )?;
        tx.commit()?;
        Ok(())
    }

    /// Ask `labeller` `query` again once they have answered `due_after`.
    pub fn plan_check(&self, query: u64, labeller: &str, due_after: u64) -> Result<()> {
        self.file.lock().execute(
            "INSERT OR IGNORE INTO checks (query, labeller, due_after) VALUES (?1, ?2, ?3)",
            params![query as i64, labeller, due_after as i64],
        )?;
        Ok(())
    }

    /// Withdraw `labeller`'s answer to `query` in one transaction: a repeat's check comes
    /// back (due at once); a first answer's repeats go with it; their count one down.
    pub fn undo(&self, query: u64, labeller: &str, repeat: bool) -> Result<()> {
        let db = self.file.lock();
        let tx = db.unchecked_transaction()?;
        tx.execute(
            "DELETE FROM answers WHERE query = ?1 AND labeller = ?2 AND repeat = ?3",
            params![query as i64, labeller, repeat],
        )?;
        if repeat {
            tx.execute(
                "INSERT OR IGNORE INTO checks (query, labeller, due_after) VALUES (?1, ?2, 0)",
                params![query as i64, labeller],
            )?;
        } else {
            // NOTE: repeats planned on the withdrawn answer go with it.
            tx.execute("DELETE FROM checks WHERE query = ?1", [query as i64])?;
        }
        tx.execute(
            "UPDATE labellers SET answered = max(answered - 1, 0) WHERE name = ?1",
            [labeller],
        )?;
        tx.commit()?;
        Ok(())
    }
}

/// Take the answer of `k` off the desk, inside the outbox's transaction that keeps it
/// ([`crate::outbox::Outbox::keep_with`]): a person's answer is on exactly one of the two.
pub(super) fn take_off(tx: &Transaction<'_>, k: &outbox::Key) -> Result<()> {
    tx.execute(
        "DELETE FROM answers WHERE query = ?1 AND labeller = ?2 AND repeat = ?3",
        params![k.0 as i64, k.1, k.2],
    )
    .with_context(|| format!("taking the answer to query {} off the desk", k.0))?;
    Ok(())
}
