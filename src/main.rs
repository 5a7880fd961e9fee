//! `pbrl`: the command line. It parses arguments, sets up logging and calls the crates.

mod bench;
mod eval;
mod exp;
mod export;
mod people;
mod plot;
mod prior;
mod train;
mod watch;

use anyhow::Result;
use clap::{CommandFactory, FromArgMatches, Parser, Subcommand};

#[derive(Parser, Debug)]
#[command(
    name = "pbrl",
    version,
    about = "Preference-based RL for personalised robot feeding"
)]
struct Cli {
    /// Show pbrl's progress on the terminal (feedback sessions, checkpoints, ...), not only
    /// the bar, the curve's rows and warnings; RUST_LOG sets the log fully.
    #[arg(long, global = true)]
    verbose: bool,
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// The feeding world: demo, bench, record, render.
    #[command(subcommand)]
    Env(pbrl_actor::cli::EnvCommand),
    /// Train in one process: an in-process Zenoh router, the learner and N actors.
    Train(train::TrainArgs),
    /// Run the learner alone, joining a Zenoh network (--connect or --listen).
    Learner(train::TrainArgs),
    /// Run one actor alone, joining a Zenoh network.
    Actor(train::ActorArgs),
    /// Run a teacher alone, answering a run's preference queries over Zenoh: scripted, or
    /// people at a labelling page (--teacher human).
    Teacher(train::TeacherProcessArgs),
    /// Experiments: a grid of runs (`pbrl exp run GRID.toml`) and its figures (`pbrl exp plot DIR`).
    #[command(subcommand)]
    Exp(exp::ExpCommand),
    /// The label store of a run: `pbrl labels stats RUN`.
    #[command(subcommand)]
    Labels(LabelsCommand),
    /// A run's learnt policy judged on fixed episodes, for its own person or others, beside
    /// other runs: `pbrl eval RUN... [--people DIR]`.
    Eval(eval::EvalArgs),
    /// A run's learnt policy on screen, as the labelling page draws attempts (two runs side
    /// by side on the same episodes): a self-contained HTML file and an animated GIF.
    Watch(watch::WatchArgs),
    /// A run's policy as an ONNX model for a robot stack, with its card (JSON):
    /// `pbrl export RUN --onnx FILE`.
    Export(export::ExportArgs),
    /// Simulated people: `pbrl people sample --n N --seed S --out DIR` writes one world
    /// config per person of the population (`docs/people.md`).
    #[command(subcommand)]
    People(people::PeopleCommand),
    /// A reward prior from other people's answers, for `pbrl train --prior FILE`: `pbrl
    /// prior RUN... --out FILE` (never from a held-out person's run).
    Prior(prior::PriorArgs),
    /// Benchmarks: `pbrl bench learner`.
    #[command(subcommand)]
    Bench(bench::BenchCommand),
}

#[derive(Subcommand, Debug)]
enum LabelsCommand {
    /// Per labeller: answers by kind, answers per minute, time to answer, consistency on
    /// queries asked again, agreement between labellers and with the oracle's shadow.
    Stats {
        /// The run folder (or its labels.sqlite).
        run: std::path::PathBuf,
    },
    /// How well the reward ensemble generalises from the run's labels: k-fold
    /// cross-validation of one training per fold with the given `--reward-...` settings
    /// (held-out accuracy), beside what the task prior alone (-d summed over each side)
    /// gets right. Read-only: safe while the run goes.
    Fit {
        /// The run folder (or its labels.sqlite).
        run: std::path::PathBuf,
        /// Folds of the cross-validation.
        #[arg(long, default_value_t = 5)]
        folds: usize,
        /// Seed of the folds and of the ensembles (fold k starts from seed + k).
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// The task the labels come from (where its observation holds the goal).
        #[arg(long, value_enum, default_value = "feeding")]
        task: pbrl_actor::runner::Task,
        #[command(flatten)]
        model: pbrl_learner::pref::reward_model::RewardModelConfig,
    },
}

