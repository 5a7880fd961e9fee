//! `pbrl exp plot`: the paper's figures (ground-truth return, success rate, preference
//! return against env steps; mean and standard deviation over seeds, one line per method)
//! and a summary table with 95% confidence intervals, for any experiment folder.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use anyhow::{anyhow, bail, Context, Result};
use clap::Args;
use plotters::prelude::*;

#[derive(Args, Debug)]
pub struct PlotArgs {
    /// Experiment folder: one run folder per run, named `<method>-s<seed>`.
    pub dir: PathBuf,
    /// Env steps at which the summary table reports each method.
    #[arg(long, value_delimiter = ',', default_value = "100000,500000,1000000")]
    pub at: Vec<u64>,
    /// Folder for the PNGs and tables (default: the experiment folder).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Plot the training episodes (sampled actions, every episode since the previous row)
    /// instead of the deterministic evaluations.
    #[arg(long, conflicts_with = "sampled")]
    pub training: bool,
    /// Plot the evaluations with sampled actions (the same seeds as the deterministic ones)
    /// instead of those with the mean action.
    #[arg(long)]
    pub sampled: bool,
    /// The summary averages each run over the rows of this many env steps up to each
    /// `--at` (0: the row at `--at` alone).
    #[arg(long, default_value_t = 100_000)]
    pub window: u64,
    /// The figures' x axis: env steps, or the labels answered so far (each row's x is the
    /// mean over seeds of `labels_answered` at that row).
    #[arg(long, value_enum, default_value = "env-steps")]
    pub x: XAxis,
    /// Also draw these curve columns (any of `curve.csv`'s, e.g. `reward_accuracy`,
    /// `rhat_step_corr`, `lambda`, `labels_answered`), one figure each.
    #[arg(long, value_delimiter = ',')]
    pub columns: Vec<String>,
}

/// What the figures are drawn against.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum XAxis {
    EnvSteps,
    Labels,
}

/// The figures: curve column (after `eval_` for the evaluations), title, y label.
const FIGURES: [(&str, &str, &str); 3] = [
    ("return_truth", "Ground-truth return", "return (sum of r)"),
    ("success_rate", "Task success rate", "success rate"),
    ("return_human", "Preference return", "return (sum of r_H)"),
];

/// One row's figures and the episodes behind them.
#[derive(Clone, Copy, Debug)]
struct Row {
    v: [f64; 3],
    episodes: f64,
}

/// One run's evaluations: bucket (env steps / log_every) -> its row.
type Run = BTreeMap<u64, Row>;

/// A run as read from its folder.
struct RunData {
    /// Env steps between rows.
    every: u64,
    rows: Run,
    /// The last row's env steps and wall time (seconds of training, over every restart;
    /// NaN where the curve has none).
    last_steps: u64,
    wall_s: f64,
    /// Labels answered at each bucket (preference runs).
    labels: BTreeMap<u64, f64>,
    /// Asked-for columns at each bucket (finite values only).
    extra: BTreeMap<String, BTreeMap<u64, f64>>,
}

