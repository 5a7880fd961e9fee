//! `pbrl bench`: the learner's unit of work (SAC steps, PPO minibatches, what preference
//! learning adds), end-to-end `pbrl train` speed, and what a checkpoint costs. Each prints
//! its figures.

use anyhow::Result;

use pbrl_learner::pref::reward_model::RewardModelConfig;

use crate::train::{explicit_flags, train_in_process, TrainArgs};

#[derive(clap::Subcommand, Debug)]
pub enum BenchCommand {
    /// SAC gradient steps and PPO minibatch updates per second (obs 25, action 7), at
    /// 256x256 / batch 256 and 512x512 / batch 512, on 1 and 2 learner threads (the SIMD path
    /// and the CPU printed first).
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
    /// `pbrl eval`'s speed: a run's policy on the same episodes on 1 thread and on every
    /// core, alternated (1, N, 1, N, ...), with the ratio of the medians.
    Eval {
        /// The run folder.
        run: std::path::PathBuf,
        /// Episodes per timing.
        #[arg(long, default_value_t = 100)]
        episodes: u32,
        /// Timings of each thread count.
        #[arg(long, default_value_t = 3)]
        rounds: usize,
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

/// The CPU's model name (`/proc/cpuinfo`), to say which machine a figure comes from.
fn cpu_model() -> String {
    std::fs::read_to_string("/proc/cpuinfo")
        .ok()
        .and_then(|t| {
            t.lines()
                .find(|l| l.starts_with("model name"))
                .and_then(|l| l.split(':').nth(1))
                .map(|m| m.trim().to_string())
        })
        .unwrap_or_else(|| "unknown".into())
}

/// `pbrl eval`'s episodes on 1 thread and on every core, alternated.
fn bench_eval(run: &std::path::Path, episodes: u32, rounds: usize) -> Result<()> {
    use pbrl_actor::evaluate::{evaluate_seeds, Acting};
    let runs = crate::eval::open_runs(&[run.to_path_buf()], None)?;
    let world = crate::eval::Person::own().world_for(&runs[0], false)?;
    let seeds = crate::eval::seeds(episodes);
    let cores = crate::eval::threads(None);
    println!(
        "pbrl eval speed: {} ({} env steps), {episodes} episodes, the mean action; CPU {}, {cores} cores",
        run.display(),
        runs[0].policy.env_steps,
        cpu_model()
    );
    let mut times: std::collections::BTreeMap<usize, Vec<f64>> = Default::default();
    let mut first: Option<Vec<pbrl_actor::evaluate::EpisodeStats>> = None;
    for round in 0..rounds.max(1) {
        for threads in [1, cores] {
            let start = std::time::Instant::now();
            let e = evaluate_seeds(
                &runs[0].policy.weights,
                &world,
                &seeds,
                Acting::Mean,
                threads,
                &|| {},
            )?;
            let s = start.elapsed().as_secs_f64();
            // NOTE: the thread count must not change what the episodes did.
            match &first {
                Some(f) if *f != e => anyhow::bail!("{threads} threads gave other episodes than 1"),
                Some(_) => {}
                None => first = Some(e),
            }
            println!(
                "round {round}: {threads} thread(s): {s:.2} s ({:.1} episodes/s)",
                episodes as f64 / s
            );
            times.entry(threads).or_default().push(s);
        }
    }
    let median = |v: &mut Vec<f64>| {
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    };
    let one = median(times.get_mut(&1).expect("timed on one thread"));
    let all = median(times.get_mut(&cores).expect("timed on every core"));
    println!(
        "median: 1 thread {one:.2} s, {cores} threads {all:.2} s: {:.2}x",
        one / all
    );
    Ok(())
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

/// Run one benchmark and print its figures.
pub fn run(cmd: BenchCommand) -> Result<()> {
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
        BenchCommand::Eval {
            run,
            episodes,
            rounds,
        } => return bench_eval(&run, episodes, rounds),
        BenchCommand::Checkpoint {
            transitions,
            increment,
        } => {
            let dir =
                std::env::temp_dir().join(format!("pbrl-bench-checkpoint-{}", std::process::id()));
            let c = pbrl_learner::bench::checkpoint(&dir, transitions, increment);
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
        "CPU: {}; SIMD path: {}; the matrix kernel on 1 thread, the step's pairs on --learner-threads",
        cpu_model(),
        pbrl_common::par::simd_path()
    );
    println!(
        "{:<8} {:>10} {:>8} {:>12} {:>12}",
        "threads", "hidden", "batch", "SAC ms/step", "PPO ms/mb"
    );
    // NOTE: candle reads RAYON_NUM_THREADS at every matmul: one thread each, as a service.
    std::env::set_var("RAYON_NUM_THREADS", "1");
    for threads in [1, 2] {
        for (hidden, batch) in [(256, 256), (512, 512)] {
            let sac = pbrl_learner::bench::sac_step_ms(hidden, batch, steps, 3, threads)?;
            let ppo = pbrl_learner::bench::ppo_update_ms(hidden, batch, 4000, threads)?;
            println!(
                "{threads:<8} {:>10} {batch:>8} {sac:>12.2} {ppo:>12.2}   ({:.0} SAC steps/s, {:.0} PPO updates/s)",
                format!("{hidden}x{hidden}"),
                1e3 / sac,
                1e3 / ppo
            );
        }
    }
    println!();
    println!("preference learning (2 learner threads, as `pbrl train` runs by default):");
    for (reward_hidden, name) in [(vec![64, 64, 64], "3x64"), (vec![256, 256, 256], "3x256")] {
        let plain = pbrl_learner::bench::sac_step_ms(256, 256, steps, 3, 2)?;
        let relabelled =
            pbrl_learner::bench::sac_step_relabelled_ms(256, 256, steps, 3, &reward_hidden, 2)?;
        let epoch = pbrl_learner::bench::bench_epoch(1000, 200, &reward_hidden)?;
        println!(
            "  ensemble 3 x {name}: SAC step (256x256, B=256) {plain:.2} ms, relabelled {relabelled:.2} ms (+{:.0}%); one training epoch over 1,000 labels of 200-step pairs {epoch:.2} s",
            100.0 * (relabelled / plain - 1.0)
        );
    }
    // What the learner waits for after a session of queries, at the default (features, 20
    // crops a label, at most `max_pairs` a member) and with those pieces off.
    for (name, cfg, labels) in [
        ("default", RewardModelConfig::default(), 200),
        ("default", RewardModelConfig::default(), 1000),
        ("plain", RewardModelConfig::plain(), 200),
    ] {
        let (secs, stats) = pbrl_learner::bench::bench_training(cfg, labels, 50)?;
        println!(
            "  a whole reward training, {name} (3 x 3x64), {labels} labels of 50-step pairs: {secs:.2} s ({} epochs, {} pairs a member)",
            stats.epochs, stats.pairs
        );
    }
    Ok(())
}
