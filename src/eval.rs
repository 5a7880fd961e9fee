//! `pbrl eval`: runs' policies judged on the same fixed episodes, for the run's own person
//! or others: success and returns with their intervals, each preference term, the food,
//! the closest approach, top speed and peak force, and paired differences against the
//! first run. Also what `watch` and `export` share: opening runs and the world to judge in.

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use pbrl_actor::evaluate::{evaluate_seeds, Acting, EpisodeStats, TERM_NAMES};
use pbrl_actor::{Profile, WorldConfig};
use pbrl_learner::run::saved_policy::SavedPolicy;
use pbrl_learner::run::service::EVAL_SEED_BASE;
use serde::Serialize;

#[derive(clap::Args, Debug)]
pub struct EvalArgs {
    /// Run folders (what `pbrl train --out DIR` wrote); the first is the one the others are
    /// compared with.
    #[arg(required = true)]
    pub runs: Vec<PathBuf>,
    #[command(flatten)]
    pub on: OnArgs,
    /// Episodes per run (and person); seeds are the curve's evaluation seeds and on.
    #[arg(long, default_value_t = 100)]
    pub episodes: u32,
    /// Act with sampled actions (noise from each episode's seed) instead of the mean.
    #[arg(long)]
    pub sampled: bool,
    /// Every run for every person: each `*.json` world config in DIR (its `profile` is the
    /// person; other fields must agree with the run's world).
    #[arg(long, value_name = "DIR", conflicts_with_all = ["world", "profile"])]
    pub people: Option<PathBuf>,
    /// Threads (default: every core).
    #[arg(long)]
    pub threads: Option<usize>,
    /// Print JSON (every figure and every episode) instead of the table.
    #[arg(long, conflicts_with = "csv")]
    pub json: bool,
    /// Print CSV (one row per person and run) instead of the table.
    #[arg(long)]
    pub csv: bool,
}

/// Which checkpoint, and which world: shared by `eval`, `watch` and `export`.
#[derive(clap::Args, Debug, Clone, Default)]
pub struct OnArgs {
    /// The checkpoint at this many env steps (default: each run's newest).
    #[arg(long, value_name = "STEPS")]
    pub checkpoint: Option<u64>,
    /// A person's world config (JSON): its fields replace the run's (the person is its
    /// `profile`; other fields must agree with the run's world unless --other-world).
    #[arg(long, value_name = "FILE")]
    pub world: Option<PathBuf>,
    /// A stock person instead of the run's own: paper or assistive-gym.
    #[arg(long)]
    pub profile: Option<String>,
    /// Let --world / --people change the world itself (physics, timing, food), not only
    /// the person: the policy then acts in a world it was not trained in.
    #[arg(long)]
    pub other_world: bool,
}

/// A run opened for judging: its policy and its world.
pub struct Run {
    pub name: String,
    pub policy: SavedPolicy,
    /// The world it trained in (the run's config).
    pub world: serde_json::Value,
}

/// Open run folders at `checkpoint` (the newest of each by default).
pub fn open_runs(dirs: &[PathBuf], checkpoint: Option<u64>) -> Result<Vec<Run>> {
    let mut names = BTreeSet::new();
    dirs.iter()
        .map(|dir| {
            let policy = SavedPolicy::load(dir, checkpoint)?;
            if policy.task() != "feeding" {
                bail!(
                    "{} trained on the {} task; eval, watch and export take feeding runs",
                    dir.display(),
                    policy.task()
                );
            }
            let world = policy
                .world_json()
                .cloned()
                .with_context(|| format!("{}: config.json records no world", dir.display()))?;
            let mut name = dir
                .file_name()
                .map(|n| n.to_string_lossy().into_owned())
                .unwrap_or_else(|| dir.display().to_string());
            // NOTE: two folders of one name (a/run, b/run) are told apart by their path.
            if !names.insert(name.clone()) {
                name = dir.display().to_string();
            }
            if !policy.finished {
                tracing::warn!(run = %dir.display(), env_steps = policy.env_steps, "the run has not finished: its newest checkpoint is used");
            }
            Ok(Run {
                name,
                policy,
                world,
            })
        })
        .collect()
}

