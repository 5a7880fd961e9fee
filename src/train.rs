//! `pbrl train`, `pbrl learner`, `pbrl actor`: the arguments and the wiring of the services.

use std::collections::BTreeSet;
use std::path::PathBuf;

use anyhow::{Context, Result};
use clap::Args;
use pbrl_actor::cli::WorldArgs;
use pbrl_actor::runner::{self, ActorConfig, Task, POINT_HORIZON};
use pbrl_common::connect::{free_local_port, ConnectArgs};
use pbrl_learner::config::{self, PrefConfig, Setting};
use pbrl_learner::ppo::PpoConfig;
use pbrl_learner::run_folder::RunFolder;
use pbrl_learner::sac::SacConfig;
use pbrl_learner::service::{self, Algo, LearnerConfig, RewardSource};
use pbrl_teacher::human::HumanConfig;
use pbrl_teacher::scripted::{ScriptedConfig, TeacherKind};
use pbrl_teacher::service::{self as teaching, default_id, TeacherConfig, TeacherSummary};
use pbrl_teacher::web::HttpConfig;

/// What to learn and how long: shared by `train` and `learner`. The backbones' and
/// preference learning's settings are flags from their own config structs (flattened).
#[derive(Args, Clone, Debug)]
pub struct LearnArgs {
    /// RL backbone: SAC (PEBBLE) or PPO (PrefPPO).
    #[arg(long, value_enum, default_value = "sac")]
    pub algo: Algo,
    /// Reward to train on: learnt from preferences and decoupled from the task reward
    /// (the paper's method), learnt alone (PEBBLE, PrefPPO), or the baselines' ground
    /// truth and task reward.
    #[arg(long, value_enum, default_value = "decoupled")]
    pub reward: RewardSource,
    /// Env steps of the run.
    #[arg(long, default_value_t = 1_000_000)]
    pub steps: u64,
    /// Seed of the run.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Task: the feeding world, or the point task made for tests.
    #[arg(long, value_enum, default_value = "feeding")]
    pub task: Task,
    /// Network sizes: 256x256 (SAC, batch 256), 512x512 (PPO) and 3x64 (reward
    /// ensemble), or the authors' sizes everywhere (`paper`: 512x512, SAC batch 512,
    /// reward 3x256). Flags given explicitly win over a preset.
    #[arg(long, default_value = "default", value_parser = ["default", "paper"])]
    pub preset: String,
    /// Env steps between rows of the learning curve.
    #[arg(long, default_value_t = 10_000)]
    pub log_every: u64,
    /// Evaluation episodes at each row of the learning curve: the policy's mean action on
    /// fixed seeds (30 give a success rate to about +-0.17 at 95%); 0 turns evaluation off.
    #[arg(long, default_value_t = 30)]
    pub eval_episodes: u32,
    /// Evaluate with the mean action only (by default the same seeds are also run with
    /// sampled actions: the policy as it trains, as the paper's figures show it).
    #[arg(long)]
    pub eval_mean_only: bool,
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
    /// its answers, so a run is a function of its seed.
    #[arg(long)]
    pub sync: bool,
    /// Start over even if the run folder holds a run (default: resume it; the label store
    /// is kept aside, never deleted).
    #[arg(long)]
    pub fresh: bool,
    /// No progress bar even on a terminal.
    #[arg(long)]
    pub quiet: bool,
    /// Run id (key expressions `pbrl/<run>/...`); default `<algo>-<reward>-s<seed>`.
    #[arg(long)]
    pub run: Option<String>,
    /// Run folder (config.json, curve.csv, labels.sqlite); default `runs/<run>`.
    #[arg(long)]
    pub out: Option<PathBuf>,
    #[command(flatten)]
    pub sac: SacConfig,
    #[command(flatten)]
    pub ppo: PpoConfig,
    #[command(flatten)]
    pub pref: PrefConfig,
    /// The clap ids of the flags given on the command line (presets leave them alone).
    #[arg(skip)]
    pub explicit: BTreeSet<String>,
}

