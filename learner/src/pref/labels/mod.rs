//! The label store: the preference dataset D, one SQLite database in the run folder.
//!
//! A label is a person's time, so nothing that carries one may be lost to a crash or a
//! restart. Every query is written (with both trajectories and the whole message as sent)
//! before it is sent, and every answer in its own transaction that is committed, and
//! synced, before [`LabelStore::answer`] returns: only then may the learner acknowledge it
//! and the teacher forget it. The database is in WAL mode with `synchronous=FULL`, so a
//! commit is on disk when it returns and readers never block the learner.
//!
//! D alone can retrain a reward model: each label names its two trajectories, and each
//! trajectory holds the steps the reward model trains on, the raw (unnormalised)
//! observation at which each action was taken and the action as the policy gave it.
//!
//! ```text
//! meta          key, value: `run` (the run's name) and `schema` (this layout, 5)
//! trajectories  id, actor, incarnation, seq (unique: the actor's numbering), seed,
//!               policy_version, steps, obs_dim, act_dim,
//!               obs (steps x obs_dim f32, little-endian), actions (steps x act_dim)
//! queries       id, session, sampler, env_steps, first, second (trajectory ids),
//!               first_start, first_len, second_start, second_len (the segment of each
//!               trajectory the query compares: steps start .. start + len; NULL in a
//!               store of schema 2 or older, where queries compared whole trajectories),
//!               asked_at_ms, message (the encoded query while it is open, else NULL),
//!               answer (NULL while open; first, second, equal, skip or expired),
//!               teacher, teacher_id, took_ms, answered_at_ms,
//!               expired_at_ms (kept when a late answer follows), withdrawn_at_steps
//!               (the learner's env steps when it withdrew the query as stale; its answer
//!               is then expired until a late one comes), answer_no (1, 2, ...
//!               in the order answers were stored); for a person's answer also
//!               labeller, replays_first, replays_second (how often each attempt was
//!               played) and shadow (the oracle's answer on the truth, never trained on)
//! repeats       query, teacher_id, labeller, answer, took_ms, replays_first,
//!               replays_second, shadow, answered_at_ms: queries asked again of a person
//!               (the same one or another) to measure consistency; not part of D
//! labels        a view: the answered queries (first, second, equal) with both
//!               trajectories' policy versions, seeds and lengths and both segments'
//!               bounds (whole trajectories for older queries), in answer order
//! ```
//!
//! Ids come from `AUTOINCREMENT`, so they are never reused: a query id is unique over the
//! run, across restarts. Times are Unix milliseconds. SQLite's integers are signed 64-bit:
//! unsigned values at or above 2^63 (random incarnations) are stored in two's complement
//! and read back exactly here; elsewhere take them modulo 2^64 (episode seeds of training
//! episodes are below 2^63 and read as they are).
//!
//! Anyone can read it while the learner runs, for example the answers by kind:
//!
//! ```text
//! sqlite3 RUN/labels.sqlite "SELECT coalesce(answer, 'open'), count(*) FROM queries GROUP BY 1"
//! ```
//!
//! or, in Python, the labels and one trajectory's first observation:
//!
//! ```text
//! import sqlite3, struct
//! db = sqlite3.connect("RUN/labels.sqlite")
//! labels = db.execute("SELECT query, first, second, answer FROM labels").fetchall()
//! steps, obs_dim, obs = db.execute("SELECT steps, obs_dim, obs FROM trajectories WHERE id = ?", (labels[0][1],)).fetchone()
//! print(labels[0], struct.unpack(f"<{steps * obs_dim}f", obs)[:obs_dim])
//! ```

mod read;
mod schema;
#[cfg(test)]
mod tests;

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use pbrl_common::wire::{self, Answer, Preference};
use rusqlite::{params, Connection, OptionalExtension, Transaction, TransactionBehavior};

pub use schema::SCHEMA;

/// One trajectory of a query as the store keeps it: what the reward model trains on and
/// what identifies the episode.
#[derive(Clone, Copy, Debug)]
pub struct StoredTrajectory<'a> {
    /// The actor's numbering (`TrajectoryMsg`'s `actor`, `incarnation` and `seq`): the
    /// same trajectory in two queries is stored once.
    pub actor: u32,
    pub incarnation: u64,
    pub seq: u64,
    /// Seed of the episode's reset.
    pub seed: u64,
    /// Version of the policy that acted.
    pub policy_version: u64,
    pub obs_dim: usize,
    pub act_dim: usize,
    /// The raw observation at which each action was taken: `steps` rows of `obs_dim`
    /// (a trajectory's first `steps` of its `steps + 1` observations).
    pub obs: &'a [f32],
    /// `steps` rows of `act_dim`, as the policy gave them.
    pub actions: &'a [f32],
    /// `steps` rows of comfort features (empty: none kept).
    pub features: &'a [f32],
    /// The segment the query compares: steps `start .. start + len` (`(0, steps)`: the
    /// whole trajectory). Kept with the query; the trajectory is stored whole.
    pub segment: (usize, usize),
}

