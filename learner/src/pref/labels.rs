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

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use pbrl_common::wire::{Answer, Preference};
use rusqlite::{params, Connection, OptionalExtension, Transaction, TransactionBehavior};

/// The layout this build writes and reads (`meta.schema`).
pub const SCHEMA: u32 = 5;

const CREATE: &str = "
CREATE TABLE meta (
    key TEXT PRIMARY KEY,
    value TEXT NOT NULL
);
CREATE TABLE trajectories (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    actor INTEGER NOT NULL,
    incarnation INTEGER NOT NULL,
    seq INTEGER NOT NULL,
    seed INTEGER NOT NULL,
    policy_version INTEGER NOT NULL,
    steps INTEGER NOT NULL CHECK (steps > 0),
    obs_dim INTEGER NOT NULL CHECK (obs_dim > 0),
    act_dim INTEGER NOT NULL CHECK (act_dim > 0),
    obs BLOB NOT NULL CHECK (length(obs) = 4 * steps * obs_dim),
    actions BLOB NOT NULL CHECK (length(actions) = 4 * steps * act_dim),
    features BLOB CHECK (features IS NULL OR length(features) % (4 * steps) = 0),
    UNIQUE (actor, incarnation, seq)
);
CREATE TABLE queries (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    session INTEGER NOT NULL,
    sampler TEXT NOT NULL,
    env_steps INTEGER NOT NULL,
    first INTEGER NOT NULL REFERENCES trajectories (id),
    second INTEGER NOT NULL REFERENCES trajectories (id),
    first_start INTEGER,
    first_len INTEGER,
    second_start INTEGER,
    second_len INTEGER,
    asked_at_ms INTEGER NOT NULL,
    message BLOB,
    answer TEXT CHECK (answer IN ('first', 'second', 'equal', 'skip', 'expired')),
    teacher TEXT,
    teacher_id TEXT,
    took_ms INTEGER,
    answered_at_ms INTEGER,
    expired_at_ms INTEGER,
    withdrawn_at_steps INTEGER,
    answer_no INTEGER UNIQUE,
    labeller TEXT,
    replays_first INTEGER,
    replays_second INTEGER,
    shadow TEXT,
    CHECK ((answer IS NULL) = (message IS NOT NULL))
);
CREATE INDEX queries_open ON queries (id) WHERE answer IS NULL;
";

/// What schema 2 added to schema 1's queries (its tables and view follow).
const MIGRATE_1_TO_2: &str = "
ALTER TABLE queries ADD COLUMN labeller TEXT;
ALTER TABLE queries ADD COLUMN replays_first INTEGER;
ALTER TABLE queries ADD COLUMN replays_second INTEGER;
ALTER TABLE queries ADD COLUMN shadow TEXT;
DROP VIEW IF EXISTS labels;
UPDATE meta SET value = '2' WHERE key = 'schema';
";

/// What schema 3 added to schema 2: each query's segments (NULL for the older queries,
/// which compared whole trajectories); the view is made again with them.
const MIGRATE_2_TO_3: &str = "
ALTER TABLE queries ADD COLUMN first_start INTEGER;
ALTER TABLE queries ADD COLUMN first_len INTEGER;
ALTER TABLE queries ADD COLUMN second_start INTEGER;
ALTER TABLE queries ADD COLUMN second_len INTEGER;
DROP VIEW IF EXISTS labels;
UPDATE meta SET value = '3' WHERE key = 'schema';
";

/// What schema 4 added to schema 3: each trajectory's comfort features per step (NULL for
/// the trajectories an older build stored, which did not keep them).
const MIGRATE_3_TO_4: &str = "
ALTER TABLE trajectories ADD COLUMN features BLOB
    CHECK (features IS NULL OR length(features) % (4 * steps) = 0);
UPDATE meta SET value = '4' WHERE key = 'schema';
";

/// What schema 5 added to schema 4: when a query was withdrawn as stale (NULL for every
/// query of an older build, which withdrew none).
const MIGRATE_4_TO_5: &str = "
ALTER TABLE queries ADD COLUMN withdrawn_at_steps INTEGER;
UPDATE meta SET value = '5' WHERE key = 'schema';
";

const REPEATS: &str = "
CREATE TABLE repeats (
    query INTEGER NOT NULL REFERENCES queries (id),
    teacher_id TEXT NOT NULL,
    labeller TEXT NOT NULL,
    answer TEXT NOT NULL CHECK (answer IN ('first', 'second', 'equal', 'skip')),
    took_ms INTEGER NOT NULL,
    replays_first INTEGER NOT NULL,
    replays_second INTEGER NOT NULL,
    shadow TEXT,
    answered_at_ms INTEGER NOT NULL,
    PRIMARY KEY (query, teacher_id, labeller)
);
";

const VIEW: &str = "
CREATE VIEW labels AS
SELECT q.id AS query, q.session, q.sampler, q.env_steps, q.answer, q.teacher, q.teacher_id,
       q.took_ms, q.asked_at_ms, q.answered_at_ms, q.labeller, q.replays_first,
       q.replays_second, q.shadow,
       datetime(q.answered_at_ms / 1000, 'unixepoch') AS answered_at, q.answer_no,
       q.first, a.policy_version AS first_policy_version, a.seed AS first_seed,
       a.steps AS first_steps,
       coalesce(q.first_start, 0) AS first_start, coalesce(q.first_len, a.steps) AS first_len,
       q.second, b.policy_version AS second_policy_version, b.seed AS second_seed,
       b.steps AS second_steps,
       coalesce(q.second_start, 0) AS second_start,
       coalesce(q.second_len, b.steps) AS second_len
