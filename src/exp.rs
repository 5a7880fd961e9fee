//! `pbrl exp`: a grid of runs (algorithms x rewards x seeds x config overrides), each a run
//! folder under one experiment folder, run as child `pbrl train` processes, N at a time.
//! Finished runs are skipped and unfinished ones resumed, so the same command after an
//! interruption carries on.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use anyhow::{bail, Context, Result};
use clap::{Args, Subcommand};
use pbrl_learner::run::run_folder::RunFolder;
use serde::Deserialize;

#[derive(Subcommand, Debug)]
pub enum ExpCommand {
    /// Run (or carry on) every run of a grid.
    Run(RunArgs),
    /// The paper's figures and a summary table for an experiment folder.
    Plot(crate::plot::PlotArgs),
}

#[derive(Args, Debug)]
pub struct RunArgs {
    /// The grid (TOML; see `results/baselines/grid.toml`).
    pub grid: PathBuf,
    /// Experiment folder (default: `runs/<grid name>`); each run is a folder in it.
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Runs at a time (default: half the cores, at least 1; a SAC run keeps one core busy).
    #[arg(long)]
    pub parallel: Option<usize>,
    /// This machine's part of the grid, `i/n` (runs i, i+n, i+2n, ... in name order).
    #[arg(long, default_value = "0/1")]
    pub shard: String,
    /// Seconds between progress lines.
    #[arg(long, default_value_t = 60)]
    pub progress_every: u64,
}

/// A grid file.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Grid {
    /// The experiment's name (its default folder).
    pub name: String,
    pub algos: Vec<String>,
    pub rewards: Vec<String>,
    pub seeds: Vec<u64>,
    /// Env steps of every run, or per algorithm (`[steps] sac = 1000000`).
    pub steps: Steps,
    /// Flags given to every run (`actors = 2` gives `--actors 2`).
    #[serde(default)]
    pub set: BTreeMap<String, toml::Value>,
    /// Flags with several values: every combination is a run.
    #[serde(default)]
    pub grid: BTreeMap<String, Vec<toml::Value>>,
    /// Named sets of flags, each a method of its own (an ablation: `[variants.no-crops]
    /// reward-crops = 0`); a variant's flag overrides `[set]`'s, an empty one is `[set]`
    /// alone. Every variant runs with every `[grid]` combination; the variant's name ends
    /// the method's.
    #[serde(default)]
    pub variants: BTreeMap<String, BTreeMap<String, toml::Value>>,
    /// People (`pbrl people sample`): a folder, whose every `*.json` world config is one,
    /// or a list of such files. Every run is made for every person (`--world FILE`), the
    /// person's file name ending the method's name. A relative path is from where `pbrl
    /// exp` runs, as paths in `[set]`.
    #[serde(default)]
    pub people: Option<People>,
}

/// The grid's `people`: a folder or a list of files.
#[derive(Debug, Deserialize)]
#[serde(untagged)]
pub enum People {
    Folder(PathBuf),
    Files(Vec<PathBuf>),
}

#[derive(Debug, Deserialize)]
#[serde(untagged)]
pub enum Steps {
    All(u64),
    PerAlgo(BTreeMap<String, u64>),
}

/// One run of the grid.
#[derive(Clone, Debug, PartialEq)]
pub struct Cell {
    /// Folder name, e.g. `sac-true-s1` or `sac-true-preset=paper-s1`.
    pub name: String,
    /// The method (the name without the seed): what the plots group by.
    pub method: String,
    pub steps: u64,
    pub args: Vec<String>,
}

/// `n runs`, or `1 run`.
fn runs(n: usize) -> String {
    if n == 1 {
        "1 run".into()
    } else {
        format!("{n} runs")
    }
}

/// A grid value as text (in run names and flags).
fn value_text(v: &toml::Value) -> Result<String> {
    Ok(match v {
        toml::Value::String(s) => s.clone(),
        toml::Value::Integer(i) => i.to_string(),
        toml::Value::Float(f) => f.to_string(),
        toml::Value::Boolean(b) => b.to_string(),
        other => bail!("grid values must be strings, numbers or booleans, not {other}"),
    })
}