/// The label store of a run folder, or the file given.
fn label_store_path(run: std::path::PathBuf) -> Result<std::path::PathBuf> {
    let path = if run.is_dir() {
        pbrl_learner::run::run_folder::RunFolder::new(&run).labels()
    } else {
        run
    };
    if !path.exists() {
        anyhow::bail!("no label store at {}", path.display());
    }
    Ok(path)
}

fn labels(cmd: LabelsCommand) -> Result<()> {
    match cmd {
        LabelsCommand::Stats { run } => {
            let path = label_store_path(run)?;
            let s = pbrl_learner::pref::label_stats::stats(&path)?;
            print!("{}", pbrl_learner::pref::label_stats::report(&s));
            Ok(())
        }
        LabelsCommand::Fit {
            run,
            folds,
            seed,
            task,
            mut model,
        } => {
            use pbrl_learner::pref::label_fit;
            let path = label_store_path(run)?;
            let labels = label_fit::read_labels(&path)?;
            if labels.obs_dim != task.dims().0 {
                anyhow::bail!(
                    "the labels' observations have {} numbers, task {task:?}'s {}: pass --task",
                    labels.obs_dim,
                    task.dims().0
                );
            }
            let goal = Some(task.goal_obs());
            model.seed = seed;
            if model.anchor > 0.0 {
                model.goal = goal;
            }
            let r = label_fit::cross_validate(&labels, &model, folds, seed, goal)?;
            print!("{}", label_fit::report(&r));
            Ok(())
        }
    }
}

/// The log: on the terminal (stderr) and, for a run, in its folder's `train.log`
/// (appended). Returns the run's log again, for the error that may end the run.
fn logging(command: &Command, verbose: bool) -> Result<Option<std::fs::File>> {
    use tracing_subscriber::layer::{Layer, SubscriberExt};
    use tracing_subscriber::util::SubscriberInitExt;
    let log_file = match command {
        Command::Train(a) | Command::Learner(a) => {
            let dir = a.learn.out_dir();
            std::fs::create_dir_all(&dir)?;
            let path = pbrl_learner::run::run_folder::RunFolder::new(dir).log();
            Some(
                std::fs::OpenOptions::new()
                    .create(true)
                    .append(true)
                    .open(&path)
                    .map_err(|e| anyhow::anyhow!("opening {}: {e}", path.display()))?,
            )
        }
        _ => None,
    };
    // NOTE: the error that ends a run goes to its log too (a run under `pbrl exp` has no
    // terminal; the runner points at the log).
    let error_log = log_file.as_ref().and_then(|f| f.try_clone().ok());
    // NOTE: the terminal shows by default the bar, one line per curve row (printed by the
    // bar; without a terminal, as log lines) and every crate's warnings and errors; the
    // run's `train.log` also keeps pbrl's own progress (feedback sessions, checkpoints).
    // `--verbose` brings pbrl's progress to the terminal too, and RUST_LOG sets both (zenoh's
    // INFO lines, the resolved config at debug). A benchmark prints its table and warnings
    // only (its runs' progress lines would break the table).
    let progress =
        "warn,pbrl=info,pbrl_common=info,pbrl_actor=info,pbrl_learner=info,pbrl_teacher=info";
    let on_terminal = std::io::IsTerminal::is_terminal(&std::io::stderr());
    let from_env = || tracing_subscriber::EnvFilter::try_from_default_env().ok();
    let terminal = from_env().unwrap_or_else(|| {
        if matches!(command, Command::Bench(_)) {
            "warn".into()
        } else if verbose {
            progress.into()
        } else if on_terminal {
            "warn".into()
        } else {
            format!("warn,{}=info", pbrl_learner::run::curve::CURVE_TARGET).into()
        }
    });
    let file = from_env().unwrap_or_else(|| progress.into());
    tracing_subscriber::registry()
        // NOTE: colour escapes only on a terminal; a pipe or a file gets plain text.
        .with(
            tracing_subscriber::fmt::layer()
                .with_ansi(on_terminal)
                .with_writer(pbrl_learner::run::curve::AroundTheBar)
                .with_filter(terminal),
        )
        .with(log_file.map(|f| {
            tracing_subscriber::fmt::layer()
                .with_ansi(false)
                .with_writer(std::sync::Mutex::new(f))
                .with_filter(file)
        }))
        .init();
    Ok(error_log)
}

