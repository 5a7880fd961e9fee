//! The learner's settings, defined once: each swept hyperparameter is a field of a struct
//! that is both a `pbrl train` flag (clap) and the run folder's `config.json` (serde).
//! Presets (the authors' network sizes, PrefPPO's preference defaults, the point task's
//! small networks) change only what the user did not set on the command line.

use std::collections::BTreeSet;
use std::path::PathBuf;

use anyhow::{Context, Result};
use serde::{Deserialize, Serialize};

pub use crate::pref::config::PrefConfig;
use crate::pref::reward::RewardSource;
use crate::rl::ppo::PpoConfig;
use crate::rl::sac::SacConfig;

/// The RL backbone.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "kebab-case")]
pub enum Algo {
    Sac,
    Ppo,
}

/// The learner's settings: the flags of `pbrl train` and `pbrl learner` (clap) and the run
/// folder's `config.json` (serde), one definition with one default each. Fields marked
/// `arg(skip)` are not flags: the binary fills them from the task, the world and the other
/// flags.
#[derive(Clone, Debug, Serialize, Deserialize, clap::Args)]
pub struct LearnerConfig {
    /// Run id (`--run`, or `<algo>-<reward>-s<seed>`).
    #[arg(skip)]
    pub run: String,
    /// RL backbone: SAC (PEBBLE) or PPO (PrefPPO).
    #[arg(long, value_enum, default_value = "sac")]
    pub algo: Algo,
    /// Reward to train on: learnt from preferences and decoupled from the task reward
    /// (the paper's method), learnt alone (PEBBLE, PrefPPO), or the baselines' ground
    /// truth and task reward.
    #[arg(long, value_enum, default_value = "decoupled")]
    pub reward: RewardSource,
    /// Env steps of the run.
    #[arg(id = "steps", long = "steps", default_value_t = 1_000_000)]
    pub total_steps: u64,
    #[arg(skip)]
    pub obs_dim: usize,
    #[arg(skip)]
    pub act_dim: usize,
    #[command(flatten)]
    pub sac: SacConfig,
    #[command(flatten)]
    pub ppo: PpoConfig,
    /// Preference learning (used by the `pref` and `decoupled` rewards).
    #[command(flatten)]
    pub pref: PrefConfig,
    /// The world the actors simulate, with the person's profile (a scripted teacher's
    /// truth is that profile): a resume with another one is refused.
    #[arg(skip)]
    pub world: serde_json::Value,
    /// SAC: publish new weights every this many gradient steps.
    #[arg(skip = 50u64)]
    pub publish_every: u64,
    /// Env steps between rows of the learning curve.
    #[arg(long, default_value_t = 10_000)]
    pub log_every: u64,
    /// Actors feeding this learner (for flow control; `--actors`).
    #[arg(skip = 1u32)]
    pub actors: u32,
    /// Env steps of one episode (for flow control; from the task).
    #[arg(skip = 200u32)]
    pub episode_steps: u32,
    /// Evaluation episodes at each row of the learning curve: the policy's mean action on
    /// fixed seeds (30 give a success rate to about +-0.17 at 95%); 0 turns evaluation off
    /// (the row then has only the training episodes' figures).
    #[arg(long, default_value_t = 30)]
    pub eval_episodes: u32,
    /// Evaluate with the mean action only (by default the same seeds are also run with
    /// sampled actions: the policy as it trains, as the paper's figures show it).
    #[arg(long = "eval-mean-only", action = clap::ArgAction::SetFalse)]
    pub eval_sampled: bool,
    /// Env steps between checkpoints (each at the next weights publication after the mark;
    /// 0: only at the end or on a stop).
    #[arg(long, default_value_t = 50_000)]
    pub checkpoint_every: u64,
    /// Also checkpoint when this many seconds have passed since the last one (0: off).
    #[arg(long, default_value_t = 600)]
    pub checkpoint_secs: u64,
    /// Checkpoints kept (the newest).
    #[arg(long, default_value_t = 3)]
    pub keep_checkpoints: usize,
    /// Deterministic mode (use with one actor): each weights version runs exactly its
    /// share of episodes and the next waits for them, and each feedback session waits for
    /// its answers, so a run is a function of its seed (and its teacher).
    #[arg(long)]
    pub sync: bool,
    /// Threads of the learner's gradient steps: with 2, each step's pairs of independent
    /// work (SAC's twin critics, the policy on two minibatches, the target update beside
    /// the actor's backward pass; PPO's policy and value) run side by side on the core the
    /// actors leave idle. The results are the same to the bit.
    #[arg(long, default_value_t = 2)]
    #[serde(default = "two")]
    pub learner_threads: usize,
    /// Run folder (config.json, curve.csv, labels.sqlite); default `runs/<run>`. None in
    /// tests.
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Show a progress bar (on a terminal) instead of periodic log lines.
    #[serde(skip)]
    #[arg(skip)]
    pub progress: bool,
}