fn read_run(
    dir: &Path,
    prefix: &str,
    episodes_col: &str,
    columns: &[String],
) -> Result<Option<RunData>> {
    let config = dir.join("config.json");
    let curve = dir.join("curve.csv");
    if !config.exists() || !curve.exists() {
        return Ok(None);
    }
    let cfg: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(&config)
            .with_context(|| format!("reading {}", config.display()))?,
    )
    .with_context(|| format!("parsing {}", config.display()))?;
    let every = cfg["log_every"]
        .as_u64()
        .filter(|n| *n > 0)
        .ok_or_else(|| anyhow!("{}: no log_every", config.display()))?;
    let text =
        std::fs::read_to_string(&curve).with_context(|| format!("reading {}", curve.display()))?;
    let mut lines = text.lines();
    let header: Vec<&str> = lines.next().unwrap_or_default().split(',').collect();
    let col = |name: &str| {
        header
            .iter()
            .position(|h| *h == name)
            .ok_or_else(|| anyhow!("{}: no column {name}", curve.display()))
    };
    let steps = col("env_steps")?;
    // NOTE: curves written before wall times were logged have none.
    let wall = col("wall_s").ok();
    let name = |i: usize| format!("{prefix}{}", FIGURES[i].0);
    let cols = [col(&name(0))?, col(&name(1))?, col(&name(2))?];
    let episodes = col(episodes_col)?;
    let labels_col = col("labels_answered").ok();
    let mut extra_cols = Vec::new();
    for c in columns {
        extra_cols.push((c.clone(), col(c)?));
    }
    let (mut labels, mut extra) = (
        BTreeMap::new(),
        BTreeMap::<String, BTreeMap<u64, f64>>::new(),
    );
    let mut run = Run::new();
    let (mut last_steps, mut wall_s) = (0, 0.0);
    for (k, line) in lines.enumerate() {
        let f: Vec<&str> = line.split(',').collect();
        let num = |i: usize| -> Result<f64> {
            f.get(i).and_then(|s| s.parse::<f64>().ok()).ok_or_else(|| {
                anyhow!(
                    "{} row {}: column {i} is not a number",
                    curve.display(),
                    k + 2
                )
            })
        };
        let s = num(steps)? as u64;
        (last_steps, wall_s) = (s, wall.map_or(Ok(f64::NAN), num)?);
        if let Some(c) = labels_col {
            labels.insert(s / every, num(c)?);
        }
        for (name, c) in &extra_cols {
            let v = num(*c)?;
            if v.is_finite() {
                extra.entry(name.clone()).or_default().insert(s / every, v);
            }
        }
        let v = [num(cols[0])?, num(cols[1])?, num(cols[2])?];
        if v.iter().all(|x| x.is_finite()) {
            let episodes = num(episodes)?;
            run.insert(s / every, Row { v, episodes });
        }
    }
    Ok(Some(RunData {
        every,
        rows: run,
        last_steps,
        wall_s,
        labels,
        extra,
    }))
}

/// Mean, standard deviation (over seeds, n - 1) and count.
fn stats(xs: &[f64]) -> (f64, f64, usize) {
    let n = xs.len();
    let mean = xs.iter().sum::<f64>() / n.max(1) as f64;
    let var = if n > 1 {
        xs.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (n - 1) as f64
    } else {
        0.0
    };
    (mean, var.sqrt(), n)
}

/// The 97.5% quantile of Student's t with `df` degrees of freedom (a 95% interval).
fn t975(df: usize) -> f64 {
    const T: [f64; 10] = [
        12.706, 4.303, 3.182, 2.776, 2.571, 2.447, 2.365, 2.306, 2.262, 2.228,
    ];
    match df {
        0 => f64::NAN,
        1..=10 => T[df - 1],
        11..=30 => 2.1,
        _ => 1.96,
    }
}

/// Mean and 95% confidence interval of the mean (Student's t over `xs`).
fn mean_ci(xs: &[f64]) -> (f64, f64, f64) {
    let (mean, std, n) = stats(xs);
    let half = t975(n.saturating_sub(1)) * std / (n.max(1) as f64).sqrt();
    (mean, mean - half, mean + half)
}

/// `mean [lo, hi]` with `digits` decimals (the mean alone when there is no interval).
fn interval((mean, lo, hi): (f64, f64, f64), digits: usize) -> String {
    if lo.is_finite() && hi.is_finite() {
        format!("{mean:.digits$} [{lo:.digits$}, {hi:.digits$}]")
    } else {
        format!("{mean:.digits$} (one seed)")
    }
}

/// Wilson's 95% interval of a rate: `k` successes in `n` trials.
fn wilson(k: f64, n: f64) -> (f64, f64) {
    if n <= 0.0 {
        return (f64::NAN, f64::NAN);
    }
    let (z, p) = (1.96f64, k / n);
    let centre = (p + z * z / (2.0 * n)) / (1.0 + z * z / n);
    let half = z * (p * (1.0 - p) / n + z * z / (4.0 * n * n)).sqrt() / (1.0 + z * z / n);
    (centre - half, centre + half)
}

/// A method's curve: (x, [(mean, std, n); 3]) per bucket.
type Curve = Vec<(f64, [(f64, f64, usize); 3])>;

/// The x of bucket `b` of `runs`: its env steps, or the mean labels answered there (none
/// where no run has a count).
fn x_of(x: XAxis, runs: &[RunData], b: u64, every: u64) -> Option<f64> {
    match x {
        XAxis::EnvSteps => Some((b * every) as f64),
        XAxis::Labels => {
            let xs: Vec<f64> = runs
                .iter()
                .filter_map(|r| r.labels.get(&b).copied())
                .collect();
            (!xs.is_empty()).then(|| xs.iter().sum::<f64>() / xs.len() as f64)
        }
    }
}