/// Runs judged side by side must share a world beyond the person (else their episodes
/// differ): each run's world against the first's, every field but `profile`.
pub fn same_world(runs: &[Run], other_world: bool) -> Result<()> {
    let Some(first) = runs.first() else {
        return Ok(());
    };
    for r in &runs[1..] {
        let (Some(a), Some(b)) = (first.world.as_object(), r.world.as_object()) else {
            continue;
        };
        let differ: Vec<&str> = a
            .keys()
            .chain(b.keys())
            .filter(|k| k.as_str() != "profile" && a.get(k.as_str()) != b.get(k.as_str()))
            .map(|k| k.as_str())
            .collect::<BTreeSet<_>>()
            .into_iter()
            .collect();
        if !differ.is_empty() && !other_world {
            bail!(
                "runs {} and {} were trained in different worlds ({} differ): their episodes would not be the same (--other-world judges each in its own world)",
                first.name,
                r.name,
                differ.join(", ")
            );
        }
    }
    Ok(())
}

/// `base` with `over`'s fields put in (objects merged key by key, anything else replaced).
fn merge(base: &mut serde_json::Value, over: &serde_json::Value) {
    match (base, over) {
        (serde_json::Value::Object(b), serde_json::Value::Object(o)) => {
            for (k, v) in o {
                match b.get_mut(k) {
                    Some(bv) => merge(bv, v),
                    None => {
                        b.insert(k.clone(), v.clone());
                    }
                }
            }
        }
        (b, o) => *b = o.clone(),
    }
}

/// A person to judge for: a name and the world (the run's, with the person's fields).
#[derive(Clone, Debug)]
pub struct Person {
    pub name: String,
    /// The world config's fields the person file sets (None: the run's own world).
    pub file: Option<(PathBuf, serde_json::Value)>,
    /// A stock profile instead of the run's.
    pub profile: Option<Profile>,
}

impl Person {
    /// The run's own person.
    pub fn own() -> Self {
        Self {
            name: String::new(),
            file: None,
            profile: None,
        }
    }

    /// A person's world config file (any fields of the world config).
    pub fn from_file(path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(path)
            .with_context(|| format!("reading the person's world config {}", path.display()))?;
        let json: serde_json::Value =
            serde_json::from_str(&text).with_context(|| format!("{}: not JSON", path.display()))?;
        if !json.is_object() {
            bail!("{}: a world config is a JSON object", path.display());
        }
        // NOTE: checked on the default world first, so that an unknown or ill-typed field is
        // named with the file before any run is opened (a person file may give only some
        // of the profile's fields; the rest are the run's).
        let mut check = serde_json::to_value(WorldConfig::default())?;
        merge(&mut check, &json);
        serde_json::from_value::<WorldConfig>(check)
            .map_err(anyhow::Error::from)
            .and_then(|w| Ok(w.validate()?))
            .with_context(|| format!("world config {}", path.display()))?;
        let stem = path
            .file_stem()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_default();
        let name = json
            .pointer("/profile/name")
            .and_then(|n| n.as_str())
            .map(str::to_string)
            .unwrap_or(stem);
        Ok(Self {
            name,
            file: Some((path.to_path_buf(), json)),
            profile: None,
        })
    }

