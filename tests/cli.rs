//! The `pbrl env` commands, run as a user runs them.

mod support;

fn pbrl(args: &[&str]) -> std::process::Output {
    support::proc::pbrl(args).output()
}

fn text(out: &std::process::Output) -> (String, String) {
    (
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

#[test]
fn demo_prints_each_episode_and_a_summary() {
    let out = pbrl(&[
        "env",
        "demo",
        "--controller",
        "scripted",
        "--episodes",
        "2",
        "--seed",
        "4",
    ]);
    let (stdout, stderr) = text(&out);
    assert!(out.status.success(), "{stderr}");
    assert!(
        stdout.lines().any(|l| l.trim_start().starts_with('4')),
        "{stdout}"
    );
    assert!(
        stdout.lines().any(|l| l.trim_start().starts_with('5')),
        "{stdout}"
    );
    assert!(
        stdout.contains("summary: controller Scripted, 2 episodes"),
        "{stdout}"
    );
}

#[test]
fn bench_prints_steps_per_second() {
    let out = pbrl(&["env", "bench", "--steps", "300"]);
    let (stdout, stderr) = text(&out);
    assert!(out.status.success(), "{stderr}");
    let line = stdout
        .lines()
        .find(|l| l.starts_with("env steps per second"))
        .expect(&stdout);
    let rate: f64 = line
        .split(':')
        .nth(1)
        .unwrap()
        .split_whitespace()
        .next()
        .unwrap()
        .parse()
        .unwrap();
    assert!(rate > 0.0);
    assert!(stdout.contains("per physics substep"));
}

#[test]
fn record_then_render_from_the_record() {
    let dir = tempfile::tempdir().unwrap();
    let rec = dir.path().join("ep.bin");
    let png = dir.path().join("ep.png");
    let out = pbrl(&[
        "env",
        "record",
        "--controller",
        "zero",
        "--seed",
        "2",
        "--out",
        rec.to_str().unwrap(),
    ]);
    assert!(out.status.success(), "{}", text(&out).1);
    let bytes = std::fs::read(&rec).unwrap();
    let t = pbrl_common::Trajectory::decode(&bytes).unwrap();
    assert_eq!(t.seed, 2);
    assert_eq!(t.outcome.steps, 200);
    let out = pbrl(&[
        "env",
        "render",
        "--from",
        rec.to_str().unwrap(),
        "--out",
        png.to_str().unwrap(),
    ]);
    assert!(out.status.success(), "{}", text(&out).1);
    let head = std::fs::read(&png).unwrap();
    assert_eq!(&head[1..4], b"PNG");
    assert!(
        head.len() > 20_000,
        "a near-empty picture: {} bytes",
        head.len()
    );
}

#[test]
fn bad_input_is_refused_without_a_panic() {
    let out = pbrl(&["env", "demo", "--controller", "bogus"]);
    let (_, stderr) = text(&out);
    assert!(!out.status.success());
    assert!(
        stderr.contains("bogus") && stderr.contains("--controller"),
        "{stderr}"
    );
    assert!(!stderr.contains("panicked"), "{stderr}");

    let dir = tempfile::tempdir().unwrap();
    for (json, field) in [
        (r#"{"food_count": 0}"#, "food_count = 0"),
        (r#"{"food_radius": -0.01}"#, "food_radius = -0.01"),
        (r#"{"food_radus": 0.01}"#, "food_radus"),
    ] {
        let cfg = dir.path().join("world.json");
        std::fs::write(&cfg, json).unwrap();
        let out = pbrl(&[
            "env",
            "demo",
            "--episodes",
            "1",
            "--world",
            cfg.to_str().unwrap(),
        ]);
        let (_, stderr) = text(&out);
        assert!(!out.status.success(), "{json} was accepted");
        assert!(stderr.contains(field), "{json}: {stderr}");
        assert!(!stderr.contains("panicked"), "{stderr}");
    }
    let out = pbrl(&["env", "demo", "--episodes", "1", "--profile", "nobody"]);
    let (_, stderr) = text(&out);
    assert!(
        !out.status.success() && stderr.contains("profile = nobody"),
        "{stderr}"
    );
    let out = pbrl(&[
        "env",
        "render",
        "--from",
        "/no/such/file",
        "--out",
        "/tmp/x.png",
    ]);
    let (_, stderr) = text(&out);
    assert!(
        !out.status.success() && stderr.contains("/no/such/file"),
        "{stderr}"
    );
    // A label store that is not there, and one that is not a label store.
    let out = pbrl(&["labels", "fit", "/no/such/run"]);
    let (_, stderr) = text(&out);
    assert!(
        !out.status.success() && stderr.contains("no label store at /no/such/run"),
        "{stderr}"
    );
    let junk = dir.path().join("junk.sqlite");
    std::fs::write(&junk, "not a database").unwrap();
    let out = pbrl(&["labels", "fit", junk.to_str().unwrap()]);
    let (_, stderr) = text(&out);
    assert!(
        !out.status.success() && stderr.contains("junk.sqlite") && !stderr.contains("panicked"),
        "{stderr}"
    );
}

#[test]
fn logs_to_a_pipe_carry_no_colour_escapes() {
    let dir = tempfile::tempdir().unwrap();
    let out_dir = dir.path().join("run");
    let out = pbrl(&[
        "train",
        "--task=point",
        "--reward=truth",
        "--steps=600",
        "--log-every=300",
        "--eval-episodes=0",
        "--actors=1",
        "--run=colours",
        &format!("--out={}", out_dir.display()),
    ]);
    let (_, stderr) = text(&out);
    assert!(out.status.success(), "{stderr}");
    // Without a terminal the curve's rows are log lines; pbrl's progress is in train.log.
    assert!(stderr.contains("600 env steps: eval return"), "{stderr}");
    assert!(!stderr.contains("learner starts"), "{stderr}");
    let log = std::fs::read_to_string(out_dir.join("train.log")).unwrap();
    assert!(log.contains("learner starts"), "{log}");
    assert!(
        !stderr.contains('\u{1b}'),
        "an escape in a piped log: {stderr:?}"
    );
}

#[test]
fn an_experiment_with_no_runs_at_a_time_is_refused_before_it_starts() {
    let dir = tempfile::tempdir().unwrap();
    let grid = dir.path().join("g.toml");
    std::fs::write(
        &grid,
        "name = \"g\"\nalgos = [\"sac\"]\nrewards = [\"truth\"]\nseeds = [1]\nsteps = 100\n",
    )
    .unwrap();
    let out_dir = dir.path().join("out");
    let out = pbrl(&[
        "exp",
        "run",
        grid.to_str().unwrap(),
        "--parallel",
        "0",
        "--out",
        out_dir.to_str().unwrap(),
    ]);
    let (_, stderr) = text(&out);
    assert!(!out.status.success());
    assert!(stderr.contains("--parallel 0"), "{stderr}");
    assert!(!out_dir.exists(), "nothing made");
}