impl StoredTrajectory<'_> {
    /// Env steps: rows of `actions`.
    pub fn steps(&self) -> usize {
        self.actions.len() / self.act_dim.max(1)
    }

    fn check(&self, side: &str) -> Result<()> {
        let steps = self.steps();
        if self.obs_dim == 0 || self.act_dim == 0 {
            bail!(
                "{side} trajectory {}: obs_dim {} and act_dim {} must be positive",
                self.key(),
                self.obs_dim,
                self.act_dim
            );
        }
        if steps == 0 || self.actions.len() != steps * self.act_dim {
            bail!(
                "{side} trajectory {}: {} actions are not a positive number of rows of {}",
                self.key(),
                self.actions.len(),
                self.act_dim
            );
        }
        if self.obs.len() != steps * self.obs_dim {
            bail!(
                "{side} trajectory {}: {} observation numbers, expected {steps} rows of {}",
                self.key(),
                self.obs.len(),
                self.obs_dim
            );
        }
        if !self.features.len().is_multiple_of(steps) {
            bail!(
                "{side} trajectory {}: {} comfort feature numbers are not {steps} rows",
                self.key(),
                self.features.len()
            );
        }
        let (start, len) = self.segment;
        if len == 0 || start + len > steps {
            bail!(
                "{side} trajectory {}: segment start {start}, length {len} is not within its {steps} steps",
                self.key()
            );
        }
        Ok(())
    }

    fn key(&self) -> String {
        format!(
            "(actor {}, incarnation {}, seq {})",
            self.actor, self.incarnation, self.seq
        )
    }
}

/// The store's ids of a query and its two trajectories.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Asked {
    pub query: u64,
    pub first: u64,
    pub second: u64,
    /// A ranking's attempts after the first two.
    pub more: Vec<u64>,
}

/// What storing an answer did. Each outcome means the answer may be acknowledged: it is
/// either stored now or an earlier answer to the query stands.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Stored {
    /// The query's answer, stored.
    New,
    /// The query had an answer already; that one stands (a teacher sent it again).
    Repeated,
    /// No query has this id in this store.
    Unknown,
    /// The query had expired (the learner gave up waiting); the answer is stored all the
    /// same, since it is a person's judgement. It was not among the queries in flight.
    Late,
    /// The answer does not fit the query (places for a pair, a pair's answer to a ranking,
    /// or places for another number of attempts): not stored, and not acknowledged.
    Misfit,
}

/// The queries by state.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Counts {
    /// Queries ever asked.
    pub asked: u64,
    /// Answered by a teacher: first + second + equal + skipped.
    pub answered: u64,
    pub first: u64,
    pub second: u64,
    pub equal: u64,
    pub skipped: u64,
    /// Given up on and never answered (the withdrawn among them).
    pub expired: u64,
    /// Withdrawn as stale and never answered: a person never spent time on them, so they
    /// do not count against the budget.
    pub withdrawn: u64,
    /// Asked and waiting for an answer.
    pub open: u64,
    /// Answered after they had expired (counted in `answered` too).
    pub late: u64,
}

impl Counts {
    /// Queries that count against the budget: all asked but the withdrawn ones.
    pub fn spent(&self) -> u64 {
        self.asked - self.withdrawn
    }

    /// Labels in D: first + second + equal.
    pub fn labels(&self) -> u64 {
        self.first + self.second + self.equal
    }
}

/// One label of D.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct LabelRow {
    /// Its place in the order answers were stored (1, 2, ...): the cursor for
    /// [`LabelStore::labels_since`].
    pub answer_no: u64,
    pub query: u64,
    pub session: u64,
    /// The trajectories' ids (see [`LabelStore::segment`]).
    pub first: u64,
    pub second: u64,
    /// The segments compared, `(start, len)` in each trajectory (whole trajectories for
    /// the queries of an older store).
    pub first_segment: (usize, usize),
    pub second_segment: (usize, usize),
    /// First, Second or Equal (never Skip): for a ranking, the order of its first two.
    pub preference: Preference,
    pub answered_at_ms: u64,
    /// A ranking's attempts after the first two: trajectory ids and segments.
    pub more: Vec<(u64, (usize, usize))>,
    /// A ranking's places, one per attempt (empty: a pair, which `preference` says).
    pub ranks: Vec<u8>,
}