    /// Every `*.json` in `dir`, by file name.
    pub fn folder(dir: &Path) -> Result<Vec<Self>> {
        let mut files: Vec<PathBuf> = std::fs::read_dir(dir)
            .with_context(|| format!("reading the people folder {}", dir.display()))?
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| p.extension().is_some_and(|e| e == "json"))
            .collect();
        files.sort();
        if files.is_empty() {
            bail!(
                "{}: no person files (*.json world configs) in it",
                dir.display()
            );
        }
        files.iter().map(|f| Self::from_file(f)).collect()
    }

    /// The person `--world` / `--profile` name, or else the first run's own (every run is
    /// then judged for the person the first was trained for).
    pub fn from_args(on: &OnArgs, runs: &[Run]) -> Result<Self> {
        let mut p = match &on.world {
            Some(f) => Self::from_file(f)?,
            None => match runs.first().and_then(|r| r.world.get("profile")) {
                Some(profile) => Self {
                    name: String::new(),
                    file: Some((
                        runs[0].policy.folder.join("config.json"),
                        serde_json::json!({ "profile": profile }),
                    )),
                    profile: None,
                },
                None => Self::own(),
            },
        };
        if let Some(name) = &on.profile {
            let profile = Profile::by_name(name).map_err(|e| anyhow::anyhow!("--profile: {e}"))?;
            p.name = profile.name.clone();
            p.profile = Some(profile);
        }
        Ok(p)
    }

    /// The world to judge `run` in for this person: the run's world with the person's
    /// fields. Fields other than the person's (`profile`) must agree with the run's world
    /// unless `other_world`.
    pub fn world_for(&self, run: &Run, other_world: bool) -> Result<WorldConfig> {
        let mut json = run.world.clone();
        if let Some((_, over)) = &self.file {
            merge(&mut json, over);
        }
        let mut world: WorldConfig = serde_json::from_value(json.clone()).with_context(|| {
            format!(
                "the world of run {} with {}",
                run.name,
                self.file
                    .as_ref()
                    .map_or("its own person".into(), |(p, _)| p.display().to_string())
            )
        })?;
        if let Some(p) = &self.profile {
            world.profile = p.clone();
        }
        world.validate()?;
        if !other_world {
            let now = serde_json::to_value(&world)?;
            let (Some(a), Some(b)) = (run.world.as_object(), now.as_object()) else {
                bail!("run {}: its world config is not a JSON object", run.name);
            };
            let differ: Vec<String> = b
                .iter()
                .filter(|(k, v)| k.as_str() != "profile" && a.get(k.as_str()) != Some(v))
                .map(|(k, v)| {
                    format!(
                        "{k} ({} for the run, {v} here)",
                        a.get(k.as_str()).map_or("unset".into(), |x| x.to_string())
                    )
                })
                .collect();
            if !differ.is_empty() {
                bail!(
                    "{}: the world differs from run {}'s beyond the person: {}; the policy was not trained there (--other-world evaluates it there anyway)",
                    self.file
                        .as_ref()
                        .map_or("--profile".into(), |(p, _)| p.display().to_string()),
                    run.name,
                    differ.join(", ")
                );
            }
        }
        Ok(world)
    }

    /// The name shown: the person's, or the run's own profile's.
    pub fn shown(&self, world: &WorldConfig) -> String {
        if self.name.is_empty() {
            world.profile.name.clone()
        } else {
            self.name.clone()
        }
    }
}

/// The episode seeds: the curve's evaluation seeds and on.
pub fn seeds(episodes: u32) -> Vec<u64> {
    (0..episodes as u64).map(|k| EVAL_SEED_BASE + k).collect()
}

/// Threads to use: `asked`, or every core.
pub fn threads(asked: Option<usize>) -> usize {
    asked.unwrap_or_else(|| {
        std::thread::available_parallelism()
            .map(|n| n.get())
            .unwrap_or(1)
    })
}

/// A mean with its 95% interval.
#[derive(Clone, Copy, Debug, Serialize)]
pub struct Estimate {
    pub mean: f64,
    pub lo: f64,
    pub hi: f64,
}

/// Student's t at 97.5% for `df` degrees of freedom (df >= 1; the normal's 1.96 past 30).
fn t975(df: usize) -> f64 {
    const T: [f64; 30] = [
        12.706, 4.303, 3.182, 2.776, 2.571, 2.447, 2.365, 2.306, 2.262, 2.228, 2.201, 2.179, 2.160,
        2.145, 2.131, 2.120, 2.110, 2.101, 2.093, 2.086, 2.080, 2.074, 2.069, 2.064, 2.060, 2.056,
        2.052, 2.048, 2.045, 2.042,
    ];
    match df {
        0 => f64::NAN,
        d if d <= 30 => T[d - 1],
        _ => 1.96,
    }
}

