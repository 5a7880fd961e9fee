//! The learner service: take trajectories from the actors, train SAC or PPO on the chosen
//! reward, publish weights, write the learning curve.

use std::collections::VecDeque;
use std::future::Future;
use std::io::Write;
use std::path::PathBuf;
use std::time::{Duration, Instant};

use anyhow::{Context, Result};
use pbrl_common::bus::{put_message, Inbox, MessagePublisher, Receipts, WeightsServer};
use pbrl_common::nets::export;
use pbrl_common::nets::import;
use pbrl_common::wire::{self, Body, EvalRequest, EvalResult, Stop, Weights};
use pbrl_common::{Keys, RunningNorm, StepRewards, Trajectory};
use serde::{Deserialize, Serialize};
use zenoh::qos::Priority;
use zenoh::Session;

use crate::ppo::{Ppo, PpoConfig, PpoState};
use crate::run_folder::{FileSum, RunFolder};
use crate::sac::{Sac, SacConfig, SacState};

/// The RL backbone.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "kebab-case")]
pub enum Algo {
    Sac,
    Ppo,
}

/// The reward the policy is trained on: one pluggable piece (preference learning adds the
/// learnt ensemble here).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "kebab-case")]
pub enum RewardSource {
    /// The ground truth r = r_R + r_H.
    True,
    /// The sketchy task reward r_task = -d alone.
    Task,
}

impl RewardSource {
    pub fn of(self, r: &StepRewards) -> f32 {
        match self {
            RewardSource::True => r.truth,
            RewardSource::Task => r.task,
        }
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
    /// version waits for all of them (with one actor, a run is a function of its seed).
    pub sync: bool,
    /// Run folder (`run_folder` has its layout); none in tests.
    pub out: Option<PathBuf>,
    /// Show a progress bar (on a terminal) instead of periodic log lines.
    #[serde(skip)]
    pub progress: bool,
}

/// Seeds of the evaluation episodes: the same at every row, apart from training seeds
/// (`actor::runner::episode_seed`, below 2^63).
pub const EVAL_SEED_BASE: u64 = 1 << 63;

/// An evaluation unanswered this long is asked again, of another actor if there is one
/// (it is asked until answered; a row waits for its evaluation).
const EVAL_TIMEOUT: Duration = Duration::from_secs(60);

/// One row of the learning curve: the training episodes since the previous row, and the
/// deterministic evaluation episodes of the weights at `env_steps` (NaN when not run).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct CurveRow {
    pub env_steps: u64,
    pub wall_s: f64,
    pub eval_episodes: u64,
    pub eval_return_truth: f64,
    pub eval_success_rate: f64,
    pub eval_return_human: f64,
    pub eval_return_task: f64,
    pub eval_version: u64,
    /// The same seeds with sampled actions (NaN when not run).
    pub eval_sampled_return_truth: f64,
    pub eval_sampled_success_rate: f64,
    pub eval_sampled_return_human: f64,
    pub episodes: u64,
    pub return_truth: f64,
    pub success_rate: f64,
    pub return_human: f64,
    pub return_task: f64,
    pub loss_critic_or_value: f64,
    pub loss_actor: f64,
    pub alpha_or_kl: f64,
    pub env_steps_per_s: f64,
    pub updates_per_s: f64,
    pub updates: u64,
    pub policy_version: u64,
    pub dropped_messages: u64,
    pub stale_trajectories: u64,
    /// Messages that came again (a trajectory sent again, taken once) or were asked again
    /// (an evaluation), over the run.
    pub retried_messages: u64,
    /// Trajectories known to be missing now (a later one of the same actor arrived).
    pub lost_messages: u64,
}

const CURVE_HEADER: &str = "env_steps,wall_s,eval_episodes,eval_return_truth,eval_success_rate,eval_return_human,eval_return_task,eval_version,eval_sampled_return_truth,eval_sampled_success_rate,eval_sampled_return_human,episodes,return_truth,success_rate,return_human,return_task,loss_critic_or_value,loss_actor,alpha_or_kl,env_steps_per_s,updates_per_s,updates,policy_version,dropped_messages,stale_trajectories,retried_messages,lost_messages";

impl CurveRow {
    fn csv(&self) -> String {
        format!(
            "{},{:.1},{},{:.4},{:.4},{:.4},{:.4},{},{:.4},{:.4},{:.4},{},{:.4},{:.4},{:.4},{:.4},{:.6},{:.6},{:.6},{:.1},{:.2},{},{},{},{},{},{}",
            self.env_steps,
            self.wall_s,
            self.eval_episodes,
            self.eval_return_truth,
            self.eval_success_rate,
            self.eval_return_human,
            self.eval_return_task,
            self.eval_version,
            self.eval_sampled_return_truth,
            self.eval_sampled_success_rate,
            self.eval_sampled_return_human,
            self.episodes,
            self.return_truth,
            self.success_rate,
            self.return_human,
            self.return_task,
            self.loss_critic_or_value,
            self.loss_actor,
            self.alpha_or_kl,
            self.env_steps_per_s,
            self.updates_per_s,
            self.updates,
            self.policy_version,
            self.dropped_messages,
            self.stale_trajectories,
            self.retried_messages,
            self.lost_messages
        )
    }
}

