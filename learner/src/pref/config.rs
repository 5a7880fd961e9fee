//! Preference learning's settings (`shared/method.md` sections 1-5): one struct that is
//! both `pbrl train`'s flags (clap) and the run folder's `config.json` (serde).

use serde::{Deserialize, Serialize};

use crate::pref::query::Sampler;
use crate::pref::reward_model::RewardModelConfig;

fn default_max_open() -> u64 {
    200
}

fn one() -> f64 {
    1.0
}

fn guard_gain() -> f64 {
    9.0
}

/// How lambda_t decays (paper Eq. 4-5).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "kebab-case")]
pub enum Schedule {
    /// lambda_0 (T - t) / T.
    Linear,
    /// lambda_0 (1 - rho)^t.
    Exp,
}

/// Preference learning (`shared/method.md` sections 1-5). The defaults are PEBBLE's; the
/// PPO backbone's (PrefPPO) apply where the user did not set a value ([`ppo_preset`]).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, clap::Args)]
pub struct PrefConfig {
    /// Decoupled: the task reward's weight at the start, lambda_0 (PEBBLE 15, PrefPPO 1).
    #[arg(long, default_value_t = 15.0)]
    pub lambda0: f64,
    /// Decoupled: how lambda_t decays: linear, lambda_0 (T - t) / T, or exponential,
    /// lambda_0 (1 - rho)^t (t: env steps so far, T: the run's env steps). The default is
    /// exponential for PEBBLE (measured on feeding: over a 1M-step run the linear schedule
    /// takes the task away as lambda_t nears 0, and success falls with it); the authors'
    /// linear one is PrefPPO's default and `--preset paper`'s.
    #[arg(long, value_enum, default_value = "exp")]
    pub lambda_schedule: Schedule,
    /// Decoupled: the exponential schedule's rate (3e-7: lambda_t is 0.74 lambda_0 at 1M
    /// env steps; measured on feeding at 200 labels, 3 seeds at 1M env steps: success
    /// 0.66 where 1e-6, lambda_0 / e at 1M, gives 0.23; `results/pref/README.md`).
    #[arg(long, default_value_t = 3e-7)]
    pub rho: f64,
    /// Decoupled: the task guard (`docs/people.md`): while the success of
    /// the newest 100 training episodes is below this share of the best the run reached,
    /// lambda_t is raised (0: off), so the task is never traded away for the taste.
    #[arg(long, default_value_t = 0.0)]
    #[serde(default)]
    pub task_guard: f64,
    /// Decoupled: the task guard's gain: lambda_t is multiplied by up to 1 + this, when no
    /// training episode feeds.
    #[arg(long, default_value_t = 9.0)]
    #[serde(default = "guard_gain")]
    pub task_guard_gain: f64,
    /// How queries are chosen among the candidates (the first session is always uniform).
    #[arg(long, value_enum, default_value = "disagreement")]
    pub sampler: Sampler,
    /// Start the reward ensemble from a prior learnt from other people's answers (a file
    /// of `pbrl prior`): its weights and normaliser; this person's answers adapt it, and it
    /// is the reward from the end of the pretraining on.
    #[arg(long)]
    #[serde(default)]
    pub prior: Option<std::path::PathBuf>,
    /// Attempts each query shows: 2 asks which of two was better (B-Pref's pairs); 3 or 4
    /// ask the teacher to rank them, ties allowed, as one answer (learnt from as all its
    /// pairs). A ranking counts once against the budget.
    #[arg(long, default_value_t = 2)]
    #[serde(default = "two")]
    pub query_attempts: usize,
    /// Queries in all (the budget; skipped ones count). Then the reward model is frozen.
    /// The default is what a person gives in one sitting of about a quarter of an hour;
    /// `--preset paper` keeps the authors' 50,000 (PrefPPO 10,000).
    #[arg(long, default_value_t = 200)]
    pub max_feedback: u64,
    /// Queries asked per feedback session (with `--feedback-span`, the budget's schedule
    /// sets each session's size instead).
    #[arg(long, default_value_t = 100)]
    pub queries_per_session: u64,
    /// Spread the whole budget (`--max-feedback`) over the feedback sessions of this many
    /// env steps after the pretraining (0: `--queries-per-session` each session until the
    /// budget is spent). A person's budget is then asked while it can still shape the
    /// policy, whatever its size.
    #[arg(long, default_value_t = 240_000)]
    #[serde(default)]
    pub feedback_span: u64,
    /// With `--feedback-span`: each session asks this share of the one before (1: all
    /// alike; below 1: more and earlier, then fewer).
    #[arg(long, default_value_t = 0.95)]
    #[serde(default = "one")]
    pub feedback_decay: f64,
    /// Env steps between feedback sessions.
    #[arg(long, default_value_t = 6_000)]
    pub feedback_interval: u64,
    /// Candidate pairs per query (disagreement and entropy keep the best of them).
    #[arg(long, default_value_t = 50)]
    pub candidate_factor: u64,
    /// Env steps of unsupervised pretraining on the k-NN state-entropy bonus; the first
    /// feedback session comes at its end.
    #[arg(long, default_value_t = 10_000)]
    pub unsup_steps: u64,
    /// k of the k-NN state-entropy bonus.
    #[arg(long, default_value_t = 5)]
    pub knn_k: usize,
    /// Raw observations the state-entropy bonus compares with (the newest).
    #[arg(long, default_value_t = 10_000)]
    pub knn_pool: usize,
    /// Trajectories kept for queries (the annotation buffer; the oldest leave first).
    #[arg(long, default_value_t = 10_000)]
    pub annotation_capacity: usize,
    /// An unanswered query is asked again after this many seconds.
    #[arg(long, default_value_t = 10)]
    pub query_retry_s: u64,
    /// An unanswered query expires after this many seconds (0: never); it stays in the
    /// label store as expired and still counts against the budget.
    #[arg(long, default_value_t = 0)]
    pub query_expiry_s: u64,
    /// At most this many queries wait for answers at once (0: no bound); a session that is
    /// due waits for answers (a person's pace) and asks only what the bound leaves. Training
    /// goes on meanwhile with the reward model it has.
    #[arg(long, default_value_t = 200)]
    #[serde(default = "default_max_open")]
    pub max_open_queries: u64,
    /// With people: at most this many queries are open per person at a labelling page
    /// (counted by their liveliness tokens; as for one while nobody is there), so that a
    /// pair is chosen when a person is ready for one, from the newest episodes, by the
    /// session's sampler; a session's queries that find no room are asked as room appears
    /// (0: only `--max-open-queries`; `--teacher human`: 3).
    #[arg(long, default_value_t = 0)]
    #[serde(default)]
    pub open_per_labeller: u64,
    /// An unanswered query is stale this many env steps after it was asked: withdrawn (the
    /// label store keeps it as withdrawn and does not count it against the budget; an
    /// answer that still comes is stored as late) and a fresh one asked in its place, and a
    /// teacher offers it to nobody new (0: never; `--teacher human`: 20,000).
    #[arg(long, default_value_t = 0)]
    #[serde(default)]
    pub query_stale_steps: u64,
    /// Keep time with the teacher: the learner runs at most this many env steps past a
    /// feedback session whose answers are not all in and trained on, then stops (no
    /// training, no new weights, the actors idle) until they are (0: it stops at the
    /// session; unset: it never waits, the default). The sitting's pace then bounds the
    /// run's, and no session's answers come too late to shape the policy.
    #[arg(long)]
    #[serde(default)]
    pub label_slack_steps: Option<u64>,
    /// Keep time with the teacher, in seconds: the learner runs at most this long past a
    /// feedback session whose answers are not all in and trained on, then stops until
    /// they are (with `--label-slack-steps`, whichever comes first; unset: never).
    #[arg(long)]
    #[serde(default)]
    pub label_slack_s: Option<f64>,
    /// A trajectory is in at most this many open queries at once (0: no bound; `--teacher
    /// human`: 1), so that a person is not shown the same attempt over and over.
    #[arg(long, default_value_t = 0)]
    #[serde(default)]
    pub queries_per_trajectory: u64,
    /// Steps of each side of a query: a segment of each trajectory (B-Pref: 50; 0: whole
    /// trajectories, the authors' and the presets'; a trajectory shorter than this is shown
    /// whole). One label then says which of two short stretches was better, which gives
    /// the reward model credit near the steps that made the difference.
    #[arg(long, default_value_t = 50)]
    #[serde(default)]
    pub segment_len: usize,
    /// Where a segment starts: uniform over the trajectory (B-Pref), or at its end.
    #[arg(long, value_enum, default_value = "uniform")]
    #[serde(default)]
    pub segment_start: SegmentStart,
    /// Candidate pairs come from the newest this-many trajectories of the annotation
    /// buffer (QPA's policy-aligned queries: the person judges what the policy does now;
    /// 0: the whole buffer, B-Pref).
    #[arg(long, default_value_t = 10)]
    #[serde(default)]
    pub query_recent: usize,
    /// Unlabelled pairs drawn at each training of the ensemble (after the first) and
    /// trained on with the ensemble's own answer where it is sure (SURF's pseudo-labels;
    /// 0: off). They are never stored and never count against the budget.
    #[arg(long, default_value_t = 0)]
    #[serde(default)]
    pub pseudo_pairs: usize,
    /// How sure the ensemble must be for a pseudo-label: its mean P of the preferred side
    /// at least this (SURF: 0.95 to 0.99).
    #[arg(long, default_value_t = 0.95)]
    #[serde(default = "pseudo_tau")]
    pub pseudo_tau: f64,
    #[command(flatten)]
    pub model: RewardModelConfig,
}