impl LabelRow {
    /// Every attempt compared: trajectory id and segment, in the query's order.
    pub fn attempts(&self) -> Vec<(u64, (usize, usize))> {
        let mut v = vec![
            (self.first, self.first_segment),
            (self.second, self.second_segment),
        ];
        v.extend(self.more.iter().copied());
        v
    }
}

/// The steps of one stored trajectory.
#[derive(Clone, Debug, PartialEq)]
pub struct StoredSteps {
    pub steps: usize,
    pub obs_dim: usize,
    pub act_dim: usize,
    /// `steps` rows of `obs_dim`, raw.
    pub obs: Vec<f32>,
    /// `steps` rows of `act_dim`.
    pub actions: Vec<f32>,
    /// `steps` rows of comfort features (empty: none kept).
    pub features: Vec<f32>,
}

/// The preference dataset D of one run.
pub struct LabelStore {
    conn: Connection,
    path: PathBuf,
    /// The trajectories table has its features column (false only for a schema-3 store
    /// opened read-only).
    features: bool,
    /// The queries table has its withdrawn_at_steps column (false only for a store of
    /// schema 3 or 4 opened read-only).
    withdrawals: bool,
    /// The queries table has its ranks column and the rankings' attempts their table
    /// (false only for a store of schema 3 to 5 opened read-only: pairs only).
    rankings: bool,
}

// NOTE: SQLite's integers are i64; u64 values are stored by their bits and read back the
// same way, so every u64 round-trips exactly (see the module doc).

fn int(x: u64) -> i64 {
    x as i64
}

fn uint(x: i64) -> u64 {
    x as u64
}

type Blob = Vec<u8>;

fn to_blob(xs: &[f32]) -> Blob {
    xs.iter().flat_map(|x| x.to_le_bytes()).collect()
}

fn from_blob(bytes: &[u8]) -> Vec<f32> {
    bytes
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        .collect()
}

impl LabelStore {
    /// Open the label store at `path` for run `run`, creating it if it does not exist. A
    /// store of another run or another schema version is refused.
    pub fn open(path: &Path, run: &str) -> Result<Self> {
        let existed = path.exists();
        let conn = Connection::open(path)
            .with_context(|| format!("opening label store {}", path.display()))?;
        let mut store = Self {
            conn,
            path: path.to_path_buf(),
            features: true,
            withdrawals: true,
            rankings: true,
        };
        store
            .configure()
            .with_context(|| format!("configuring label store {}", path.display()))?;
        store.check_or_create(run)?;
        if !existed && path.as_os_str() != ":memory:" {
            // NOTE: the new file's name lives in the directory: synced, or a crash may lose
            // the whole store (SQLite syncs the WAL's own entry, not the database's).
            let dir = match path.parent() {
                Some(d) if !d.as_os_str().is_empty() => d,
                _ => Path::new("."),
            };
            std::fs::File::open(dir)
                .and_then(|f| f.sync_all())
                .with_context(|| format!("syncing {}", dir.display()))?;
        }
        Ok(store)
    }

    /// Open the label store at `path` to read it only (safe while its run goes): no
    /// upgrade, nothing written; a file that is not a label store of this schema (or of
    /// schema 5, read as pairs only; 4, also as having withdrawn nothing; or 3, also as
    /// keeping no features) is refused.
    pub fn open_read_only(path: &Path) -> Result<Self> {
        let conn = Connection::open_with_flags(path, rusqlite::OpenFlags::SQLITE_OPEN_READ_ONLY)
            .with_context(|| format!("opening label store {}", path.display()))?;
        let schema: Option<String> = conn
            .query_row("SELECT value FROM meta WHERE key = 'schema'", [], |r| {
                r.get(0)
            })
            .optional()
            .with_context(|| format!("{} is not a label store", path.display()))?;
        let version = schema.as_deref().and_then(|s| s.parse::<u32>().ok());
        if !version.is_some_and(|v| (3..=SCHEMA).contains(&v)) {
            bail!(
                "label store {} has schema {}, this build reads {SCHEMA} (open it with its run once to upgrade it)",
                path.display(),
                schema.unwrap_or_else(|| "none".into())
            );
        }
        let version = version.unwrap_or(SCHEMA);
        Ok(Self {
            conn,
            path: path.to_path_buf(),
            features: version >= 4,
            withdrawals: version >= 5,
            rankings: version >= 6,
        })
    }

