//! The teacher's file: one SQLite database (WAL, every commit synced) and one connection to
//! it, shared by the [`crate::outbox::Outbox`] and the human [`crate::human::Desk`], so that
//! an answer handed from the desk to the outbox moves in one transaction: it is on exactly
//! one of the two at every moment, whatever stops the teacher.

use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex, MutexGuard};

use anyhow::{Context, Result};
use rusqlite::Connection;

/// The teacher's file, opened once; clones share its connection.
#[derive(Clone)]
pub struct TeacherFile {
    conn: Arc<Mutex<Connection>>,
    path: Arc<PathBuf>,
}

impl TeacherFile {
    /// Open (creating it, and its folder) the teacher's file at `path`. `:memory:` keeps
    /// nothing.
    pub fn open(path: &Path) -> Result<Self> {
        Ok(Self {
            conn: Arc::new(Mutex::new(open_durable(path, "teacher's file")?)),
            path: Arc::new(path.to_path_buf()),
        })
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    /// The connection, for one statement or one transaction. (Held only while SQLite works,
    /// never across an await.)
    pub(crate) fn lock(&self) -> MutexGuard<'_, Connection> {
        // NOTE: a panic while holding it leaves SQLite consistent (an open transaction is
        // rolled back when it drops), so a poisoned lock is still usable.
        self.conn.lock().unwrap_or_else(|e| e.into_inner())
    }
}

/// Open a SQLite file (creating it, and its folder) for a store that must survive a power
/// cut: WAL, and every commit synced. `:memory:` keeps nothing.
pub fn open_durable(path: &Path, what: &str) -> Result<Connection> {
    if path.as_os_str() != ":memory:" {
        if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
            // NOTE: an in-process teacher may start before the learner makes the run folder.
            std::fs::create_dir_all(dir)
                .with_context(|| format!("creating the folder of the {what} {}", path.display()))?;
        }
    }
    let db =
        Connection::open(path).with_context(|| format!("opening the {what} {}", path.display()))?;
    let context = || format!("setting up the {what} {}", path.display());
    if path.as_os_str() != ":memory:" {
        db.pragma_update(None, "journal_mode", "WAL")
            .with_context(context)?;
    }
    db.pragma_update(None, "synchronous", "FULL")
        .with_context(context)?;
    Ok(db)
}

/// The encoding of every query and answer the teacher's file keeps.
pub(crate) fn code() -> bincode::config::Configuration {
    bincode::config::standard()
}

/// An answer as the teacher's file keeps it: this build's layout, or the layout before
/// rankings (which an older build wrote), read as a pair's.
pub fn stored_answer(bytes: &[u8]) -> Result<pbrl_common::wire::Answer> {
    if let Ok((a, n)) =
        bincode::serde::decode_from_slice::<pbrl_common::wire::Answer, _>(bytes, code())
    {
        if n == bytes.len() {
            return Ok(a);
        }
    }
    let (a, _): (pbrl_common::wire::v9::Answer, usize) =
        bincode::serde::decode_from_slice(bytes, code())?;
    Ok(a.upgrade())
}