/// Whether `pbrl train`'s flag `--key` takes a value (`--reward-features=false`) rather
/// than being a bare switch (`--sync`).
fn takes_value(key: &str) -> bool {
    // The long names of `pbrl train`'s flags that take a value, read once from clap.
    static VALUED: std::sync::OnceLock<std::collections::BTreeSet<String>> =
        std::sync::OnceLock::new();
    VALUED
        .get_or_init(|| {
            let cli = <crate::Cli as clap::CommandFactory>::command();
            cli.find_subcommand("train")
                .map(|train| {
                    train
                        .get_arguments()
                        .filter(|a| a.get_action().takes_values())
                        .filter_map(|a| a.get_long().map(str::to_owned))
                        .collect()
                })
                .unwrap_or_default()
        })
        .contains(key)
}

/// The flag for `key = value`: `--key=value`. A boolean of a switch is the bare switch or
/// nothing; of a flag that takes a value (on by default, say), `--key=true` or
/// `--key=false`, so that `false` always means off.
fn flag(key: &str, v: &toml::Value) -> Result<Option<String>> {
    Ok(match v {
        toml::Value::Boolean(b) if takes_value(key) => Some(format!("--{key}={b}")),
        toml::Value::Boolean(true) => Some(format!("--{key}")),
        toml::Value::Boolean(false) => None,
        v => Some(format!("--{key}={}", value_text(v)?)),
    })
}

impl Grid {
    pub fn load(path: &Path) -> Result<Self> {
        let text =
            std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
        Self::parse(&text).with_context(|| format!("in {}", path.display()))
    }

    /// A grid from its TOML, checked: everything [`Self::cells`] relies on.
    pub fn parse(text: &str) -> Result<Self> {
        let grid: Grid = toml::from_str(text).context("parsing the grid")?;
        for (field, empty) in [
            ("algos", grid.algos.is_empty()),
            ("rewards", grid.rewards.is_empty()),
            ("seeds", grid.seeds.is_empty()),
        ] {
            if empty {
                bail!("{field} is empty");
            }
        }
        grid.check()?;
        Ok(grid)
    }

    /// Keys the grid sets itself, and a flag both in `[grid]` and a variant.
    fn check(&self) -> Result<()> {
        let variant_keys = self.variants.values().flat_map(|v| v.keys());
        for key in self.set.keys().chain(self.grid.keys()).chain(variant_keys) {
            if ["algo", "reward", "seed", "steps", "out", "run", "fresh"].contains(&key.as_str()) {
                bail!("`{key}` is set by the grid itself, not in [set], [grid] or [variants]");
            }
            if self.people.is_some() && ["world", "profile"].contains(&key.as_str()) {
                bail!("`{key}` is set by `people`, which gives each run its person's world");
            }
        }
        for (name, flags) in &self.variants {
            if let Some(key) = flags.keys().find(|k| self.grid.contains_key(*k)) {
                bail!(
                    "variant {name:?} sets `{key}`, which [grid] varies: a run would have it twice"
                );
            }
        }
        Ok(())
    }

