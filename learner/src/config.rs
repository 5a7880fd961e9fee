//! The learner's settings, defined once: each swept hyperparameter is a field of a struct
//! that is both a `pbrl train` flag (clap) and the run folder's `config.json` (serde).
//! Presets (the authors' network sizes, PrefPPO's preference defaults, the point task's
//! small networks) change only what the user did not set on the command line.

use std::collections::BTreeSet;
use std::path::PathBuf;

use anyhow::{Context, Result};
use serde::{Deserialize, Serialize};

use crate::ppo::PpoConfig;
use crate::query::Sampler;
use crate::reward::{RewardSource, Schedule};
use crate::reward_model::RewardModelConfig;
use crate::sac::SacConfig;

fn default_max_open() -> u64 {
    200
}

/// The RL backbone.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "kebab-case")]
pub enum Algo {
    Sac,
    Ppo,
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
    fn default() -> Self {
        use clap::Parser;
        #[derive(clap::Parser)]
        struct Defaults {
            #[command(flatten)]
            pref: PrefConfig,
        }
        // NOTE: the defaults are clap's, so the two cannot drift apart; parsing no
        // arguments cannot fail.
        Defaults::parse_from(["pbrl"]).pref
    }
}

/// The learner's settings.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct LearnerConfig {
    pub run: String,
    pub algo: Algo,
    pub reward: RewardSource,
    /// Env steps of the run.
    pub total_steps: u64,
    pub obs_dim: usize,
    pub act_dim: usize,
    pub sac: SacConfig,
    pub ppo: PpoConfig,
    /// Preference learning (used by the `pref` and `decoupled` rewards).
    pub pref: PrefConfig,
    /// The world the actors simulate, with the person's profile (a scripted teacher's
    /// truth is that profile): a resume with another one is refused.
    pub world: serde_json::Value,
    /// SAC: publish new weights every this many gradient steps.
    pub publish_every: u64,
    /// Env steps between rows of the learning curve.
    pub log_every: u64,
    /// Actors feeding this learner (for flow control).
    pub actors: u32,
    /// Env steps of one episode (for flow control).
    pub episode_steps: u32,
    /// Deterministic evaluation episodes at each row of the curve (0: none; the row then
    /// has only the training episodes' figures).
    pub eval_episodes: u32,
    /// Also evaluate the same seeds with sampled actions (the policy as it trains).
    pub eval_sampled: bool,
    /// Env steps between checkpoints (taken at the next weights publication after the
    /// mark); 0: only when the run ends or is stopped.
    pub checkpoint_every: u64,
    /// Also checkpoint when this many seconds have passed since the last (0: off).
    pub checkpoint_secs: u64,
    /// Checkpoints kept (the newest).
    pub keep_checkpoints: usize,
    /// Deterministic mode: each version runs exactly its share of episodes and the next
    /// version waits for all of them, and each feedback session waits for its answers
    /// (with one actor, a run is a function of its seed and its teacher).
    pub sync: bool,
    /// Run folder (`run_folder` has its layout); none in tests.
    pub out: Option<PathBuf>,
    /// Show a progress bar (on a terminal) instead of periodic log lines.
    #[serde(skip)]
    pub progress: bool,
}

impl LearnerConfig {
    /// A config with every default, for `obs_dim` x `act_dim` (tests and benchmarks set
    /// what they need on top).
    pub fn new(
        run: &str,
        algo: Algo,
        reward: RewardSource,
        obs_dim: usize,
        act_dim: usize,
    ) -> Self {
        Self {
            run: run.into(),
            algo,
            reward,
            total_steps: 1_000_000,
            obs_dim,
            act_dim,
            sac: SacConfig::default(),
            ppo: PpoConfig::default(),
            pref: PrefConfig::default(),
            world: serde_json::Value::Null,
            publish_every: 50,
            log_every: 10_000,
            actors: 1,
            episode_steps: 200,
            eval_episodes: 0,
            eval_sampled: false,
            checkpoint_every: 0,
            checkpoint_secs: 0,
            keep_checkpoints: 2,
            sync: false,
            out: None,
            progress: false,
        }
    }

