//! The learner service: take trajectories from the actors, train SAC or PPO on the chosen
//! reward, publish weights, write the learning curve.

use std::collections::VecDeque;
use std::future::Future;
use std::io::Write;
use std::path::PathBuf;
use std::time::{Duration, Instant};

use anyhow::{Context, Result};
use pbrl_common::bus::{put_message, MessageSubscriber, TrajectorySubscriber, WeightsServer};
use pbrl_common::nets::export;
use pbrl_common::wire::{self, Body, EvalRequest, EvalResult, Weights};
use pbrl_common::{Keys, RunningNorm, StepRewards, Trajectory};
use serde::{Deserialize, Serialize};
use zenoh::qos::{CongestionControl, Priority};
use zenoh::Session;

use crate::ppo::{Ppo, PpoConfig};
use crate::sac::{Sac, SacConfig};

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
    /// Run folder for the curve (`curve.csv`) and the resolved config; none in tests.
    pub out: Option<PathBuf>,
    /// Show a progress bar (on a terminal) instead of periodic log lines.
    #[serde(skip)]
    pub progress: bool,
}

/// Seeds of the evaluation episodes: the same at every row, apart from training seeds
/// (those are `seed * 2^32 ^ actor ^ episode * 2^16`, below 2^63 for any sane run).
pub const EVAL_SEED_BASE: u64 = 1 << 63;

/// An evaluation unanswered this long is asked of another actor.
const EVAL_TIMEOUT: Duration = Duration::from_secs(60);

/// Times an evaluation is asked before its row is written without it.
const EVAL_TRIES: u32 = 3;

/// One row of the learning curve: the training episodes since the previous row, and the
/// deterministic evaluation episodes of the weights at `env_steps` (NaN when not run).
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct CurveRow {
    pub env_steps: u64,
    pub wall_s: f64,
    pub eval_episodes: u64,
    pub eval_return_truth: f64,
    pub eval_success_rate: f64,
    pub eval_return_human: f64,
    pub eval_return_task: f64,
    pub eval_version: u64,
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
}

const CURVE_HEADER: &str = "env_steps,wall_s,eval_episodes,eval_return_truth,eval_success_rate,eval_return_human,eval_return_task,eval_version,episodes,return_truth,success_rate,return_human,return_task,loss_critic_or_value,loss_actor,alpha_or_kl,env_steps_per_s,updates_per_s,updates,policy_version,dropped_messages,stale_trajectories";

impl CurveRow {
    fn csv(&self) -> String {
        format!(
            "{},{:.1},{},{:.4},{:.4},{:.4},{:.4},{},{},{:.4},{:.4},{:.4},{:.4},{:.6},{:.6},{:.6},{:.1},{:.2},{},{},{},{}",
            self.env_steps,
            self.wall_s,
            self.eval_episodes,
            self.eval_return_truth,
            self.eval_success_rate,
            self.eval_return_human,
            self.eval_return_task,
            self.eval_version,
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
            self.stale_trajectories
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
}

enum Backbone {
    Sac(Box<Sac>),
    Ppo(Box<Ppo>, Vec<Trajectory>),
}

/// Episode statistics accumulated between curve rows.
#[derive(Default)]
struct Window {
    episodes: u64,
    truth: f64,
    success: f64,
    human: f64,
    task: f64,
}

fn weights_of(
    cfg: &LearnerConfig,
    backbone: &Backbone,
    version: u64,
    env_steps: u64,
) -> Result<Weights> {
    let (obs_dim, act_dim) = (cfg.obs_dim, cfg.act_dim);
    // Flow control: each actor runs only its share of the env steps this version is for
    // (SAC: until the next publication, or the random steps; PPO: one rollout), plus one.
    let per_version = match backbone {
        Backbone::Sac(s) if env_steps < s.cfg.random_steps => s.cfg.random_steps - env_steps,
        Backbone::Sac(s) => cfg.publish_every * s.cfg.update_every,
        Backbone::Ppo(p, _) => p.cfg.rollout_steps as u64,
    };
    let share = per_version.div_ceil(cfg.actors.max(1) as u64 * cfg.episode_steps.max(1) as u64);
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
        episodes_per_actor: (share + 1).min(u32::MAX as u64) as u32,
    })
}