/// The mean of `xs` with a t interval (NaN bounds for fewer than two).
pub fn mean_ci(xs: &[f64]) -> Estimate {
    let n = xs.len();
    let mean = xs.iter().sum::<f64>() / n as f64;
    if n < 2 {
        return Estimate {
            mean,
            lo: f64::NAN,
            hi: f64::NAN,
        };
    }
    let var = xs.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (n - 1) as f64;
    let half = t975(n - 1) * (var / n as f64).sqrt();
    Estimate {
        mean,
        lo: mean - half,
        hi: mean + half,
    }
}

/// A success rate with its 95% Wilson interval.
pub fn wilson(successes: usize, n: usize) -> Estimate {
    if n == 0 {
        return Estimate {
            mean: f64::NAN,
            lo: f64::NAN,
            hi: f64::NAN,
        };
    }
    let (p, n) = (successes as f64 / n as f64, n as f64);
    let z = 1.96f64;
    let d = 1.0 + z * z / n;
    let c = (p + z * z / (2.0 * n)) / d;
    let h = z * ((p * (1.0 - p) / n + z * z / (4.0 * n * n)).sqrt()) / d;
    Estimate {
        mean: p,
        lo: (c - h).max(0.0),
        hi: (c + h).min(1.0),
    }
}

/// The measures of the table, by name, with how to read each from an episode.
type Measure = (&'static str, &'static str, fn(&EpisodeStats) -> f64);

fn measures() -> Vec<Measure> {
    let mut m: Vec<Measure> = vec![
        ("success", "success", |e| e.success as u8 as f64),
        ("return_truth", "ground-truth return", |e| e.return_truth),
        ("return_human", "preference return r_H", |e| e.return_human),
        ("return_task", "task return r_task", |e| e.return_task),
    ];
    const TERMS: [Measure; 7] = [
        ("term_distance", "  of it: distance (w C_d)", |e| e.terms[0]),
        ("term_eaten", "  of it: eaten (w C_e)", |e| e.terms[1]),
        ("term_velocity", "  of it: speed (w C_v)", |e| e.terms[2]),
        ("term_force", "  of it: force (w C_f)", |e| e.terms[3]),
        ("term_high_force", "  of it: hard spoon (w C_hf)", |e| {
            e.terms[4]
        }),
        (
            "term_food_hit",
            "  of it: food on the person (w C_fd)",
            |e| e.terms[5],
        ),
        (
            "term_food_velocity",
            "  of it: food speed at the mouth (w C_fdv)",
            |e| e.terms[6],
        ),
    ];
    debug_assert_eq!(TERMS.len(), TERM_NAMES.len());
    m.extend(TERMS);
    m.push((
        "term_taste",
        "  of it: taste no feature names (C_ap, C_bite)",
        |e| e.taste,
    ));
    m.extend([
        (
            "eaten",
            "food eaten per attempt",
            (|e| e.eaten as f64) as fn(&EpisodeStats) -> f64,
        ),
        ("spilled", "food spilled per attempt", |e| e.spilled as f64),
        ("on_person", "food on the person per attempt", |e| {
            e.on_person as f64
        }),
        ("closest_cm", "closest approach (cm)", |e| {
            100.0 * e.closest_m
        }),
        ("top_speed_cm_s", "top speed (cm/s)", |e| {
            100.0 * e.top_speed
        }),
        ("peak_force_n", "peak force on the person (N)", |e| {
            e.peak_force
        }),
    ]);
    m
}

/// Each measure of `episodes`: its mean and 95% interval (success: Wilson; others: t).
pub fn summarise(episodes: &[EpisodeStats]) -> Vec<(String, Estimate)> {
    measures()
        .iter()
        .map(|(key, _, f)| {
            let est = if *key == "success" {
                wilson(
                    episodes.iter().filter(|e| e.success).count(),
                    episodes.len(),
                )
            } else {
                mean_ci(&episodes.iter().map(f).collect::<Vec<_>>())
            };
            (key.to_string(), est)
        })
        .collect()
}