/// The clap ids of the flags a subcommand's matches got from the command line.
pub fn explicit_flags(m: &clap::ArgMatches) -> BTreeSet<String> {
    m.ids()
        .filter(|id| m.value_source(id.as_str()) == Some(clap::parser::ValueSource::CommandLine))
        .map(|id| id.to_string())
        .collect()
}

/// The point task learns in seconds with small networks and short sessions.
fn point_preset() -> Vec<Setting> {
    use serde_json::json;
    let rollout = 32 * POINT_HORIZON;
    vec![
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
    ]
}

impl LearnArgs {
    pub fn run_id(&self) -> String {
        self.run.clone().unwrap_or_else(|| {
            format!("{:?}-{}-s{}", self.algo, self.reward.name(), self.seed).to_lowercase()
        })
    }

    /// The resolved learner config: the flags, then the presets on what was not given.
    fn learner_config(
        &self,
        actors: u32,
        episode_steps: u32,
        world: serde_json::Value,
    ) -> Result<LearnerConfig> {
        let (obs_dim, act_dim) = self.task.dims();
        let mut cfg = LearnerConfig::new(&self.run_id(), self.algo, self.reward, obs_dim, act_dim);
        cfg.total_steps = self.steps;
        cfg.sac = SacConfig {
            seed: self.seed,
            ..self.sac.clone()
        };
        cfg.ppo = PpoConfig {
            seed: self.seed,
            ..self.ppo.clone()
        };
        cfg.pref = self.pref.clone();
        cfg.world = world;
        cfg.log_every = self.log_every;
        cfg.actors = actors;
        cfg.episode_steps = episode_steps;
        cfg.eval_episodes = self.eval_episodes;
        cfg.eval_sampled = !self.eval_mean_only;
        cfg.checkpoint_every = self.checkpoint_every;
        cfg.checkpoint_secs = self.checkpoint_secs;
        cfg.keep_checkpoints = self.keep_checkpoints;
        cfg.sync = self.sync;
        cfg.progress = !self.quiet && std::io::IsTerminal::is_terminal(&std::io::stderr());
        cfg.out = Some(self.out_dir());
        if self.algo == Algo::Ppo {
            config::apply_preset(&mut cfg, &config::ppo_preset(), &self.explicit)?;
        }
        if self.preset == "paper" {
            config::apply_preset(&mut cfg, &config::paper_preset(), &self.explicit)?;
        }
        if self.task == Task::Point {
            config::apply_preset(&mut cfg, &point_preset(), &self.explicit)?;
        }
        // NOTE: Decoupled PEBBLE trains on lambda_t r_task + r_hat with lambda_0 15: SAC's
        // critics then chase targets 15 times the task baseline's, and learn them slower
        // at the same learning rate. Scaled by 1 / lambda_0 they keep the baseline's size
        // (measured on feeding, 3 seeds at 1M env steps: success 0.60 against 0.46).
        let scaled = self.algo == Algo::Sac
            && self.reward == RewardSource::Decoupled
            && self.preset != "paper"
            && !self.explicit.contains("sac_reward_scale")
            && !cfg.sac.lambda_scale;
        if scaled {
            cfg.sac.reward_scale = 1.0 / cfg.pref.lambda0.max(1.0);
        }
        cfg.validate()?;
        Ok(cfg)
    }

    /// The run folder.
    pub fn out_dir(&self) -> PathBuf {
        self.out
            .clone()
            .unwrap_or_else(|| PathBuf::from("runs").join(self.run_id()))
    }

    /// Prepare the run folder: cleared with `--fresh`. Returns false when the run there
    /// has already reached this total (nothing to do).
    fn prepare(&self) -> Result<bool> {
        let folder = RunFolder::new(self.out_dir());
        if self.fresh {
            folder.clear_fresh()?;
            return Ok(true);
        }
        if let Some(steps) = folder.finished_steps()? {
            if steps >= self.steps {
                println!(
                    "{}: finished at {steps} env steps (asked for {}); nothing to do (--fresh starts over)",
                    folder.root.display(),
                    self.steps
                );
                return Ok(false);
            }
        }
        Ok(true)
    }
}