    /// Every run, sorted by name.
    pub fn cells(&self) -> Result<Vec<Cell>> {
        // Every variant's flags over [set]'s (none: [set] alone, the method unnamed).
        type Flags = BTreeMap<String, toml::Value>;
        fn over<'a>(
            set: &'a Flags,
            flags: Option<&'a Flags>,
        ) -> BTreeMap<&'a str, &'a toml::Value> {
            let mut merged: BTreeMap<&str, &toml::Value> =
                set.iter().map(|(k, v)| (k.as_str(), v)).collect();
            merged.extend(flags.into_iter().flatten().map(|(k, v)| (k.as_str(), v)));
            merged
        }
        let variants: Vec<(Option<&str>, BTreeMap<&str, &toml::Value>)> =
            if self.variants.is_empty() {
                vec![(None, over(&self.set, None))]
            } else {
                self.variants
                    .iter()
                    .map(|(name, flags)| (Some(name.as_str()), over(&self.set, Some(flags))))
                    .collect()
            };
        // Every combination of the [grid] flags.
        let mut combos: Vec<Vec<(&str, &toml::Value)>> = vec![vec![]];
        for (key, values) in &self.grid {
            let mut next = Vec::new();
            for c in &combos {
                for v in values {
                    let mut c = c.clone();
                    c.push((key, v));
                    next.push(c);
                }
            }
            combos = next;
        }
        // Every person of `people` (none: the runs' own world).
        let people: Vec<Option<(String, String)>> = match &self.people {
            None => vec![None],
            Some(People::Folder(dir)) => people_files(dir)?.into_iter().map(Some).collect(),
            Some(People::Files(files)) => files
                .iter()
                .map(|f| person_file(f).map(Some))
                .collect::<Result<_>>()?,
        };
        let mut cells = Vec::new();
        for algo in &self.algos {
            let steps = match &self.steps {
                Steps::All(n) => *n,
                Steps::PerAlgo(m) => *m
                    .get(algo)
                    .with_context(|| format!("[steps] has no entry for algorithm {algo}"))?,
            };
            for reward in &self.rewards {
                for (combo, (variant, flags), person) in combos
                    .iter()
                    .flat_map(|c| variants.iter().map(move |v| (c, v)))
                    .flat_map(|(c, v)| people.iter().map(move |p| (c, v, p)))
                {
                    {
                        let mut method = format!("{algo}-{reward}");
                        for (k, v) in combo {
                            method.push_str(&format!("-{k}={}", value_text(v)?));
                        }
                        if let Some(variant) = variant {
                            method.push_str(&format!("-{variant}"));
                        }
                        if let Some((name, _)) = person {
                            method.push_str(&format!("-{name}"));
                        }
                        if method.contains(['/', '\\']) || method.contains("..") {
                            bail!(
                                "run name {method:?} would not be one folder: algorithms, rewards, [grid] values and variant names may not hold '/', '\\' or '..' (a path can go in [set])"
                            );
                        }
                        for seed in &self.seeds {
                            let mut args = vec![
                                format!("--algo={algo}"),
                                format!("--reward={reward}"),
                                format!("--seed={seed}"),
                                format!("--steps={steps}"),
                            ];
                            for (k, v) in flags {
                                args.extend(flag(k, v)?);
                            }
                            for (k, v) in combo {
                                args.extend(flag(k, v)?);
                            }
                            if let Some((_, path)) = person {
                                args.push(format!("--world={path}"));
                            }
                            cells.push(Cell {
                                name: format!("{method}-s{seed}"),
                                method: method.clone(),
                                steps,
                                args,
                            });
                        }
                    }
                }
            }
        }
        cells.sort_by(|a, b| a.name.cmp(&b.name));
        // NOTE: two runs in one folder would overwrite each other.
        if let Some(w) = cells.windows(2).find(|w| w[0].name == w[1].name) {
            bail!(
                "the grid has run {} twice: a value repeats in algos, rewards, seeds or [grid], or a variant is named like a [grid] value",
                w[0].name
            );
        }
        Ok(cells)
    }
}

/// Every run's flags, checked as `pbrl train` will parse them, so that a mistake in the
/// grid is reported once, before anything starts, not by every run as it fails.
fn check_flags(cells: &[Cell]) -> Result<()> {
    for c in cells {
        let line = ["pbrl", "train"]
            .into_iter()
            .map(String::from)
            .chain(c.args.iter().cloned());
        if let Err(e) = <crate::Cli as clap::Parser>::try_parse_from(line) {
            bail!(
                "run {} would not start (flags {}):\n{}",
                c.name,
                c.args.join(" "),
                e.render()
            );
        }
    }
    Ok(())
}

/// The people of a folder: (file stem, path) of every `*.json` in it, by name.
fn people_files(dir: &Path) -> Result<Vec<(String, String)>> {
    let entries = std::fs::read_dir(dir)
        .with_context(|| format!("people = {}: not a folder", dir.display()))?;
    let mut people = Vec::new();
    for e in entries {
        let path = e?.path();
        if path.extension().is_some_and(|x| x == "json") {
            people.push(person_file(&path)?);
        }
    }
    if people.is_empty() {
        bail!("people = {}: holds no *.json world config", dir.display());
    }
    people.sort();
    Ok(people)
}

/// (file stem, path) of one person's world config, which must exist.
fn person_file(path: &Path) -> Result<(String, String)> {
    if !path.is_file() {
        bail!("people: {} is not a file", path.display());
    }
    let stem = path
        .file_stem()
        .and_then(|s| s.to_str())
        .with_context(|| format!("people: {} is not a UTF-8 name", path.display()))?;
    let text = path
        .to_str()
        .with_context(|| format!("people: {} is not a UTF-8 path", path.display()))?;
    Ok((stem.to_string(), text.to_string()))
}