/// One run judged for one person.
#[derive(Debug, Serialize)]
pub struct Judged {
    pub person: String,
    pub run: String,
    pub folder: PathBuf,
    pub checkpoint_env_steps: u64,
    pub version: u64,
    pub acting: &'static str,
    /// Each measure: mean and 95% interval (success: Wilson; others: t).
    pub measures: Vec<(String, Estimate)>,
    /// Each measure's paired difference with the first run on the same episodes (this run
    /// minus the first; empty for the first).
    pub versus_first: Vec<(String, Estimate)>,
    pub episodes: Vec<EpisodeStats>,
}

/// Judge every run for `person` on `seeds`.
fn judge_all(
    runs: &[Run],
    person: &Person,
    args: &EvalArgs,
    seeds: &[u64],
    bar: &indicatif::ProgressBar,
) -> Result<Vec<Judged>> {
    let acting = if args.sampled {
        Acting::Sampled
    } else {
        Acting::Mean
    };
    let threads = threads(args.threads);
    let mut out: Vec<Judged> = Vec::new();
    for run in runs {
        let world = person.world_for(run, args.on.other_world)?;
        let episodes = evaluate_seeds(&run.policy.weights, &world, seeds, acting, threads, &|| {
            bar.inc(1)
        })
        .with_context(|| format!("evaluating run {}", run.name))?;
        let ms = measures();
        let measures = summarise(&episodes);
        let versus_first = match out.first() {
            Some(first) => ms
                .iter()
                .map(|(key, _, f)| {
                    let d: Vec<f64> = episodes
                        .iter()
                        .zip(&first.episodes)
                        .map(|(b, a)| f(b) - f(a))
                        .collect();
                    (key.to_string(), mean_ci(&d))
                })
                .collect(),
            None => Vec::new(),
        };
        out.push(Judged {
            person: person.shown(&world),
            run: run.name.clone(),
            folder: run.policy.folder.clone(),
            checkpoint_env_steps: run.policy.env_steps,
            version: run.policy.version,
            acting: if args.sampled { "sampled" } else { "mean" },
            measures,
            versus_first,
            episodes,
        });
    }
    Ok(out)
}

/// A figure for people: rounded to its size.
fn fig(x: f64) -> String {
    if !x.is_finite() {
        return "-".into();
    }
    let a = x.abs();
    if a >= 100.0 {
        format!("{x:.0}")
    } else if a >= 10.0 {
        format!("{x:.1}")
    } else {
        format!("{x:.2}")
    }
}

fn est(e: &Estimate) -> String {
    if e.lo.is_finite() {
        format!("{} [{}, {}]", fig(e.mean), fig(e.lo), fig(e.hi))
    } else {
        fig(e.mean)
    }
}

/// The table of one person: measures down, runs across, then each later run's paired
/// difference with the first.
pub fn table(judged: &[Judged]) -> String {
    let ms = measures();
    let mut head = vec!["".to_string()];
    for (i, j) in judged.iter().enumerate() {
        head.push(j.run.clone());
        if i > 0 {
            head.push(format!("{} - {}", j.run, judged[0].run));
        }
    }
    let mut rows = vec![head];
    for (k, (_, label, _)) in ms.iter().enumerate() {
        let mut row = vec![label.to_string()];
        for (i, j) in judged.iter().enumerate() {
            row.push(est(&j.measures[k].1));
            if i > 0 {
                row.push(est(&j.versus_first[k].1));
            }
        }
        rows.push(row);
    }
    aligned(&rows, true)
}