fn two() -> usize {
    2
}

fn pseudo_tau() -> f64 {
    0.95
}

/// Where a query's segment starts in its trajectory.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "kebab-case")]
pub enum SegmentStart {
    /// Uniform over the starts that fit (B-Pref), drawn for each side apart.
    #[default]
    Uniform,
    /// The trajectory's last steps (where a feeding attempt meets the mouth).
    End,
}

impl PrefConfig {
    /// Queries session `session` (1, 2, ...) asks with `asked` asked before it: with a
    /// span, the budget's share of the sessions so far less what was asked (a late or
    /// short session's queries come later; after the span, all that is left); else
    /// `queries_per_session`. Never more than the budget leaves.
    pub fn session_queries(&self, session: u64, asked: u64) -> u64 {
        let left = self.max_feedback.saturating_sub(asked);
        if self.feedback_span == 0 {
            return self.queries_per_session.min(left);
        }
        let sessions = self.feedback_span / self.feedback_interval.max(1) + 1;
        if session >= sessions {
            return left;
        }
        let d = self.feedback_decay;
        let weight = |k: u64| d.powi(k as i32);
        let total: f64 = (0..sessions).map(weight).sum();
        let upto: f64 = (0..session).map(weight).sum();
        let target = (self.max_feedback as f64 * upto / total).round() as u64;
        target.saturating_sub(asked).min(left)
    }
}