/// Parse `i/n`.
fn shard(s: &str) -> Result<(usize, usize)> {
    let parsed = s
        .split_once('/')
        .and_then(|(i, n)| Some((i.parse().ok()?, n.parse().ok()?)));
    match parsed {
        Some((i, n)) if n > 0 && i < n => Ok((i, n)),
        _ => bail!("--shard {s:?}: expected i/n with 0 <= i < n, e.g. 0/2"),
    }
}

/// A run id for key expressions: the cell name with anything else than a-z, 0-9, - and _
/// replaced.
fn run_id(grid: &str, cell: &str) -> String {
    let id: String = format!("{grid}-{cell}")
        .to_lowercase()
        .chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || c == '-' || c == '_' {
                c
            } else {
                '_'
            }
        })
        .collect();
    id.chars().take(64).collect()
}

/// The newest row of a run's curve: (env steps, eval success rate).
fn last_row(folder: &RunFolder) -> Option<(u64, f64)> {
    let text = std::fs::read_to_string(folder.curve()).ok()?;
    let mut lines = text.lines();
    let header: Vec<&str> = lines.next()?.split(',').collect();
    let steps = header.iter().position(|h| *h == "env_steps")?;
    let success = header.iter().position(|h| *h == "eval_success_rate")?;
    let last: Vec<&str> = lines.last()?.split(',').collect();
    Some((
        last.get(steps)?.parse().ok()?,
        last.get(success)?.parse().ok()?,
    ))
}

struct Running {
    cell: Cell,
    child: Child,
    started: Instant,
    from_steps: u64,
}

/// The grid's output folder, made, with the grid kept in it.
fn prepare(args: &RunArgs, grid: &Grid) -> Result<PathBuf> {
    let out = args
        .out
        .clone()
        .unwrap_or_else(|| PathBuf::from("runs").join(&grid.name));
    std::fs::create_dir_all(&out).with_context(|| format!("creating {}", out.display()))?;
    // NOTE: the grid is kept beside its runs; copying a file onto itself would empty it.
    let kept = out.join("grid.toml");
    let same = std::fs::canonicalize(&kept).ok() == Some(std::fs::canonicalize(&args.grid)?);
    if !same {
        std::fs::copy(&args.grid, &kept)
            .with_context(|| format!("copying the grid into {}", out.display()))?;
    }
    Ok(out)
}

/// Start `cell`'s run (resuming it where its folder stands); its name back if it could not
/// start.
fn launch(exe: &Path, grid: &str, cell: Cell, out: &Path) -> Result<Running, String> {
    let folder = RunFolder::new(out.join(&cell.name));
    let from_steps = last_row(&folder).map_or(0, |r| r.0);
    let mut cmd = Command::new(exe);
    cmd.arg("train")
        .args(&cell.args)
        .arg(format!("--run={}", run_id(grid, &cell.name)))
        .arg(format!("--out={}", folder.root.display()))
        .arg("--quiet")
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::null());
    // NOTE: its own process group: a Ctrl-C reaches the runner, which forwards one
    // stop to each run (a second signal would make a run exit without checkpoint).
    std::os::unix::process::CommandExt::process_group(&mut cmd, 0);
    let child = match cmd.spawn() {
        Ok(child) => child,
        Err(e) => {
            // NOTE: the other runs go on (e.g. the executable was rebuilt under a
            // long grid); this one is reported with the failures.
            println!("{}: could not start {}: {e}", cell.name, exe.display());
            return Err(cell.name);
        }
    };
    println!(
        "{}: {} (log in {})",
        cell.name,
        if from_steps > 0 {
            format!("resuming after {from_steps} env steps")
        } else {
            "starting".to_string()
        },
        folder.log().display()
    );
    Ok(Running {
        cell,
        child,
        started: Instant::now(),
        from_steps,
    })
}

/// Take the runs that ended off `running`, saying how each ended; a run that exited before
/// its total (and not for a stop) is added to `failed`.
fn reap(
    running: &mut Vec<Running>,
    out: &Path,
    stop: &std::sync::atomic::AtomicBool,
    failed: &mut Vec<String>,
) -> Result<()> {
    let mut k = 0;
    while k < running.len() {
        if let Some(status) = running[k].child.try_wait()? {
            let r = running.swap_remove(k);
            let folder = RunFolder::new(out.join(&r.cell.name));
            let finished = folder.finished_steps()?.is_some_and(|s| s >= r.cell.steps);
            if finished {
                println!(
                    "{}: finished in {:.0} s",
                    r.cell.name,
                    r.started.elapsed().as_secs_f64()
                );
            } else if stop.load(std::sync::atomic::Ordering::Relaxed) && status.success() {
                println!("{}: stopped with a checkpoint", r.cell.name);
            } else {
                println!(
                    "{}: exited ({status}) before its total; see {}",
                    r.cell.name,
                    folder.log().display()
                );
                failed.push(r.cell.name.clone());
            }
        } else {
            k += 1;
        }
    }
    Ok(())
}