/// Rows as text columns: the first left-aligned, the others right; a rule under the
/// header when `rule`.
fn aligned(rows: &[Vec<String>], rule: bool) -> String {
    let widths: Vec<usize> = (0..rows[0].len())
        .map(|c| rows.iter().map(|r| r[c].chars().count()).max().unwrap_or(0))
        .collect();
    let mut s = String::new();
    for (i, r) in rows.iter().enumerate() {
        let cells: Vec<String> = r
            .iter()
            .enumerate()
            .map(|(c, x)| {
                if c == 0 {
                    format!("{x:<w$}", w = widths[c])
                } else {
                    format!("{x:>w$}", w = widths[c])
                }
            })
            .collect();
        s.push_str(cells.join("  ").trim_end());
        s.push('\n');
        if rule && i == 0 {
            s.push_str(&"-".repeat(widths.iter().sum::<usize>() + 2 * (widths.len() - 1)));
            s.push('\n');
        }
    }
    s
}

/// The CSV header: person and run, then each measure's mean and interval, then each
/// paired difference with the first run (empty for the first).
pub fn csv_header() -> String {
    let mut cols: Vec<String> = [
        "person",
        "run",
        "checkpoint_env_steps",
        "version",
        "acting",
        "episodes",
    ]
    .iter()
    .map(|s| s.to_string())
    .collect();
    for (k, _, _) in measures() {
        cols.extend([k.to_string(), format!("{k}_lo"), format!("{k}_hi")]);
    }
    for (k, _, _) in measures() {
        cols.extend([format!("d_{k}"), format!("d_{k}_lo"), format!("d_{k}_hi")]);
    }
    cols.join(",")
}

pub fn csv_row(j: &Judged) -> String {
    let q = |s: &str| {
        if s.contains([',', '"', '\n']) {
            format!("\"{}\"", s.replace('"', "\"\""))
        } else {
            s.to_string()
        }
    };
    let mut cells = vec![
        q(&j.person),
        q(&j.run),
        j.checkpoint_env_steps.to_string(),
        j.version.to_string(),
        j.acting.to_string(),
        j.episodes.len().to_string(),
    ];
    let num = |x: f64| {
        if x.is_finite() {
            format!("{x:.6}")
        } else {
            String::new()
        }
    };
    for (_, e) in &j.measures {
        cells.extend([num(e.mean), num(e.lo), num(e.hi)]);
    }
    if j.versus_first.is_empty() {
        cells.extend(std::iter::repeat_n(String::new(), 3 * j.measures.len()));
    } else {
        for (_, e) in &j.versus_first {
            cells.extend([num(e.mean), num(e.lo), num(e.hi)]);
        }
    }
    cells.join(",")
}

/// Rows are people, columns runs: one measure's means and intervals.
fn people_table(all: &[Vec<Judged>], key: &str, title: &str) -> String {
    let k = measures()
        .iter()
        .position(|(m, _, _)| *m == key)
        .expect("a measure of the table");
    let mut rows = vec![std::iter::once(title.to_string())
        .chain(all[0].iter().map(|j| j.run.clone()))
        .collect::<Vec<_>>()];
    for judged in all {
        rows.push(
            std::iter::once(judged[0].person.clone())
                .chain(judged.iter().map(|j| est(&j.measures[k].1)))
                .collect(),
        );
    }
    aligned(&rows, false)
}

/// A progress bar over `total` episodes (hidden off a terminal).
pub fn episode_bar(total: u64) -> indicatif::ProgressBar {
    if !std::io::IsTerminal::is_terminal(&std::io::stderr()) {
        return indicatif::ProgressBar::hidden();
    }
    let bar = indicatif::ProgressBar::new(total);
    bar.set_style(
        indicatif::ProgressStyle::with_template(
            "{elapsed_precise} [{bar:30}] {pos}/{len} episodes, {eta} left",
        )
        .expect("the progress template is valid")
        .progress_chars("=> "),
    );
    bar
}

