//! Preference learning's settings (`shared/method.md` sections 1-5): one struct that is
//! both `pbrl train`'s flags (clap) and the run folder's `config.json` (serde).

use serde::{Deserialize, Serialize};

use crate::pref::query::Sampler;
use crate::pref::reward::Schedule;
use crate::pref::reward_model::RewardModelConfig;

fn default_max_open() -> u64 {
    200
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
    /// Decoupled: the exponential schedule's rate (1e-6: lambda_t is lambda_0 / e at 1M
    /// env steps).
    #[arg(long, default_value_t = 1e-6)]
    pub rho: f64,
    /// How queries are chosen among the candidates (the first session is always uniform).
    #[arg(long, value_enum, default_value = "disagreement")]
    pub sampler: Sampler,
    /// Queries in all (the budget; skipped ones count). Then the reward model is frozen.
    #[arg(long, default_value_t = 50_000)]
    pub max_feedback: u64,
    /// Queries asked per feedback session.
    #[arg(long, default_value_t = 100)]
    pub queries_per_session: u64,
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
    #[command(flatten)]
    pub model: RewardModelConfig,
}

impl Default for PrefConfig {
    /// Every field at its flag's default.
    fn default() -> Self {
        crate::flags::defaults()
    }
}
