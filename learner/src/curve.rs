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
        }
    }
}

/// Episode statistics accumulated between curve rows.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct Window {
    pub episodes: u64,
    pub truth: f64,
    pub success: f64,
    pub human: f64,
    pub task: f64,
}

impl Window {
    pub fn add(&mut self, o: &Outcome) {
        self.episodes += 1;
        self.truth += o.return_truth as f64;
        self.human += o.return_human as f64;
        self.task += o.return_task as f64;
        self.success += o.success as u8 as f64;
    }
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
        match &self.bar {
            Some(bar) => {
                bar.println(&line);
                bar.set_message(format!(
                    "eval success {:.0}%, return {:.1}",
                    100.0 * row.eval_success_rate,
                    row.eval_return_truth
                ));
            }
            None => tracing::info!("{line}"),
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
    pub fn complete(&mut self, r: EvalResult, tracking: Option<(f64, f64)>) -> Result<()> {
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
        if let Some((step, sum)) = tracking {
            p.row.rhat_step_corr = step;
            p.row.rhat_return_corr = sum;
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
    fn correlation_of_known_series() {
        // Reference: numpy.corrcoef([1, 2, 3, 4], [2, 4, 5, 9])[0, 1] = 11 / sqrt(5 * 26) = 0.964764...
        let c = correlation(&[1.0, 2.0, 3.0, 4.0], &[2.0, 4.0, 5.0, 9.0]);
        assert!((c - 0.964_764).abs() < 1e-5, "{c}");
        assert!(correlation(&[1.0, 1.0], &[2.0, 3.0]).is_nan());
    }
}