pub fn eval(args: EvalArgs) -> Result<()> {
    if args.episodes == 0 {
        bail!("--episodes: 0; evaluate at least one episode");
    }
    if args.threads == Some(0) {
        bail!("--threads: 0; at least one");
    }
    let runs = open_runs(&args.runs, args.on.checkpoint)?;
    same_world(&runs, args.on.other_world)?;
    let people = match &args.people {
        Some(dir) => Person::folder(dir)?,
        None => vec![Person::from_args(&args.on, &runs)?],
    };
    // Every world is checked before the first episode runs.
    for p in &people {
        for r in &runs {
            p.world_for(r, args.on.other_world)?;
        }
    }
    let seeds = seeds(args.episodes);
    let total = (people.len() * runs.len() * seeds.len()) as u64;
    let bar = episode_bar(total);
    let start = std::time::Instant::now();
    let mut all = Vec::new();
    for p in &people {
        all.push(judge_all(&runs, p, &args, &seeds, &bar)?);
    }
    bar.finish_and_clear();
    let secs = start.elapsed().as_secs_f64();
    let threads = threads(args.threads);
    if args.json {
        let out = serde_json::json!({
            "episodes": seeds.len(),
            "seeds": { "first": seeds[0], "count": seeds.len() },
            "acting": if args.sampled { "sampled" } else { "mean" },
            "threads": threads,
            "seconds": secs,
            "people": all,
        });
        println!("{}", serde_json::to_string_pretty(&out)?);
    } else if args.csv {
        println!("{}", csv_header());
        for judged in &all {
            for j in judged {
                println!("{}", csv_row(j));
            }
        }
    } else {
        let acting = if args.sampled {
            "sampled actions"
        } else {
            "the mean action"
        };
        for judged in &all {
            println!(
                "person {}: {} episodes each (the curve's evaluation seeds and on), {acting}; 95% intervals, differences paired on the same episodes",
                judged[0].person,
                seeds.len(),
            );
            for j in judged {
                println!(
                    "  {}: checkpoint at {} env steps (version {}), {}",
                    j.run,
                    j.checkpoint_env_steps,
                    j.version,
                    j.folder.display()
                );
            }
            print!("{}", table(judged));
            println!();
        }
        if all.len() > 1 {
            println!("across people (rows) and runs (columns):");
            print!("{}", people_table(&all, "success", "success"));
            println!();
            print!(
                "{}",
                people_table(&all, "return_human", "preference return")
            );
            println!();
        }
    }
    eprintln!(
        "evaluated {total} episodes in {secs:.1} s on {threads} thread{}",
        if threads == 1 { "" } else { "s" }
    );
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn intervals_match_the_reference_formulas() {
        // statsmodels: proportion_confint(5, 10, method="wilson") = (0.2366, 0.7634)
        let w = wilson(5, 10);
        assert!(
            (w.lo - 0.2366).abs() < 1e-4 && (w.hi - 0.7634).abs() < 1e-4,
            "{w:?}"
        );
        // proportion_confint(0, 4, method="wilson") = (0.0, 0.4899)
        let w = wilson(0, 4);
        assert!(w.lo == 0.0 && (w.hi - 0.4899).abs() < 1e-4, "{w:?}");
        // scipy: 2.5 -+ t.ppf(0.975, 3) * std([1, 2, 3, 4], ddof=1) / 2 = (0.4459, 4.5541)
        let m = mean_ci(&[1.0, 2.0, 3.0, 4.0]);
        assert!(
            (m.lo - 0.4459).abs() < 2e-3 && (m.hi - 4.5541).abs() < 2e-3,
            "{m:?}"
        );
        assert!(mean_ci(&[3.0]).lo.is_nan());
    }

    #[test]
    fn a_person_file_merges_into_the_runs_world() {
        let mut base =
            serde_json::json!({"a": 1, "profile": {"name": "paper", "weights": {"x": 1, "y": 2}}});
        merge(
            &mut base,
            &serde_json::json!({"profile": {"weights": {"y": 5}}, "b": 2}),
        );
        assert_eq!(
            base,
            serde_json::json!({"a": 1, "b": 2, "profile": {"name": "paper", "weights": {"x": 1, "y": 5}}})
        );
    }
}