    /// The file this store lives in.
    pub fn path(&self) -> &Path {
        &self.path
    }

    fn configure(&self) -> Result<()> {
        let mode: String = self
            .conn
            .pragma_update_and_check(None, "journal_mode", "WAL", |r| r.get(0))?;
        // NOTE: a store in memory (a learner with no run folder: tests) has no WAL.
        let in_memory = self.path.as_os_str() == ":memory:";
        if !mode.eq_ignore_ascii_case("wal") && !in_memory {
            bail!("journal_mode is {mode:?} after asking for WAL");
        }
        // NOTE: FULL syncs the WAL at every commit: an answer is on disk before it is
        // acknowledged (NORMAL, the usual WAL setting, may lose the last commits).
        self.conn.pragma_update(None, "synchronous", "FULL")?;
        self.conn.pragma_update(None, "foreign_keys", "ON")?;
        Ok(())
    }

    /// A write transaction, taking the write lock at once.
    fn write(&mut self) -> Result<Transaction<'_>> {
        self.conn
            .transaction_with_behavior(TransactionBehavior::Immediate)
            .with_context(|| format!("starting a transaction on {}", self.path.display()))
    }

    /// Record a pair's query before it is sent ([`LabelStore::ask_attempts`] of two):
    /// `message(query, first, second)` builds the encoded query from the new ids.
    #[allow(clippy::too_many_arguments)]
    pub fn ask(
        &mut self,
        session: u64,
        sampler: &str,
        env_steps: u64,
        asked_at_ms: u64,
        first: &StoredTrajectory<'_>,
        second: &StoredTrajectory<'_>,
        message: impl FnOnce(u64, u64, u64) -> Vec<u8>,
    ) -> Result<Asked> {
        self.ask_attempts(
            session,
            sampler,
            env_steps,
            asked_at_ms,
            &[first, second],
            |query, ids| message(query, ids[0], ids[1]),
        )
    }

    /// Record a query of two to four attempts before it is sent, in one transaction: every
    /// trajectory (stored once per actor, incarnation and seq), then the query (the
    /// attempts after the first two in `query_attempts`). `message(query, ids)` builds the
    /// encoded query from the new ids; it is kept until the query is answered or expires,
    /// so that it can be asked again after a restart.
    pub fn ask_attempts(
        &mut self,
        session: u64,
        sampler: &str,
        env_steps: u64,
        asked_at_ms: u64,
        attempts: &[&StoredTrajectory<'_>],
        message: impl FnOnce(u64, &[u64]) -> Vec<u8>,
    ) -> Result<Asked> {
        if !(2..=wire::MAX_ATTEMPTS).contains(&attempts.len()) {
            bail!("a query shows 2 to 4 attempts, not {}", attempts.len());
        }
        const NAMES: [&str; 4] = ["first", "second", "third", "fourth"];
        for (t, name) in attempts.iter().zip(NAMES) {
            t.check(name)?;
        }
        for (k, a) in attempts.iter().enumerate() {
            if attempts[..k]
                .iter()
                .any(|b| (a.actor, a.incarnation, a.seq) == (b.actor, b.incarnation, b.seq))
            {
                bail!("a query compares trajectory {} with itself", a.key());
            }
        }
        let path = self.path.clone();
        let tx = self.write()?;
        let context = || format!("storing a query of session {session} in {}", path.display());
        let ids = attempts
            .iter()
            .map(|t| put_trajectory(&tx, t))
            .collect::<Result<Vec<u64>>>()
            .with_context(context)?;
        let (first, second) = (attempts[0], attempts[1]);
        // NOTE: the message needs the query's id, which the insert draws: the row holds an
        // empty message until the update below, in the same transaction.
        tx.execute(
            "INSERT INTO queries (session, sampler, env_steps, first, second, asked_at_ms, message,
                 first_start, first_len, second_start, second_len)
             VALUES (?1, ?2, ?3, ?4, ?5, ?6, zeroblob(0), ?7, ?8, ?9, ?10)",
            params![
                int(session),
                sampler,
                int(env_steps),
                int(ids[0]),
                int(ids[1]),
                int(asked_at_ms),
                first.segment.0 as i64,
                first.segment.1 as i64,
                second.segment.0 as i64,
                second.segment.1 as i64,
            ],
        )
        .with_context(context)?;
        let query = uint(tx.last_insert_rowid());
        for (k, (t, id)) in attempts.iter().zip(&ids).enumerate().skip(2) {
            tx.execute(
                "INSERT INTO query_attempts (query, k, trajectory, start, len)
                 VALUES (?1, ?2, ?3, ?4, ?5)",
                params![
                    int(query),
                    k as i64,
                    int(*id),
                    t.segment.0 as i64,
                    t.segment.1 as i64
                ],
            )
            .with_context(context)?;
        }
        let bytes = message(query, &ids);
        tx.execute(
            "UPDATE queries SET message = ?1 WHERE id = ?2",
            params![bytes, int(query)],
        )
        .with_context(|| format!("storing the message of query {query} in {}", path.display()))?;
        tx.commit()
            .with_context(|| format!("committing query {query} to {}", path.display()))?;
        Ok(Asked {
            query,
            first: ids[0],
            second: ids[1],
            more: ids[2..].to_vec(),
        })
    }

    /// Store a teacher's answer to `query` in its own transaction; returns once it is on
    /// disk. A second answer to a query is [`Stored::Repeated`] and changes nothing.
    pub fn answer(&mut self, a: &Answer, answered_at_ms: u64) -> Result<Stored> {
        let query = a.query;
        let path = self.path.clone();
        let context = || format!("storing the answer to query {query} in {}", path.display());
        let tx = self.write()?;
        let state: Option<Option<String>> = tx
            .query_row(
                "SELECT answer FROM queries WHERE id = ?1",
                [int(query)],
                |r| r.get(0),
            )
            .optional()
            .with_context(context)?;
        let stored = match state.as_ref().map(|a| a.as_deref()) {
            None => return Ok(Stored::Unknown),
            Some(None) => Stored::New,
            Some(Some("expired")) => Stored::Late,
            Some(Some(_)) => return Ok(Stored::Repeated),
        };
        let more: i64 = tx
            .query_row(
                "SELECT count(*) FROM query_attempts WHERE query = ?1",
                [int(query)],
                |r| r.get(0),
            )
            .with_context(context)?;
        let attempts = 2 + more as usize;
        let fits = match a.ranks.len() {
            0 => attempts == 2 || a.preference == Preference::Skip,
            n => n == attempts && attempts > 2,
        };
        if !fits {
            return Ok(Stored::Misfit);
        }
        let ranks = (!a.ranks.is_empty()).then(|| {
            a.ranks
                .iter()
                .map(|r| r.to_string())
                .collect::<Vec<_>>()
                .join(",")
        });
        tx.execute(
            "UPDATE queries SET answer = ?1, teacher = ?2, teacher_id = ?3, took_ms = ?4,
                 answered_at_ms = ?5, message = NULL,
                 answer_no = (SELECT coalesce(max(answer_no), 0) + 1 FROM queries),
                 labeller = ?7, replays_first = ?8, replays_second = ?9, shadow = ?10,
                 ranks = ?11
             WHERE id = ?6",
            params![
                a.preference.name(),
                a.teacher,
                a.teacher_id,
                int(a.took_ms),
                int(answered_at_ms),
                int(query),
                (!a.labeller.is_empty()).then_some(&a.labeller),
                (!a.labeller.is_empty()).then_some(a.replays[0]),
                (!a.labeller.is_empty()).then_some(a.replays[1]),
                a.shadow.map(|p| p.name()),
                ranks,
            ],
        )
        .with_context(context)?;
        tx.commit().with_context(context)?;
        Ok(stored)
    }

    /// Store a person's answer to a query asked again ([`Answer::repeat`]), apart from D:
    /// [`Stored::New`], [`Stored::Repeated`] if this labeller's repeat of it is stored
    /// already, or [`Stored::Unknown`] for a query this run never asked.
    pub fn repeat(&mut self, a: &Answer, answered_at_ms: u64) -> Result<Stored> {
        let path = self.path.clone();
        let context = || {
            format!(
                "storing a repeated answer to query {} in {}",
                a.query,
                path.display()
            )
        };
        let tx = self.write()?;
        let known: Option<i64> = tx
            .query_row(
                "SELECT id FROM queries WHERE id = ?1",
                [int(a.query)],
                |r| r.get(0),
            )
            .optional()
            .with_context(context)?;
        if known.is_none() {
            return Ok(Stored::Unknown);
        }
        let n = tx
            .execute(
                "INSERT OR IGNORE INTO repeats (query, teacher_id, labeller, answer, took_ms,
                     replays_first, replays_second, shadow, answered_at_ms)
                 VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9)",
                params![
                    int(a.query),
                    a.teacher_id,
                    a.labeller,
                    a.preference.name(),
                    int(a.took_ms),
                    a.replays[0],
                    a.replays[1],
                    a.shadow.map(|p| p.name()),
                    int(answered_at_ms),
                ],
            )
            .with_context(context)?;
        tx.commit().with_context(context)?;
        Ok(if n == 1 {
            Stored::New
        } else {
            Stored::Repeated
        })
    }

    /// Give up waiting for an answer to `query`: true if it was open (a later answer is
    /// still stored, as [`Stored::Late`]); false if it was answered, expired or unknown.
    pub fn expire(&mut self, query: u64, at_ms: u64) -> Result<bool> {
        let changed = self
            .conn
            .execute(
                "UPDATE queries SET answer = 'expired', expired_at_ms = ?1, message = NULL
                 WHERE id = ?2 AND answer IS NULL",
                params![int(at_ms), int(query)],
            )
            .with_context(|| format!("expiring query {query} in {}", self.path.display()))?;
        Ok(changed == 1)
    }

    /// Withdraw `query` as stale at the learner's `env_steps`: expired, noting why (a later
    /// answer is still stored, as [`Stored::Late`]). True if it was open.
    pub fn withdraw(&mut self, query: u64, at_ms: u64, env_steps: u64) -> Result<bool> {
        let changed = self
            .conn
            .execute(
                "UPDATE queries SET answer = 'expired', expired_at_ms = ?1,
                     withdrawn_at_steps = ?2, message = NULL
                 WHERE id = ?3 AND answer IS NULL",
                params![int(at_ms), int(env_steps), int(query)],
            )
            .with_context(|| format!("withdrawing query {query} in {}", self.path.display()))?;
        Ok(changed == 1)
    }
}