/// `pbrl train` (router, learner and actors in one process) and `pbrl learner` (the
/// learner alone, joining a Zenoh network).
#[derive(Args, Debug)]
pub struct TrainArgs {
    #[command(flatten)]
    pub learn: LearnArgs,
    /// Actors: `train` starts this many tasks (on the process's one Zenoh session); for
    /// `learner` it is how many will join (the learner's flow control counts on it).
    #[arg(long, default_value_t = 2)]
    pub actors: u32,
    #[command(flatten)]
    pub teacher: TeacherArgs,
    /// `train`: no teacher in this process (one joins over Zenoh: `pbrl teacher`).
    #[arg(long)]
    pub external_teacher: bool,
    #[command(flatten)]
    pub world: WorldArgs,
    #[command(flatten)]
    pub connect: ConnectArgs,
}

/// Who answers preference queries.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Who {
    /// A scripted teacher of paper Table I.
    Scripted(TeacherKind),
    /// People, at the labelling page (or any client of its API).
    Human,
}

fn parse_teacher(s: &str) -> Result<Who, String> {
    if s == "human" {
        return Ok(Who::Human);
    }
    TeacherKind::ALL
        .into_iter()
        .find(|k| k.name() == s)
        .map(Who::Scripted)
        .ok_or_else(|| {
            let names: Vec<&str> = TeacherKind::ALL.iter().map(|k| k.name()).collect();
            format!("{s:?} is not a teacher: {} or human", names.join(", "))
        })
}

/// The shadow teacher of a person (`--shadow`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum Shadow {
    /// The oracle judges each query a person answers, on the ground truth; recorded
    /// beside the person's answer, never shown and never trained on.
    Oracle,
}

/// The human teacher's page and queue.
#[derive(Args, Clone, Debug)]
pub struct HumanArgs {
    /// Human teacher: where the labelling page listens (loopback unless a --token is set).
    #[arg(long, default_value = "127.0.0.1:8080")]
    pub http: std::net::SocketAddr,
    /// Human teacher: the access token every API call must carry (needed beyond loopback;
    /// default: the PBRL_TOKEN environment variable).
    #[arg(long)]
    pub token: Option<String>,
    /// Human teacher: seconds an answer can be undone before it goes to the learner.
    #[arg(long, default_value_t = 10)]
    pub undo_s: u64,
    /// Human teacher: share of answered queries asked again (of the same person, and of
    /// another when two are labelling), to measure consistency and agreement.
    #[arg(long, default_value_t = 0.1)]
    pub repeat_share: f64,
    /// Human teacher: record a scripted teacher's answer beside each person's.
    #[arg(long, value_enum)]
    pub shadow: Option<Shadow>,
    /// Human teacher: the queue's file (default: `teacher.sqlite` in the run folder for
    /// `train`, `teacher-<run>.sqlite` here for `teacher`).
    #[arg(long)]
    pub teacher_state: Option<PathBuf>,
}

impl HumanArgs {
    fn config(&self, state: PathBuf, seed: u64) -> HumanConfig {
        HumanConfig {
            undo_s: self.undo_s,
            repeat_share: self.repeat_share,
            shadow: self.shadow.is_some(),
            seed,
            ..HumanConfig::new(&self.teacher_state.clone().unwrap_or(state))
        }
    }

    fn http(&self) -> HttpConfig {
        HttpConfig {
            addr: self.http,
            token: self
                .token
                .clone()
                .or_else(|| std::env::var("PBRL_TOKEN").ok().filter(|t| !t.is_empty())),
        }
    }
}

