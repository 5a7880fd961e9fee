//! When the feedback loop acts: a session is due, queries are owed, the ensemble is due a
//! training, the learner waits for labels or keeps time with them; the bounds on open
//! queries and the budget.

use std::time::Instant;

use anyhow::Result;

use super::Feedback;

impl Feedback {
    /// A session is due at `env_steps`.
    pub(super) fn session_due(&self, env_steps: u64) -> Result<bool> {
        Ok(env_steps >= self.counters.next_session_at
            && self.buffer.len() >= 2
            && self.room() > 0
            && !self.frozen()?)
    }

    /// Queries the bounds on open ones leave room for: `max_open_queries` in all, and
    /// `open_per_labeller` for each person at a page (as for one while nobody is, so that
    /// the first to come finds a pair).
    pub(super) fn room(&self) -> u64 {
        let mut bound = match self.cfg.max_open_queries {
            0 => u64::MAX,
            n => n,
        };
        if self.cfg.open_per_labeller > 0 {
            let people = u64::from(self.labellers.max(1));
            bound = bound.min(self.cfg.open_per_labeller.saturating_mul(people));
        }
        bound.saturating_sub(self.in_flight.len() as u64)
    }

    /// Queries the budget still allows, with `spent` counted against it so far
    /// ([`crate::pref::labels::Counts::spent`]).
    pub fn budget_left(&self, spent: u64) -> u64 {
        self.cfg.max_feedback.saturating_sub(spent)
    }

    /// A session is due at `env_steps`, or queries are owed, and they wait for open queries
    /// to be answered (the bound on open queries is reached): the learner is waiting for
    /// labels.
    pub fn waiting(&self, env_steps: u64) -> Result<bool> {
        Ok(
            (env_steps >= self.counters.next_session_at || self.owed > 0)
                && self.room() == 0
                && !self.frozen()?,
        )
    }

    /// Queries are owed and there is room to ask them now (just in time, from the newest
    /// episodes), unless the last try found no pair and no trajectory came since.
    pub(super) fn top_up_due(&self) -> Result<bool> {
        Ok(self.owed > 0
            && self.room() > 0
            && self.buffer.len() >= 2
            && self.top_up_stuck_at != Some(self.observed)
            && !self.frozen()?)
    }

    /// New labels wait for training, and the session that asked them is answered (or the
    /// next one is due).
    pub(super) fn training_due(&self, env_steps: u64) -> bool {
        self.data.len() > self.counters.trained_labels
            && (self.in_flight.is_empty() || env_steps >= self.counters.next_session_at)
    }

    /// Keep time with the teacher (`label_slack_steps`, `label_slack_s`): an answer the
    /// ensemble is not trained on yet (open, or in D) was asked that many env steps or
    /// seconds ago, or more. The learner then stops until it is in and trained on.
    pub fn holds(&self, env_steps: u64, now: Instant) -> bool {
        let (steps, s) = (self.cfg.label_slack_steps, self.cfg.label_slack_s);
        if steps.is_none() && s.is_none() {
            return false;
        }
        let oldest = self
            .in_flight
            .values()
            .map(|f| f.asked)
            .chain(self.untrained_from)
            .min_by_key(|a| a.0);
        oldest.is_some_and(|(at, when)| {
            steps.is_some_and(|k| env_steps >= at.saturating_add(k))
                || s.is_some_and(|k| now.saturating_duration_since(when).as_secs_f64() >= k)
        })
    }

    /// Env steps of the last session held (its queries' start, for those asked again after
    /// a restart).
    pub(super) fn last_session_at(&self) -> u64 {
        if self.counters.sessions == 0 {
            return self.cfg.unsup_steps;
        }
        self.counters
            .next_session_at
            .saturating_sub(self.cfg.feedback_interval)
    }
}