pub fn run(args: RunArgs) -> Result<()> {
    if args.parallel == Some(0) {
        bail!("--parallel 0: runs at a time must be at least 1");
    }
    let grid = Grid::load(&args.grid)?;
    let (i, n) = shard(&args.shard)?;
    let out = prepare(&args, &grid)?;
    let all = grid.cells()?;
    check_flags(&all)?;
    let cells: Vec<Cell> = all
        .into_iter()
        .enumerate()
        .filter(|(k, _)| k % n == i)
        .map(|(_, c)| c)
        .collect();
    let cores = std::thread::available_parallelism().map_or(1, |c| c.get());
    let parallel = args.parallel.unwrap_or((cores / 2).max(1));
    let exe = std::env::current_exe().context("finding the pbrl executable")?;
    let mut todo: Vec<Cell> = Vec::new();
    for c in &cells {
        let folder = RunFolder::new(out.join(&c.name));
        match folder.finished_steps()? {
            Some(s) if s >= c.steps => println!("{}: finished ({s} env steps), skipped", c.name),
            _ => todo.push(c.clone()),
        }
    }
    println!(
        "experiment {} in {}: {} in this shard ({}/{}), {} to run, {parallel} at a time",
        grid.name,
        out.display(),
        runs(cells.len()),
        i,
        n,
        todo.len()
    );
    todo.reverse();
    let mut running: Vec<Running> = Vec::new();
    let mut failed = Vec::new();
    let mut last_report = Instant::now();
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .enable_all()
        .build()?;
    let stop = crate::train::stop_flag(&runtime);
    let mut forwarded = false;
    loop {
        while running.len() < parallel && !stop.load(std::sync::atomic::Ordering::Relaxed) {
            let Some(cell) = todo.pop() else { break };
            match launch(&exe, &grid.name, cell, &out) {
                Ok(r) => running.push(r),
                Err(name) => failed.push(name),
            }
        }
        if running.is_empty() {
            break;
        }
        reap(&mut running, &out, &stop, &mut failed)?;
        if stop.load(std::sync::atomic::Ordering::Relaxed) && !forwarded {
            forwarded = true;
            for r in &running {
                // NOTE: forward the stop; each run checkpoints and exits.
                let _ = Command::new("kill")
                    .args(["-TERM", &r.child.id().to_string()])
                    .status();
            }
        }
        if last_report.elapsed() >= Duration::from_secs(args.progress_every) {
            last_report = Instant::now();
            report(&out, &cells, &running);
        }
        std::thread::sleep(Duration::from_millis(200));
    }
    report(&out, &cells, &running);
    if !failed.is_empty() {
        bail!("{} failed: {}", runs(failed.len()), failed.join(", "));
    }
    if stop.load(std::sync::atomic::Ordering::Relaxed) {
        println!("stopped; the same command carries on");
    }
    Ok(())
}