/// The teacher, in `train` (in-process) and `teacher`.
#[derive(Args, Clone, Debug)]
pub struct TeacherArgs {
    /// Who answers preference queries: a scripted teacher of paper Table I (oracle, noisy,
    /// mistake, skip, equal, myopic) or people at a labelling page (human).
    #[arg(long = "teacher", default_value = "oracle", value_parser = parse_teacher)]
    pub kind: Who,
    /// Lowest possible ground-truth return (the skip and equal thresholds are fractions of
    /// the mean return above it); default -350 on feeding (the authors'), -100 on the
    /// point task.
    #[arg(long)]
    pub teacher_r_min: Option<f64>,
    /// The teacher's id on the network (default `<kind>-<seed>`).
    #[arg(long)]
    pub teacher_id: Option<String>,
    #[command(flatten)]
    pub human: HumanArgs,
}

impl TeacherArgs {
    fn configs(&self, run: &str, task: Task, seed: u64) -> (TeacherConfig, ScriptedConfig) {
        let kind = match self.kind {
            Who::Scripted(k) => k,
            Who::Human => TeacherKind::Oracle,
        };
        let mut scripted = ScriptedConfig::of(kind, seed);
        scripted.r_min = self.teacher_r_min.unwrap_or(match task {
            Task::Feeding => -350.0,
            Task::Point => -100.0,
        });
        let id = self.teacher_id.clone().unwrap_or_else(|| match self.kind {
            Who::Scripted(k) => default_id(k, seed),
            Who::Human => format!("human-{seed}"),
        });
        (TeacherConfig::new(run, &id), scripted)
    }

    /// Run the teacher until `shutdown`: scripted, or the human teacher's page (feeding
    /// only: a person watches the episodes) with its queue in `state`.
    #[allow(clippy::too_many_arguments)]
    async fn run(
        &self,
        run: &str,
        task: Task,
        seed: u64,
        world: &pbrl_actor::WorldConfig,
        state: PathBuf,
        session: zenoh::Session,
        shutdown: impl std::future::Future<Output = ()>,
    ) -> Result<TeacherSummary> {
        let (cfg, scripted) = self.configs(run, task, seed);
        match self.kind {
            Who::Scripted(_) => teaching::run(cfg, scripted, session, shutdown).await,
            Who::Human => {
                if task != Task::Feeding {
                    anyhow::bail!(
                        "--teacher human: people judge feeding episodes; the {task:?} task has nothing to watch"
                    );
                }
                teaching::run_human(
                    cfg,
                    self.human.config(state, seed),
                    self.human.http(),
                    world.clone(),
                    session,
                    shutdown,
                )
                .await
            }
        }
    }
}

/// `pbrl teacher`: a scripted teacher, or people at a labelling page, joining a Zenoh
/// network.
#[derive(Args, Debug)]
pub struct TeacherProcessArgs {
    /// Run id, as the learner's.
    #[arg(long)]
    pub run: String,
    #[command(flatten)]
    pub teacher: TeacherArgs,
    /// People answer, at the labelling page on --http (as `--teacher human`).
    #[arg(long)]
    pub human: bool,
    #[command(flatten)]
    pub world: WorldArgs,
    #[arg(long, value_enum, default_value = "feeding")]
    pub task: Task,
    /// Seed of the teacher's random choices (noisy, mistake).
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    #[command(flatten)]
    pub connect: ConnectArgs,
}

pub async fn teacher(mut args: TeacherProcessArgs) -> Result<()> {
    if args.human {
        args.teacher.kind = Who::Human;
    }
    let world = args.world.config()?;
    let state = PathBuf::from(format!("teacher-{}.sqlite", args.run));
    let session = args.connect.open().await?;
    let s = args
        .teacher
        .run(
            &args.run,
            args.task,
            args.seed,
            &world,
            state,
            session,
            stop_signal(),
        )
        .await?;
    println!(
        "teacher done: {} queries judged ({:?}), {} answers sent again, {} acknowledged",
        s.judged, s.by_kind, s.resent, s.acknowledged
    );
    Ok(())
}

