//! The learning curve (`curve.csv`): one row per `log_every` env steps, written once its
//! evaluation is in, in env-step order. The columns, their CSV header and their format
//! come from one list ([`columns!`]).

use std::collections::VecDeque;
use std::io::Write;
use std::time::Instant;

use anyhow::Result;
use pbrl_common::wire::{EvalRequest, EvalResult};
use pbrl_common::Outcome;
use serde::{Deserialize, Serialize};

use crate::pref::feedback::Feedback;
use crate::pref::reward::TrainReward;
use crate::run::progress::{Progress, Window};

/// The row struct, its CSV header and its CSV line from one list of
/// `name: type => "format"`.
macro_rules! columns {
    ($(#[$m:meta])* pub struct $name:ident { $($(#[$fm:meta])* $field:ident : $ty:ty => $fmt:literal),* $(,)? }) => {
        $(#[$m])*
        pub struct $name { $($(#[$fm])* pub $field: $ty),* }

        impl $name {
            /// The CSV header.
            pub fn header() -> String {
                [$(stringify!($field)),*].join(",")
            }

            /// The row as a CSV line.
            pub fn csv(&self) -> String {
                [$(format!($fmt, self.$field)),*].join(",")
            }
        }
    };
}

columns! {
    /// One row of the learning curve: the training episodes since the previous row, the
    /// evaluation episodes of the weights at `env_steps` (NaN when not run), the losses of
    /// the backbone (NaN for the other backbone's), and preference learning's counters.
    #[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
    pub struct CurveRow {
        env_steps: u64 => "{}",
        wall_s: f64 => "{:.1}",
        eval_episodes: u64 => "{}",
        eval_return_truth: f64 => "{:.4}",
        eval_success_rate: f64 => "{:.4}",
        eval_return_human: f64 => "{:.4}",
        eval_return_task: f64 => "{:.4}",
        eval_version: u64 => "{}",
        /// The same seeds with sampled actions (NaN when not run).
        eval_sampled_return_truth: f64 => "{:.4}",
        eval_sampled_success_rate: f64 => "{:.4}",
        eval_sampled_return_human: f64 => "{:.4}",
        episodes: u64 => "{}",
        return_truth: f64 => "{:.4}",
        success_rate: f64 => "{:.4}",
        return_human: f64 => "{:.4}",
        return_task: f64 => "{:.4}",
        /// SAC.
        loss_critic: f64 => "{:.6}",
        loss_actor: f64 => "{:.6}",
        alpha: f64 => "{:.6}",
        /// PPO.
        loss_value: f64 => "{:.6}",
        loss_policy: f64 => "{:.6}",
        approx_kl: f64 => "{:.6}",
        env_steps_per_s: f64 => "{:.1}",
        updates_per_s: f64 => "{:.2}",
        updates: u64 => "{}",
        policy_version: u64 => "{}",
        dropped_messages: u64 => "{}",
        stale_trajectories: u64 => "{}",
        /// Messages that came again (a trajectory sent again, taken once) or were asked
        /// again (an evaluation, a query), over the run.
        retried_messages: u64 => "{}",
        /// Trajectories known to be missing now (a later one of the same actor arrived).
        lost_messages: u64 => "{}",
        /// Preference learning, over the run: queries asked, answered (equal and skipped
        /// included), answered equal, skipped, expired; feedback sessions.
        labels_asked: u64 => "{}",
        labels_answered: u64 => "{}",
        labels_equal: u64 => "{}",
        labels_skipped: u64 => "{}",
        labels_expired: u64 => "{}",
        sessions: u64 => "{}",
        /// The task reward's weight now (decoupled), 0 otherwise.
        lambda: f64 => "{:.6}",
        /// 1 while pretraining on the state-entropy bonus.
        pretraining: u8 => "{}",
        /// The ensemble's accuracy on all of D after its last training, and on the newest
        /// labels before it trained on them (NaN before any).
        reward_accuracy: f64 => "{:.4}",
        reward_accuracy_new: f64 => "{:.4}",
        /// How well r_hat tracks the ground truth on the newest training episodes: Pearson
        /// correlation of per-step r_hat with r, and of episode sums (NaN before a model).
        rhat_step_corr: f64 => "{:.4}",
        rhat_return_corr: f64 => "{:.4}",
        /// Queries waiting for an answer now; 1 while a feedback session is due and waits
        /// for them (the learner is waiting for labels; training goes on); people
        /// labelling now.
        labels_open: u64 => "{}",
        waiting_labels: u8 => "{}",
        labellers: u64 => "{}",
        /// Per-step correlation of r_hat, on the evaluation episodes, with the preference
        /// part r_H alone and with the task part r_task (the truth r = robot + r_H; NaN
        /// before a model).
        rhat_step_corr_human: f64 => "{:.4}",
        rhat_step_corr_task: f64 => "{:.4}",
    }
}

impl CurveRow {
    /// A row with no figures yet (counters 0, figures NaN).
    pub fn empty(env_steps: u64) -> Self {
        let nan = f64::NAN;
        Self {
            env_steps,
            wall_s: 0.0,
            eval_episodes: 0,
            eval_return_truth: nan,
            eval_success_rate: nan,
            eval_return_human: nan,
            eval_return_task: nan,
            eval_version: 0,
            eval_sampled_return_truth: nan,
            eval_sampled_success_rate: nan,
            eval_sampled_return_human: nan,
            episodes: 0,
            return_truth: nan,
            success_rate: nan,
            return_human: nan,
            return_task: nan,
            loss_critic: nan,
            loss_actor: nan,
            alpha: nan,
            loss_value: nan,
            loss_policy: nan,
            approx_kl: nan,
            env_steps_per_s: 0.0,
            updates_per_s: 0.0,
            updates: 0,
            policy_version: 0,
            dropped_messages: 0,
            stale_trajectories: 0,
            retried_messages: 0,
            lost_messages: 0,
            labels_asked: 0,
            labels_answered: 0,
            labels_equal: 0,
            labels_skipped: 0,
            labels_expired: 0,
            sessions: 0,
            lambda: 0.0,
            pretraining: 0,
            reward_accuracy: nan,
            reward_accuracy_new: nan,
            rhat_step_corr: nan,
            rhat_return_corr: nan,
            labels_open: 0,
            waiting_labels: 0,
            labellers: 0,
            rhat_step_corr_human: nan,
            rhat_step_corr_task: nan,
        }
    }
}

impl CurveRow {
    /// The row at `p.env_steps`: the training episodes of `window`, the loop's counters
    /// and speeds, the reward's state and preference learning's counters. `dropped`: the
    /// run's one count of messages dropped ([`crate::run::learner::Learner::dropped`]).
    pub fn at(
        p: &Progress,
        window: Window,
        clock: &Clock,
        reward: &TrainReward,
        feedback: Option<&Feedback>,
        dropped: u64,
        labellers: u64,
    ) -> Result<Self> {
        let here = clock.start.elapsed().as_secs_f64().max(1e-9);
        let n = window.episodes.max(1) as f64;
        let mut row = CurveRow {
            wall_s: clock.wall_s(p).max(1e-9),
            episodes: window.episodes,
            return_truth: window.truth / n,
            success_rate: window.success / n,
            return_human: window.human / n,
            return_task: window.task / n,
            loss_critic: p.losses.critic,
            loss_actor: p.losses.actor,
            alpha: p.losses.alpha,
            loss_value: p.losses.value,
            loss_policy: p.losses.policy,
            approx_kl: p.losses.approx_kl,
            env_steps_per_s: (p.env_steps - clock.env_steps_at) as f64 / here,
            updates_per_s: (p.updates - clock.updates_at) as f64 / here,
            updates: p.updates,
            policy_version: p.version,
            dropped_messages: dropped,
            stale_trajectories: p.stale,
            retried_messages: p.receipts.repeated + p.eval_retries,
            lost_messages: p.receipts.missing(),
            lambda: reward.lambda(p.env_steps),
            pretraining: reward.pretraining() as u8,
            ..CurveRow::empty(p.env_steps)
        };
        if let Some(f) = feedback {
            let c = f.counts()?;
            row.labels_asked = c.asked;
            row.labels_answered = c.answered;
            row.labels_equal = c.equal;
            row.labels_skipped = c.skipped;
            row.labels_expired = c.expired;
            row.sessions = f.counters.sessions;
            row.reward_accuracy = f.counters.accuracy;
            row.reward_accuracy_new = f.counters.accuracy_new;
            row.retried_messages += f.counters.retried_queries;
            row.labels_open = c.open;
            row.waiting_labels = f.waiting(p.env_steps)? as u8;
            row.labellers = labellers;
        }
        Ok(row)
    }
}

/// The run's clock: the wall time of the processes before this one, and where this one
/// started (its speeds count from there).
pub struct Clock {
    pub start: Instant,
    pub env_steps_at: u64,
    pub updates_at: u64,
}

impl Clock {
    pub fn new(p: &Progress) -> Self {
        Self {
            start: Instant::now(),
            env_steps_at: p.env_steps,
            updates_at: p.updates,
        }
    }

    /// Wall time of the whole run so far.
    pub fn wall_s(&self, p: &Progress) -> f64 {
        p.wall_s + self.start.elapsed().as_secs_f64()
    }
}

/// The progress bar of a run of `total` env steps now at `at`: figures rounded for people.
pub fn progress_bar(total: u64, at: u64) -> indicatif::ProgressBar {
    let bar = indicatif::ProgressBar::new(total);
    let rate = |s: &indicatif::ProgressState, w: &mut dyn std::fmt::Write| {
        // NOTE: the write can only fail if the bar's buffer does; nothing to do then.
        let _ = write!(w, "{}/s", indicatif::HumanCount(s.per_sec().round() as u64));
    };
    bar.set_style(
        indicatif::ProgressStyle::with_template(
            "{elapsed_precise} [{bar:30}] {human_pos}/{human_len} env steps, {rate}, {eta} left, {msg}",
        )
        .expect("the progress template is valid")
        .with_key("rate", rate)
        .progress_chars("=> "),
    );
    bar.set_position(at.min(total));
    bar.reset_eta();
    *lock_bar() = Some(bar.clone());
    bar
}

/// The log target of the curve's lines (one per row).
pub const CURVE_TARGET: &str = "pbrl::curve";

/// The bar on the terminal now, if any: the log's stderr writer draws around it.
static SHOWN_BAR: std::sync::Mutex<Option<indicatif::ProgressBar>> = std::sync::Mutex::new(None);

fn lock_bar() -> std::sync::MutexGuard<'static, Option<indicatif::ProgressBar>> {
    // NOTE: a panic while holding it cannot leave the Option half-written.
    SHOWN_BAR.lock().unwrap_or_else(|e| e.into_inner())
}

/// The log's writer for stderr: each line is written with the progress bar taken off the
/// screen and drawn again after it ([`indicatif::ProgressBar::suspend`]), so a warning
/// never leaves a stale copy of the bar in the scrollback. Without a bar, plain stderr.
#[derive(Clone, Copy, Debug, Default)]
pub struct AroundTheBar;

impl std::io::Write for AroundTheBar {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        self.write_all(buf)?;
        Ok(buf.len())
    }

    fn write_all(&mut self, buf: &[u8]) -> std::io::Result<()> {
        let bar = lock_bar().clone();
        match bar.filter(|b| !b.is_finished() && !b.is_hidden()) {
            Some(bar) => bar.suspend(|| std::io::stderr().write_all(buf)),
            None => std::io::stderr().write_all(buf),
        }
    }

    fn flush(&mut self) -> std::io::Result<()> {
        std::io::stderr().flush()
    }
}

impl<'a> tracing_subscriber::fmt::MakeWriter<'a> for AroundTheBar {
    type Writer = AroundTheBar;

    fn make_writer(&'a self) -> Self::Writer {
        *self
    }
}

/// How well a learnt reward tracks the ground truth on an evaluation's episodes (Pearson
/// correlations; NaN where undefined).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Tracking {
    /// r_hat with r, per step.
    pub step: f64,
    /// r_hat with the preference part r_H alone, and with the task part r_task, per step.
    pub step_human: f64,
    pub step_task: f64,
    /// Episode sums of r_hat with those of r.
    pub sum: f64,
}

/// A row waiting for its evaluation.
pub struct Pending {
    pub row: CurveRow,
    pub request: EvalRequest,
    pub sent: Instant,
    pub tries: u32,
}

/// The learning curve: rows in env-step order, each written once its evaluation is in.
pub struct Curve {
    pub file: Option<std::fs::File>,
    /// Rows in the file, over the whole run.
    pub written: u64,
    pub pending: VecDeque<Pending>,
    pub bar: Option<indicatif::ProgressBar>,
    /// The rows written by this process.
    pub rows: Vec<CurveRow>,
    /// Evaluations dropped for the wrong number of episodes.
    pub dropped: u64,
}

impl Curve {
    pub fn new(
        file: Option<std::fs::File>,
        written: u64,
        bar: Option<indicatif::ProgressBar>,
    ) -> Self {
        Self {
            file,
            written,
            pending: VecDeque::new(),
            bar,
            rows: Vec::new(),
            dropped: 0,
        }
    }

    pub fn write(&mut self, row: CurveRow) -> Result<()> {
        let sampled = if row.eval_sampled_success_rate.is_nan() {
            String::new()
        } else {
            format!(
                " (sampled actions: {:.0}%)",
                100.0 * row.eval_sampled_success_rate
            )
        };
        let labels = if row.labels_asked > 0 || row.pretraining > 0 {
            format!(
                "; labels {}/{}{}{}{}",
                row.labels_answered,
                row.labels_asked,
                if row.pretraining > 0 {
                    ", pretraining"
                } else {
                    ""
                },
                if row.waiting_labels > 0 {
                    format!(", waiting for labels ({} open)", row.labels_open)
                } else {
                    String::new()
                },
                match row.labellers {
                    0 => String::new(),
                    1 => ", 1 person labelling".to_string(),
                    n => format!(", {n} people labelling"),
                }
            )
        } else {
            String::new()
        };
        let line = format!(
            "{} env steps: eval return {:.1}, success {:.0}%{sampled} ({} episodes, v{}); training return {:.1}, success {:.0}%, {:.0} env steps/s{labels}",
            row.env_steps,
            row.eval_return_truth,
            100.0 * row.eval_success_rate,
            row.eval_episodes,
            row.eval_version,
            row.return_truth,
            100.0 * row.success_rate,
            row.env_steps_per_s,
        );
        // NOTE: the row goes to the log under its own target, which the terminal shows
        // only where there is no bar (main.rs); on a terminal the bar prints it.
        tracing::info!(target: CURVE_TARGET, "{line}");
        if let Some(bar) = &self.bar {
            bar.println(&line);
            bar.set_message(format!(
                "eval success {:.0}%, return {:.1}",
                100.0 * row.eval_success_rate,
                row.eval_return_truth
            ));
        }
        if let Some(f) = self.file.as_mut() {
            writeln!(f, "{}", row.csv())?;
            f.flush()?;
        }
        self.written += 1;
        self.rows.push(row);
        Ok(())
    }

    /// Fill in an evaluation's figures, then write every row that is complete in order.
    /// `tracking`: the learnt reward's correlations with the truth on the evaluation's
    /// episodes (per step, per episode sum), when there is one.
    pub fn complete(&mut self, r: EvalResult, tracking: Option<Tracking>) -> Result<()> {
        let Some(p) = self.pending.iter_mut().find(|p| p.request.id == r.id) else {
            tracing::debug!(id = r.id, "an evaluation answered twice or after its row");
            return Ok(());
        };
        let seeds = p.request.seeds.len();
        let sampled = if p.request.sampled { seeds } else { 0 };
        if r.episodes.len() != seeds || r.sampled.len() != sampled {
            self.dropped += 1;
            tracing::warn!(
                id = r.id,
                actor = r.actor,
                found = r.episodes.len(),
                found_sampled = r.sampled.len(),
                expected = seeds,
                expected_sampled = sampled,
                "dropped an evaluation with the wrong number of episodes"
            );
            return Ok(());
        }
        if p.row.eval_episodes > 0 {
            tracing::debug!(id = r.id, "an evaluation answered twice");
            return Ok(());
        }
        type Of = dyn Fn(&Outcome) -> f64;
        let mean = |xs: &[Outcome], f: &Of| {
            if xs.is_empty() {
                f64::NAN
            } else {
                xs.iter().map(f).sum::<f64>() / xs.len() as f64
            }
        };
        let (truth, success, human): (&Of, &Of, &Of) = (
            &|o| o.return_truth as f64,
            &|o| o.success as u8 as f64,
            &|o| o.return_human as f64,
        );
        p.row.eval_episodes = r.episodes.len() as u64;
        p.row.eval_return_truth = mean(&r.episodes, truth);
        p.row.eval_success_rate = mean(&r.episodes, success);
        p.row.eval_return_human = mean(&r.episodes, human);
        p.row.eval_return_task = mean(&r.episodes, &|o| o.return_task as f64);
        p.row.eval_sampled_return_truth = mean(&r.sampled, truth);
        p.row.eval_sampled_success_rate = mean(&r.sampled, success);
        p.row.eval_sampled_return_human = mean(&r.sampled, human);
        p.row.eval_version = r.version;
        if let Some(t) = tracking {
            p.row.rhat_step_corr = t.step;
            p.row.rhat_return_corr = t.sum;
            p.row.rhat_step_corr_human = t.step_human;
            p.row.rhat_step_corr_task = t.step_task;
        }
        self.write_ready()
    }

    /// Write the rows at the front that are evaluated.
    pub fn write_ready(&mut self) -> Result<()> {
        while let Some(p) = self.pending.pop_front() {
            if p.row.eval_episodes == 0 {
                self.pending.push_front(p);
                break;
            }
            self.write(p.row)?;
        }
        Ok(())
    }

    /// Write every pending row as it is (an evaluation not answered stays NaN).
    pub fn flush(&mut self) -> Result<()> {
        while let Some(p) = self.pending.pop_front() {
            self.write(p.row)?;
        }
        Ok(())
    }

    /// The run is over: the bar says it finished, or where it was stopped (it stays
    /// there, not at the total).
    pub fn end_bar(&self, stopped_at: Option<u64>) {
        let Some(bar) = &self.bar else {
            return;
        };
        match stopped_at {
            None => bar.finish(),
            Some(env_steps) => bar.abandon_with_message(format!(
                "stopped at {} env steps (the same command resumes)",
                indicatif::HumanCount(env_steps)
            )),
        }
    }
}

/// Pearson correlation of `a` and `b` (NaN when either is constant or they are empty).
pub fn correlation(a: &[f64], b: &[f64]) -> f64 {
    let n = a.len().min(b.len());
    if n < 2 {
        return f64::NAN;
    }
    let (ma, mb) = (
        a[..n].iter().sum::<f64>() / n as f64,
        b[..n].iter().sum::<f64>() / n as f64,
    );
    let (mut sab, mut saa, mut sbb) = (0.0, 0.0, 0.0);
    for (x, y) in a[..n].iter().zip(&b[..n]) {
        sab += (x - ma) * (y - mb);
        saa += (x - ma) * (x - ma);
        sbb += (y - mb) * (y - mb);
    }
    if saa <= 0.0 || sbb <= 0.0 {
        return f64::NAN;
    }
    sab / (saa * sbb).sqrt()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn header_and_line_have_the_same_columns() {
        let row = CurveRow::empty(5);
        assert_eq!(
            CurveRow::header().split(',').count(),
            row.csv().split(',').count()
        );
        assert!(CurveRow::header().starts_with("env_steps,wall_s,"));
    }

    #[test]
    fn the_bar_rounds_its_rate_and_a_stop_says_where_the_run_stopped() {
        let term = indicatif::InMemoryTerm::new(4, 160);
        let bar = progress_bar(1_000_000, 0);
        bar.set_draw_target(indicatif::ProgressDrawTarget::term_like(Box::new(
            term.clone(),
        )));
        for at in (0..=23_400).step_by(600) {
            bar.set_position(at);
        }
        let curve = Curve::new(None, 0, Some(bar));
        curve.end_bar(Some(23_400));
        let shown = term.contents();
        assert!(shown.contains("23,400/1,000,000 env steps"), "{shown}");
        assert!(shown.contains("stopped at 23,400 env steps"), "{shown}");
        assert!(!shown.contains("1,000,000/1,000,000"), "{shown}");
        let rate = shown
            .split(" env steps, ")
            .nth(1)
            .and_then(|r| r.split("/s").next())
            .unwrap_or_default();
        assert!(
            !rate.is_empty() && rate.chars().all(|c| c.is_ascii_digit() || c == ','),
            "a rounded rate: {rate:?} in {shown}"
        );
    }

    #[test]
    fn correlation_of_known_series() {
        // Reference: numpy.corrcoef([1, 2, 3, 4], [2, 4, 5, 9])[0, 1] = 11 / sqrt(5 * 26) = 0.964764...
        let c = correlation(&[1.0, 2.0, 3.0, 4.0], &[2.0, 4.0, 5.0, 9.0]);
        assert!((c - 0.964_764).abs() < 1e-5, "{c}");
        assert!(correlation(&[1.0, 1.0], &[2.0, 3.0]).is_nan());
    }
}