fn two() -> usize {
    2
}

impl LearnerConfig {
    /// A config with every default (its flags'), for `obs_dim` x `act_dim` (tests and
    /// benchmarks set what they need on top).
    pub fn new(
        run: &str,
        algo: Algo,
        reward: RewardSource,
        obs_dim: usize,
        act_dim: usize,
    ) -> Self {
        let mut cfg: LearnerConfig = pbrl_common::flags::defaults();
        cfg.run = run.into();
        cfg.algo = algo;
        cfg.reward = reward;
        cfg.obs_dim = obs_dim;
        cfg.act_dim = act_dim;
        cfg
    }

    /// The clap ids of every flag (to check that presets name real ones).
    pub fn flag_ids() -> BTreeSet<String> {
        use clap::Args;
        LearnerConfig::augment_args(clap::Command::new("pbrl"))
            .get_arguments()
            .map(|a| a.get_id().to_string())
            .collect()
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
        if !(2..=pbrl_common::wire::MAX_ATTEMPTS).contains(&p.query_attempts) {
            return bad(
                "query_attempts",
                &p.query_attempts,
                "must be 2 (pairs), 3 or 4 (rankings)",
            );
        }
        if p.queries_per_session == 0 {
            return bad("queries_per_session", &0, "must be at least 1");
        }
        let h = self.sac.hybrid_share;
        if !(0.0..=1.0).contains(&h) {
            return bad("sac_hybrid_share", &h, "must be in [0, 1]");
        }
        if self.sac.hybrid_steps == 0 {
            return bad("sac_hybrid_steps", &0, "must be at least 1");
        }
        if !(p.pseudo_tau > 0.5 && p.pseudo_tau <= 1.0) {
            return bad("pseudo_tau", &p.pseudo_tau, "must be in (0.5, 1]");
        }
        let (lo, hi) = (p.model.crop_min, p.model.crop_max);
        if !(lo > 0.0 && lo <= 1.0) {
            return bad("reward_crop_min", &lo, "must be in (0, 1]");
        }
        if !(hi >= lo && hi <= 1.0) {
            return bad("reward_crop_max", &hi, "must be in [reward_crop_min, 1]");
        }
        let c = p.model.anchor;
        if !(c.is_finite() && c >= 0.0) {
            return bad("reward_anchor", &c, "must be finite and >= 0");
        }
        if let Some(s) = p.label_slack_s {
            if !(s.is_finite() && s >= 0.0) {
                return bad(
                    "label_slack_s",
                    &s,
                    "must be a number of seconds, 0 or more",
                );
            }
        }
        if p.feedback_interval == 0 {
            return bad("feedback_interval", &0, "must be at least 1");
        }
        if !(p.feedback_decay.is_finite() && p.feedback_decay > 0.0 && p.feedback_decay <= 1.0) {
            return bad("feedback_decay", &p.feedback_decay, "must be in (0, 1]");
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
        if !(1..=2).contains(&self.learner_threads) {
            return bad("learner_threads", &self.learner_threads, "must be 1 or 2");
        }
        Ok(())
    }
}

/// One preset setting: the clap id of the flag, the JSON path of the config field, the
/// value.
pub type Setting = (&'static str, &'static str, serde_json::Value);

/// The label-efficiency settings off: whole trajectories, queries from the whole
/// annotation buffer, fixed session sizes, no crops, pseudo-labels, hybrid replay or
/// comfort features, and the exponential schedule's rate before issue 23 (the authors'
/// method, and what the presets below keep although the defaults are label-efficient).
/// `PrefConfig::plain` is the defaults with these applied (checked in the tests).
pub fn label_efficiency_off() -> Vec<Setting> {
    use serde_json::json;
    vec![
        ("segment_len", "/pref/segment_len", json!(0)),
        ("query_recent", "/pref/query_recent", json!(0)),
        ("feedback_span", "/pref/feedback_span", json!(0)),
        ("pseudo_pairs", "/pref/pseudo_pairs", json!(0)),
        ("reward_crops", "/pref/model/crops", json!(0)),
        ("sac_hybrid_share", "/sac/hybrid_share", json!(0.0)),
        ("reward_anchor", "/pref/model/anchor", json!(0.0)),
        ("reward_features", "/pref/model/features", json!(false)),
        ("feedback_decay", "/pref/feedback_decay", json!(1.0)),
        ("rho", "/pref/rho", json!(1e-6)),
    ]
}

/// The authors' settings where the defaults differ (`--preset paper`): their network
/// sizes, their ensemble training unbounded by `max_pairs`, the linear schedule, their
/// budget (PEBBLE 50,000 queries, PrefPPO 10,000; 100 a session) and whole-trajectory
/// queries.
pub fn paper_preset(algo: Algo) -> Vec<Setting> {
    use serde_json::json;
    let mut v = label_efficiency_off();
    let budget = match algo {
        Algo::Sac => 50_000,
        Algo::Ppo => 10_000,
    };
    v.extend([
        ("max_feedback", "/pref/max_feedback", json!(budget)),
        (
            "queries_per_session",
            "/pref/queries_per_session",
            json!(100),
        ),
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
    ]);
    v
}

/// PrefPPO's preference settings (`shared/method.md` sections 3 and 5), applied with the
/// PPO backbone (whole-trajectory queries: the label-efficiency pieces are measured with
/// SAC only).
pub fn ppo_preset() -> Vec<Setting> {
    use serde_json::json;
    let mut v = label_efficiency_off();
    v.extend([
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
    ]);
    v
}

/// The point task (made for tests) learns in seconds with small networks and short
/// sessions; `horizon` is its episode length. Its preference settings are the plain ones
/// ([`label_efficiency_off`]) unless `label_efficient`.
pub fn point_preset(horizon: u32, label_efficient: bool) -> Vec<Setting> {
    use serde_json::json;
    let rollout = 32 * horizon;
    let mut v = if label_efficient {
        Vec::new()
    } else {
        label_efficiency_off()
    };
    v.extend([
        ("sac_hidden", "/sac/hidden", json!([64, 64])),
        ("sac_batch", "/sac/batch", json!(64)),
        ("ppo_hidden", "/ppo/hidden", json!([64, 64])),
        ("ppo_rollout_steps", "/ppo/rollout_steps", json!(rollout)),
        ("reward_hidden", "/pref/model/hidden", json!([64, 64])),
        ("unsup_steps", "/pref/unsup_steps", json!(1_200)),
        ("feedback_interval", "/pref/feedback_interval", json!(1_500)),
        (
            "queries_per_session",
            "/pref/queries_per_session",
            json!(40),
        ),
        ("max_feedback", "/pref/max_feedback", json!(400)),
        ("candidate_factor", "/pref/candidate_factor", json!(10)),
        ("lambda0", "/pref/lambda0", json!(1.0)),
        ("knn_pool", "/pref/knn_pool", json!(2_000)),
        (
            "annotation_capacity",
            "/pref/annotation_capacity",
            json!(1_000),
        ),
    ]);
    v
}

/// With a person at the labelling page (`--teacher human`): a few queries open per person,
/// chosen when one is ready for them; stale ones withdrawn for fresh ones; no attempt in
/// two open queries at once.
pub fn person_preset() -> Vec<Setting> {
    use serde_json::json;
    vec![
        ("open_per_labeller", "/pref/open_per_labeller", json!(3)),
        (
            "query_stale_steps",
            "/pref/query_stale_steps",
            json!(20_000),
        ),
        (
            "queries_per_trajectory",
            "/pref/queries_per_trajectory",
            json!(1),
        ),
    ]
}

impl LearnerConfig {
    /// SAC's reward scale for Decoupled PEBBLE: lambda_t r_task + r_hat with lambda_0 15
    /// makes SAC's critics chase targets 15 times the task baseline's, and learn them slower
    /// at the same learning rate; scaled by 1 / lambda_0 they keep the baseline's size
    /// (measured on feeding, 3 seeds at 1M env steps: success 0.60 against 0.46). Not for
    /// the paper's preset (the authors' unscaled reward), a scale the user gave
    /// (`explicit` holds `sac_reward_scale`), or `--sac-lambda-scale` (which scales instead).
    pub fn scale_decoupled_reward(&mut self, paper: bool, explicit: &BTreeSet<String>) {
        let scaled = self.algo == Algo::Sac
            && self.reward == RewardSource::Decoupled
            && !paper
            && !explicit.contains("sac_reward_scale")
            && !self.sac.lambda_scale;
        if scaled {
            self.sac.reward_scale = 1.0 / self.pref.lambda0.max(1.0);
        }
    }
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
    "learner_threads",
    // How a person is asked (the pace of a sitting), not what is learnt.
    "pref.open_per_labeller",
    "pref.query_stale_steps",
    "pref.queries_per_trajectory",
    "pref.label_slack_steps",
    "pref.label_slack_s",
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
                    if RESUMABLE_FIELDS.contains(&sub.as_str()) {
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
    use crate::pref::config::Schedule;

    #[test]
    fn the_plain_config_is_the_defaults_with_the_label_efficiency_off() {
        let mut cfg = LearnerConfig::new("r", Algo::Sac, RewardSource::Decoupled, 4, 2);
        apply_preset(&mut cfg, &label_efficiency_off(), &BTreeSet::new()).unwrap();
        let plain = crate::pref::config::PrefConfig::plain();
        assert_eq!(
            serde_json::to_value(&cfg.pref).unwrap(),
            serde_json::to_value(&plain).unwrap()
        );
        assert_eq!(cfg.sac.hybrid_share, 0.0);
        // And the defaults are not plain: the test above would hold for a preset that
        // changed nothing.
        let default = LearnerConfig::new("r", Algo::Sac, RewardSource::Decoupled, 4, 2);
        assert_ne!(
            serde_json::to_value(&default.pref).unwrap(),
            serde_json::to_value(&plain).unwrap()
        );
    }

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
        apply_preset(&mut sac, &paper_preset(Algo::Sac), &explicit).unwrap();
        assert_eq!(sac.pref.max_feedback, 50_000, "PEBBLE's budget");
        // PrefPPO under the paper's preset keeps PrefPPO's budget, whichever comes last.
        let mut ppo = LearnerConfig::new("r", Algo::Ppo, RewardSource::Decoupled, 4, 2);
        apply_preset(&mut ppo, &ppo_preset(), &BTreeSet::new()).unwrap();
        apply_preset(&mut ppo, &paper_preset(Algo::Ppo), &BTreeSet::new()).unwrap();
        assert_eq!(ppo.pref.max_feedback, 10_000, "PrefPPO's budget");
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
    fn every_preset_names_a_real_flag_and_a_real_field() {
        let flags = LearnerConfig::flag_ids();
        assert!(
            flags.contains("sac_hidden") && flags.contains("lambda0"),
            "{flags:?}"
        );
        let cfg = LearnerConfig::new("r", Algo::Sac, RewardSource::Decoupled, 4, 2);
        let json = serde_json::to_value(&cfg).unwrap();
        for (name, preset) in [
            ("paper", paper_preset(Algo::Sac)),
            ("paper-ppo", paper_preset(Algo::Ppo)),
            ("ppo", ppo_preset()),
            ("point", point_preset(50, false)),
        ] {
            for (id, path, _) in preset {
                assert!(flags.contains(id), "the {name} preset names no flag {id}");
                assert!(
                    json.pointer(path).is_some(),
                    "the {name} preset's {id} names no field {path}"
                );
            }
        }
        // A misspelt id is caught.
        assert!(!flags.contains("sac_hiden"));
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
        let refused = |f: &dyn Fn(&mut LearnerConfig), want: &str| {
            let mut cfg = LearnerConfig::new("r", Algo::Sac, RewardSource::Decoupled, 4, 2);
            f(&mut cfg);
            let e = cfg.validate().unwrap_err().to_string();
            assert!(e.contains(want), "{e}");
        };
        refused(&|c| c.sac.hybrid_share = 1.5, "sac_hybrid_share is 1.5");
        refused(&|c| c.pref.model.crop_min = 0.0, "reward_crop_min is 0");
        refused(&|c| c.pref.model.crop_max = 0.5, "reward_crop_max is 0.5");
        refused(&|c| c.pref.pseudo_tau = 0.4, "pseudo_tau is 0.4");
        refused(&|c| c.pref.feedback_decay = 0.0, "feedback_decay is 0");
        refused(&|c| c.pref.model.anchor = -1.0, "reward_anchor is -1");
    }

    #[test]
    fn decoupled_sac_is_scaled_by_one_over_lambda0_unless_told_otherwise() {
        let none = BTreeSet::new();
        let mut cfg = LearnerConfig::new("r", Algo::Sac, RewardSource::Decoupled, 4, 2);
        cfg.pref.lambda0 = 20.0;
        cfg.scale_decoupled_reward(false, &none);
        assert_eq!(cfg.sac.reward_scale, 1.0 / 20.0);
        let unscaled = |mut c: LearnerConfig, paper, explicit: &BTreeSet<String>| {
            let before = c.sac.reward_scale;
            c.scale_decoupled_reward(paper, explicit);
            c.sac.reward_scale == before
        };
        let fresh = || {
            let mut c = LearnerConfig::new("r", Algo::Sac, RewardSource::Decoupled, 4, 2);
            c.pref.lambda0 = 20.0;
            c
        };
        assert!(unscaled(fresh(), true, &none), "the paper's preset");
        let given = BTreeSet::from(["sac_reward_scale".to_string()]);
        assert!(unscaled(fresh(), false, &given), "the user's own scale");
        let mut lambda_scale = fresh();
        lambda_scale.sac.lambda_scale = true;
        assert!(unscaled(lambda_scale, false, &none));
        let truth = LearnerConfig::new("r", Algo::Sac, RewardSource::Truth, 4, 2);
        assert!(unscaled(truth, false, &none));
        // lambda_0 below 1 is not scaled up.
        let mut small = fresh();
        small.pref.lambda0 = 0.5;
        small.scale_decoupled_reward(false, &none);
        assert_eq!(small.sac.reward_scale, 1.0);
    }
}