/// The world the actors simulate, as the run folder records it.
fn world_json(task: Task, world: &pbrl_actor::WorldConfig) -> Result<serde_json::Value> {
    Ok(match task {
        Task::Feeding => {
            serde_json::json!({ "task": "feeding", "config": serde_json::to_value(world)? })
        }
        Task::Point => serde_json::json!({ "task": "point" }),
    })
}

/// `pbrl actor`: one actor, joining a Zenoh network.
#[derive(Args, Debug)]
pub struct ActorArgs {
    /// This actor's number (distinct per actor of a run).
    #[arg(long, default_value_t = 0)]
    pub id: u32,
    /// Run id, as the learner's.
    #[arg(long)]
    pub run: String,
    #[arg(long, value_enum, default_value = "feeding")]
    pub task: Task,
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    #[command(flatten)]
    pub world: WorldArgs,
    #[command(flatten)]
    pub connect: ConnectArgs,
}

fn episode_steps(task: Task, world: &pbrl_actor::WorldConfig) -> u32 {
    match task {
        Task::Feeding => world.episode_steps,
        Task::Point => POINT_HORIZON,
    }
}

/// A flag set at the first SIGINT or SIGTERM (a second one exits at once), watched on
/// `runtime`.
pub fn stop_flag(
    runtime: &tokio::runtime::Runtime,
) -> std::sync::Arc<std::sync::atomic::AtomicBool> {
    let flag = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    let f = flag.clone();
    runtime.spawn(async move {
        stop_signal().await;
        f.store(true, std::sync::atomic::Ordering::Relaxed);
    });
    flag
}

/// Resolves at the first SIGINT or SIGTERM (the learner then finishes its update, writes
/// a checkpoint and stops the actors); a second signal exits at once.
async fn stop_signal() {
    use tokio::signal::unix::{signal, SignalKind};
    // NOTE: if the handlers cannot be installed, run until done instead.
    let (Ok(mut term), Ok(mut int)) = (
        signal(SignalKind::terminate()),
        signal(SignalKind::interrupt()),
    ) else {
        return std::future::pending().await;
    };
    tokio::select! {
        _ = term.recv() => {}
        _ = int.recv() => {}
    }
    tracing::warn!(
        "stopping: finishing the update and writing a checkpoint; a second signal exits at once"
    );
    tokio::spawn(async move {
        tokio::select! {
            _ = term.recv() => {}
            _ = int.recv() => {}
        }
        eprintln!("second signal: exiting now");
        std::process::exit(130);
    });
}

pub async fn train(args: TrainArgs) -> Result<()> {
    if !args.learn.prepare()? {
        return Ok(());
    }
    let (summary, out) = train_in_process(args).await?;
    if summary.stopped {
        println!(
            "stopped at {} env steps; a checkpoint is written: run the same command to go on",
            summary.env_steps
        );
        return Ok(());
    }
    if let Some(last) = summary.rows.last() {
        println!(
            "done: {} env steps, {} updates, version {}; last evaluation: return {:.1}, success {:.0}%, preference return {:.1}; curve in {}",
            summary.env_steps,
            summary.updates,
            summary.policy_version,
            last.eval_return_truth,
            100.0 * last.eval_success_rate,
            last.eval_return_human,
            out.map(|p| p.join("curve.csv").display().to_string()).unwrap_or_default()
        );
    }
    Ok(())
}