/// Write `varmap` as `<dir>/<name>.safetensors` atomically: a temporary file, synced, then
/// renamed over the old one.
fn save_atomic(dir: &std::path::Path, name: &str, varmap: &candle_nn::VarMap) -> Result<()> {
    let tmp = dir.join(format!("{name}.safetensors.tmp"));
    varmap
        .save(&tmp)
        .with_context(|| format!("writing {}", tmp.display()))?;
    std::fs::File::open(&tmp)
        .and_then(|f| f.sync_all())
        .with_context(|| format!("syncing {}", tmp.display()))?;
    let dst = dir.join(format!("{name}.safetensors"));
    std::fs::rename(&tmp, &dst)
        .with_context(|| format!("renaming {} to {}", tmp.display(), dst.display()))
}

/// The networks of the run, under `<out>/checkpoint/`, with `checkpoint.json` (version,
/// env steps, updates) written last. (Full checkpoints for resuming, with optimiser state,
/// replay buffer and RNGs, come with run resume.)
fn save_networks(
    out: &std::path::Path,
    backbone: &Backbone,
    version: u64,
    env_steps: u64,
    updates: u64,
) -> Result<()> {
    let dir = out.join("checkpoint");
    std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
    match backbone {
        Backbone::Sac(s) => {
            save_atomic(&dir, "policy", &s.policy.varmap)?;
            save_atomic(&dir, "critic", s.critic_varmap())?;
            save_atomic(&dir, "target_critic", s.target_varmap())?;
        }
        Backbone::Ppo(p, _) => {
            save_atomic(&dir, "policy", &p.policy.varmap)?;
            save_atomic(&dir, "value", &p.value.varmap)?;
        }
    }
    let manifest =
        serde_json::json!({ "version": version, "env_steps": env_steps, "updates": updates });
    let tmp = dir.join("checkpoint.json.tmp");
    std::fs::write(&tmp, manifest.to_string())
        .with_context(|| format!("writing {}", tmp.display()))?;
    std::fs::rename(&tmp, dir.join("checkpoint.json"))
        .with_context(|| format!("renaming {}", tmp.display()))
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
    pending: VecDeque<Pending>,
    bar: Option<indicatif::ProgressBar>,
}