/// candle's and rayon's thread pools at one thread each, unless the user says otherwise.
fn one_thread_pools() {
    // NOTE: candle's elementwise pool spins while its workers run; beside the actors and
    // zenoh, on 2 cores, a descheduled worker stalls the learner for whole time slices (a
    // SAC run next to another went at 60 env steps/s). It gains nothing at these sizes
    // (`shared/perf.md`), so pbrl runs it with one thread unless the user says otherwise.
    if std::env::var_os("CANDLE_NUM_THREADS").is_none() {
        std::env::set_var("CANDLE_NUM_THREADS", "1");
    }
    // NOTE: the same for candle's matmul: it asks rayon's thread count at every call, which
    // with RAYON_NUM_THREADS unset parses /proc/cpuinfo (thousands of opens a second in a
    // run), and its 2-thread gemm spins against zenoh's and the actors' threads. One thread
    // per service (`pbrl bench learner` sets its own); children of `exp run` inherit it.
    if std::env::var_os("RAYON_NUM_THREADS").is_none() {
        std::env::set_var("RAYON_NUM_THREADS", "1");
    }
}

fn main() -> Result<()> {
    // NOTE: before any thread starts (glibc's arenas are made as threads first allocate).
    pbrl_common::alloc::steady_allocator();
    let matches = Cli::command().get_matches();
    let (mut command, verbose) = match Cli::from_arg_matches(&matches) {
        Ok(cli) => (cli.command, cli.verbose),
        Err(e) => e.exit(),
    };
    // NOTE: presets change only what the user did not give on the command line.
    if let (Command::Train(a) | Command::Learner(a), Some((_, m))) =
        (&mut command, matches.subcommand())
    {
        a.learn.explicit = train::explicit_flags(m);
    }
    let mut error_log = logging(&command, verbose)?;
    one_thread_pools();
    match command {
        Command::Env(cmd) => return pbrl_actor::cli::run(cmd),
        Command::Bench(cmd) => return bench::run(cmd),
        Command::Labels(cmd) => return labels(cmd),
        Command::Eval(a) => return eval::eval(a),
        Command::Watch(a) => return watch::watch(a),
        Command::Export(a) => return export::export(a),
        Command::People(c) => return people::run(c),
        Command::Prior(a) => return prior::run(a),
        Command::Exp(exp::ExpCommand::Run(a)) => return exp::run(a),
        Command::Exp(exp::ExpCommand::Plot(a)) => return plot::plot(a),
        _ => {}
    }
    // NOTE: zenoh needs tokio's multi-thread scheduler; two workers match the 2 cores.
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()?;
    let result = runtime.block_on(async {
        match command {
            Command::Train(a) => train::train(a).await,
            Command::Learner(a) => train::learner(a).await,
            Command::Actor(a) => train::actor(a).await,
            Command::Teacher(a) => train::teacher(a).await,
            Command::Env(_)
            | Command::Bench(_)
            | Command::Exp(_)
            | Command::Labels(_)
            | Command::Eval(_)
            | Command::Watch(_)
            | Command::Export(_)
            | Command::People(_)
            | Command::Prior(_) => {
                unreachable!("handled above")
            }
        }
    });
    if let (Err(e), Some(f)) = (&result, error_log.as_mut()) {
        use std::io::Write;
        let _ = writeln!(f, "error: {e:#}");
    }
    result
}