    /// Every value a user might get wrong, each error naming the field and its value.
    pub fn validate(&self) -> Result<()> {
        let p = &self.pref;
        let bad = |field: &str, value: &dyn std::fmt::Display, why: &str| {
            Err(anyhow::anyhow!("{field} is {value}: {why}"))
        };
        let scale = self.sac.reward_scale;
        if !(scale.is_finite() && scale > 0.0) {
            return bad("sac_reward_scale", &scale, "must be a finite number > 0");
        }
        if self.sac.lambda_scale
            && !(self.algo == Algo::Sac && self.reward == RewardSource::Decoupled)
        {
            return bad(
                "sac_lambda_scale",
                &true,
                "scales only SAC's decoupled reward (--algo sac --reward decoupled)",
            );
        }
        if !(p.lambda0.is_finite() && p.lambda0 >= 0.0) {
            return bad("lambda0", &p.lambda0, "must be a finite number >= 0");
        }
        if !(p.rho.is_finite() && (0.0..1.0).contains(&p.rho)) {
            return bad("rho", &p.rho, "must be in [0, 1)");
        }
        if p.queries_per_session == 0 {
            return bad("queries_per_session", &0, "must be at least 1");
        }
        if p.feedback_interval == 0 {
            return bad("feedback_interval", &0, "must be at least 1");
        }
        if p.candidate_factor == 0 {
            return bad("candidate_factor", &0, "must be at least 1");
        }
        if p.knn_k == 0 {
            return bad("knn_k", &0, "must be at least 1");
        }
        if p.annotation_capacity < 2 {
            return bad(
                "annotation_capacity",
                &p.annotation_capacity,
                "must hold at least 2 trajectories",
            );
        }
        if p.model.members == 0 {
            return bad("reward_members", &0, "must be at least 1");
        }
        if self.sac.batch == 0 || self.ppo.minibatch == 0 {
            return bad("sac_batch or ppo_minibatch", &0, "must be at least 1");
        }
        if self.actors == 0 {
            return bad("actors", &0, "must be at least 1");
        }
        Ok(())
    }
}

/// One preset setting: the clap id of the flag, the JSON path of the config field, the
/// value.
pub type Setting = (&'static str, &'static str, serde_json::Value);

/// The authors' settings where the defaults differ (`--preset paper`): their network
/// sizes, their ensemble training unbounded by `max_pairs`, and the linear schedule.
pub fn paper_preset() -> Vec<Setting> {
    use serde_json::json;
    vec![
        ("sac_hidden", "/sac/hidden", json!([512, 512])),
        ("sac_batch", "/sac/batch", json!(512)),
        ("ppo_hidden", "/ppo/hidden", json!([512, 512])),
        (
            "reward_hidden",
            "/pref/model/hidden",
            json!([256, 256, 256]),
        ),
        ("reward_max_pairs", "/pref/model/max_pairs", json!(0)),
        ("lambda_schedule", "/pref/lambda_schedule", json!("linear")),
    ]
}

/// PrefPPO's preference settings (`shared/method.md` sections 3 and 5), applied with the
/// PPO backbone.
pub fn ppo_preset() -> Vec<Setting> {
    use serde_json::json;
    vec![
        ("lambda0", "/pref/lambda0", json!(1.0)),
        ("lambda_schedule", "/pref/lambda_schedule", json!("linear")),
        ("max_feedback", "/pref/max_feedback", json!(10_000)),
        (
            "feedback_interval",
            "/pref/feedback_interval",
            json!(16_000),
        ),
        ("candidate_factor", "/pref/candidate_factor", json!(10)),
        ("unsup_steps", "/pref/unsup_steps", json!(32_000)),
        // NOTE: PPO's sessions come about 3 s apart (16,000 env steps at ~5,000 a second);
        // a 4,096-pair training (about 4 s) would hold every session back.
        ("reward_max_pairs", "/pref/model/max_pairs", json!(1024)),
    ]
}

/// Set each of `settings` the user did not give on the command line (`explicit` holds
/// the clap ids of those given).
pub fn apply_preset(
    cfg: &mut LearnerConfig,
    settings: &[Setting],
    explicit: &BTreeSet<String>,
) -> Result<()> {
    let mut v = serde_json::to_value(&*cfg)?;
    for (id, path, value) in settings {
        if explicit.contains(*id) {
            continue;
        }
        let slot = v
            .pointer_mut(path)
            .with_context(|| format!("preset field {path} is not in the config"))?;
        *slot = value.clone();
    }
    let progress = cfg.progress;
    *cfg = serde_json::from_value(v).context("applying a preset")?;
    cfg.progress = progress;
    Ok(())
}

/// Fields of the config that may change when a run is resumed.
pub const RESUMABLE_FIELDS: &[&str] = &[
    "run",
    "total_steps",
    "actors",
    "checkpoint_every",
    "checkpoint_secs",
    "keep_checkpoints",
    "log_every",
    "eval_episodes",
    "eval_sampled",
    "out",
];