/// Insert trajectory `t`, or find it if a query stored it already; its id.
fn put_trajectory(tx: &Transaction<'_>, t: &StoredTrajectory<'_>) -> Result<u64> {
    let context = || format!("storing trajectory {}", t.key());
    let found: Option<(i64, i64, i64, i64, i64, i64)> = tx
        .query_row(
            "SELECT id, seed, policy_version, steps, obs_dim, act_dim FROM trajectories
             WHERE actor = ?1 AND incarnation = ?2 AND seq = ?3",
            params![t.actor, int(t.incarnation), int(t.seq)],
            |r| {
                Ok((
                    r.get(0)?,
                    r.get(1)?,
                    r.get(2)?,
                    r.get(3)?,
                    r.get(4)?,
                    r.get(5)?,
                ))
            },
        )
        .optional()
        .with_context(context)?;
    let steps = t.steps();
    if let Some((id, seed, version, s, o, a)) = found {
        let stored = (uint(seed), uint(version), s, o, a);
        let given = (
            t.seed,
            t.policy_version,
            steps as i64,
            t.obs_dim as i64,
            t.act_dim as i64,
        );
        if stored != given {
            bail!(
                "trajectory {} is stored as id {id} with (seed, policy_version, steps, \
                 obs_dim, act_dim) = {stored:?}, and given again as {given:?}",
                t.key()
            );
        }
        // NOTE: a trajectory stored without features (by an older build) gains them.
        if !t.features.is_empty() {
            tx.execute(
                "UPDATE trajectories SET features = ?1 WHERE id = ?2 AND features IS NULL",
                params![to_blob(t.features), id],
            )
            .with_context(context)?;
        }
        return Ok(uint(id));
    }
    tx.execute(
        "INSERT INTO trajectories
             (actor, incarnation, seq, seed, policy_version, steps, obs_dim, act_dim, obs, actions,
              features)
         VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9, ?10, ?11)",
        params![
            t.actor,
            int(t.incarnation),
            int(t.seq),
            int(t.seed),
            int(t.policy_version),
            steps as i64,
            t.obs_dim as i64,
            t.act_dim as i64,
            to_blob(t.obs),
            to_blob(t.actions),
            (!t.features.is_empty()).then(|| to_blob(t.features))
        ],
    )
    .with_context(context)?;
    Ok(uint(tx.last_insert_rowid()))
}
