//! `pbrl train`, `pbrl learner`, `pbrl actor`: the arguments and the wiring of the services.

use std::collections::BTreeSet;
use std::path::PathBuf;

use anyhow::{Context, Result};
use clap::Args;
use pbrl_actor::cli::WorldArgs;
use pbrl_actor::runner::{self, ActorConfig, Task, POINT_HORIZON};
use pbrl_common::connect::{free_local_port, ConnectArgs};
use pbrl_learner::run::config;
use pbrl_learner::run::run_folder::RunFolder;
use pbrl_learner::run::service::{self, Algo, LearnerConfig};
use pbrl_teacher::human::HumanConfig;
use pbrl_teacher::pace::PaceConfig;
use pbrl_teacher::scripted::{ScriptedConfig, TeacherKind};
use pbrl_teacher::service::{self as teaching, default_id, TeacherConfig, TeacherSummary};
use pbrl_teacher::web::HttpConfig;

/// What to learn and how long: shared by `train` and `learner`. The learner's settings
/// (backbones, preference learning, the run's curve and checkpoints) are its config's own
/// flags (flattened); these are the ones that choose among them.
#[derive(Args, Clone, Debug)]
pub struct LearnArgs {
    #[command(flatten)]
    pub learner: LearnerConfig,
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
    /// Start over even if the run folder holds a run (default: resume it; the label store
    /// is kept aside, never deleted).
    #[arg(long)]
    pub fresh: bool,
    /// No progress bar even on a terminal.
    #[arg(long)]
    pub quiet: bool,
    /// On the point task, keep the default label-efficient settings (segments, the
    /// budget's schedule, crops, comfort features, hybrid replay, the task prior) rather
    /// than the point preset's plain ones: what `pbrl train` runs on feeding, on a task
    /// small enough for the fault and multi-host tests.
    #[arg(long)]
    pub label_efficient: bool,
    /// Run id (key expressions `pbrl/<run>/...`); default `<algo>-<reward>-s<seed>`.
    #[arg(long)]
    pub run: Option<String>,
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

impl LearnArgs {
    pub fn run_id(&self) -> String {
        let l = &self.learner;
        self.run.clone().unwrap_or_else(|| {
            format!("{:?}-{}-s{}", l.algo, l.reward.name(), self.seed).to_lowercase()
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
        let mut cfg = self.learner.clone();
        cfg.run = self.run_id();
        (cfg.obs_dim, cfg.act_dim) = (obs_dim, act_dim);
        (cfg.sac.seed, cfg.ppo.seed) = (self.seed, self.seed);
        cfg.world = world;
        cfg.actors = actors;
        cfg.episode_steps = episode_steps;
        cfg.progress = !self.quiet && std::io::IsTerminal::is_terminal(&std::io::stderr());
        cfg.out = Some(self.out_dir());
        if cfg.algo == Algo::Ppo {
            config::apply_preset(&mut cfg, &config::ppo_preset(), &self.explicit)?;
        }
        if self.preset == "paper" {
            let preset = config::paper_preset(cfg.algo);
            config::apply_preset(&mut cfg, &preset, &self.explicit)?;
        }
        if self.task == Task::Point {
            let preset = config::point_preset(POINT_HORIZON, self.label_efficient);
            config::apply_preset(&mut cfg, &preset, &self.explicit)?;
        }
        // NOTE: only where it is read: a run checkpointed without it resumes.
        if cfg.pref.model.anchor > 0.0 {
            cfg.pref.model.goal = Some(self.task.goal_obs());
        }
        cfg.scale_decoupled_reward(self.preset == "paper", &self.explicit);
        cfg.validate()?;
        Ok(cfg)
    }

    /// The run folder.
    pub fn out_dir(&self) -> PathBuf {
        self.learner
            .out
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
        let total = self.learner.total_steps;
        if let Some(steps) = folder.finished_steps()? {
            if steps >= total {
                println!(
                    "{}: finished at {steps} env steps (asked for {total}); nothing to do (--fresh starts over)",
                    folder.root.display(),
                );
                if self.task == Task::Feeding {
                    print!("{}", next_steps(&folder.root));
                }
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
    TeacherKind::EVERY
        .into_iter()
        .find(|k| k.name() == s)
        .map(Who::Scripted)
        .ok_or_else(|| {
            let names: Vec<&str> = TeacherKind::EVERY.iter().map(|k| k.name()).collect();
            format!("{s:?} is not a teacher: {} or human", names.join(", "))
        })
}

/// The human teacher's page and queue.
#[derive(Args, Clone, Debug)]
pub struct HumanArgs {
    #[command(flatten)]
    pub http: HttpConfig,
    #[command(flatten)]
    pub desk: HumanConfig,
}

impl HumanArgs {
    fn config(&self, seed: u64) -> HumanConfig {
        HumanConfig {
            seed,
            ..self.desk.clone()
        }
    }

    fn http(&self) -> HttpConfig {
        self.http.clone().with_env_token()
    }
}

/// The teacher, in `train` (in-process) and `teacher`.
#[derive(Args, Clone, Debug)]
pub struct TeacherArgs {
    /// Who answers preference queries: a scripted teacher of paper Table I (oracle, noisy,
    /// mistake, skip, equal, myopic), one that errs like a person (hurried: takes the
    /// livelier of two attempts too close to tell apart) or people at a labelling page
    /// (human).
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
    /// The teacher's file: every answer it gives, kept until the learner has stored it
    /// (a teacher restarted on it sends those again, never judging a query twice), and
    /// people's queue (default: `teacher.sqlite` in the run folder for `train`,
    /// `teacher-<run>.sqlite` here for `teacher`).
    #[arg(long)]
    pub teacher_state: Option<PathBuf>,
    #[command(flatten)]
    pub human: HumanArgs,
    /// A scripted teacher at a person's pace (it then stands in for a person: the learner
    /// asks it as it asks people at a page, just in time).
    #[command(flatten)]
    pub pace: PaceConfig,
}

impl TeacherArgs {
    /// The pace's settings hold, and are for a scripted teacher (people keep their own).
    fn validate(&self) -> Result<()> {
        self.pace.validate()?;
        if self.kind == Who::Human && self.pace.paced() {
            anyhow::bail!(
                "--answer-s and --answer-watch pace a scripted teacher; people at the page answer at their own pace"
            );
        }
        Ok(())
    }

    /// The teacher stands in for a person (people at a page, or a scripted teacher at a
    /// person's pace).
    fn is_person(&self) -> bool {
        self.kind == Who::Human || self.pace.paced()
    }

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
    /// only: a person watches the episodes), with its outbox (and people's queue) in
    /// `state` unless `--teacher-state` says where.
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
        let (mut cfg, scripted) = self.configs(run, task, seed);
        cfg.state = self.teacher_state.clone().unwrap_or(state);
        match self.kind {
            Who::Scripted(_) => {
                teaching::run_paced(cfg, scripted, self.pace.clone(), session, shutdown).await
            }
            Who::Human => {
                if task != Task::Feeding {
                    anyhow::bail!(
                        "--teacher human: people judge feeding episodes; the {task:?} task has nothing to watch"
                    );
                }
                teaching::run_human(
                    cfg,
                    self.human.config(seed),
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
    /// Who answers: `--teacher human` for people at the labelling page on --http.
    #[command(flatten)]
    pub teacher: TeacherArgs,
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

pub async fn teacher(args: TeacherProcessArgs) -> Result<()> {
    let world = args.world.config()?;
    args.teacher.validate()?;
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

/// A run folder's stored feeding world, read through this build's `WorldConfig` and
/// written back when that adds fields (at their defaults, which keep the world as it was),
/// so that a run begun by an older build resumes (the learner compares configs field by
/// field). Nothing else in `config.json` changes.
fn upgrade_stored_world(out: &std::path::Path) -> Result<()> {
    let path = out.join("config.json");
    let Ok(text) = std::fs::read_to_string(&path) else {
        return Ok(());
    };
    let Ok(mut stored) = serde_json::from_str::<serde_json::Value>(&text) else {
        return Ok(()); // the learner names what is wrong with it
    };
    let Some(world) = stored.pointer_mut("/world/config") else {
        return Ok(());
    };
    let Ok(parsed) = serde_json::from_value::<pbrl_actor::WorldConfig>(world.clone()) else {
        return Ok(());
    };
    let upgraded = serde_json::to_value(parsed)?;
    if *world == upgraded {
        return Ok(());
    }
    *world = upgraded;
    let tmp = out.join("config.json.tmp");
    std::fs::write(&tmp, serde_json::to_string_pretty(&stored)?)
        .with_context(|| format!("writing {}", tmp.display()))?;
    std::fs::rename(&tmp, &path).with_context(|| format!("replacing {}", path.display()))?;
    tracing::info!(path = %path.display(), "the stored world gained this build's new fields, at their defaults");
    Ok(())
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
    // NOTE: eval, watch and export take feeding runs (the point task has nothing to show).
    let feeding = args.learn.task == Task::Feeding;
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
            out.as_ref().map(|p| p.join("curve.csv").display().to_string()).unwrap_or_default()
        );
    }
    if let (Some(dir), true) = (out, feeding) {
        print!("{}", next_steps(&dir));
    }
    Ok(())
}

/// What a finished run's folder is for next: its policy judged, watched and exported.
pub fn next_steps(dir: &std::path::Path) -> String {
    let d = dir.display();
    format!(
        "next:\n  pbrl eval {d}      its policy on 100 fixed episodes: success, returns, what the person minds (--people DIR: for others)\n  pbrl watch {d}     its episodes as the labelling page draws them: {d}/watch.html and watch.gif\n  pbrl export {d} --onnx {d}/policy.onnx     an ONNX model and its card for a robot stack\n"
    )
}

impl TrainArgs {
    /// The world the actors simulate and the learner's resolved config for it.
    fn configs(&self) -> Result<(pbrl_actor::WorldConfig, LearnerConfig)> {
        let world = self.world.config()?;
        let mut cfg = self.learn.learner_config(
            self.actors,
            episode_steps(self.learn.task, &world),
            world_json(self.learn.task, &world)?,
        )?;
        if let Some(out) = &cfg.out {
            upgrade_stored_world(out)?;
        }
        // NOTE: a person at the page (or a scripted teacher at a person's pace) is asked
        // just in time; scripted teachers as before.
        self.teacher.validate()?;
        if self.teacher.is_person() && !self.external_teacher {
            config::apply_preset(&mut cfg, &config::person_preset(), &self.learn.explicit)?;
            cfg.validate()?;
        }
        Ok((world, cfg))
    }
}

/// Router, actors and learner in this process; the learner's summary and run folder.
///
/// NOTE: the learner and the actors share one Zenoh session (the router's, or the one that
/// joins `--connect`): between them a message is a function call, with no transport to
/// stall or close. Each session that talks over a transport runs its reads on zenoh's two
/// receive threads, shared by every session of a process, so a router and client sessions
/// in one process can block one another (`common::bus` tells how).
pub(crate) async fn train_in_process(
    args: TrainArgs,
) -> Result<(service::Summary, Option<PathBuf>)> {
    let (world, cfg) = args.configs()?;
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
    // The teacher, on the same session, when the reward is learnt (its outbox in the run
    // folder).
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
    let (_, cfg) = args.configs()?;
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

#[cfg(test)]
mod tests {
    use super::*;
    use clap::{CommandFactory, FromArgMatches};

    /// `pbrl train ARGS`'s resolved learner config, as `main` resolves it.
    fn resolved(args: &[&str]) -> LearnerConfig {
        let line = ["pbrl", "train"].into_iter().chain(args.iter().copied());
        let m = crate::Cli::command().try_get_matches_from(line).unwrap();
        let crate::Command::Train(mut a) = crate::Cli::from_arg_matches(&m).unwrap().command else {
            panic!("not a train command");
        };
        a.learn.explicit = explicit_flags(m.subcommand().unwrap().1);
        a.learn
            .learner_config(2, 200, serde_json::Value::Null)
            .unwrap()
    }

    #[test]
    fn the_default_is_a_persons_budget_with_the_label_efficient_settings() {
        let c = resolved(&[]);
        assert_eq!(c.pref.max_feedback, 200);
        assert_eq!((c.pref.segment_len, c.pref.query_recent), (50, 10));
        assert_eq!(
            (c.pref.feedback_span, c.pref.feedback_decay),
            (240_000, 0.95)
        );
        assert_eq!((c.pref.model.crops, c.pref.model.features), (20, true));
        assert_eq!((c.sac.hybrid_share, c.pref.rho), (0.5, 3e-7));

        let off = resolved(&["--reward-features=false", "--segment-len", "0"]);
        assert!(!off.pref.model.features);
        assert_eq!(off.pref.segment_len, 0);
        assert!(resolved(&["--reward-features"]).pref.model.features);

        // The authors' method and budget, but what the user gave stays.
        let paper = resolved(&["--preset", "paper", "--segment-len", "25"]);
        assert_eq!(paper.pref.max_feedback, 50_000);
        assert_eq!(paper.pref.segment_len, 25);
        assert_eq!((paper.pref.query_recent, paper.pref.feedback_span), (0, 0));
        assert_eq!(
            (paper.pref.model.crops, paper.pref.model.features),
            (0, false)
        );
        assert_eq!(paper.sac.hybrid_share, 0.0);
    }
}