/// Router, actors and learner in this process; the learner's summary and run folder.
///
/// NOTE: the learner and the actors share one Zenoh session (the router's, or the one that
/// joins `--connect`): between them a message is a function call, with no transport to
/// stall or close. Each session that talks over a transport runs its reads on zenoh's two
/// receive threads, shared by every session of a process, so a router and client sessions
/// in one process can block one another (`common::bus` tells how).
async fn train_in_process(args: TrainArgs) -> Result<(service::Summary, Option<PathBuf>)> {
    let world = args.world.config()?;
    let cfg = args.learn.learner_config(
        args.actors,
        episode_steps(args.learn.task, &world),
        world_json(args.learn.task, &world)?,
    )?;
    // The embedded router on loopback, unless told to join an existing network.
    let (endpoint, session) = if args.connect.connect.is_empty() {
        let listen = match args.connect.listen.first() {
            Some(e) => e.clone(),
            None => format!("tcp/127.0.0.1:{}", free_local_port()?),
        };
        let router = ConnectArgs {
            multicast: args.connect.multicast,
            config: args.connect.config.clone(),
            ..ConnectArgs::router_on(&listen)
        }
        .open()
        .await
        .context("starting the in-process router")?;
        (listen, router)
    } else {
        let session = args.connect.open().await?;
        (args.connect.connect[0].clone(), session)
    };
    tracing::info!(%endpoint, run = %cfg.run, actors = args.actors, "train");
    if args.teacher.kind == Who::Human && cfg.reward.learnt() && !args.external_teacher {
        // NOTE: fail before training starts, not when the page cannot be served.
        args.teacher.human.http().validate()?;
        if args.learn.task != Task::Feeding {
            anyhow::bail!("--teacher human: people judge feeding episodes; use --task feeding");
        }
    }
    let mut actors = Vec::new();
    let (tx, rx) = tokio::sync::watch::channel(false);
    for id in 0..args.actors {
        let acfg = ActorConfig {
            id,
            run: cfg.run.clone(),
            task: args.learn.task,
            world: world.clone(),
            seed: args.learn.seed,
        };
        let mut rx = rx.clone();
        actors.push(tokio::spawn(runner::run(
            acfg,
            session.clone(),
            async move {
                let _ = rx.wait_for(|stop| *stop).await;
            },
        )));
    }
    // The scripted teacher, on the same session, when the reward is learnt.
    let teacher = (cfg.reward.learnt() && !args.external_teacher).then(|| {
        let mut rx = rx.clone();
        let teacher = args.teacher.clone();
        let (run, task, seed) = (cfg.run.clone(), args.learn.task, args.learn.seed);
        let state = cfg.out.as_ref().map_or_else(
            || PathBuf::from(":memory:"),
            |o| RunFolder::new(o).teacher(),
        );
        let (world, session) = (world.clone(), session.clone());
        tokio::spawn(async move {
            teacher
                .run(&run, task, seed, &world, state, session, async move {
                    let _ = rx.wait_for(|stop| *stop).await;
                })
                .await
        })
    });
    let out = cfg.out.clone();
    let summary = service::run(cfg, session, stop_signal()).await?;
    let _ = tx.send(true);
    if let Some(t) = teacher {
        match t.await {
            Ok(Err(e)) => tracing::warn!(error = %e, "the teacher failed"),
            Err(e) => tracing::warn!(error = %e, "the teacher task died"),
            Ok(Ok(_)) => {}
        }
    }
    for a in actors {
        match a.await {
            Ok(Err(e)) => tracing::warn!(error = %e, "an actor failed"),
            Err(e) => tracing::warn!(error = %e, "an actor task died"),
            Ok(Ok(())) => {}
        }
    }
    Ok((summary, out))
}

pub async fn learner(args: TrainArgs) -> Result<()> {
    if !args.learn.prepare()? {
        return Ok(());
    }
    let world = args.world.config()?;
    let cfg = args.learn.learner_config(
        args.actors,
        episode_steps(args.learn.task, &world),
        world_json(args.learn.task, &world)?,
    )?;
    let session = args.connect.open().await?;
    let summary = service::run(cfg, session, stop_signal()).await?;
    println!(
        "done: {} env steps, {} updates, version {}",
        summary.env_steps, summary.updates, summary.policy_version
    );
    Ok(())
}

pub async fn actor(args: ActorArgs) -> Result<()> {
    let cfg = ActorConfig {
        id: args.id,
        run: args.run,
        task: args.task,
        world: args.world.config()?,
        seed: args.seed,
    };
    let session = args.connect.open().await?;
    runner::run(cfg, session, stop_signal()).await
}