fn method_of(run: &str) -> Option<&str> {
    let (method, seed) = run.rsplit_once("-s")?;
    seed.parse::<u64>().ok()?;
    Some(method)
}

/// The runs of `args.dir`, grouped by method (folders `<method>-s<seed>`).
fn read_methods(
    args: &PlotArgs,
    prefix: &str,
    episodes: &str,
) -> Result<BTreeMap<String, Vec<RunData>>> {
    let mut methods: BTreeMap<String, Vec<RunData>> = BTreeMap::new();
    let entries =
        std::fs::read_dir(&args.dir).with_context(|| format!("reading {}", args.dir.display()))?;
    for e in entries.filter_map(|e| e.ok()) {
        let name = e.file_name().to_string_lossy().into_owned();
        let Some(method) = method_of(&name) else {
            continue;
        };
        match read_run(&e.path(), prefix, episodes, &args.columns) {
            Ok(Some(run)) => methods.entry(method.to_string()).or_default().push(run),
            Ok(None) => {}
            Err(e) => eprintln!("skipped {name}: {e:#}"),
        }
    }
    if methods.is_empty() {
        bail!(
            "{} holds no runs (folders named <method>-s<seed> with config.json and curve.csv)",
            args.dir.display()
        );
    }
    Ok(methods)
}

/// Each method's curve: the mean over its seeds (with the interval) at every row.
fn mean_curves(
    methods: &BTreeMap<String, Vec<RunData>>,
    args: &PlotArgs,
    what: &str,
) -> Result<BTreeMap<String, Curve>> {
    let mut curves: BTreeMap<String, Curve> = BTreeMap::new();
    for (method, runs) in methods {
        let every = runs[0].every;
        if runs.iter().any(|r| r.every != every) {
            bail!("runs of {method} have different log_every; they cannot be averaged");
        }
        let buckets: std::collections::BTreeSet<u64> =
            runs.iter().flat_map(|r| r.rows.keys().copied()).collect();
        let curve: Curve = buckets
            .into_iter()
            .filter_map(|b| {
                let fig = |i: usize| {
                    let xs: Vec<f64> = runs
                        .iter()
                        .filter_map(|r| r.rows.get(&b).map(|row| row.v[i]))
                        .collect();
                    stats(&xs)
                };
                Some((x_of(args.x, runs, b, every)?, [fig(0), fig(1), fig(2)]))
            })
            .collect();
        if curve.is_empty() {
            eprintln!("skipped {method}: no {what} rows yet");
            continue;
        }
        curves.insert(method.clone(), curve);
    }
    if curves.is_empty() {
        bail!("{}: no run has {what} rows yet", args.dir.display());
    }
    Ok(curves)
}

/// Each method's curve of the extra column `column`.
fn extra_curves(
    methods: &BTreeMap<String, Vec<RunData>>,
    column: &str,
    x: XAxis,
) -> BTreeMap<String, Curve> {
    let mut extra: BTreeMap<String, Curve> = BTreeMap::new();
    for (method, runs) in methods {
        let every = runs[0].every;
        let buckets: std::collections::BTreeSet<u64> = runs
            .iter()
            .flat_map(|r| {
                r.extra
                    .get(column)
                    .into_iter()
                    .flat_map(|m| m.keys().copied())
            })
            .collect();
        let curve: Curve = buckets
            .into_iter()
            .filter_map(|b| {
                let xs: Vec<f64> = runs
                    .iter()
                    .filter_map(|r| r.extra.get(column).and_then(|m| m.get(&b)).copied())
                    .collect();
                let none = (f64::NAN, 0.0, 0);
                Some((x_of(x, runs, b, every)?, [stats(&xs), none, none]))
            })
            .collect();
        if !curve.is_empty() {
            extra.insert(method.clone(), curve);
        }
    }
    extra
}

