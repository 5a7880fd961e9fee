//! Reading the label store: D, the open queries, the counts, a trajectory's steps.

use anyhow::{bail, Context, Result};
use pbrl_common::wire::Preference;
use rusqlite::OptionalExtension;

use super::{from_blob, int, uint, Blob, Counts, LabelRow, LabelStore, StoredSteps};

impl LabelStore {
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
        // NOTE: a store of an older build opened read-only has no places: pairs only.
        let ranks = if self.rankings { "q.ranks" } else { "NULL" };
        let mut stmt = self
            .conn
            .prepare(&format!(
                "SELECT q.answer_no, q.id, q.session, q.first, q.second, q.answer,
                        q.answered_at_ms,
                        coalesce(q.first_start, 0), coalesce(q.first_len, a.steps),
                        coalesce(q.second_start, 0), coalesce(q.second_len, b.steps), {ranks}
                 FROM queries q
                 JOIN trajectories a ON a.id = q.first
                 JOIN trajectories b ON b.id = q.second
                 WHERE q.answer IN ('first', 'second', 'equal') AND q.answer_no > ?1
                 ORDER BY q.answer_no"
            ))
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
                    r.get::<_, Option<String>>(11)?,
                ))
            })
            .with_context(context)?
            .collect::<rusqlite::Result<Vec<_>>>()
            .with_context(context)?;
        rows.into_iter()
            .map(
                |(
                    answer_no,
                    query,
                    session,
                    first,
                    second,
                    answer,
                    answered_at_ms,
                    bounds,
                    ranks,
                )| {
                    let preference = Preference::parse(&answer).with_context(|| {
                        format!(
                            "query {query} in {} has answer {answer:?}",
                            self.path.display()
                        )
                    })?;
                    let [a0, a1, b0, b1] = bounds.map(|x| x.max(0) as usize);
                    let (more, ranks) = match ranks {
                        Some(r) => (self.more_attempts(query)?, self.places(query, &r)?),
                        None => (Vec::new(), Vec::new()),
                    };
                    Ok(LabelRow {
                        more,
                        ranks,
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

    /// A ranking's attempts after the first two: trajectory ids and segments, in order.
    fn more_attempts(&self, query: u64) -> Result<Vec<(u64, (usize, usize))>> {
        let context = || {
            format!(
                "reading the attempts of query {query} from {}",
                self.path.display()
            )
        };
        let mut stmt = self
            .conn
            .prepare_cached(
                "SELECT trajectory, start, len FROM query_attempts WHERE query = ?1 ORDER BY k",
            )
            .with_context(context)?;
        let rows = stmt
            .query_map([int(query)], |r| {
                Ok((
                    uint(r.get(0)?),
                    (
                        r.get::<_, i64>(1)?.max(0) as usize,
                        r.get::<_, i64>(2)?.max(0) as usize,
                    ),
                ))
            })
            .with_context(context)?
            .collect::<rusqlite::Result<Vec<_>>>()
            .with_context(context)?;
        Ok(rows)
    }

    /// A ranking's places as the store writes them ("1,0,1,2").
    fn places(&self, query: u64, text: &str) -> Result<Vec<u8>> {
        text.split(',')
            .map(|p| p.trim().parse::<u8>())
            .collect::<Result<Vec<u8>, _>>()
            .with_context(|| {
                format!(
                    "query {query} in {} has places {text:?}",
                    self.path.display()
                )
            })
    }

    /// The steps of trajectory `trajectory` (an id from [`Asked`] or [`LabelRow`]).
    pub fn steps(&self, trajectory: u64) -> Result<StoredSteps> {
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
        Ok(StoredSteps {
            steps,
            obs_dim,
            act_dim,
            obs: from_blob(&obs),
            actions: from_blob(&actions),
            features: from_blob(&features),
        })
    }
}