/// What a finished run did.
#[derive(Clone, Debug, Default)]
pub struct Summary {
    pub env_steps: u64,
    pub updates: u64,
    pub policy_version: u64,
    pub rows: Vec<CurveRow>,
    pub dropped_messages: u64,
    pub stale_trajectories: u64,
    /// Episodes received from each actor.
    pub episodes_by_actor: std::collections::BTreeMap<u32, u64>,
    /// The policy version of each actor's first episode.
    pub first_version_by_actor: std::collections::BTreeMap<u32, u64>,
    /// The policy version of each actor's last episode taken.
    pub last_version_by_actor: std::collections::BTreeMap<u32, u64>,
    /// The run was stopped (a signal) before its total.
    pub stopped: bool,
}

enum Backbone {
    Sac(Box<Sac>),
    Ppo(Box<Ppo>, Vec<Trajectory>),
}

/// Episode statistics accumulated between curve rows.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
struct Window {
    episodes: u64,
    truth: f64,
    success: f64,
    human: f64,
    task: f64,
}

/// Episodes each actor runs with the version published at `env_steps`: its share of the
/// env steps that version is for (SAC: until the next publication, or the random steps;
/// PPO: one rollout).
fn version_share(cfg: &LearnerConfig, backbone: &Backbone, env_steps: u64) -> u64 {
    let per_version = match backbone {
        Backbone::Sac(s) if env_steps < s.cfg.random_steps => s.cfg.random_steps - env_steps,
        Backbone::Sac(s) => cfg.publish_every * s.cfg.update_every,
        Backbone::Ppo(p, _) => p.cfg.rollout_steps as u64,
    };
    per_version
        .div_ceil(cfg.actors.max(1) as u64 * cfg.episode_steps.max(1) as u64)
        .max(1)
}

fn weights_of(
    cfg: &LearnerConfig,
    backbone: &Backbone,
    version: u64,
    env_steps: u64,
) -> Result<Weights> {
    let (obs_dim, act_dim) = (cfg.obs_dim, cfg.act_dim);
    let share = version_share(cfg, backbone, env_steps);
    let (tensors, norm, random) = match backbone {
        Backbone::Sac(s) => (
            export(&s.policy.varmap)?,
            // NOTE: SAC trains on raw observations; an identity normaliser travels.
            RunningNorm {
                mean: vec![0.0; obs_dim],
                var: vec![1.0 - 1e-8; obs_dim],
                count: 1.0,
                clip: f32::MAX as f64,
            },
            env_steps < s.cfg.random_steps,
        ),
        Backbone::Ppo(p, _) => (export(&p.policy.varmap)?, p.norm.clone(), false),
    };
    Ok(Weights {
        version,
        env_steps,
        obs_dim: obs_dim as u32,
        act_dim: act_dim as u32,
        tensors,
        obs_mean: norm.mean.iter().map(|x| *x as f32).collect(),
        obs_var: norm.var.iter().map(|x| *x as f32).collect(),
        obs_clip: norm.clip as f32,
        random_actions: random,
        // NOTE: the credit each actor gets: its share of the steps until the next version,
        // and one more to keep it busy while that version comes (the deterministic mode runs
        // exactly the share). What waits for the learner is at most this per actor.
        episodes_per_actor: (share + (!cfg.sync) as u64).min(u32::MAX as u64) as u32,
        acks: Vec::new(),
    })
}

/// A row waiting for its evaluation.
struct Pending {
    row: CurveRow,
    request: EvalRequest,
    sent: Instant,
    tries: u32,
}

/// The learning curve: rows in env-step order, each written once its evaluation is in.
struct Curve {
    file: Option<std::fs::File>,
    /// Rows in the file, over the whole run.
    written: u64,
    pending: VecDeque<Pending>,
    bar: Option<indicatif::ProgressBar>,
}