/// The summary table (markdown and CSV): each run's mean over the window up to each mark,
/// then the mean over seeds with its 95% interval; for the success rate also the rate
/// pooled over every episode of every seed in the window, with Wilson's interval (what the
/// evaluation's own noise allows).
fn summary(
    methods: &BTreeMap<String, Vec<RunData>>,
    curves: &BTreeMap<String, Curve>,
    args: &PlotArgs,
    what: &str,
) -> (String, String) {
    let window = |every: u64| args.window.max(every);
    let mut md = format!(
        "Figures of the {what}: each seed's mean over the rows of the last {} env steps up to the mark, then the mean over seeds [95% interval, Student's t]; \"pooled\" is the success rate over every episode of every seed in that window [Wilson's 95% interval].\n\n| method | env steps | seeds | ground-truth return | success rate | success, pooled (episodes) | preference return | labels |\n|---|---|---|---|---|---|---|---|\n",
        args.window
    );
    let mut csv = String::from("method,env_steps,seeds,window,return_truth_mean,return_truth_lo,return_truth_hi,success_rate_mean,success_rate_lo,success_rate_hi,pooled_success,pooled_lo,pooled_hi,pooled_episodes,return_human_mean,return_human_lo,return_human_hi,labels\n");
    for method in curves.keys() {
        let runs = &methods[method];
        let every = runs[0].every;
        for &at in &args.at {
            let mark = at / every * every;
            if !runs.iter().any(|r| r.rows.contains_key(&(mark / every))) {
                continue;
            }
            // Labels answered by the mark (mean over seeds; blank for a run without).
            let labels: Vec<f64> = runs
                .iter()
                .filter_map(|r| r.labels.range(..=mark / every).next_back().map(|(_, l)| *l))
                .collect();
            let labels = if labels.is_empty() {
                String::new()
            } else {
                format!("{:.0}", labels.iter().sum::<f64>() / labels.len() as f64)
            };
            let from = mark.saturating_sub(window(every)) / every + 1;
            let (mut per_seed, mut k, mut n): ([Vec<f64>; 3], f64, f64) = Default::default();
            for r in runs {
                let rows: Vec<&Row> = r
                    .rows
                    .range(from..=mark / every)
                    .map(|(_, row)| row)
                    .collect();
                if rows.is_empty() {
                    continue;
                }
                for (i, xs) in per_seed.iter_mut().enumerate() {
                    xs.push(rows.iter().map(|row| row.v[i]).sum::<f64>() / rows.len() as f64);
                }
                k += rows.iter().map(|row| row.v[1] * row.episodes).sum::<f64>();
                n += rows.iter().map(|row| row.episodes).sum::<f64>();
            }
            let seeds = per_seed[0].len();
            let [truth, success, human] = [0, 1, 2].map(|i| mean_ci(&per_seed[i]));
            let (lo, hi) = wilson(k.round(), n);
            let pooled = k / n.max(1.0);
            // NOTE: a rate's interval stops at 0 and 1 (NaN, for one seed, stays NaN).
            let clip = |x: f64| if x.is_nan() { x } else { x.clamp(0.0, 1.0) };
            let rate = (success.0, clip(success.1), clip(success.2));
            md.push_str(&format!(
                "| {method} | {mark} | {seeds} | {} | {} | {pooled:.2} [{lo:.2}, {hi:.2}] ({n:.0}) | {} | {labels} |\n",
                interval(truth, 1),
                interval(rate, 2),
                interval(human, 1)
            ));
            csv.push_str(&format!(
                "{method},{mark},{seeds},{},{:.4},{:.4},{:.4},{:.4},{:.4},{:.4},{pooled:.4},{lo:.4},{hi:.4},{n:.0},{:.4},{:.4},{:.4},{labels}\n",
                window(every), truth.0, truth.1, truth.2, success.0, success.1, success.2, human.0, human.1, human.2
            ));
        }
    }
    (md, csv)
}