#[derive(clap::Subcommand, Debug)]
pub enum BenchCommand {
    /// SAC gradient steps and PPO minibatch updates per second (obs 25, action 7), at
    /// 256x256 / batch 256 and 512x512 / batch 512, on 1 and 2 threads.
    Learner {
        /// Gradient steps per timing.
        #[arg(long, default_value_t = 30)]
        steps: usize,
    },
    /// End-to-end env steps per second of `pbrl train` (feeding, in-process router, no
    /// evaluation) with 1 and 2 actors, for SAC and PPO.
    Train {
        /// Env steps per run (SAC's first 600 are random actions without updates).
        #[arg(long, default_value_t = 20_000)]
        steps: u64,
        /// Env steps between checkpoints (0: only the final one).
        #[arg(long, default_value_t = 0)]
        checkpoint_every: u64,
        /// Only this algorithm.
        #[arg(long)]
        algo: Option<String>,
        /// Rewards to time, each a run (the learnt ones with the in-process oracle;
        /// comma-separated).
        #[arg(long, value_delimiter = ',', default_value = "truth,decoupled")]
        rewards: Vec<String>,
        /// Actor counts to time (comma-separated).
        #[arg(long, value_delimiter = ',', default_value = "1,2")]
        actors: Vec<u32>,
        /// More `pbrl train` flags for every run, after `--` (say, `-- --reward-max-pairs
        /// 4096`).
        #[arg(last = true)]
        train_flags: Vec<String>,
    },
    /// What a checkpoint costs with a full SAC replay buffer (feeding-sized transitions).
    Checkpoint {
        /// Transitions in the buffer.
        #[arg(long, default_value_t = 1_000_000)]
        transitions: u64,
        /// Transitions added before the second (incremental) checkpoint.
        #[arg(long, default_value_t = 50_000)]
        increment: u64,
    },
}

/// `pbrl train`'s arguments, parsed from a command line (for the benchmark).
#[derive(clap::Parser, Debug)]
struct TrainLine {
    #[command(flatten)]
    args: TrainArgs,
}

fn bench_train(
    steps: u64,
    checkpoint_every: u64,
    only: Option<String>,
    rewards: &[String],
    actor_counts: &[u32],
    train_flags: &[String],
) -> Result<()> {
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()?;
    println!(
        "{:<5} {:<10} {:>6} {:>10} {:>12} {:>10} {:>8} {:>7}",
        "algo", "reward", "actors", "env steps", "env steps/s", "updates/s", "wall s", "labels"
    );
    for algo in ["sac", "ppo"] {
        if only.as_deref().is_some_and(|a| a != algo) {
            continue;
        }
        for &actors in actor_counts {
            // NOTE: the rewards of one algorithm and actor count run one after the other,
            // so their ratio is measured under the same conditions.
            for reward in rewards {
                let out = std::env::temp_dir().join(format!(
                    "pbrl-bench-train-{}-{algo}-{reward}-{actors}",
                    std::process::id()
                ));
                let line = [
                    "train".to_string(),
                    format!("--algo={algo}"),
                    format!("--reward={reward}"),
                    format!("--actors={actors}"),
                    format!("--steps={steps}"),
                    format!("--log-every={steps}"),
                    "--eval-episodes=0".into(),
                    format!("--checkpoint-every={checkpoint_every}"),
                    format!("--run=bench-{algo}-{reward}-{actors}"),
                    format!("--out={}", out.display()),
                ];
                let line = line.into_iter().chain(train_flags.iter().cloned());
                let matches =
                    <TrainLine as clap::CommandFactory>::command().try_get_matches_from(line)?;
                let TrainLine { mut args } =
                    <TrainLine as clap::FromArgMatches>::from_arg_matches(&matches)?;
                args.learn.explicit = explicit_flags(&matches);
                args.learn.quiet = true;
                let start = std::time::Instant::now();
                let (summary, _) = runtime.block_on(train_in_process(args))?;
                let wall = start.elapsed().as_secs_f64();
                let _ = std::fs::remove_dir_all(&out);
                println!(
                    "{algo:<5} {reward:<10} {actors:>6} {:>10} {:>12.0} {:>10.1} {wall:>8.1} {:>7}",
                    summary.env_steps,
                    summary.env_steps as f64 / wall,
                    summary.updates as f64 / wall,
                    summary.labels.map_or(0, |c| c.answered),
                );
            }
        }
    }
    Ok(())
}

