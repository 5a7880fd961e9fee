//! The SQLite files a run leaves (the learner's label store, a teacher's state) read from
//! outside: with Python's sqlite3 module, read-only, as another tool would (the root package
//! has no SQLite dev-dependency, and `LabelStore` does not show everything a test checks),
//! or through the learner's own `LabelStore`.

use std::path::Path;
use std::process::Command;
use std::time::{Duration, Instant};

use pbrl_learner::pref::labels::LabelStore;
use serde_json::Value;

use super::poll::{poll, poll_async};
use super::proc::tail;

/// argv[1] the file (read-only), argv[2] the query: one JSON object a row.
const PY_SQL: &str = "import json, sqlite3, sys
c = sqlite3.connect('file:' + sys.argv[1] + '?mode=ro', uri=True, timeout=5)
c.row_factory = sqlite3.Row
for r in c.execute(sys.argv[2]): print(json.dumps(dict(r)))";

/// Rows of `query` on the SQLite file `db` as JSON objects, or why not (no file yet, a
/// query SQLite refuses).
pub fn sql(db: &Path, query: &str) -> Result<Vec<Value>, String> {
    if !db.exists() {
        return Err(format!("{} does not exist yet", db.display()));
    }
    let out = Command::new("python3")
        .env("PYTHONDONTWRITEBYTECODE", "1")
        .args(["-c", PY_SQL])
        .arg(db)
        .arg(query)
        .output()
        .map_err(|e| format!("python3 does not run: {e}"))?;
    if !out.status.success() {
        return Err(format!(
            "{} {query:?}: {}",
            db.display(),
            String::from_utf8_lossy(&out.stderr)
        ));
    }
    String::from_utf8_lossy(&out.stdout)
        .lines()
        .map(|l| serde_json::from_str(l).map_err(|e| format!("a row's JSON: {e}: {l}")))
        .collect()
}

/// Wait (at most `secs`) until the label store of `run` at `path` says yes to `ready`;
/// the failure names `what` and ends with the end of `log` (a process's), if any.
pub async fn store_until(
    path: &Path,
    run: &str,
    what: &str,
    secs: u64,
    log: Option<&Path>,
    ready: impl Fn(&LabelStore) -> bool,
) {
    poll_async(
        secs,
        || {
            format!(
                "the label store to hold {what}{}",
                log.map(tail).unwrap_or_default()
            )
        },
        || {
            // NOTE: opened only once the learner made it (opening would make it).
            if !path.exists() {
                return None;
            }
            let store = LabelStore::open(path, run).ok()?;
            ready(&store).then_some(())
        },
    )
    .await
}

/// The human answers in the label store, in the order stored.
pub fn human_answers(db: &Path) -> Result<Vec<Value>, String> {
    sql(
        db,
        "SELECT id, answer, teacher, teacher_id, labeller, took_ms, replays_first, \
         replays_second, shadow FROM queries \
         WHERE teacher = 'human' AND answer IS NOT NULL ORDER BY answer_no",
    )
}

/// Wait until the store holds `n` human answers (panics on more); then check for
/// `hold_s` more seconds that no other comes.
pub fn wait_for_answers(db: &Path, n: usize, secs: u64, hold_s: u64, log: &Path) -> Vec<Value> {
    let last = std::cell::RefCell::new(String::new());
    let rows = poll(
        secs,
        || {
            format!(
                "{n} human answers in the label store (last: {}){}",
                last.borrow(),
                tail(log)
            )
        },
        || match human_answers(db) {
            Ok(rows) => {
                assert!(rows.len() <= n, "more than {n} answers stored: {rows:?}");
                *last.borrow_mut() = format!("{rows:?}");
                (rows.len() == n).then_some(rows)
            }
            Err(e) => {
                *last.borrow_mut() = e;
                None
            }
        },
    );
    // NOTE: polled to a deadline: a check that nothing more arrives, not a timing.
    let until = Instant::now() + Duration::from_secs(hold_s);
    while Instant::now() < until {
        let now = human_answers(db).unwrap();
        assert_eq!(now, rows, "the store changed after holding {n} answers");
        std::thread::sleep(Duration::from_millis(200));
    }
    rows
}

pub fn ids(rows: &[Value]) -> Vec<u64> {
    rows.iter().map(|r| r["id"].as_u64().unwrap()).collect()
}