FROM queries q
JOIN trajectories a ON a.id = q.first
JOIN trajectories b ON b.id = q.second
WHERE q.answer IN ('first', 'second', 'equal')
ORDER BY q.answer_no;
";

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
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Asked {
    pub query: u64,
    pub first: u64,
    pub second: u64,
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
    /// First, Second or Equal (never Skip).
    pub preference: Preference,
    pub answered_at_ms: u64,
}

/// The steps of one stored trajectory.
#[derive(Clone, Debug, PartialEq)]
pub struct Segment {
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
    /// schema 4, read as having withdrawn nothing, or 3, also as keeping no features) is
    /// refused.
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

    fn check_or_create(&mut self, run: &str) -> Result<()> {
        let path = self.path.clone();
        let tx = self.write()?;
        let tables = tx
            .prepare(
                "SELECT name FROM sqlite_master WHERE type = 'table' AND name NOT LIKE 'sqlite_%'",
            )
            .and_then(|mut stmt| {
                stmt.query_map([], |r| r.get(0))?
                    .collect::<rusqlite::Result<Vec<String>>>()
            })
            .with_context(|| format!("listing the tables of {}", path.display()))?;
        if tables.is_empty() {
            tx.execute_batch(&format!("{CREATE}{REPEATS}{VIEW}"))
                .with_context(|| {
                    format!("creating the tables of label store {}", path.display())
                })?;
            tx.execute(
                "INSERT INTO meta (key, value) VALUES ('run', ?1), ('schema', ?2)",
                params![run, SCHEMA.to_string()],
            )
            .and_then(|_| tx.commit())
            .with_context(|| format!("creating label store {}", path.display()))?;
            return Ok(());
        }
        if !tables.iter().any(|t| t == "meta") {
            bail!(
                "{} is not a label store: it has tables ({}) but no meta",
                path.display(),
                tables.join(", ")
            );
        }
        let get = |key: &str| -> Result<Option<String>> {
            tx.query_row("SELECT value FROM meta WHERE key = ?1", [key], |r| r.get(0))
                .optional()
                .with_context(|| format!("reading meta.{key} of label store {}", path.display()))
        };
        let mut schema = get("schema")?.unwrap_or_default();
        if schema == "1" {
            // NOTE: a store of an older build (its run resumed by this one) gains the
            // columns of a person's answers and the repeats; nothing it holds changes.
            tx.execute_batch(&format!("{MIGRATE_1_TO_2}{REPEATS}"))
                .with_context(|| format!("upgrading label store {} to schema 2", path.display()))?;
            schema = "2".into();
        }
        if schema == "2" {
            // NOTE: the queries of an older build compared whole trajectories: their
            // segments stay NULL and read as the whole trajectory.
            tx.execute_batch(&format!("{MIGRATE_2_TO_3}{VIEW}"))
                .with_context(|| format!("upgrading label store {} to schema 3", path.display()))?;
            schema = "3".into();
        }
        if schema == "3" {
            // NOTE: the trajectories of an older build keep no features: NULL, read as none.
            tx.execute_batch(MIGRATE_3_TO_4)
                .with_context(|| format!("upgrading label store {} to schema 4", path.display()))?;
            schema = "4".into();
        }
        if schema == "4" {
            // NOTE: an older build withdrew no query: NULL throughout.
            tx.execute_batch(MIGRATE_4_TO_5)
                .with_context(|| format!("upgrading label store {} to schema 5", path.display()))?;
            schema = SCHEMA.to_string();
        }
        if schema != SCHEMA.to_string() {
            bail!(
                "label store {} has schema version {schema:?}, this build reads version {SCHEMA}",
                path.display()
            );
        }
        let found = get("run")?.unwrap_or_default();
        if found != run {
            bail!(
                "label store {} belongs to run {found:?}, not to this run {run:?}",
                path.display()
            );
        }
        tx.commit()
            .with_context(|| format!("opening label store {}", path.display()))
    }