impl Default for PrefConfig {
    /// Every field at its flag's default.
    fn default() -> Self {
        pbrl_common::flags::defaults()
    }
}

impl PrefConfig {
    /// The defaults with the label-efficiency pieces off (whole trajectories, queries from
    /// the whole annotation buffer, fixed session sizes, the rate of lambda_t before issue
    /// 23, [`RewardModelConfig::plain`]): the authors' method, what the presets run.
    pub fn plain() -> Self {
        Self {
            rho: 1e-6,
            segment_len: 0,
            query_recent: 0,
            feedback_span: 0,
            feedback_decay: 1.0,
            pseudo_pairs: 0,
            model: RewardModelConfig::plain(),
            ..Self::default()
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_budget_schedule_spends_the_budget_within_its_span_front_first() {
        let cfg = |span, decay| PrefConfig {
            max_feedback: 200,
            feedback_interval: 6_000,
            feedback_span: span,
            feedback_decay: decay,
            ..PrefConfig::default()
        };
        // No span: the fixed session size until the budget is spent.
        let fixed = cfg(0, 1.0);
        assert_eq!(fixed.session_queries(1, 0), 100);
        assert_eq!(fixed.session_queries(3, 150), 50);
        // 114,000 env steps at 6,000 a session: 20 sessions of 10.
        let even = cfg(114_000, 1.0);
        let mut asked = 0;
        let sizes: Vec<u64> = (1..=20)
            .map(|s| {
                let k = even.session_queries(s, asked);
                asked += k;
                k
            })
            .collect();
        assert_eq!(sizes, vec![10; 20]);
        assert_eq!(even.session_queries(21, asked), 0, "the budget is spent");
        // Front-loaded: each session 0.8 of the one before, all 200 within the span.
        let front = cfg(114_000, 0.8);
        let mut asked = 0;
        let sizes: Vec<u64> = (1..=20)
            .map(|s| {
                let k = front.session_queries(s, asked);
                asked += k;
                k
            })
            .collect();
        assert_eq!(asked, 200);
        assert_eq!(sizes[0], 40, "{sizes:?}");
        assert!(sizes.windows(2).all(|w| w[0] + 1 >= w[1]), "{sizes:?}");
        // A session that asked too few (the open bound): the next makes it up.
        assert_eq!(even.session_queries(2, 4), 16);
        // Past the span: everything left.
        assert_eq!(even.session_queries(25, 150), 50);
    }
}
