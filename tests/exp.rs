//! `pbrl exp`: a tiny grid, interrupted and run again, finishes without redoing a
//! finished run; `pbrl exp plot` draws it.

use pbrl_learner::run::run_folder::RunFolder;

mod support;

use support::poll::poll;
use support::proc::pbrl;

const GRID: &str = r#"
name = "tiny"
algos = ["sac"]
rewards = ["true"]
seeds = [1, 2]
steps = 20000
[set]
task = "point"
actors = 1
log-every = 1000
checkpoint-every = 1000
eval-episodes = 2
"#;

#[test]
fn an_interrupted_grid_carries_on_without_redoing_a_finished_run() {
    let dir = tempfile::tempdir().unwrap();
    let grid = dir.path().join("grid.toml");
    std::fs::write(&grid, GRID).unwrap();
    let out = dir.path().join("exp");
    let exp = |extra: &[&str]| {
        pbrl(["exp", "run"])
            .args([&grid])
            .args(["--out"])
            .args([&out])
            .args(["--parallel", "1", "--progress-every", "1"])
            .args(extra)
    };
    let first = RunFolder::new(out.join("sac-true-s1"));
    let second = RunFolder::new(out.join("sac-true-s2"));
    let mut child = exp(&[]).piped().spawn();
    poll(
        180,
        || "the first run to finish".into(),
        || first.finished_steps().unwrap().map(|_| ()),
    );
    poll(
        180,
        || "the second run's first checkpoint".into(),
        || second.latest_checkpoint().unwrap().map(|_| ()),
    );
    let finished_curve = std::fs::read(first.curve()).unwrap();
    child.signal("-TERM");
    let (done, _) = child.finish();
    assert!(done.success());
    assert!(
        second.finished_steps().unwrap().is_none(),
        "the second run finished before the interruption; the test proves nothing"
    );

    let again = exp(&[]).output();
    let text = String::from_utf8_lossy(&again.stdout);
    assert!(again.status.success(), "{text}");
    assert!(text.contains("sac-true-s1: finished (20"), "{text}");
    assert!(!text.contains("sac-true-s1: starting"), "{text}");
    assert!(text.contains("sac-true-s2: resuming after"), "{text}");
    assert_eq!(std::fs::read(first.curve()).unwrap(), finished_curve);
    assert!(second.finished_steps().unwrap() >= Some(20_000));

    // The figures and the table.
    let plot = pbrl(["exp", "plot"])
        .args([&out])
        .args(["--at", "10000,20000"])
        .output();
    assert!(
        plot.status.success(),
        "{}",
        String::from_utf8_lossy(&plot.stderr)
    );
    for f in [
        "return_truth.png",
        "success_rate.png",
        "return_human.png",
        "summary.csv",
    ] {
        assert!(out.join(f).exists(), "{f}");
    }
    let summary = std::fs::read_to_string(out.join("summary.md")).unwrap();
    assert!(summary.contains("| sac-true | 20000 | 2 |"), "{summary}");
    // What the runs cost: both reached the total, with a wall time each.
    let runs = std::fs::read_to_string(out.join("runs.csv")).unwrap();
    let row: Vec<&str> = runs
        .lines()
        .find(|l| l.starts_with("sac-true,"))
        .unwrap_or_else(|| panic!("{runs}"))
        .split(',')
        .collect();
    assert_eq!(row[1], "2", "{runs}");
    let steps: Vec<u64> = row[2..4].iter().map(|x| x.parse().unwrap()).collect();
    assert!(steps.iter().all(|s| (20_000..20_100).contains(s)), "{runs}");
    let wall: Vec<f64> = row[4..].iter().map(|x| x.parse().unwrap()).collect();
    assert!(
        wall[1] > 0.0 && wall[1] <= wall[0] && wall[0] <= wall[2],
        "{runs}"
    );
}