/// Refuse a resume whose config contradicts the stored one (the world and the person's
/// profile included), naming the field and both values.
pub fn check_resume(stored: &serde_json::Value, new: &serde_json::Value) -> Result<()> {
    fn walk(path: &str, a: &serde_json::Value, b: &serde_json::Value) -> Result<()> {
        match (a, b) {
            (serde_json::Value::Object(x), serde_json::Value::Object(y)) => {
                let keys: BTreeSet<&String> = x.keys().chain(y.keys()).collect();
                for k in keys {
                    let sub = if path.is_empty() {
                        k.clone()
                    } else {
                        format!("{path}.{k}")
                    };
                    if path.is_empty() && RESUMABLE_FIELDS.contains(&k.as_str()) {
                        continue;
                    }
                    let null = serde_json::Value::Null;
                    walk(&sub, x.get(k).unwrap_or(&null), y.get(k).unwrap_or(&null))?;
                }
                Ok(())
            }
            _ if a == b => Ok(()),
            _ => anyhow::bail!(
                "cannot resume: {path} is {a} in the stored run and {b} now (start over with --fresh, or change only {})",
                RESUMABLE_FIELDS.join(", ")
            ),
        }
    }
    // A field added since the run began reads as its serde default: the stored config
    // goes through the struct before the walk, so only a real change is refused.
    let upgraded = serde_json::from_value::<LearnerConfig>(stored.clone())
        .ok()
        .and_then(|c| serde_json::to_value(c).ok());
    walk("", upgraded.as_ref().unwrap_or(stored), new)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn presets_change_only_what_the_user_did_not_set() {
        let mut cfg = LearnerConfig::new("r", Algo::Ppo, RewardSource::Decoupled, 4, 2);
        let explicit: BTreeSet<String> = ["lambda0".to_string()].into();
        cfg.pref.lambda0 = 7.0;
        apply_preset(&mut cfg, &ppo_preset(), &explicit).unwrap();
        assert_eq!(cfg.pref.lambda0, 7.0, "set by the user");
        assert_eq!(cfg.pref.feedback_interval, 16_000, "PrefPPO's default");
        assert_eq!(cfg.pref.model.max_pairs, 1024, "PrefPPO's default");
        assert_eq!(
            cfg.pref.lambda_schedule,
            Schedule::Linear,
            "PrefPPO's default"
        );
        let mut sac = LearnerConfig::new("r", Algo::Sac, RewardSource::Decoupled, 4, 2);
        assert_eq!(sac.pref.lambda_schedule, Schedule::Exp, "PEBBLE's default");
        assert_eq!(sac.pref.model.max_pairs, 4096, "PEBBLE's default");
        let explicit: BTreeSet<String> = ["sac_batch".to_string()].into();
        sac.sac.batch = 64;
        apply_preset(&mut sac, &paper_preset(), &explicit).unwrap();
        assert_eq!(
            (sac.sac.hidden.clone(), sac.sac.batch),
            (vec![512, 512], 64)
        );
        assert_eq!(
            sac.pref.model.max_pairs, 0,
            "the authors' unbounded training"
        );
        assert_eq!(
            sac.pref.lambda_schedule,
            Schedule::Linear,
            "the authors' schedule"
        );
    }

    #[test]
    fn a_resume_with_another_person_is_refused() {
        let mut a = LearnerConfig::new("r", Algo::Sac, RewardSource::Pref, 4, 2);
        a.world = serde_json::json!({"profile": {"name": "paper", "weights": [1, 2]}});
        let mut b = a.clone();
        b.world = serde_json::json!({"profile": {"name": "paper", "weights": [1, 3]}});
        let e = check_resume(
            &serde_json::to_value(&a).unwrap(),
            &serde_json::to_value(&b).unwrap(),
        )
        .unwrap_err();
        assert!(e.to_string().contains("world.profile.weights"), "{e}");
        b.world = a.world.clone();
        b.total_steps += 10;
        check_resume(
            &serde_json::to_value(&a).unwrap(),
            &serde_json::to_value(&b).unwrap(),
        )
        .unwrap();
    }

    #[test]
    fn a_stored_config_read_back_resumes() {
        // An f32 field such as the world's eat_distance (0.03) is stored as the f64
        // 0.029999999329447746; serde_json's default float parser read it back one ULP
        // off, and a resume was refused for a field nobody changed.
        let mut a = LearnerConfig::new("r", Algo::Sac, RewardSource::Pref, 4, 2);
        a.world = serde_json::json!({"config": {"eat_distance": 0.03f32, "dt": 0.02f32}});
        let now = serde_json::to_value(&a).unwrap();
        let text = serde_json::to_string_pretty(&now).unwrap();
        let stored: serde_json::Value = serde_json::from_str(&text).unwrap();
        check_resume(&stored, &now).unwrap();
    }

    #[test]
    fn a_field_added_since_the_run_began_reads_as_its_default() {
        let a = LearnerConfig::new("r", Algo::Sac, RewardSource::Decoupled, 4, 2);
        let now = serde_json::to_value(&a).unwrap();
        let mut stored = now.clone();
        let sac = stored["sac"].as_object_mut().unwrap();
        assert_eq!(sac.remove("lambda_scale"), Some(serde_json::json!(false)));
        check_resume(&stored, &now).unwrap();
        // The same field set now, against a run that began without it, is a change.
        let mut b = a.clone();
        b.sac.lambda_scale = true;
        let e = check_resume(&stored, &serde_json::to_value(&b).unwrap()).unwrap_err();
        assert!(e.to_string().contains("sac.lambda_scale is false"), "{e}");
    }

    #[test]
    fn bad_values_are_named() {
        let mut cfg = LearnerConfig::new("r", Algo::Sac, RewardSource::Pref, 4, 2);
        cfg.pref.rho = 1.5;
        let e = cfg.validate().unwrap_err().to_string();
        assert!(e.contains("rho is 1.5"), "{e}");
    }
}