    /// A write transaction, taking the write lock at once.
    fn write(&mut self) -> Result<Transaction<'_>> {
        self.conn
            .transaction_with_behavior(TransactionBehavior::Immediate)
            .with_context(|| format!("starting a transaction on {}", self.path.display()))
    }

    /// Record a query before it is sent, in one transaction: both trajectories (stored once
    /// per actor, incarnation and seq), then the query. `message(query, first, second)`
    /// builds the encoded query from the new ids; it is kept until the query is answered
    /// or expires, so that it can be asked again after a restart.
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
        first.check("first")?;
        second.check("second")?;
        if (first.actor, first.incarnation, first.seq)
            == (second.actor, second.incarnation, second.seq)
        {
            bail!("a query compares trajectory {} with itself", first.key());
        }
        let path = self.path.clone();
        let tx = self.write()?;
        let context = || format!("storing a query of session {session} in {}", path.display());
        let first_id = put_trajectory(&tx, first).with_context(context)?;
        let second_id = put_trajectory(&tx, second).with_context(context)?;
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
                int(first_id),
                int(second_id),
                int(asked_at_ms),
                first.segment.0 as i64,
                first.segment.1 as i64,
                second.segment.0 as i64,
                second.segment.1 as i64,
            ],
        )
        .with_context(context)?;
        let query = uint(tx.last_insert_rowid());
        let bytes = message(query, first_id, second_id);
        tx.execute(
            "UPDATE queries SET message = ?1 WHERE id = ?2",
            params![bytes, int(query)],
        )
        .with_context(|| format!("storing the message of query {query} in {}", path.display()))?;
        tx.commit()
            .with_context(|| format!("committing query {query} to {}", path.display()))?;
        Ok(Asked {
            query,
            first: first_id,
            second: second_id,
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
        tx.execute(
            "UPDATE queries SET answer = ?1, teacher = ?2, teacher_id = ?3, took_ms = ?4,
                 answered_at_ms = ?5, message = NULL,
                 answer_no = (SELECT coalesce(max(answer_no), 0) + 1 FROM queries),
                 labeller = ?7, replays_first = ?8, replays_second = ?9, shadow = ?10
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

    /// The actor's numbering of stored trajectory `id`: (actor, incarnation, seq).
    pub fn trajectory_key(&self, id: u64) -> Result<crate::pref::query::TrajKey> {
        self.conn
            .query_row(
                "SELECT actor, incarnation, seq FROM trajectories WHERE id = ?1",
                [int(id)],
                |r| {
                    Ok(crate::pref::query::TrajKey {
                        actor: r.get::<_, i64>(0)? as u32,
                        incarnation: uint(r.get(1)?),
                        seq: uint(r.get(2)?),
                    })
                },
            )
            .with_context(|| format!("reading trajectory {id} of {}", self.path.display()))
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

    /// The open queries, oldest first: id, when first asked, and the message as sent.
    pub fn open_queries(&self) -> Result<Vec<(u64, u64, Vec<u8>)>> {
        let context = || format!("reading the open queries of {}", self.path.display());
        let mut stmt = self
            .conn
            .prepare(
                "SELECT id, asked_at_ms, message FROM queries WHERE answer IS NULL ORDER BY id",
            )
            .with_context(context)?;
        let rows = stmt
            .query_map([], |r| {
                Ok((uint(r.get(0)?), uint(r.get(1)?), r.get::<_, Vec<u8>>(2)?))
            })
            .with_context(context)?
            .collect::<rusqlite::Result<Vec<_>>>()
            .with_context(context)?;
        Ok(rows)
    }

    /// The newest feedback session that asked a query (0: none).
    pub fn last_session(&self) -> Result<u64> {
        let n: i64 = self
            .conn
            .query_row("SELECT coalesce(max(session), 0) FROM queries", [], |r| {
                r.get(0)
            })
            .with_context(|| format!("reading the last session of {}", self.path.display()))?;
        Ok(uint(n))
    }

    /// The queries by state.
    pub fn counts(&self) -> Result<Counts> {
        let withdrawn = if self.withdrawals {
            "coalesce(sum(answer = 'expired' AND withdrawn_at_steps IS NOT NULL), 0)"
        } else {
            "0"
        };
        let (asked, first, second, equal, skipped, expired, open, late, withdrawn) = self
            .conn
            .query_row(
                &format!(
                    "SELECT count(*),
                        coalesce(sum(answer = 'first'), 0),
                        coalesce(sum(answer = 'second'), 0),
                        coalesce(sum(answer = 'equal'), 0),
                        coalesce(sum(answer = 'skip'), 0),
                        coalesce(sum(answer = 'expired'), 0),
                        coalesce(sum(answer IS NULL), 0),
                        coalesce(sum(answer <> 'expired' AND expired_at_ms IS NOT NULL), 0),
                        {withdrawn}
                 FROM queries"
                ),
                [],
                |r| {
                    Ok((
                        uint(r.get(0)?),
                        uint(r.get(1)?),
                        uint(r.get(2)?),
                        uint(r.get(3)?),
                        uint(r.get(4)?),
                        uint(r.get(5)?),
                        uint(r.get(6)?),
                        uint(r.get(7)?),
                        uint(r.get(8)?),
                    ))
                },
            )
            .with_context(|| format!("counting the queries of {}", self.path.display()))?;
        Ok(Counts {
            asked,
            answered: first + second + equal + skipped,
            first,
            second,
            equal,
            skipped,
            expired,
            withdrawn,
            open,
            late,
        })
    }

    /// The labels (answers first, second and equal) stored after answer number
    /// `after_answer`, in the order they were stored; 0 gives all of D. Answers arrive out
    /// of query order, so the cursor is the answer's number, not the query's id.
    pub fn labels_since(&self, after_answer: u64) -> Result<Vec<LabelRow>> {
        let context = || {
            format!(
                "reading the labels after answer {after_answer} from {}",
                self.path.display()
            )
        };
        let mut stmt = self
            .conn
            .prepare(
                "SELECT q.answer_no, q.id, q.session, q.first, q.second, q.answer,
                        q.answered_at_ms,
                        coalesce(q.first_start, 0), coalesce(q.first_len, a.steps),
                        coalesce(q.second_start, 0), coalesce(q.second_len, b.steps)
                 FROM queries q
                 JOIN trajectories a ON a.id = q.first
                 JOIN trajectories b ON b.id = q.second
                 WHERE q.answer IN ('first', 'second', 'equal') AND q.answer_no > ?1
                 ORDER BY q.answer_no",
            )
            .with_context(context)?;
        let rows = stmt
            .query_map([int(after_answer)], |r| {
                Ok((
                    uint(r.get(0)?),
                    uint(r.get(1)?),
                    uint(r.get(2)?),
                    uint(r.get(3)?),
                    uint(r.get(4)?),
                    r.get::<_, String>(5)?,
                    uint(r.get(6)?),
                    [
                        r.get::<_, i64>(7)?,
                        r.get::<_, i64>(8)?,
                        r.get::<_, i64>(9)?,
                        r.get::<_, i64>(10)?,
                    ],
                ))
            })
            .with_context(context)?
            .collect::<rusqlite::Result<Vec<_>>>()
            .with_context(context)?;
        rows.into_iter()
            .map(
                |(answer_no, query, session, first, second, answer, answered_at_ms, bounds)| {
                    let preference = Preference::parse(&answer).with_context(|| {
                        format!(
                            "query {query} in {} has answer {answer:?}",
                            self.path.display()
                        )
                    })?;
                    let [a0, a1, b0, b1] = bounds.map(|x| x.max(0) as usize);
                    Ok(LabelRow {
                        answer_no,
                        query,
                        session,
                        first,
                        second,
                        first_segment: (a0, a1),
                        second_segment: (b0, b1),
                        preference,
                        answered_at_ms,
                    })
                },
            )
            .collect()
    }

    /// The steps of trajectory `trajectory` (an id from [`Asked`] or [`LabelRow`]).
    pub fn segment(&self, trajectory: u64) -> Result<Segment> {
        let context = || {
            format!(
                "reading trajectory {trajectory} from {}",
                self.path.display()
            )
        };
        let sql = if self.features {
            "SELECT steps, obs_dim, act_dim, obs, actions, features FROM trajectories WHERE id = ?1"
        } else {
            "SELECT steps, obs_dim, act_dim, obs, actions, NULL FROM trajectories WHERE id = ?1"
        };
        type Row = (i64, i64, i64, Blob, Blob, Option<Blob>);
        let row: Option<Row> = self
            .conn
            .query_row(sql, [int(trajectory)], |r| {
                Ok((
                    r.get(0)?,
                    r.get(1)?,
                    r.get(2)?,
                    r.get(3)?,
                    r.get(4)?,
                    r.get(5)?,
                ))
            })
            .optional()
            .with_context(context)?;
        let Some((steps, obs_dim, act_dim, obs, actions, features)) = row else {
            bail!(
                "label store {} has no trajectory {trajectory}",
                self.path.display()
            );
        };
        let dim = |x: i64, what: &str| {
            usize::try_from(x).with_context(|| format!("{what} is {x}: {}", context()))
        };
        let (steps, obs_dim, act_dim) = (
            dim(steps, "steps")?,
            dim(obs_dim, "obs_dim")?,
            dim(act_dim, "act_dim")?,
        );
        for (what, bytes, width) in [("obs", &obs, obs_dim), ("actions", &actions, act_dim)] {
            if bytes.len() != 4 * steps * width {
                bail!(
                    "{what} has {} bytes, expected {steps} rows of {width} f32: {}",
                    bytes.len(),
                    context()
                );
            }
        }
        let features = features.unwrap_or_default();
        if !features.len().is_multiple_of(4 * steps.max(1)) {
            bail!(
                "features have {} bytes, not {steps} rows of f32: {}",
                features.len(),
                context()
            );
        }
        Ok(Segment {
            steps,
            obs_dim,
            act_dim,
            obs: from_blob(&obs),
            actions: from_blob(&actions),
            features: from_blob(&features),
        })
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

#[cfg(test)]
mod tests {
    use super::*;

    /// A trajectory's numbers: odd values (negative zero, subnormals, ...) to check that
    /// every bit comes back.
    struct Traj {
        actor: u32,
        incarnation: u64,
        seq: u64,
        obs: Vec<f32>,
        actions: Vec<f32>,
    }

    const OBS_DIM: usize = 3;
    const ACT_DIM: usize = 2;

    fn traj(actor: u32, seq: u64, steps: usize) -> Traj {
        let odd = [-0.0, f32::MIN_POSITIVE / 3.0, 1.0 / 3.0, f32::MAX, -1.5e-30];
        Traj {
            actor,
            // Above 2^63, as random incarnations are half the time.
            incarnation: u64::MAX - 7,
            seq,
            obs: (0..steps * OBS_DIM)
                .map(|i| odd[(i + seq as usize) % odd.len()])
                .collect(),
            actions: (0..steps * ACT_DIM)
                .map(|i| odd[(i + 2 + actor as usize) % odd.len()])
                .collect(),
        }
    }

    fn stored(t: &Traj) -> StoredTrajectory<'_> {
        StoredTrajectory {
            actor: t.actor,
            incarnation: t.incarnation,
            seq: t.seq,
            seed: (1 << 63) + t.seq,
            policy_version: 4 + t.seq,
            obs_dim: OBS_DIM,
            act_dim: ACT_DIM,
            obs: &t.obs,
            actions: &t.actions,
            features: &[],
            segment: (0, t.actions.len() / ACT_DIM),
        }
    }

    fn message(q: u64, a: u64, b: u64) -> Vec<u8> {
        format!("query {q} of {a} and {b}").into_bytes()
    }

    fn ask(store: &mut LabelStore, a: &Traj, b: &Traj) -> Asked {
        store
            .ask(
                1,
                "disagreement",
                5_000,
                1_000,
                &stored(a),
                &stored(b),
                message,
            )
            .unwrap()
    }

    /// What a run leaves in the store at `path`: one query of two trajectories, answered
    /// `p` if given, and the store closed.
    fn left_behind(path: &Path, p: Option<Preference>) -> Asked {
        let mut store = LabelStore::open(path, "run").unwrap();
        let q = ask(&mut store, &traj(0, 1, 3), &traj(1, 1, 3));
        if let Some(p) = p {
            answer(&mut store, q.query, p);
        }
        q
    }

    fn answer(store: &mut LabelStore, query: u64, p: Preference) -> Stored {
        store
            .answer(
                &Answer::scripted(query, p, "oracle", "oracle-0", 1_500),
                2_000 + query,
            )
            .unwrap()
    }

    fn bits(xs: &[f32]) -> Vec<u32> {
        xs.iter().map(|x| x.to_bits()).collect()
    }

    #[test]
    fn a_label_round_trips_through_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("labels.sqlite");
        let (a, b, c) = (traj(0, 1, 4), traj(1, 2, 5), traj(0, 3, 2));
        let (q1, q2) = {
            let mut store = LabelStore::open(&path, "run").unwrap();
            let q1 = ask(&mut store, &a, &b);
            let q2 = ask(&mut store, &c, &b);
            assert_eq!(
                answer(&mut store, q1.query, Preference::Second),
                Stored::New
            );
            assert_eq!(answer(&mut store, q2.query, Preference::Skip), Stored::New);
            (q1, q2)
        };
        assert!(q2.query > q1.query);
        let store = LabelStore::open(&path, "run").unwrap();
        assert_eq!(
            store.counts().unwrap(),
            Counts {
                asked: 2,
                answered: 2,
                second: 1,
                skipped: 1,
                ..Counts::default()
            }
        );
        // A skip counts against the budget, but is no label.
        assert_eq!(
            store.labels_since(0).unwrap(),
            vec![LabelRow {
                answer_no: 1,
                query: q1.query,
                session: 1,
                first: q1.first,
                second: q1.second,
                first_segment: (0, a.actions.len() / ACT_DIM),
                second_segment: (0, b.actions.len() / ACT_DIM),
                preference: Preference::Second,
                answered_at_ms: 2_000 + q1.query,
            }]
        );
        assert!(store.labels_since(1).unwrap().is_empty());
        for (id, t) in [(q1.first, &a), (q1.second, &b), (q2.first, &c)] {
            let s = store.segment(id).unwrap();
            assert_eq!(
                (s.steps, s.obs_dim, s.act_dim),
                (t.actions.len() / ACT_DIM, OBS_DIM, ACT_DIM)
            );
            assert_eq!(bits(&s.obs), bits(&t.obs));
            assert_eq!(bits(&s.actions), bits(&t.actions));
        }
        let e = store.segment(99).unwrap_err().to_string();
        assert!(e.contains("99") && e.contains("labels.sqlite"), "{e}");
        // The view for people: both trajectories' versions and seeds, u64 seeds by bits.
        let (seed, version): (i64, i64) = store
            .conn
            .query_row(
                "SELECT second_seed, second_policy_version FROM labels WHERE query = ?1",
                [q1.query as i64],
                |r| Ok((r.get(0)?, r.get(1)?)),
            )
            .unwrap();
        assert_eq!((seed as u64, version), ((1 << 63) + 2, 6));
        // Durable settings, as read back.
        let sync: i64 = store
            .conn
            .pragma_query_value(None, "synchronous", |r| r.get(0))
            .unwrap();
        let mode: String = store
            .conn
            .pragma_query_value(None, "journal_mode", |r| r.get(0))
            .unwrap();
        assert_eq!((sync, mode.as_str()), (2, "wal"));
    }

    #[test]
    fn a_repeated_answer_leaves_the_first_and_an_unknown_query_is_unknown() {
        let dir = tempfile::tempdir().unwrap();
        let mut store = LabelStore::open(&dir.path().join("labels.sqlite"), "run").unwrap();
        let q = ask(&mut store, &traj(0, 1, 3), &traj(0, 2, 3));
        assert_eq!(answer(&mut store, q.query, Preference::First), Stored::New);
        assert_eq!(
            store
                .answer(
                    &Answer::scripted(q.query, Preference::Second, "human", "ann", 9),
                    9
                )
                .unwrap(),
            Stored::Repeated
        );
        let labels = store.labels_since(0).unwrap();
        assert_eq!(labels.len(), 1);
        assert_eq!(labels[0].preference, Preference::First);
        assert_eq!(labels[0].answered_at_ms, 2_000 + q.query);
        let teacher: String = store
            .conn
            .query_row("SELECT teacher_id FROM queries", [], |r| r.get(0))
            .unwrap();
        assert_eq!(teacher, "oracle-0");
        assert_eq!(
            answer(&mut store, q.query + 1, Preference::First),
            Stored::Unknown
        );
        assert_eq!(store.counts().unwrap().asked, 1);
    }

    #[test]
    fn an_answer_after_a_restart_is_stored_once() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("labels.sqlite");
        let q = left_behind(&path, None);
        // The learner restarts; the teacher, unacknowledged, sends its answer twice.
        let mut store = LabelStore::open(&path, "run").unwrap();
        assert_eq!(store.open_queries().unwrap().len(), 1);
        assert_eq!(answer(&mut store, q.query, Preference::Equal), Stored::New);
        drop(store);
        let mut store = LabelStore::open(&path, "run").unwrap();
        assert_eq!(
            answer(&mut store, q.query, Preference::Equal),
            Stored::Repeated
        );
        let c = store.counts().unwrap();
        assert_eq!((c.asked, c.answered, c.equal, c.open), (1, 1, 1, 0));
        // Ids are never reused: the next query's id is above every earlier one.
        let next = ask(&mut store, &traj(0, 5, 3), &traj(1, 5, 3));
        assert!(next.query > q.query && next.first > q.second);
    }

    #[test]
    fn a_trajectory_in_two_queries_is_stored_once() {
        let dir = tempfile::tempdir().unwrap();
        let mut store = LabelStore::open(&dir.path().join("labels.sqlite"), "run").unwrap();
        let (a, b, c) = (traj(0, 1, 3), traj(0, 2, 3), traj(2, 1, 3));
        let q1 = ask(&mut store, &a, &b);
        let q2 = ask(&mut store, &c, &a);
        assert_eq!(q2.second, q1.first);
        let n: i64 = store
            .conn
            .query_row("SELECT count(*) FROM trajectories", [], |r| r.get(0))
            .unwrap();
        assert_eq!(n, 3);
        // The same numbering with another episode is a bug upstream: refused, named.
        let mut other = stored(&a);
        other.seed += 1;
        let e = store
            .ask(1, "uniform", 0, 0, &other, &stored(&b), message)
            .unwrap_err();
        assert!(format!("{e:#}").contains("(actor 0, incarnation"), "{e:#}");
        // A trajectory against itself, or of the wrong shape, is refused before storing.
        assert!(store
            .ask(1, "uniform", 0, 0, &stored(&a), &stored(&a), message)
            .is_err());
        let mut short = stored(&c);
        short.obs = &c.obs[1..];
        let e = store
            .ask(1, "uniform", 0, 0, &stored(&a), &short, message)
            .unwrap_err();
        assert!(e.to_string().contains("second trajectory"), "{e}");
        assert_eq!(store.counts().unwrap().asked, 2);
    }

    #[test]
    fn a_schema_1_store_is_upgraded_in_place_and_keeps_its_labels() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("labels.sqlite");
        let q = left_behind(&path, Some(Preference::First));
        // Back to the layout of schema 1, as an older build wrote it.
        let conn = Connection::open(&path).unwrap();
        conn.execute_batch(
            "DROP VIEW labels; DROP TABLE repeats;
             ALTER TABLE queries DROP COLUMN labeller;
             ALTER TABLE queries DROP COLUMN replays_first;
             ALTER TABLE queries DROP COLUMN replays_second;
             ALTER TABLE queries DROP COLUMN shadow;
             ALTER TABLE queries DROP COLUMN first_start;
             ALTER TABLE queries DROP COLUMN first_len;
             ALTER TABLE queries DROP COLUMN second_start;
             ALTER TABLE queries DROP COLUMN second_len;
             ALTER TABLE trajectories DROP COLUMN features;
             ALTER TABLE queries DROP COLUMN withdrawn_at_steps;
             CREATE VIEW labels AS SELECT id AS query FROM queries;
             UPDATE meta SET value = '1' WHERE key = 'schema';",
        )
        .unwrap();
        drop(conn);
        let mut store = LabelStore::open(&path, "run").unwrap();
        assert_eq!(store.counts().unwrap().first, 1);
        let a = Answer {
            labeller: "ann".into(),
            repeat: true,
            ..Answer::scripted(q.query, Preference::Second, "human", "human-0", 5)
        };
        assert_eq!(store.repeat(&a, 9).unwrap(), Stored::New);
        assert_eq!(store.repeat(&a, 9).unwrap(), Stored::Repeated);
        let schema: String = store
            .conn
            .query_row("SELECT value FROM meta WHERE key = 'schema'", [], |r| {
                r.get(0)
            })
            .unwrap();
        assert_eq!(schema, SCHEMA.to_string());
        let rows = store.labels_since(0).unwrap();
        assert_eq!(
            (rows[0].first_segment, rows[0].second_segment),
            ((0, 3), (0, 3))
        );
    }

    #[test]
    fn a_schema_2_store_reads_its_queries_as_whole_trajectories_and_stores_segments() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("labels.sqlite");
        let q = left_behind(&path, Some(Preference::Second));
        // Back to the layout of schema 2, as the build before segments wrote it.
        let conn = Connection::open(&path).unwrap();
        conn.execute_batch(
            "DROP VIEW labels;
             ALTER TABLE queries DROP COLUMN first_start;
             ALTER TABLE queries DROP COLUMN first_len;
             ALTER TABLE queries DROP COLUMN second_start;
             ALTER TABLE queries DROP COLUMN second_len;
             ALTER TABLE trajectories DROP COLUMN features;
             ALTER TABLE queries DROP COLUMN withdrawn_at_steps;
             CREATE VIEW labels AS SELECT id AS query FROM queries;
             UPDATE meta SET value = '2' WHERE key = 'schema';",
        )
        .unwrap();
        drop(conn);
        let mut store = LabelStore::open(&path, "run").unwrap();
        let rows = store.labels_since(0).unwrap();
        assert_eq!(rows.len(), 1);
        assert_eq!(rows[0].query, q.query);
        assert_eq!(rows[0].preference, Preference::Second);
        assert_eq!(
            (rows[0].first_segment, rows[0].second_segment),
            ((0, 3), (0, 3))
        );
        // A new query compares segments; they come back with its label and in the view.
        let (a, b) = (traj(0, 7, 5), traj(1, 7, 5));
        let (mut sa, mut sb) = (stored(&a), stored(&b));
        (sa.segment, sb.segment) = ((1, 3), (2, 3));
        // Schema 4: a trajectory keeps its comfort features (the older ones none).
        let features: Vec<f32> = (0..5 * 6).map(|i| i as f32 * 0.5).collect();
        sa.features = &features;
        let asked = store.ask(2, "uniform", 10, 5, &sa, &sb, message).unwrap();
        answer(&mut store, asked.query, Preference::First);
        assert!(store.segment(rows[0].first).unwrap().features.is_empty());
        // Asked again with its features, an older trajectory gains them.
        let old = traj(0, 1, 3);
        let mut again = stored(&old);
        let old_features = vec![1.5; 3 * 6];
        again.features = &old_features;
        let re = store
            .ask(2, "uniform", 10, 5, &again, &sb, message)
            .unwrap();
        assert_eq!(re.first, rows[0].first, "the same trajectory");
        assert_eq!(store.segment(re.first).unwrap().features, old_features);
        assert_eq!(store.segment(asked.first).unwrap().features, features);
        assert!(store.segment(asked.second).unwrap().features.is_empty());
        let mut ragged = stored(&a);
        ragged.features = &features[..7];
        let e = store
            .ask(2, "uniform", 10, 5, &ragged, &sb, message)
            .unwrap_err();
        assert!(format!("{e:#}").contains("comfort feature"), "{e:#}");
        let rows = store.labels_since(rows[0].answer_no).unwrap();
        assert_eq!(
            (rows[0].first_segment, rows[0].second_segment),
            ((1, 3), (2, 3))
        );
        let view: Vec<(i64, i64, i64, i64)> = store
            .conn
            .prepare("SELECT first_start, first_len, second_start, second_len FROM labels")
            .unwrap()
            .query_map([], |r| Ok((r.get(0)?, r.get(1)?, r.get(2)?, r.get(3)?)))
            .unwrap()
            .collect::<rusqlite::Result<_>>()
            .unwrap();
        assert_eq!(view, vec![(0, 3, 0, 3), (1, 3, 2, 3)]);
        // A segment outside its trajectory is refused, named.
        sa.segment = (3, 3);
        let e = store
            .ask(2, "uniform", 10, 5, &sa, &sb, message)
            .unwrap_err();
        assert!(
            format!("{e:#}").contains("segment start 3, length 3"),
            "{e:#}"
        );
    }

    #[test]
    fn open_queries_keep_their_message_until_answered_or_expired() {
        let dir = tempfile::tempdir().unwrap();
        let mut store = LabelStore::open(&dir.path().join("labels.sqlite"), "run").unwrap();
        let q1 = ask(&mut store, &traj(0, 1, 3), &traj(0, 2, 3));
        let q2 = ask(&mut store, &traj(0, 3, 3), &traj(0, 4, 3));
        let q3 = ask(&mut store, &traj(0, 5, 3), &traj(0, 6, 3));
        let open = store.open_queries().unwrap();
        assert_eq!(
            open,
            [q1, q2, q3]
                .map(|q| (q.query, 1_000, message(q.query, q.first, q.second)))
                .to_vec()
        );
        assert_eq!(answer(&mut store, q2.query, Preference::First), Stored::New);
        assert!(store.expire(q1.query, 3_000).unwrap());
        assert!(!store.expire(q1.query, 3_001).unwrap());
        assert!(!store.expire(q2.query, 3_001).unwrap());
        assert_eq!(
            store.open_queries().unwrap(),
            vec![(q3.query, 1_000, message(q3.query, q3.first, q3.second))]
        );
        let c = store.counts().unwrap();
        assert_eq!((c.asked, c.answered, c.expired, c.open), (3, 1, 1, 1));
        // A late answer is a person's judgement too: stored, and counted as late.
        assert_eq!(
            answer(&mut store, q1.query, Preference::Second),
            Stored::Late
        );
        let c = store.counts().unwrap();
        assert_eq!((c.answered, c.expired, c.late, c.labels()), (2, 0, 1, 2));
        // Answered out of query order: the cursor is the answer's number.
        let labels = store.labels_since(0).unwrap();
        assert_eq!(
            labels.iter().map(|l| l.query).collect::<Vec<_>>(),
            vec![q2.query, q1.query]
        );
        let after = store.labels_since(labels[0].answer_no).unwrap();
        assert_eq!(after.len(), 1);
        assert_eq!(after[0].query, q1.query);
    }

    #[test]
    fn a_withdrawn_query_spends_no_budget_and_its_late_answer_is_stored_once() {
        let dir = tempfile::tempdir().unwrap();
        let mut store = LabelStore::open(&dir.path().join("labels.sqlite"), "run").unwrap();
        let q1 = ask(&mut store, &traj(0, 1, 3), &traj(1, 1, 3));
        // A second query stays open throughout.
        ask(&mut store, &traj(0, 2, 3), &traj(1, 2, 3));
        assert!(store.withdraw(q1.query, 2_000, 7_000).unwrap());
        assert!(
            !store.withdraw(q1.query, 2_001, 7_100).unwrap(),
            "withdrawn once"
        );
        let c = store.counts().unwrap();
        assert_eq!((c.asked, c.expired, c.withdrawn, c.open), (2, 1, 1, 1));
        assert_eq!(c.spent(), 1, "a withdrawn query spent no one's time");
        assert_eq!(store.open_queries().unwrap().len(), 1);
        // The person who held it answers after all: stored once, as late, and it counts.
        assert_eq!(
            answer(&mut store, q1.query, Preference::First),
            Stored::Late
        );
        assert_eq!(
            answer(&mut store, q1.query, Preference::First),
            Stored::Repeated
        );
        let c = store.counts().unwrap();
        assert_eq!((c.withdrawn, c.late, c.labels(), c.spent()), (0, 1, 1, 2));
        let at: i64 = store
            .conn
            .query_row(
                "SELECT withdrawn_at_steps FROM queries WHERE id = ?1",
                [int(q1.query)],
                |r| r.get(0),
            )
            .unwrap();
        assert_eq!(at, 7_000, "where it was withdrawn is kept");
        assert_eq!(store.labels_since(0).unwrap().len(), 1);
    }

    #[test]
    fn another_runs_store_is_refused() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("labels.sqlite");
        drop(LabelStore::open(&path, "feeding-a").unwrap());
        let e = LabelStore::open(&path, "feeding-b")
            .err()
            .unwrap()
            .to_string();
        assert!(
            e.contains("\"feeding-a\"")
                && e.contains("\"feeding-b\"")
                && e.contains("labels.sqlite"),
            "{e}"
        );
        // Nor is a file that is not a store taken for one.
        let junk = dir.path().join("junk.sqlite");
        std::fs::write(&junk, vec![0x5a; 4096]).unwrap();
        let e = format!("{:#}", LabelStore::open(&junk, "feeding-a").err().unwrap());
        assert!(e.contains("junk.sqlite"), "{e}");
    }

    #[test]
    fn a_second_connection_reads_while_the_first_writes() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("labels.sqlite");
        let mut writer = LabelStore::open(&path, "run").unwrap();
        let reader = LabelStore::open(&path, "run").unwrap();
        let q = ask(&mut writer, &traj(0, 1, 3), &traj(0, 2, 3));
        answer(&mut writer, q.query, Preference::Equal);
        assert_eq!(reader.labels_since(0).unwrap().len(), 1);
        assert_eq!(reader.segment(q.first).unwrap().steps, 3);
    }

    #[test]
    fn a_committed_answer_survives_a_crash() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("labels.sqlite");
        let wal = dir.path().join("labels.sqlite-wal");
        let mut store = LabelStore::open(&path, "run").unwrap();
        let q = ask(&mut store, &traj(0, 1, 3), &traj(0, 2, 3));
        let open = ask(&mut store, &traj(0, 3, 3), &traj(0, 2, 3));
        assert_eq!(answer(&mut store, q.query, Preference::First), Stored::New);
        // NOTE: the crash: copy the files as they are while the store is still open (no
        // close, no checkpoint; the WAL still holds the commits), and open the copy.
        assert!(std::fs::metadata(&wal).unwrap().len() > 0);
        let crashed = tempfile::tempdir().unwrap();
        let copy = crashed.path().join("labels.sqlite");
        std::fs::copy(&path, &copy).unwrap();
        std::fs::copy(&wal, crashed.path().join("labels.sqlite-wal")).unwrap();
        let recovered = LabelStore::open(&copy, "run").unwrap();
        let labels = recovered.labels_since(0).unwrap();
        assert_eq!(labels.len(), 1);
        assert_eq!(
            (labels[0].query, labels[0].preference),
            (q.query, Preference::First)
        );
        assert_eq!(recovered.segment(q.second).unwrap().steps, 3);
        // The open query can be asked again, as it was sent.
        assert_eq!(
            recovered.open_queries().unwrap(),
            vec![(
                open.query,
                1_000,
                message(open.query, open.first, open.second)
            )]
        );
        // (Open until here, so that nothing closed it cleanly before the copy.)
        drop(store);
    }
}