/// One line per running run and the grid's total.
fn report(out: &Path, cells: &[Cell], running: &[Running]) {
    let (mut done, mut total) = (0u64, 0u64);
    for c in cells {
        let folder = RunFolder::new(out.join(&c.name));
        let steps = last_row(&folder).map_or(0, |r| r.0).min(c.steps);
        done += steps;
        total += c.steps;
    }
    for r in running {
        let folder = RunFolder::new(out.join(&r.cell.name));
        let (steps, success) = last_row(&folder).unwrap_or((0, f64::NAN));
        let rate = (steps.saturating_sub(r.from_steps)) as f64
            / r.started.elapsed().as_secs_f64().max(1.0);
        let left = if rate > 0.0 {
            format!(
                "{:.0} min left",
                (r.cell.steps.saturating_sub(steps)) as f64 / rate / 60.0
            )
        } else {
            "time left unknown".to_string()
        };
        let success = if success.is_finite() {
            format!("eval success {:.0}%", 100.0 * success)
        } else {
            "no evaluation yet".to_string()
        };
        println!(
            "  {}: {steps}/{} env steps, {success}, {left}",
            r.cell.name, r.cell.steps
        );
    }
    println!(
        "grid: {done}/{total} env steps ({:.1}%)",
        100.0 * done as f64 / total.max(1) as f64
    );
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_grid_expands_to_named_runs() {
        let g = Grid::parse(
            r#"
name = "t"
algos = ["sac", "ppo"]
rewards = ["true"]
seeds = [1, 2]
[steps]
sac = 100
ppo = 200
[set]
actors = 1
[grid]
preset = ["default", "paper"]
"#,
        )
        .unwrap();
        let cells = g.cells().unwrap();
        assert_eq!(cells.len(), 8);
        let c = cells
            .iter()
            .find(|c| c.name == "sac-true-preset=paper-s2")
            .unwrap();
        assert_eq!(c.method, "sac-true-preset=paper");
        assert_eq!(c.steps, 100);
        assert!(c.args.contains(&"--actors=1".to_string()));
        assert!(c.args.contains(&"--preset=paper".to_string()));
        assert_eq!(shard("1/3").unwrap(), (1, 3));
        assert!(shard("3/3").is_err());
        assert_eq!(
            run_id("t", "sac-true-preset=paper-s2"),
            "t-sac-true-preset_paper-s2"
        );
        check_flags(&cells).unwrap();
    }

    /// Every grid file under `results/` (the committed experiments, and the copies `pbrl exp
    /// run` keeps with their runs) still parses, and every run's flags still parse as
    /// `pbrl train`'s: a table's command stays one that runs.
    #[test]
    fn every_grid_committed_under_results_parses_and_its_flags_check() {
        let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR"));
        let mut grids = Vec::new();
        let mut dirs = vec![root.join("results")];
        while let Some(dir) = dirs.pop() {
            for e in std::fs::read_dir(&dir).unwrap() {
                let path = e.unwrap().path();
                let name = path.file_name().unwrap().to_string_lossy().to_string();
                if path.is_dir() {
                    dirs.push(path);
                } else if name.starts_with("grid") && name.ends_with(".toml") {
                    grids.push(path);
                }
            }
        }
        assert!(grids.len() >= 10, "found {grids:?}");
        // NOTE: a grid's people are paths from the repository's root.
        std::env::set_current_dir(root).unwrap();
        for path in grids {
            let g = Grid::load(&path).unwrap_or_else(|e| panic!("{}: {e:#}", path.display()));
            let cells = g
                .cells()
                .unwrap_or_else(|e| panic!("{}: {e:#}", path.display()));
            check_flags(&cells).unwrap_or_else(|e| panic!("{}: {e:#}", path.display()));
        }
    }

    #[test]
    fn variants_are_methods_whose_flags_override_the_set() {
        let g = Grid::parse(
            r#"
name = "t"
algos = ["sac"]
rewards = ["decoupled"]
seeds = [1, 2]
steps = 100
[set]
segment-len = 50
reward-features = true
[grid]
teacher = ["oracle", "noisy"]
[variants.default]
[variants.whole]
segment-len = 0
[variants.no-features]
reward-features = false
"#,
        )
        .unwrap();
        let cells = g.cells().unwrap();
        // 3 variants x 2 teachers x 2 seeds.
        assert_eq!(cells.len(), 12);
        let args = |name: &str| &cells.iter().find(|c| c.name == name).unwrap().args;
        let default = args("sac-decoupled-teacher=oracle-default-s1");
        assert!(default.contains(&"--segment-len=50".to_string()));
        assert!(default.contains(&"--reward-features=true".to_string()));
        let whole = args("sac-decoupled-teacher=noisy-whole-s2");
        assert!(whole.contains(&"--segment-len=0".to_string()));
        assert!(
            !whole.contains(&"--segment-len=50".to_string()),
            "{whole:?}"
        );
        assert!(whole.contains(&"--teacher=noisy".to_string()));
        let off = args("sac-decoupled-teacher=oracle-no-features-s1");
        assert!(
            off.contains(&"--reward-features=false".to_string()),
            "{off:?}"
        );
        assert!(off.contains(&"--segment-len=50".to_string()));
        let methods: std::collections::BTreeSet<&str> =
            cells.iter().map(|c| c.method.as_str()).collect();
        assert_eq!(methods.len(), 6);
        check_flags(&cells).unwrap();
    }

    fn grid(extra: &str) -> Result<Vec<Cell>> {
        let g = Grid::parse(&format!(
            "name = \"t\"\nalgos = [\"sac\"]\nrewards = [\"true\"]\nsteps = 100\n{extra}"
        ))?;
        g.cells()
    }

    #[test]
    fn a_grid_of_people_makes_every_run_for_every_person() {
        let dir = tempfile::tempdir().unwrap();
        for name in ["b", "a"] {
            std::fs::write(dir.path().join(format!("{name}.json")), "{}").unwrap();
        }
        std::fs::write(dir.path().join("people.csv"), "not a person").unwrap();
        let d = dir.path().display().to_string();
        let cells = grid(&format!(
            "seeds = [1, 2]\npeople = {d:?}\n[variants.x]\nrho = 1\n[variants.y]\nrho = 2"
        ))
        .unwrap();
        let names: Vec<&str> = cells.iter().map(|c| c.name.as_str()).collect();
        assert_eq!(
            names,
            [
                "sac-true-x-a-s1",
                "sac-true-x-a-s2",
                "sac-true-x-b-s1",
                "sac-true-x-b-s2",
                "sac-true-y-a-s1",
                "sac-true-y-a-s2",
                "sac-true-y-b-s1",
                "sac-true-y-b-s2"
            ]
        );
        let a = format!("--world={}", dir.path().join("a.json").display());
        assert!(cells[0].args.contains(&a), "{:?}", cells[0].args);
        check_flags(&cells).unwrap();
        // A list of files.
        let b = dir.path().join("b.json").display().to_string();
        let cells = grid(&format!("seeds = [1]\npeople = [{b:?}]")).unwrap();
        assert_eq!(cells.len(), 1);
        assert_eq!(cells[0].name, "sac-true-b-s1");
        // Mistakes, named.
        let e = grid("seeds = [1]\npeople = [\"no/such.json\"]").unwrap_err();
        assert!(e.to_string().contains("no/such.json is not a file"), "{e}");
        let empty = tempfile::tempdir().unwrap();
        let e = grid(&format!(
            "seeds = [1]\npeople = {:?}",
            empty.path().display().to_string()
        ))
        .unwrap_err();
        assert!(e.to_string().contains("holds no *.json"), "{e}");
        let e = grid(&format!(
            "seeds = [1]\npeople = {d:?}\n[set]\nworld = \"w.json\""
        ))
        .unwrap_err();
        assert!(e.to_string().contains("`world` is set by `people`"), "{e}");
    }

    #[test]
    fn grid_mistakes_are_refused_before_any_run_starts() {
        // A boolean is the bare switch, or nothing.
        let cells = grid("seeds = [1]\n[grid]\nsync = [true, false]").unwrap();
        let sync = |name: &str| {
            let c = cells.iter().find(|c| c.name == name).unwrap();
            c.args.contains(&"--sync".to_string())
        };
        assert!(sync("sac-true-sync=true-s1"));
        assert!(!sync("sac-true-sync=false-s1"));
        check_flags(&cells).unwrap();
        // A flag that takes a value (on by default) is turned off by `false`.
        let cells = grid("seeds = [1]\n[set]\nreward-features = false").unwrap();
        assert!(cells[0]
            .args
            .contains(&"--reward-features=false".to_string()));
        check_flags(&cells).unwrap();
        // A variant may not set what [grid] varies.
        let e = grid("seeds = [1]\n[grid]\nrho = [1e-6]\n[variants.a]\nrho = 3e-7")
            .unwrap_err()
            .to_string();
        assert!(e.contains("variant \"a\" sets `rho`"), "{e}");
        // Two runs in one folder.
        let e = grid("seeds = [1, 1]").unwrap_err().to_string();
        assert!(e.contains("sac-true-s1 twice"), "{e}");
        // A run name that would be a path.
        let e = grid("seeds = [1]\n[grid]\nworld = [\"w/a.json\"]")
            .unwrap_err()
            .to_string();
        assert!(e.contains("would not be one folder"), "{e}");
        // A flag `pbrl train` does not know, named with the run, before anything starts.
        let cells = grid("seeds = [1]\n[set]\nlog_every = 5").unwrap();
        let e = check_flags(&cells).unwrap_err().to_string();
        assert!(
            e.contains("run sac-true-s1") && e.contains("log_every"),
            "{e}"
        );
    }
}
