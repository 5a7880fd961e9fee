//! The label store's layout (schema 6) and its migrations from older stores.

use anyhow::{bail, Context, Result};
use rusqlite::{params, OptionalExtension};

use super::LabelStore;

/// The layout this build writes and reads (`meta.schema`).
pub const SCHEMA: u32 = 6;

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
    ranks TEXT,
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

/// What schema 6 added to schema 5: a ranking's attempts after the first two, and its
/// places (NULL for every query of an older build: pairs).
const MIGRATE_5_TO_6: &str = "
ALTER TABLE queries ADD COLUMN ranks TEXT;
DROP VIEW IF EXISTS labels;
UPDATE meta SET value = '6' WHERE key = 'schema';
";

/// A ranking's attempts after the first two (attempt `k`, 2 or 3, of query `query`).
const ATTEMPTS: &str = "
CREATE TABLE query_attempts (
    query INTEGER NOT NULL REFERENCES queries (id),
    k INTEGER NOT NULL CHECK (k >= 2),
    trajectory INTEGER NOT NULL REFERENCES trajectories (id),
    start INTEGER NOT NULL,
    len INTEGER NOT NULL CHECK (len > 0),
    PRIMARY KEY (query, k)
);
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
       coalesce(q.second_len, b.steps) AS second_len, q.ranks
FROM queries q
JOIN trajectories a ON a.id = q.first
JOIN trajectories b ON b.id = q.second
WHERE q.answer IN ('first', 'second', 'equal')
ORDER BY q.answer_no;
";

impl LabelStore {
    pub(super) fn check_or_create(&mut self, run: &str) -> Result<()> {
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
            tx.execute_batch(&format!("{CREATE}{ATTEMPTS}{REPEATS}{VIEW}"))
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
            // NOTE: the view is made again at the last step, with every column.
            tx.execute_batch(MIGRATE_2_TO_3)
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
            schema = "5".into();
        }
        if schema == "5" {
            // NOTE: an older build asked pairs only: no attempts beyond two, no places.
            tx.execute_batch(&format!("{MIGRATE_5_TO_6}{ATTEMPTS}{VIEW}"))
                .with_context(|| format!("upgrading label store {} to schema 6", path.display()))?;
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
}