impl Curve {
    fn write(&mut self, row: CurveRow, summary: &mut Summary) -> Result<()> {
        let sampled = if row.eval_sampled_success_rate.is_nan() {
            String::new()
        } else {
            format!(
                " (sampled actions: {:.0}%)",
                100.0 * row.eval_sampled_success_rate
            )
        };
        let line = format!(
            "{} env steps: eval return {:.1}, success {:.0}%{sampled} ({} episodes, v{}); training return {:.1}, success {:.0}%, {:.0} env steps/s",
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
        summary.rows.push(row);
        Ok(())
    }

    /// Fill in an evaluation's figures, then write every row that is complete in order.
    fn complete(&mut self, r: EvalResult, summary: &mut Summary) -> Result<()> {
        let Some(p) = self.pending.iter_mut().find(|p| p.request.id == r.id) else {
            tracing::debug!(id = r.id, "an evaluation answered twice or after its row");
            return Ok(());
        };
        let seeds = p.request.seeds.len();
        let sampled = if p.request.sampled { seeds } else { 0 };
        if r.episodes.len() != seeds || r.sampled.len() != sampled {
            summary.dropped_messages += 1;
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
        type Of = dyn Fn(&pbrl_common::Outcome) -> f64;
        let mean = |xs: &[pbrl_common::Outcome], f: &Of| {
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
        self.write_ready(summary)
    }

    /// Write the rows at the front that are evaluated.
    fn write_ready(&mut self, summary: &mut Summary) -> Result<()> {
        while self
            .pending
            .front()
            .is_some_and(|p| p.row.eval_episodes > 0)
        {
            let p = self.pending.pop_front().expect("the front exists");
            self.write(p.row, summary)?;
        }
        Ok(())
    }

    /// Ask for the evaluation of `row`'s weights; the row waits for it.
    async fn ask(
        &mut self,
        session: &Session,
        keys: &Keys,
        row: CurveRow,
        request: EvalRequest,
    ) -> Result<()> {
        send_eval(session, keys, &request).await?;
        self.pending.push_back(Pending {
            row,
            request,
            sent: Instant::now(),
            tries: 1,
        });
        Ok(())
    }

    /// Write every pending row as it is (an evaluation not answered stays NaN).
    fn flush(&mut self, summary: &mut Summary) -> Result<()> {
        while let Some(p) = self.pending.pop_front() {
            self.write(p.row, summary)?;
        }
        Ok(())
    }
}

/// The actors that sent a trajectory recently, for evaluation requests.
#[derive(Default)]
struct Actors {
    last_seen: std::collections::BTreeMap<u32, Instant>,
    turn: usize,
}

impl Actors {
    /// The next live actor in turn.
    fn next(&mut self) -> u32 {
        let live: Vec<u32> = self
            .last_seen
            .iter()
            .filter(|(_, t)| t.elapsed() < EVAL_TIMEOUT)
            .map(|(a, _)| *a)
            .collect();
        self.turn += 1;
        if live.is_empty() {
            // NOTE: nobody sent anything for a while; ask the first actor known.
            return self.last_seen.keys().next().copied().unwrap_or(0);
        }
        live[self.turn % live.len()]
    }
}

/// Ask again (another actor, if there is one) for evaluations not answered in time;
/// returns how many were asked again.
async fn retry_evaluations(
    session: &Session,
    keys: &Keys,
    curve: &mut Curve,
    actors: &mut Actors,
) -> Result<u64> {
    let mut asked = 0;
    for p in curve.pending.iter_mut() {
        if p.row.eval_episodes > 0 || p.sent.elapsed() < EVAL_TIMEOUT {
            continue;
        }
        p.request.actor = actors.next();
        p.tries += 1;
        p.sent = Instant::now();
        asked += 1;
        tracing::warn!(
            env_steps = p.row.env_steps,
            actor = p.request.actor,
            tries = p.tries,
            "an evaluation went unanswered; asking again"
        );
        send_eval(session, keys, &p.request).await?;
    }
    Ok(asked)
}

async fn send_eval(session: &Session, keys: &Keys, request: &EvalRequest) -> Result<()> {
    put_message(
        session,
        keys,
        keys.eval_request(request.actor),
        &Body::EvalRequest(Box::new(request.clone())),
        Priority::Data,
    )
    .await
}

/// The learner loop's counters and bookkeeping: with the networks, optimisers, generators
/// and replay buffer, everything a resumed run needs.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
struct Progress {
    version: u64,
    env_steps: u64,
    updates: u64,
    since_publish: u64,
    /// Episodes of the current version received (deterministic mode).
    version_episodes: u64,
    /// Env steps the current version was made at.
    weights_env_steps: u64,
    next_row: u64,
    next_checkpoint: u64,
    window: Window,
    /// Numbered trajectories received, per actor (each taken once).
    receipts: Receipts,
    /// Evaluations asked again.
    eval_retries: u64,
    last_losses: [f64; 3],
    /// Wall time of the run in earlier processes.
    wall_s: f64,
    rows_written: u64,
    stale: u64,
}

#[derive(Serialize, Deserialize)]
enum BackboneState {
    Sac(SacState),
    Ppo(PpoState),
}

/// A checkpoint's `state.bin`.
#[derive(Serialize, Deserialize)]
struct Saved {
    /// The config as JSON (for a reader; the run folder's `config.json` is the one used).
    config: String,
    progress: Progress,
    /// Rows made but not written yet, with their evaluation requests.
    pending: Vec<(CurveRow, EvalRequest)>,
    backbone: BackboneState,
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

/// Refuse a resume whose config contradicts the stored one, naming the field and both
/// values.
pub fn check_resume(stored: &serde_json::Value, new: &serde_json::Value) -> Result<()> {
    fn walk(path: &str, a: &serde_json::Value, b: &serde_json::Value) -> Result<()> {
        match (a, b) {
            (serde_json::Value::Object(x), serde_json::Value::Object(y)) => {
                let keys: std::collections::BTreeSet<&String> = x.keys().chain(y.keys()).collect();
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
    walk("", stored, new)
}

impl Backbone {
    fn networks(&self) -> Vec<(&'static str, &candle_nn::VarMap)> {
        match self {
            Backbone::Sac(s) => s.networks().to_vec(),
            Backbone::Ppo(p, _) => p.networks().to_vec(),
        }
    }
}

/// The start of a replay segment's range, from its name.
fn segment_range(s: &FileSum) -> Option<(u64, u64)> {
    let name = std::path::Path::new(&s.path).file_stem()?.to_str()?;
    let (a, b) = name.split_once('-')?;
    Some((a.parse().ok()?, b.parse().ok()?))
}

/// Write a checkpoint: the SAC transitions since the last one as a new replay segment,
/// then networks, state and manifest.
fn write_checkpoint(
    folder: &RunFolder,
    cfg: &LearnerConfig,
    backbone: &Backbone,
    progress: &Progress,
    curve: &Curve,
    segments: &mut Vec<FileSum>,
) -> Result<()> {
    let start = Instant::now();
    let state = match backbone {
        Backbone::Sac(sac) => {
            let total = sac.replay.total;
            let held_from = total - sac.replay.len() as u64;
            let from = segments
                .last()
                .and_then(segment_range)
                .map_or(0, |(_, end)| end)
                .max(held_from);
            if total > from {
                let rows = sac.replay.rows(from, total);
                segments.push(folder.write_replay_segment(from, total, &rows)?);
            }
            // Segments wholly out of the buffer are no longer needed.
            segments.retain(|s| segment_range(s).is_some_and(|(_, end)| end > held_from));
            BackboneState::Sac(sac.state()?)
        }
        Backbone::Ppo(ppo, _) => BackboneState::Ppo(ppo.state()?),
    };
    let saved = Saved {
        config: serde_json::to_string(cfg)?,
        progress: Progress {
            rows_written: curve.written,
            ..progress.clone()
        },
        pending: curve
            .pending
            .iter()
            .map(|p| (p.row.clone(), p.request.clone()))
            .collect(),
        backbone: state,
    };
    let bytes = bincode::serde::encode_to_vec(&saved, bincode::config::standard())?;
    // The checkpoint counts the curve's rows: they must be on disk before it is.
    if let Some(f) = &curve.file {
        f.sync_data().context("syncing the curve")?;
    }
    folder.write_checkpoint(
        progress.env_steps,
        progress.version,
        &backbone.networks(),
        &bytes,
        segments.clone(),
        cfg.keep_checkpoints,
    )?;
    let replay_bytes: u64 = segments.iter().map(|s| s.bytes).sum();
    tracing::info!(
        env_steps = progress.env_steps,
        version = progress.version,
        ms = start.elapsed().as_millis() as u64,
        state_bytes = bytes.len(),
        replay_bytes,
        "checkpoint written"
    );
    Ok(())
}

/// Open the run folder: a new run writes its config and curve header; a folder that holds
/// a run resumes from its newest complete checkpoint. Returns the curve file, the saved
/// state (if resuming) and the replay segments.
fn open_folder(
    folder: &RunFolder,
    cfg: &LearnerConfig,
    backbone: &mut Backbone,
) -> Result<(std::fs::File, Option<Saved>, Vec<FileSum>)> {
    let config = serde_json::to_value(cfg)?;
    if folder.holds_run() {
        let text = std::fs::read_to_string(folder.config())
            .with_context(|| format!("reading {}", folder.config().display()))?;
        let stored: serde_json::Value = serde_json::from_str(&text)
            .with_context(|| format!("parsing {}", folder.config().display()))?;
        check_resume(&stored, &config)?;
        match folder.latest_checkpoint()? {
            Some(c) => {
                let bytes = folder.read(&c, "state.bin")?;
                let (saved, _): (Saved, usize) =
                    bincode::serde::decode_from_slice(&bytes, bincode::config::standard())
                        .with_context(|| format!("decoding {}/state.bin", c.dir.display()))?;
                for (name, varmap) in backbone.networks() {
                    let path = c.dir.join(format!("{name}.safetensors"));
                    let tensors = candle_core::safetensors::load(&path, &candle_core::Device::Cpu)
                        .with_context(|| format!("reading {}", path.display()))?;
                    let tensors: Vec<wire::Tensor> = tensors
                        .iter()
                        .map(|(name, t)| pbrl_common::nets::to_wire(name, t))
                        .collect::<candle_core::Result<_>>()?;
                    import(varmap, &tensors)
                        .with_context(|| format!("loading {}", path.display()))?;
                }
                match (&mut *backbone, &saved.backbone) {
                    (Backbone::Sac(sac), BackboneState::Sac(s)) => {
                        sac.restore(s)?;
                        let rows = folder.read_replay(&c.manifest.replay)?;
                        let from = c
                            .manifest
                            .replay
                            .first()
                            .and_then(segment_range)
                            .map_or(0, |r| r.0);
                        sac.replay.restore(from, &rows)?;
                    }
                    (Backbone::Ppo(ppo, _), BackboneState::Ppo(s)) => ppo.restore(s)?,
                    _ => anyhow::bail!("checkpoint {} is of another algorithm", c.dir.display()),
                }
                // The curve keeps the rows written before the checkpoint; later ones are
                // made again.
                let curve = std::fs::read_to_string(folder.curve())
                    .with_context(|| format!("reading {}", folder.curve().display()))?;
                let keep: Vec<&str> = curve
                    .lines()
                    .take(1 + saved.progress.rows_written as usize)
                    .collect();
                if keep.len() != 1 + saved.progress.rows_written as usize {
                    anyhow::bail!(
                        "{} has {} rows, the checkpoint counts {}",
                        folder.curve().display(),
                        keep.len().saturating_sub(1),
                        saved.progress.rows_written
                    );
                }
                let mut text = keep.join("\n");
                text.push('\n');
                folder.write_atomic(&folder.curve(), text.as_bytes())?;
                folder.write_atomic(
                    &folder.config(),
                    serde_json::to_string_pretty(cfg)?.as_bytes(),
                )?;
                let file = std::fs::OpenOptions::new()
                    .append(true)
                    .open(folder.curve())
                    .with_context(|| format!("opening {}", folder.curve().display()))?;
                tracing::info!(
                    checkpoint = %c.dir.display(),
                    env_steps = saved.progress.env_steps,
                    version = saved.progress.version,
                    rows = saved.progress.rows_written,
                    "resuming the run"
                );
                return Ok((file, Some(saved), c.manifest.replay));
            }
            None => tracing::warn!(
                folder = %folder.root.display(),
                "the folder holds a run but no complete checkpoint; starting it over"
            ),
        }
    }
    folder.clear()?;
    folder.create()?;
    folder.write_atomic(
        &folder.config(),
        serde_json::to_string_pretty(cfg)?.as_bytes(),
    )?;
    let path = folder.curve();
    let mut f =
        std::fs::File::create(&path).with_context(|| format!("creating {}", path.display()))?;
    writeln!(f, "{CURVE_HEADER}")?;
    Ok((f, None, Vec::new()))
}

/// Train until `total_steps` env steps or `shutdown`; then write a checkpoint and tell the
/// actors to stop. With a run folder that holds a run, it continues that run.
pub async fn run(
    cfg: LearnerConfig,
    session: Session,
    shutdown: impl Future<Output = ()>,
) -> Result<Summary> {
    let keys = Keys::new(&cfg.run)?;
    let (obs_dim, act_dim) = (cfg.obs_dim, cfg.act_dim);
    let mut backbone = match cfg.algo {
        Algo::Sac => Backbone::Sac(Box::new(Sac::new(cfg.sac.clone(), obs_dim, act_dim)?)),
        Algo::Ppo => Backbone::Ppo(
            Box::new(Ppo::new(cfg.ppo.clone(), obs_dim, act_dim)?),
            Vec::new(),
        ),
    };
    let folder = cfg.out.as_ref().map(RunFolder::new);
    let (file, saved, mut segments) = match &folder {
        Some(f) => {
            let (file, saved, segments) = open_folder(f, &cfg, &mut backbone)?;
            (Some(file), saved, segments)
        }
        None => (None, None, Vec::new()),
    };
    let every = |n: u64| if n == 0 { u64::MAX } else { n };
    let (mut p, pending) = match saved {
        Some(s) => {
            let mut p = s.progress;
            // NOTE: versions published after the checkpoint may still be held by actors;
            // count on from above every version this run ever published.
            p.version = p
                .version
                .max(folder.as_ref().map_or(0, |f| f.published_version()))
                + 1;
            (p, s.pending)
        }
        None => (
            Progress {
                version: 1,
                next_row: cfg.log_every,
                next_checkpoint: every(cfg.checkpoint_every),
                ..Progress::default()
            },
            Vec::new(),
        ),
    };
    let (resumed_at, updates_at) = (p.env_steps, p.updates);

    let server = WeightsServer::new(&session, &keys).await?;
    let mut trajectories = Inbox::trajectories(&session, &keys).await?;
    let mut eval_results = Inbox::eval_results(&session, &keys).await?;
    let stop = MessagePublisher::new(&session, &keys, keys.stop(), Priority::DataHigh).await?;
    tracing::debug!(config = %serde_json::to_string(&cfg)?, "learner config");
    tracing::info!(
        run = %cfg.run,
        algo = ?cfg.algo,
        reward = ?cfg.reward,
        steps = cfg.total_steps,
        from = p.env_steps,
        "learner starts"
    );
    let bar = cfg.progress.then(|| {
        let bar = indicatif::ProgressBar::new(cfg.total_steps);
        bar.set_style(
            indicatif::ProgressStyle::with_template(
                "{elapsed_precise} [{bar:30}] {human_pos}/{human_len} env steps, {per_sec}, {eta} left, {msg}",
            )
            .expect("the progress template is valid")
            .progress_chars("=> "),
        );
        bar.set_position(p.env_steps.min(cfg.total_steps));
        bar.reset_eta();
        bar
    });
    let mut curve = Curve {
        file,
        written: p.rows_written,
        pending: VecDeque::new(),
        bar,
    };
    let mut actors = Actors::default();
    let seeds: Vec<u64> = (0..cfg.eval_episodes as u64)
        .map(|k| EVAL_SEED_BASE + k)
        .collect();
    let publish = |backbone: &Backbone, p: &Progress| -> Result<Weights> {
        if let Some(f) = &folder {
            f.mark_version(p.version)?;
        }
        let mut w = weights_of(&cfg, backbone, p.version, p.env_steps)?;
        w.acks = p.receipts.acks();
        Ok(w)
    };
    server.publish(&publish(&backbone, &p)?).await?;
    // Rows made before the checkpoint and not written: evaluated again.
    for (row, mut request) in pending {
        request.actor = 0;
        curve.ask(&session, &keys, row, request).await?;
    }

    let mut summary = Summary::default();
    let start = Instant::now();
    let wall = |p: &Progress| p.wall_s + start.elapsed().as_secs_f64();
    let mut tick = tokio::time::interval(Duration::from_secs(1));
    let mut last_checkpoint = Instant::now();
    tokio::pin!(shutdown);
    let mut stopped = false;
    while p.env_steps < cfg.total_steps {
        let msg = tokio::select! {
            _ = &mut shutdown => { stopped = true; break }
            r = eval_results.next() => {
                curve.complete(r?, &mut summary)?;
                continue;
            }
            _ = tick.tick() => {
                p.eval_retries += retry_evaluations(&session, &keys, &mut curve, &mut actors).await?;
                continue;
            }
            m = trajectories.next() => m?,
        };
        actors.last_seen.insert(msg.actor, Instant::now());
        // NOTE: a trajectory sent again (its actor waited long for weights) is taken once.
        if !p.receipts.take(&msg) {
            continue;
        }
        let t = msg.trajectory;
        *summary.episodes_by_actor.entry(msg.actor).or_default() += 1;
        summary
            .first_version_by_actor
            .entry(msg.actor)
            .or_insert(t.policy_version);
        summary
            .last_version_by_actor
            .insert(msg.actor, t.policy_version);
        // NOTE: PPO trains only on the current version's data, and so does the
        // deterministic mode; older trajectories are dropped and counted.
        if (cfg.sync || matches!(backbone, Backbone::Ppo(..))) && t.policy_version != p.version {
            p.stale += 1;
            continue;
        }
        p.version_episodes += 1;
        let mut publish_now = false;
        // The weights published at this message, reused when a row falls on it.
        let mut published = None;
        match &mut backbone {
            Backbone::Sac(sac) => {
                let was_random = sac.env_steps < sac.cfg.random_steps;
                sac.observe(&t, |r| cfg.reward.of(r));
                let due = sac.updates_due();
                if due > 0 {
                    let losses = tokio::task::block_in_place(|| -> Result<_> {
                        let mut last = None;
                        for _ in 0..due {
                            last = Some(sac.update()?);
                        }
                        Ok(last)
                    })?;
                    if let Some(l) = losses {
                        p.last_losses = [l.critic as f64, l.actor as f64, l.alpha as f64];
                    }
                    p.updates += due;
                    p.since_publish += due;
                }
                publish_now = if cfg.sync {
                    p.version_episodes
                        >= version_share(&cfg, &backbone, p.weights_env_steps) * cfg.actors as u64
                } else {
                    p.since_publish >= cfg.publish_every
                        || (was_random && sac.env_steps >= sac.cfg.random_steps)
                };
            }
            Backbone::Ppo(ppo, rollout) => {
                rollout.push(t.clone());
                let steps: usize = rollout.iter().map(|t| t.steps()).sum();
                if steps >= ppo.cfg.rollout_steps {
                    let total = cfg.total_steps;
                    let stats = tokio::task::block_in_place(|| {
                        ppo.train(rollout, |r| cfg.reward.of(r), total)
                    })?;
                    p.last_losses = [
                        stats.value_loss as f64,
                        stats.policy_loss as f64,
                        stats.approx_kl as f64,
                    ];
                    p.updates += stats.minibatch_updates;
                    rollout.clear();
                    publish_now = true;
                }
            }
        }
        p.env_steps += t.steps() as u64;
        if let Some(bar) = &curve.bar {
            bar.set_position(p.env_steps.min(cfg.total_steps));
        }
        p.window.episodes += 1;
        p.window.truth += t.outcome.return_truth as f64;
        p.window.human += t.outcome.return_human as f64;
        p.window.task += t.outcome.return_task as f64;
        p.window.success += t.outcome.success as u8 as f64;
        if publish_now {
            p.version += 1;
            p.since_publish = 0;
            p.version_episodes = 0;
            p.weights_env_steps = p.env_steps;
            let w = publish(&backbone, &p)?;
            server.publish(&w).await?;
            published = Some(w);
        }
        if p.env_steps >= p.next_row || p.env_steps >= cfg.total_steps {
            while p.next_row <= p.env_steps {
                p.next_row += cfg.log_every.max(1);
            }
            let secs = wall(&p).max(1e-9);
            let here = start.elapsed().as_secs_f64().max(1e-9);
            let n = p.window.episodes.max(1) as f64;
            let row = CurveRow {
                env_steps: p.env_steps,
                wall_s: secs,
                eval_episodes: 0,
                eval_return_truth: f64::NAN,
                eval_success_rate: f64::NAN,
                eval_return_human: f64::NAN,
                eval_return_task: f64::NAN,
                eval_version: 0,
                eval_sampled_return_truth: f64::NAN,
                eval_sampled_success_rate: f64::NAN,
                eval_sampled_return_human: f64::NAN,
                episodes: p.window.episodes,
                return_truth: p.window.truth / n,
                success_rate: p.window.success / n,
                return_human: p.window.human / n,
                return_task: p.window.task / n,
                loss_critic_or_value: p.last_losses[0],
                loss_actor: p.last_losses[1],
                alpha_or_kl: p.last_losses[2],
                env_steps_per_s: (p.env_steps - resumed_at) as f64 / here,
                updates_per_s: (p.updates - updates_at) as f64 / here,
                updates: p.updates,
                policy_version: p.version,
                dropped_messages: trajectories.dropped.get()
                    + eval_results.dropped.get()
                    + summary.dropped_messages,
                stale_trajectories: p.stale,
                retried_messages: p.receipts.repeated + p.eval_retries,
                lost_messages: p.receipts.missing(),
            };
            if cfg.eval_episodes == 0 {
                curve.write(row, &mut summary)?;
            } else {
                let request = EvalRequest {
                    id: p.env_steps,
                    actor: actors.next(),
                    weights: match published.take() {
                        Some(w) => w,
                        None => weights_of(&cfg, &backbone, p.version, p.env_steps)?,
                    },
                    seeds: seeds.clone(),
                    sampled: cfg.eval_sampled,
                };
                curve.ask(&session, &keys, row, request).await?;
            }
            p.window = Window::default();
        }
        // Checkpoints at a publication (PPO: no rollout half-collected; the deterministic
        // mode: the point a resumed run starts from), once the mark is passed.
        let late = cfg.checkpoint_secs > 0
            && last_checkpoint.elapsed() >= Duration::from_secs(cfg.checkpoint_secs);
        if publish_now && (p.env_steps >= p.next_checkpoint || late) {
            last_checkpoint = Instant::now();
            while p.next_checkpoint <= p.env_steps {
                p.next_checkpoint = p
                    .next_checkpoint
                    .saturating_add(every(cfg.checkpoint_every));
            }
            if let Some(f) = &folder {
                let mut q = p.clone();
                q.wall_s = wall(&p);
                tokio::task::block_in_place(|| {
                    write_checkpoint(f, &cfg, &backbone, &q, &curve, &mut segments)
                })?;
            }
        }
    }
    // The last evaluations: the actors answer while they wait for weights that will not
    // come; their last trajectories are drained so nothing blocks.
    while !stopped && !curve.pending.is_empty() {
        tokio::select! {
            _ = &mut shutdown => break,
            r = eval_results.next() => curve.complete(r?, &mut summary)?,
            _ = tick.tick() => {
                p.eval_retries += retry_evaluations(&session, &keys, &mut curve, &mut actors).await?;
            }
            m = trajectories.next() => { m?; }
        }
    }
    // The final checkpoint (a stop, or the end): pending rows stay pending in it when
    // stopped, so a resumed run writes them.
    if let Some(f) = &folder {
        let mut q = p.clone();
        q.wall_s = wall(&p);
        if stopped {
            tracing::info!(env_steps = p.env_steps, "stopping: writing a checkpoint");
        } else {
            curve.flush(&mut summary)?;
        }
        tokio::task::block_in_place(|| {
            write_checkpoint(f, &cfg, &backbone, &q, &curve, &mut segments)
        })?;
        if !stopped {
            folder_finished(f, &p)?;
        }
    }
    // NOTE: a stopped run's rows that still wait for their evaluation stay in its checkpoint
    // (the resumed run writes them, evaluated), not in the curve.
    if !(stopped && folder.is_some()) {
        curve.flush(&mut summary)?;
    }
    if let Some(bar) = &curve.bar {
        bar.finish();
    }
    let word = Body::Stop(Stop {
        env_steps: p.env_steps,
        version: p.version,
    });
    if let Err(e) = stop.send(&word).await {
        tracing::warn!(error = %e, "could not tell the actors to stop");
    }
    summary.env_steps = p.env_steps;
    summary.updates = p.updates;
    summary.policy_version = p.version;
    summary.stale_trajectories = p.stale;
    summary.stopped = stopped;
    summary.dropped_messages += trajectories.dropped.get() + eval_results.dropped.get();
    Ok(summary)
}

fn folder_finished(f: &RunFolder, p: &Progress) -> Result<()> {
    let text =
        serde_json::json!({ "env_steps": p.env_steps, "version": p.version, "updates": p.updates });
    f.write_atomic(&f.finished(), text.to_string().as_bytes())?;
    Ok(())
}

/// What checkpoints cost with a full replay buffer (`pbrl bench checkpoint`).
#[derive(Clone, Debug)]
pub struct CheckpointCost {
    pub transitions: u64,
    /// The first checkpoint: the whole buffer as one segment.
    pub full_ms: f64,
    pub full_bytes: u64,
    /// A checkpoint after `increment` more transitions: only they are written.
    pub increment: u64,
    pub increment_ms: f64,
    pub increment_bytes: u64,
    /// Reading the newest checkpoint back (checks, networks, replay buffer).
    pub restore_ms: f64,
}

/// Fill a feeding-sized SAC (obs 25, action 7, 256x256) replay buffer with `transitions`
/// random transitions, checkpoint it into `dir`, add `increment`, checkpoint again, and
/// restore.
pub fn bench_checkpoint(
    dir: &std::path::Path,
    transitions: u64,
    increment: u64,
) -> Result<CheckpointCost> {
    use rand::{Rng, SeedableRng};
    let cfg = LearnerConfig {
        run: "bench".into(),
        algo: Algo::Sac,
        reward: RewardSource::True,
        total_steps: transitions + increment,
        obs_dim: 25,
        act_dim: 7,
        sac: SacConfig {
            replay_capacity: transitions as usize,
            ..SacConfig::default()
        },
        ppo: PpoConfig::default(),
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
        out: Some(dir.to_path_buf()),
        progress: false,
    };
    let folder = RunFolder::new(dir);
    let mut backbone = Backbone::Sac(Box::new(Sac::new(cfg.sac.clone(), 25, 7)?));
    let (file, _, mut segments) = open_folder(&folder, &cfg, &mut backbone)?;
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(0);
    let mut fill = |backbone: &mut Backbone, n: u64| {
        if let Backbone::Sac(sac) = backbone {
            for _ in 0..n {
                let obs: Vec<f32> = (0..25).map(|_| rng.random()).collect();
                let act: Vec<f32> = (0..7).map(|_| rng.random()).collect();
                sac.replay.push(&obs, &act, rng.random(), &obs, false);
            }
        }
    };
    let curve = Curve {
        file: Some(file),
        written: 0,
        pending: VecDeque::new(),
        bar: None,
    };
    let mut p = Progress {
        version: 1,
        ..Progress::default()
    };
    let timed =
        |backbone: &Backbone, p: &Progress, segments: &mut Vec<FileSum>| -> Result<(f64, u64)> {
            let before: u64 = segments.iter().map(|s| s.bytes).sum();
            let start = Instant::now();
            write_checkpoint(&folder, &cfg, backbone, p, &curve, segments)?;
            let ms = start.elapsed().as_secs_f64() * 1e3;
            let after: u64 = segments.iter().map(|s| s.bytes).sum();
            let nets: u64 = folder
                .latest_checkpoint()?
                .map_or(0, |c| c.manifest.files.iter().map(|f| f.bytes).sum());
            Ok((ms, after.saturating_sub(before) + nets))
        };
    fill(&mut backbone, transitions);
    p.env_steps = transitions;
    let (full_ms, full_bytes) = timed(&backbone, &p, &mut segments)?;
    fill(&mut backbone, increment);
    p.env_steps += increment;
    let (increment_ms, increment_bytes) = timed(&backbone, &p, &mut segments)?;
    let start = Instant::now();
    let mut fresh = Backbone::Sac(Box::new(Sac::new(cfg.sac.clone(), 25, 7)?));
    open_folder(&folder, &cfg, &mut fresh)?;
    Ok(CheckpointCost {
        transitions,
        full_ms,
        full_bytes,
        increment,
        increment_ms,
        increment_bytes,
        restore_ms: start.elapsed().as_secs_f64() * 1e3,
    })
}
