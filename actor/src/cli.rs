//! The `pbrl env ...` commands: look at, time, record and draw the feeding world.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, Result};
use clap::{Args, Subcommand};

use crate::config::{BasePlacement, Profile, WorldConfig};
use crate::controller::{Controller, ControllerKind};
use crate::rollout::run_episode;
use crate::world::{FeedingWorld, ACT_DIM};

/// World options shared by every `env` command.
#[derive(Args, Clone, Debug)]
pub struct WorldArgs {
    /// World config as JSON (any field of the world config; the rest keep their defaults).
    #[arg(long, value_name = "FILE")]
    pub world: Option<PathBuf>,
    /// Person profile: paper or assistive-gym (overrides the config file's).
    #[arg(long)]
    pub profile: Option<String>,
    /// Robot base placement (overrides the config file's).
    #[arg(long, value_enum)]
    pub base: Option<BasePlacement>,
}

impl WorldArgs {
    /// The resolved, checked world config.
    pub fn config(&self) -> Result<WorldConfig> {
        let mut cfg = match &self.world {
            Some(path) => {
                let text = std::fs::read_to_string(path)
                    .with_context(|| format!("reading world config {}", path.display()))?;
                WorldConfig::from_json(&text)
                    .with_context(|| format!("world config {}", path.display()))?
            }
            None => WorldConfig::default(),
        };
        if let Some(name) = &self.profile {
            cfg.profile = Profile::by_name(name)?;
        }
        if let Some(base) = self.base {
            cfg.base = base;
        }
        cfg.validate()?;
        Ok(cfg)
    }
}

/// One episode: the world, the controller acting in it and the seed of its reset.
#[derive(Args, Clone, Debug)]
pub struct EpisodeArgs {
    #[command(flatten)]
    pub world: WorldArgs,
    /// scripted, random or zero.
    #[arg(long, value_enum, default_value = "scripted")]
    pub controller: ControllerKind,
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
}

impl EpisodeArgs {
    /// Run the episode in a world of `cfg` (this command's world, resolved).
    fn run(&self, cfg: &WorldConfig) -> Result<pbrl_common::Trajectory> {
        let mut w = FeedingWorld::new(cfg.clone())?;
        Ok(run_episode(
            &mut w,
            &mut Controller::new(self.controller),
            self.seed,
        )?)
    }
}

#[derive(Subcommand, Debug)]
pub enum EnvCommand {
    /// Run episodes with a controller and print each outcome and a summary.
    Demo {
        #[command(flatten)]
        world: WorldArgs,
        /// scripted, random or zero.
        #[arg(long, value_enum, default_value = "scripted")]
        controller: ControllerKind,
        /// Episodes to run.
        #[arg(long, default_value_t = 10)]
        episodes: u64,
        /// Seed of the first episode (episode i uses seed + i).
        #[arg(long, default_value_t = 0)]
        seed: u64,
    },
    /// Time the world: env steps per second on one thread, resets included.
    Bench {
        #[command(flatten)]
        world: WorldArgs,
        /// Env steps to time.
        #[arg(long, default_value_t = 20_000)]
        steps: u64,
        /// Controller driving the world while it is timed.
        #[arg(long, value_enum, default_value = "random")]
        controller: ControllerKind,
        #[arg(long, default_value_t = 0)]
        seed: u64,
    },
    /// Run one episode and write its trajectory record (bincode).
    Record {
        #[command(flatten)]
        episode: EpisodeArgs,
        /// Output file.
        #[arg(long)]
        out: PathBuf,
    },
    /// Draw one episode (side and front views) as a PNG.
    Render {
        #[command(flatten)]
        episode: EpisodeArgs,
        /// Draw this recorded trajectory instead of running an episode.
        #[arg(long, value_name = "FILE")]
        from: Option<PathBuf>,
        /// Output PNG.
        #[arg(long)]
        out: PathBuf,
    },
}