/// What each method's runs cost: env steps reached and wall time (a table added to `md`,
/// and its CSV).
fn runs_table(methods: &BTreeMap<String, Vec<RunData>>, md: &mut String) -> String {
    md.push_str("\nThe runs: env steps of their last row and wall time of training (seconds, summed over restarts).\n\n| method | seeds | env steps | wall time, mean | wall time, min-max |\n|---|---|---|---|---|\n");
    let mut runs_csv = String::from(
        "method,seeds,env_steps_min,env_steps_max,wall_s_mean,wall_s_min,wall_s_max\n",
    );
    for (method, runs) in methods {
        let steps =
            |f: fn(u64, u64) -> u64| runs.iter().map(|r| r.last_steps).reduce(f).unwrap_or(0);
        let (lo, hi) = (steps(u64::min), steps(u64::max));
        let n = runs.len();
        let range = if lo == hi {
            format!("{lo}")
        } else {
            format!("{lo}-{hi}")
        };
        let walls: Vec<f64> = runs
            .iter()
            .map(|r| r.wall_s)
            .filter(|w| w.is_finite())
            .collect();
        let (md_wall, csv_wall) = if walls.len() == n {
            let (mean, _, _) = stats(&walls);
            let lo = walls.iter().copied().fold(f64::MAX, f64::min);
            let hi = walls.iter().copied().fold(f64::MIN, f64::max);
            (
                format!("{mean:.0} s | {lo:.0}-{hi:.0} s"),
                format!("{mean:.1},{lo:.1},{hi:.1}"),
            )
        } else {
            ("not logged | not logged".into(), ",,".into())
        };
        md.push_str(&format!("| {method} | {n} | {range} | {md_wall} |\n"));
        runs_csv.push_str(&format!("{method},{n},{lo},{hi},{csv_wall}\n"));
    }
    runs_csv
}

pub fn plot(args: PlotArgs) -> Result<()> {
    let out = args.out.clone().unwrap_or_else(|| args.dir.clone());
    // Column prefix, file prefix, what the figures show, the column counting episodes.
    let (prefix, file, what, episodes) = if args.training {
        ("", "training_", "training episodes", "episodes")
    } else if args.sampled {
        (
            "eval_sampled_",
            "sampled_",
            "evaluation, sampled actions",
            "eval_episodes",
        )
    } else {
        ("eval_", "", "evaluation", "eval_episodes")
    };
    std::fs::create_dir_all(&out).with_context(|| format!("creating {}", out.display()))?;
    let methods = read_methods(&args, prefix, episodes)?;
    let curves = mean_curves(&methods, &args, what)?;
    pbrl_actor::render::load_font()?;
    let (xdesc, xfile) = match args.x {
        XAxis::EnvSteps => ("env steps", ""),
        XAxis::Labels => ("labels answered", "_vs_labels"),
    };
    for (i, (column, title, ylabel)) in FIGURES.iter().enumerate() {
        let path = out.join(format!("{file}{column}{xfile}.png"));
        draw(
            &path,
            &format!("{title} ({what})"),
            ylabel,
            xdesc,
            i,
            i == 1,
            &curves,
        )?;
        println!("wrote {}", path.display());
    }
    // Any other column, one figure each.
    for column in &args.columns {
        let extra = extra_curves(&methods, column, args.x);
        if extra.is_empty() {
            eprintln!("no run has values of {column}");
            continue;
        }
        let path = out.join(format!("{column}{xfile}.png"));
        draw(&path, column, column, xdesc, 0, false, &extra)?;
        println!("wrote {}", path.display());
    }
    let (mut md, csv) = summary(&methods, &curves, &args, what);
    let runs_csv = runs_table(&methods, &mut md);
    for (name, text) in [
        ("summary.md", &md),
        ("summary.csv", &csv),
        ("runs.csv", &runs_csv),
    ] {
        let path = out.join(format!("{file}{name}"));
        std::fs::write(&path, text).with_context(|| format!("writing {}", path.display()))?;
        println!("wrote {}", path.display());
    }
    print!("{md}");
    Ok(())
}

/// Line colours that read on white (matplotlib's "tab10"; plotters' `Palette99` gives the
/// third method a pale yellow), repeated past ten methods.
fn line_color(k: usize) -> RGBColor {
    const TAB10: [(u8, u8, u8); 10] = [
        (31, 119, 180),
        (255, 127, 14),
        (44, 160, 44),
        (214, 39, 40),
        (148, 103, 189),
        (140, 86, 75),
        (227, 119, 194),
        (127, 127, 127),
        (188, 189, 34),
        (23, 190, 207),
    ];
    let (r, g, b) = TAB10[k % TAB10.len()];
    RGBColor(r, g, b)
}

fn draw_err<E: std::fmt::Debug>(e: E) -> anyhow::Error {
    anyhow!("drawing: {e:?}")
}