pub fn bench(cmd: BenchCommand) -> Result<()> {
    let steps = match cmd {
        BenchCommand::Learner { steps } => steps,
        BenchCommand::Train {
            steps,
            checkpoint_every,
            algo,
            rewards,
            actors,
            train_flags,
        } => {
            return bench_train(
                steps,
                checkpoint_every,
                algo,
                &rewards,
                &actors,
                &train_flags,
            )
        }
        BenchCommand::Checkpoint {
            transitions,
            increment,
        } => {
            let dir =
                std::env::temp_dir().join(format!("pbrl-bench-checkpoint-{}", std::process::id()));
            let c = pbrl_learner::checkpoint::bench(&dir, transitions, increment);
            let _ = std::fs::remove_dir_all(&dir);
            let c = c?;
            let mb = |b: u64| b as f64 / 1e6;
            println!(
                "replay buffer of {} transitions (obs 25, action 7), SAC 256x256:",
                c.transitions
            );
            println!(
                "  first checkpoint (whole buffer): {:.0} ms, {:.1} MB",
                c.full_ms,
                mb(c.full_bytes)
            );
            println!(
                "  next checkpoint (+{} transitions): {:.0} ms, {:.1} MB",
                c.increment,
                c.increment_ms,
                mb(c.increment_bytes)
            );
            println!(
                "  restore (checks, networks, buffer): {:.0} ms",
                c.restore_ms
            );
            return Ok(());
        }
    };
    println!(
        "{:<8} {:>10} {:>8} {:>12} {:>12}",
        "threads", "hidden", "batch", "SAC ms/step", "PPO ms/mb"
    );
    for threads in [1, 2] {
        // NOTE: candle reads RAYON_NUM_THREADS at every matmul.
        std::env::set_var("RAYON_NUM_THREADS", threads.to_string());
        for (hidden, batch) in [(256, 256), (512, 512)] {
            let sac = pbrl_learner::bench::sac_step_ms(hidden, batch, steps, 3)?;
            let ppo = pbrl_learner::bench::ppo_update_ms(hidden, batch, 4000)?;
            println!(
                "{threads:<8} {:>10} {batch:>8} {sac:>12.2} {ppo:>12.2}   ({:.0} SAC steps/s, {:.0} PPO updates/s)",
                format!("{hidden}x{hidden}"),
                1e3 / sac,
                1e3 / ppo
            );
        }
    }
    // What preference learning adds, on one thread (as a service runs).
    std::env::set_var("RAYON_NUM_THREADS", "1");
    println!();
    println!("preference learning (1 thread):");
    for (reward_hidden, name) in [(vec![64, 64, 64], "3x64"), (vec![256, 256, 256], "3x256")] {
        let plain = pbrl_learner::bench::sac_step_ms(256, 256, steps, 3)?;
        let relabelled =
            pbrl_learner::bench::sac_step_relabelled_ms(256, 256, steps, 3, &reward_hidden)?;
        let epoch = pbrl_learner::reward_model::bench_epoch(1000, 200, &reward_hidden)?;
        println!(
            "  ensemble 3 x {name}: SAC step (256x256, B=256) {plain:.2} ms, relabelled {relabelled:.2} ms (+{:.0}%); one training epoch over 1,000 labels of 200-step pairs {epoch:.2} s",
            100.0 * (relabelled / plain - 1.0)
        );
    }
    Ok(())
}