/// Run one `env` command.
pub fn run(cmd: EnvCommand) -> Result<()> {
    match cmd {
        EnvCommand::Demo {
            world,
            controller,
            episodes,
            seed,
        } => demo(&world, controller, episodes, seed),
        EnvCommand::Bench {
            world,
            steps,
            controller,
            seed,
        } => bench(&world, steps, controller, seed),
        EnvCommand::Record { episode, out } => {
            let t = episode.run(&episode.world.config()?)?;
            let bytes = t.encode();
            std::fs::write(&out, &bytes).with_context(|| format!("writing {}", out.display()))?;
            println!(
                "wrote {} ({} bytes): {} steps, eaten {}/{}, spilled {}, return {:.1}",
                out.display(),
                bytes.len(),
                t.outcome.steps,
                t.outcome.eaten,
                t.outcome.food,
                t.outcome.spilled,
                t.outcome.return_truth
            );
            Ok(())
        }
        EnvCommand::Render { episode, from, out } => {
            let cfg = episode.world.config()?;
            let t = match from {
                Some(path) => {
                    let bytes = std::fs::read(&path)
                        .with_context(|| format!("reading {}", path.display()))?;
                    pbrl_common::Trajectory::decode(&bytes)
                        .with_context(|| format!("decoding {}", path.display()))?
                }
                None => episode.run(&cfg)?,
            };
            let name = format!("{:?}", episode.controller).to_lowercase();
            crate::render::render(&t, &cfg, &name, &out)?;
            println!("wrote {}", out.display());
            Ok(())
        }
    }
}

fn demo(args: &WorldArgs, kind: ControllerKind, episodes: u64, seed: u64) -> Result<()> {
    let cfg = args.config()?;
    let mut world = FeedingWorld::new(cfg)?;
    let mut controller = Controller::new(kind);
    let end = seed
        .checked_add(episodes)
        .with_context(|| format!("--seed {seed} plus --episodes {episodes} overflows"))?;
    let (mut successes, mut ret, mut ret_h, mut eaten, mut spilled) =
        (0u64, 0.0f64, 0.0f64, 0u64, 0u64);
    println!(
        "{:>6} {:>6} {:>7} {:>5} {:>9} {:>10} {:>10}",
        "seed", "eaten", "spilled", "hits", "success", "return", "pref_ret"
    );
    for s in seed..end {
        let t = run_episode(&mut world, &mut controller, s)?;
        let o = &t.outcome;
        println!(
            "{:>6} {:>3}/{:<2} {:>7} {:>5} {:>9} {:>10.1} {:>10.1}",
            s, o.eaten, o.food, o.spilled, o.hits, o.success, o.return_truth, o.return_human
        );
        successes += o.success as u64;
        ret += o.return_truth as f64;
        ret_h += o.return_human as f64;
        eaten += o.eaten as u64;
        spilled += o.spilled as u64;
    }
    let n = episodes.max(1) as f64;
    println!(
        "summary: controller {kind:?}, {episodes} episodes from seed {seed}: success {:.0}%, mean return {:.1}, mean preference return {:.1}, mean eaten {:.2}, mean spilled {:.2}",
        100.0 * successes as f64 / n,
        ret / n,
        ret_h / n,
        eaten as f64 / n,
        spilled as f64 / n
    );
    Ok(())
}

fn bench(args: &WorldArgs, steps: u64, kind: ControllerKind, seed: u64) -> Result<()> {
    let cfg = args.config()?;
    let substeps = cfg.substeps as f64;
    let mut world = FeedingWorld::new(cfg)?;
    let mut controller = Controller::new(kind);
    let (mut done, mut resets, mut reset_time) = (0u64, 0u64, 0.0f64);
    let mut episode_seed = seed;
    let start = Instant::now();
    while done < steps {
        let t0 = Instant::now();
        world.reset(episode_seed)?;
        reset_time += t0.elapsed().as_secs_f64();
        resets += 1;
        controller.reset(episode_seed);
        episode_seed = episode_seed.wrapping_add(1);
        loop {
            let a: [f32; ACT_DIM] = controller.act(&world)?;
            let s = world.step(&a)?;
            done += 1;
            if s.truncated || s.terminated || done >= steps {
                break;
            }
        }
    }
    let total = start.elapsed().as_secs_f64();
    let stepping = total - reset_time;
    println!("env steps:            {done} ({resets} resets, controller {kind:?}, one thread)");
    println!(
        "env steps per second: {:.0} (resets included)",
        done as f64 / total
    );
    println!(
        "per env step:         {:.1} us without resets",
        1e6 * stepping / done as f64
    );
    println!(
        "per physics substep:  {:.1} us (arm, contacts and rapier)",
        1e6 * stepping / (done as f64 * substeps)
    );
    println!(
        "per reset:            {:.2} ms (IK, scene, {} settling substeps)",
        1e3 * reset_time / resets as f64,
        world.config().settle_substeps
    );
    Ok(())
}