#[allow(clippy::too_many_arguments)]
fn draw(
    path: &Path,
    title: &str,
    ylabel: &str,
    xdesc: &str,
    fig: usize,
    rate: bool,
    curves: &BTreeMap<String, Curve>,
) -> Result<()> {
    let points = curves.values().flat_map(|c| c.iter());
    let (mut x1, mut y0, mut y1) = (1f64, f64::MAX, f64::MIN);
    for (s, f) in points {
        x1 = x1.max(*s);
        y0 = y0.min(f[fig].0 - f[fig].1);
        y1 = y1.max(f[fig].0 + f[fig].1);
    }
    // A rate's axis and band stop at 0 and 1: mean ± std may pass them, the rate cannot.
    let in_range = |v: f64| if rate { v.clamp(0.0, 1.0) } else { v };
    if rate {
        (y0, y1) = (0.0, 1.0);
    }
    let pad = ((y1 - y0) * 0.05).max(1e-3);
    let root = BitMapBackend::new(path, (900, 560)).into_drawing_area();
    root.fill(&WHITE).map_err(draw_err)?;
    let mut chart = ChartBuilder::on(&root)
        .caption(title, ("sans-serif", 26))
        .margin(15)
        .x_label_area_size(45)
        .y_label_area_size(70)
        .build_cartesian_2d(0f64..x1, (y0 - pad)..(y1 + pad))
        .map_err(draw_err)?;
    chart
        .configure_mesh()
        .x_desc(xdesc)
        .y_desc(ylabel)
        .x_label_formatter(&|x| {
            if xdesc == "env steps" {
                format!("{:.0}k", x / 1e3)
            } else {
                format!("{x:.0}")
            }
        })
        .draw()
        .map_err(draw_err)?;
    for (k, (method, curve)) in curves.iter().enumerate() {
        let color = line_color(k);
        let mut band: Vec<(f64, f64)> = curve
            .iter()
            .map(|(s, f)| (*s, in_range(f[fig].0 + f[fig].1)))
            .collect();
        band.extend(
            curve
                .iter()
                .rev()
                .map(|(s, f)| (*s, in_range(f[fig].0 - f[fig].1))),
        );
        chart
            .draw_series(std::iter::once(Polygon::new(band, color.mix(0.2).filled())))
            .map_err(draw_err)?;
        let seeds = curve.iter().map(|(_, f)| f[fig].2).max().unwrap_or(0);
        chart
            .draw_series(LineSeries::new(
                curve.iter().map(|(s, f)| (*s, f[fig].0)),
                color.stroke_width(2),
            ))
            .map_err(draw_err)?
            .label(format!(
                "{method} ({seeds} seed{})",
                if seeds == 1 { "" } else { "s" }
            ))
            .legend(move |(x, y)| {
                PathElement::new(vec![(x, y), (x + 20, y)], color.stroke_width(2))
            });
    }
    chart
        .configure_series_labels()
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .position(SeriesLabelPosition::LowerRight)
        .draw()
        .map_err(draw_err)?;
    root.present().map_err(draw_err)?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn intervals_match_their_textbook_values() {
        // Wilson, 5 of 10 at 95%: 0.2366 to 0.7634 (statsmodels' proportion_confint,
        // method="wilson").
        let (lo, hi) = wilson(5.0, 10.0);
        assert!(
            (lo - 0.2366).abs() < 1e-4 && (hi - 0.7634).abs() < 1e-4,
            "{lo} {hi}"
        );
        // 0 of 30 is not an interval of width 0.
        let (lo, hi) = wilson(0.0, 30.0);
        assert!(lo.abs() < 1e-12 && (hi - 0.1135).abs() < 1e-4, "{lo} {hi}");
        // Student's t over 3 seeds: 2 +- 4.303 * 1 / sqrt(3).
        let (m, lo, hi) = mean_ci(&[1.0, 2.0, 3.0]);
        assert_eq!(m, 2.0);
        assert!(
            (hi - 2.0 - 4.303 / 3f64.sqrt()).abs() < 1e-9 && (2.0 - lo - (hi - 2.0)).abs() < 1e-12
        );
        // One seed: no interval.
        assert!(mean_ci(&[1.0]).1.is_nan());
        assert_eq!(interval((1.0, f64::NAN, f64::NAN), 1), "1.0 (one seed)");
    }
}