impl Curve {
    fn write(&mut self, row: CurveRow, summary: &mut Summary) -> Result<()> {
        let line = format!(
            "{} env steps: eval return {:.1}, success {:.0}% ({} episodes, v{}); training return {:.1}, success {:.0}%, {:.0} env steps/s",
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
        summary.rows.push(row);
        Ok(())
    }

    /// Fill in an evaluation's figures, then write every row that is complete in order.
    fn complete(&mut self, r: EvalResult, summary: &mut Summary) -> Result<()> {
        let Some(p) = self.pending.iter_mut().find(|p| p.request.id == r.id) else {
            tracing::debug!(id = r.id, "an evaluation answered twice or after its row");
            return Ok(());
        };
        if r.episodes.len() != p.request.seeds.len() {
            summary.dropped_messages += 1;
            tracing::warn!(
                id = r.id,
                actor = r.actor,
                found = r.episodes.len(),
                expected = p.request.seeds.len(),
                "dropped an evaluation with the wrong number of episodes"
            );
            return Ok(());
        }
        let n = r.episodes.len().max(1) as f64;
        let mean =
            |f: &dyn Fn(&pbrl_common::Outcome) -> f64| r.episodes.iter().map(f).sum::<f64>() / n;
        p.row.eval_episodes = r.episodes.len() as u64;
        p.row.eval_return_truth = mean(&|o| o.return_truth as f64);
        p.row.eval_success_rate = mean(&|o| o.success as u8 as f64);
        p.row.eval_return_human = mean(&|o| o.return_human as f64);
        p.row.eval_return_task = mean(&|o| o.return_task as f64);
        p.row.eval_version = r.version;
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

/// Ask again (another actor) for evaluations not answered in time; write a row without
/// its evaluation after [`EVAL_TRIES`].
async fn retry_evaluations(
    session: &Session,
    keys: &Keys,
    curve: &mut Curve,
    actors: &mut Actors,
    summary: &mut Summary,
) -> Result<()> {
    for p in curve.pending.iter_mut() {
        if p.row.eval_episodes > 0 || p.sent.elapsed() < EVAL_TIMEOUT {
            continue;
        }
        if p.tries >= EVAL_TRIES {
            tracing::warn!(
                env_steps = p.row.env_steps,
                tries = p.tries,
                "no actor answered the evaluation; its row is written without it"
            );
            p.row.eval_episodes = u64::MAX; // marks it done
            continue;
        }
        p.request.actor = actors.next();
        p.tries += 1;
        p.sent = Instant::now();
        tracing::warn!(
            env_steps = p.row.env_steps,
            actor = p.request.actor,
            "an evaluation went unanswered; asking another actor"
        );
        send_eval(session, keys, &p.request).await?;
    }
    // Rows given up on: write them in order.
    while curve
        .pending
        .front()
        .is_some_and(|p| p.row.eval_episodes > 0)
    {
        let mut p = curve.pending.pop_front().expect("the front exists");
        if p.row.eval_episodes == u64::MAX {
            p.row.eval_episodes = 0;
        }
        curve.write(p.row, summary)?;
    }
    Ok(())
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

fn pick_result(b: Body) -> Option<EvalResult> {
    match b {
        Body::EvalResult(r) => Some(r),
        _ => None,
    }
}

/// Train until `total_steps` env steps or `shutdown`; then tell the actors to stop.
pub async fn run(
    cfg: LearnerConfig,
    session: Session,
    shutdown: impl Future<Output = ()>,
) -> Result<Summary> {
    let keys = Keys::new(&cfg.run)?;
    let server = WeightsServer::new(&session, &keys).await?;
    let trajectories = TrajectorySubscriber::new(&session, &keys).await?;
    let eval_results = MessageSubscriber::new(&session, &keys, keys.all_eval_results()).await?;
    let stop = session
        .declare_publisher(keys.stop())
        .congestion_control(CongestionControl::Block)
        .await
        .map_err(|e| anyhow::anyhow!("declaring the stop publisher: {e}"))?;
    let file = match &cfg.out {
        Some(dir) => {
            std::fs::create_dir_all(dir)
                .with_context(|| format!("creating run folder {}", dir.display()))?;
            let config = serde_json::to_string_pretty(&cfg)?;
            std::fs::write(dir.join("config.json"), config)
                .with_context(|| format!("writing {}/config.json", dir.display()))?;
            let path = dir.join("curve.csv");
            let mut f = std::fs::File::create(&path)
                .with_context(|| format!("creating {}", path.display()))?;
            writeln!(f, "{CURVE_HEADER}")?;
            Some(f)
        }
        None => None,
    };
    tracing::info!(config = %serde_json::to_string(&cfg)?, "learner starts");
    let bar = cfg.progress.then(|| {
        let bar = indicatif::ProgressBar::new(cfg.total_steps);
        bar.set_style(
            indicatif::ProgressStyle::with_template(
                "{elapsed_precise} [{bar:30}] {human_pos}/{human_len} env steps, {per_sec}, {eta} left, {msg}",
            )
            .expect("the progress template is valid")
            .progress_chars("=> "),
        );
        bar
    });
    let mut curve = Curve {
        file,
        pending: VecDeque::new(),
        bar,
    };
    let mut actors = Actors::default();
    let seeds: Vec<u64> = (0..cfg.eval_episodes as u64)
        .map(|k| EVAL_SEED_BASE + k)
        .collect();

    let (obs_dim, act_dim) = (cfg.obs_dim, cfg.act_dim);
    let mut backbone = match cfg.algo {
        Algo::Sac => Backbone::Sac(Box::new(Sac::new(cfg.sac.clone(), obs_dim, act_dim)?)),
        Algo::Ppo => Backbone::Ppo(
            Box::new(Ppo::new(cfg.ppo.clone(), obs_dim, act_dim)?),
            Vec::new(),
        ),
    };
    let mut version = 1u64;
    server
        .publish(&weights_of(&cfg, &backbone, version, 0)?)
        .await?;

    let mut summary = Summary::default();
    let (mut env_steps, mut updates, mut since_publish) = (0u64, 0u64, 0u64);
    let mut window = Window::default();
    let mut next_row = cfg.log_every;
    let (mut last_loss, mut last_actor, mut last_aux) = (0.0f64, 0.0f64, 0.0f64);
    let start = Instant::now();
    let mut tick = tokio::time::interval(Duration::from_secs(1));
    tokio::pin!(shutdown);
    let mut stopped = false;
    while env_steps < cfg.total_steps {
        let msg = tokio::select! {
            _ = &mut shutdown => { stopped = true; break }
            r = eval_results.next(pick_result) => {
                curve.complete(r?, &mut summary)?;
                continue;
            }
            _ = tick.tick() => {
                retry_evaluations(&session, &keys, &mut curve, &mut actors, &mut summary).await?;
                continue;
            }
            m = trajectories.next() => m?,
        };
        let t = msg.trajectory;
        *summary.episodes_by_actor.entry(msg.actor).or_default() += 1;
        summary
            .first_version_by_actor
            .entry(msg.actor)
            .or_insert(t.policy_version);
        actors.last_seen.insert(msg.actor, Instant::now());
        let mut publish = false;
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
                        (last_loss, last_actor, last_aux) =
                            (l.critic as f64, l.actor as f64, l.alpha as f64);
                    }
                    updates += due;
                    since_publish += due;
                }
                publish = since_publish >= cfg.publish_every
                    || (was_random && sac.env_steps >= sac.cfg.random_steps);
            }
            Backbone::Ppo(ppo, rollout) => {
                // NOTE: synchronous PPO trains only on the current version's data; older
                // trajectories are dropped and counted.
                if t.policy_version != version {
                    summary.stale_trajectories += 1;
                    continue;
                }
                rollout.push(t.clone());
                let steps: usize = rollout.iter().map(|t| t.steps()).sum();
                if steps >= ppo.cfg.rollout_steps {
                    let total = cfg.total_steps;
                    let stats = tokio::task::block_in_place(|| {
                        ppo.train(rollout, |r| cfg.reward.of(r), total)
                    })?;
                    (last_loss, last_actor, last_aux) = (
                        stats.value_loss as f64,
                        stats.policy_loss as f64,
                        stats.approx_kl as f64,
                    );
                    updates += stats.minibatch_updates;
                    rollout.clear();
                    publish = true;
                }
            }
        }
        env_steps += t.steps() as u64;
        if let Some(bar) = &curve.bar {
            bar.set_position(env_steps.min(cfg.total_steps));
        }
        window.episodes += 1;
        window.truth += t.outcome.return_truth as f64;
        window.human += t.outcome.return_human as f64;
        window.task += t.outcome.return_task as f64;
        window.success += t.outcome.success as u8 as f64;
        if publish {
            version += 1;
            since_publish = 0;
            server
                .publish(&weights_of(&cfg, &backbone, version, env_steps)?)
                .await?;
        }
        if env_steps >= next_row || env_steps >= cfg.total_steps {
            next_row += cfg.log_every;
            let secs = start.elapsed().as_secs_f64().max(1e-9);
            let n = window.episodes.max(1) as f64;
            let row = CurveRow {
                env_steps,
                wall_s: secs,
                eval_episodes: 0,
                eval_return_truth: f64::NAN,
                eval_success_rate: f64::NAN,
                eval_return_human: f64::NAN,
                eval_return_task: f64::NAN,
                eval_version: 0,
                episodes: window.episodes,
                return_truth: window.truth / n,
                success_rate: window.success / n,
                return_human: window.human / n,
                return_task: window.task / n,
                loss_critic_or_value: last_loss,
                loss_actor: last_actor,
                alpha_or_kl: last_aux,
                env_steps_per_s: env_steps as f64 / secs,
                updates_per_s: updates as f64 / secs,
                updates,
                policy_version: version,
                dropped_messages: trajectories.dropped.get()
                    + eval_results.dropped.get()
                    + summary.dropped_messages,
                stale_trajectories: summary.stale_trajectories,
            };
            if let Some(out) = &cfg.out {
                save_networks(out, &backbone, version, env_steps, updates)?;
            }
            if cfg.eval_episodes == 0 {
                curve.write(row, &mut summary)?;
            } else {
                let request = EvalRequest {
                    id: env_steps,
                    actor: actors.next(),
                    weights: weights_of(&cfg, &backbone, version, env_steps)?,
                    seeds: seeds.clone(),
                };
                send_eval(&session, &keys, &request).await?;
                curve.pending.push_back(Pending {
                    row,
                    request,
                    sent: Instant::now(),
                    tries: 1,
                });
            }
            window = Window::default();
        }
    }
    // The last evaluations: the actors answer while they wait for weights that will not
    // come; their last trajectories are drained so nothing blocks.
    while !stopped && !curve.pending.is_empty() {
        tokio::select! {
            _ = &mut shutdown => break,
            r = eval_results.next(pick_result) => curve.complete(r?, &mut summary)?,
            _ = tick.tick() => {
                retry_evaluations(&session, &keys, &mut curve, &mut actors, &mut summary).await?;
            }
            m = trajectories.next() => { m?; }
        }
    }
    curve.flush(&mut summary)?;
    if let Some(bar) = &curve.bar {
        bar.finish();
    }
    let _ = stop.put(wire::encode(&cfg.run, &Body::Stop)).await;
    summary.env_steps = env_steps;
    summary.updates = updates;
    summary.policy_version = version;
    summary.dropped_messages += trajectories.dropped.get() + eval_results.dropped.get();
    Ok(summary)
}
