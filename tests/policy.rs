//! The learnt policy in a person's hands, through the commands a person runs: `pbrl eval`
//! gives the curve's last row again and compares runs across people, `pbrl export` writes
//! an ONNX model that another runtime (tract) runs to pbrl's own actions with a card that
//! parses, `pbrl watch` writes a page that plays in Chromium and a GIF, and bad input is
//! refused by name. Two small feeding runs (2,000 env steps, the default method) are
//! trained once for all of them.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::OnceLock;

use pbrl_actor::policy::Policy;
use pbrl_learner::run::export::Card;
use pbrl_learner::run::saved_policy::SavedPolicy;
use rand::{Rng, SeedableRng};
use serde_json::Value;

mod support;

fn pbrl(args: &[&str]) -> (bool, String, String) {
    let out = support::proc::pbrl(args)
        .rust_log("warn")
        .env("RUST_BACKTRACE", "0")
        .output();
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

fn s(p: &Path) -> &str {
    p.to_str().expect("a UTF-8 temporary path")
}

/// Two finished feeding runs, seeds 0 and 1: Decoupled PEBBLE as `pbrl train` runs it, cut
/// to 2,000 env steps, a row (4 evaluation episodes) every 1,000.
fn runs() -> &'static (PathBuf, PathBuf, PathBuf) {
    static RUNS: OnceLock<(PathBuf, PathBuf, PathBuf)> = OnceLock::new();
    RUNS.get_or_init(|| {
        let dir = tempfile::tempdir().unwrap().keep();
        let train = |name: &str, seed: &str| {
            let out = dir.join(name);
            let (ok, stdout, stderr) = pbrl(&[
                "train",
                "--steps=2000",
                "--log-every=1000",
                "--eval-episodes=4",
                "--sac-random-steps=1000",
                "--quiet",
                "--seed",
                seed,
                "--out",
                s(&out),
            ]);
            assert!(ok, "training {name}: {stderr}");
            // The end of a run points on.
            for cmd in ["pbrl eval", "pbrl watch", "pbrl export"] {
                assert!(
                    stdout.contains(&format!("{cmd} {}", out.display())),
                    "{cmd} not offered: {stdout}"
                );
            }
            out
        };
        (train("a", "0"), train("b", "1"), dir)
    })
}

/// The curve's last row, by column.
fn last_row(run: &Path) -> std::collections::BTreeMap<String, String> {
    let text = std::fs::read_to_string(run.join("curve.csv")).unwrap();
    let mut lines = text.lines();
    let head: Vec<&str> = lines.next().unwrap().split(',').collect();
    let last: Vec<&str> = lines.last().unwrap().split(',').collect();
    head.iter()
        .zip(last)
        .map(|(h, v)| (h.to_string(), v.to_string()))
        .collect()
}

fn measure(j: &Value, name: &str) -> f64 {
    j["measures"]
        .as_array()
        .unwrap()
        .iter()
        .find(|m| m[0] == name)
        .unwrap_or_else(|| panic!("no measure {name} in {j}"))[1]["mean"]
        .as_f64()
        .unwrap()
}

#[test]
fn eval_of_the_last_checkpoint_gives_the_curves_last_row() {
    let (a, _, _) = runs();
    let row = last_row(a);
    let eval = |threads: &str| -> Value {
        let (ok, stdout, stderr) =
            pbrl(&["eval", s(a), "--episodes=4", "--json", "--threads", threads]);
        assert!(ok, "{stderr}");
        serde_json::from_str(&stdout).unwrap()
    };
    let one = eval("1");
    let j = &one["people"][0][0];
    assert_eq!(j["checkpoint_env_steps"].to_string(), row["env_steps"]);
    for (m, col) in [
        ("return_truth", "eval_return_truth"),
        ("success", "eval_success_rate"),
        ("return_human", "eval_return_human"),
        ("return_task", "eval_return_task"),
    ] {
        assert_eq!(
            format!("{:.4}", measure(j, m)),
            row[col],
            "{m} against the curve's {col}"
        );
    }
    // Spread over two threads, the same episodes.
    let two = eval("2");
    assert_eq!(
        one["people"][0][0]["episodes"],
        two["people"][0][0]["episodes"]
    );
    // The table a person reads names every measure.
    let (ok, table, stderr) = pbrl(&["eval", s(a), "--episodes=2"]);
    assert!(ok, "{stderr}");
    for label in [
        "success",
        "ground-truth return",
        "preference return",
        "of it: speed",
        "food spilled per attempt",
        "closest approach (cm)",
        "top speed (cm/s)",
        "peak force on the person (N)",
    ] {
        assert!(table.contains(label), "{label} missing:\n{table}");
    }
}

/// A person file: the paper's person with the speed and force weights times `k`.
fn person(dir: &Path, name: &str, k: f32) -> PathBuf {
    let p = dir.join(format!("{name}.json"));
    let w = serde_json::json!({"profile": {"name": name, "weights": {
        "distance": 0.5, "eaten": 0.5, "velocity": 0.25 * k, "force": 0.3 * k,
        "high_force": 0.1 * k, "food_hit": 2.5, "food_velocity": 10.0}}});
    std::fs::write(&p, w.to_string()).unwrap();
    p
}

#[test]
fn eval_judges_every_run_for_every_person_on_the_same_episodes() {
    let (a, b, root) = runs();
    let people = root.join("people");
    std::fs::create_dir_all(&people).unwrap();
    person(&people, "easy", 0.1);
    person(&people, "gentle", 10.0);
    let (ok, stdout, stderr) = pbrl(&[
        "eval",
        s(a),
        s(b),
        "--episodes=3",
        "--people",
        s(&people),
        "--json",
    ]);
    assert!(ok, "{stderr}");
    let j: Value = serde_json::from_str(&stdout).unwrap();
    let all = j["people"].as_array().unwrap();
    assert_eq!(all.len(), 2);
    let (easy, gentle) = (&all[0], &all[1]);
    assert_eq!(
        (easy[0]["person"].as_str(), gentle[1]["person"].as_str()),
        (Some("easy"), Some("gentle"))
    );
    assert_eq!(
        (easy[0]["run"].as_str(), easy[1]["run"].as_str()),
        (Some("a"), Some("b"))
    );
    // One policy, two people who differ in taste only: the same episodes, judged apart.
    let seeds = |x: &Value| {
        x["episodes"]
            .as_array()
            .unwrap()
            .iter()
            .map(|e| e["seed"].clone())
            .collect::<Vec<_>>()
    };
    assert_eq!(seeds(&easy[0]), seeds(&easy[1]));
    assert_eq!(seeds(&easy[0]), seeds(&gentle[0]));
    for m in ["success", "closest_cm", "top_speed_cm_s", "eaten"] {
        assert_eq!(measure(&easy[0], m), measure(&gentle[0], m), "{m}");
    }
    assert!(
        measure(&gentle[0], "term_velocity") < measure(&easy[0], "term_velocity"),
        "the gentle person minds speed more"
    );
    // Paired differences: the second run against the first, on the same episodes.
    let d = easy[1]["versus_first"].as_array().unwrap();
    let diff = d.iter().find(|x| x[0] == "return_truth").unwrap()[1]["mean"]
        .as_f64()
        .unwrap();
    let want = measure(&easy[1], "return_truth") - measure(&easy[0], "return_truth");
    assert!((diff - want).abs() < 1e-6, "{diff} against {want}");
    assert!(easy[0]["versus_first"].as_array().unwrap().is_empty());
    // The same table as CSV: a row per person and run.
    let (ok, csv, stderr) = pbrl(&[
        "eval",
        s(a),
        s(b),
        "--episodes=3",
        "--people",
        s(&people),
        "--csv",
    ]);
    assert!(ok, "{stderr}");
    let rows: Vec<&str> = csv.lines().collect();
    assert_eq!(rows.len(), 5, "{csv}");
    let head: Vec<&str> = rows[0].split(',').collect();
    assert_eq!(&head[..2], ["person", "run"]);
    let col = head.iter().position(|h| *h == "d_success").unwrap();
    assert_eq!(
        rows[1].split(',').nth(col),
        Some(""),
        "the first run has no difference"
    );
    assert_ne!(
        rows[2].split(',').nth(col),
        Some(""),
        "the second run has one"
    );
}

/// The largest difference between the actions of the ONNX model `bytes`, run in tract, and
/// `policy`'s mean actions, on `obs` (rows of 25).
fn worst_difference(bytes: &[u8], policy: &Policy, obs: &[f32]) -> f32 {
    use tract_onnx::prelude::*;
    let n = obs.len() / 25;
    let runnable = tract_onnx::onnx()
        .model_for_read(&mut std::io::Cursor::new(bytes))
        .unwrap()
        .with_input_fact(0, f32::fact([n, 25]).into())
        .unwrap()
        .into_optimized()
        .unwrap()
        .into_runnable()
        .unwrap();
    let input = Tensor::from_shape(&[n, 25], obs).unwrap();
    let out = runnable.run(tvec!(input.into_tvalue())).unwrap();
    let actions = out[0].to_plain_array_view::<f32>().unwrap();
    assert_eq!(actions.shape(), [n, 7]);
    let mut rng = rand::rng();
    let mut worst = 0f32;
    for k in 0..n {
        let mine = policy
            .act(&obs[k * 25..(k + 1) * 25], &mut rng, true)
            .unwrap();
        for (i, m) in mine.iter().enumerate() {
            worst = worst.max((m - actions[[k, i]]).abs());
        }
    }
    worst
}

#[test]
fn the_exported_model_runs_in_tract_to_pbrls_actions() {
    let (a, _, root) = runs();
    let onnx = root.join("export/policy.onnx");
    let (ok, stdout, stderr) = pbrl(&["export", s(a), "--onnx", s(&onnx), "--episodes=2"]);
    assert!(ok, "{stderr}");
    assert!(stdout.contains("opset 13"), "{stdout}");
    // The card: every documented field, nothing else (Card denies unknown fields).
    let text = std::fs::read_to_string(root.join("export/policy.card.json")).unwrap();
    let card: Card = serde_json::from_str(&text).unwrap();
    assert_eq!(
        (card.opset, card.observation.len(), card.action.len()),
        (13, 25, 7)
    );
    assert_eq!(card.env_steps, 2000);
    assert_eq!(card.person["name"], "paper");
    let eval = card.evaluation.as_ref().unwrap();
    assert_eq!(eval["episodes"], 2);
    assert!(eval["measures"]["success"]["mean"].is_number());

    let policy = SavedPolicy::load(a, None).unwrap();
    let pbrl_policy = Policy::from_weights(&policy.weights).unwrap();
    let n = 1000;
    // Observations around the world's: positions within a metre, angles within pi, a
    // contact force now and then.
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
    let obs: Vec<f32> = (0..n * 25)
        .map(|i| match i % 25 {
            10..=16 => rng.random_range(-std::f32::consts::PI..std::f32::consts::PI),
            24 => rng.random_range(0.0..5.0),
            _ => rng.random_range(-1.0..1.0),
        })
        .collect();
    let bytes = std::fs::read(&onnx).unwrap();
    let worst = worst_difference(&bytes, &pbrl_policy, &obs);
    assert!(worst <= 1e-5, "tract and pbrl differ by up to {worst}");
}

#[test]
fn bad_input_is_refused_by_name() {
    let (a, b, root) = runs();
    let refused = |args: &[&str], want: &[&str]| {
        let (ok, _, stderr) = pbrl(args);
        assert!(!ok, "{args:?} was taken");
        for w in want {
            assert!(stderr.contains(w), "{args:?}: {w:?} not in: {stderr}");
        }
        assert!(!stderr.contains("panicked"), "{stderr}");
    };
    let empty = root.join("not-a-run");
    std::fs::create_dir_all(&empty).unwrap();
    refused(
        &["eval", s(&empty)],
        &["is not a run folder", "config.json"],
    );
    refused(&["eval", s(&root.join("nowhere"))], &["no such folder"]);
    refused(
        &["eval", s(a), "--checkpoint=7"],
        &["no checkpoint at 7 env steps", "2000"],
    );
    refused(&["eval", s(a), "--episodes=0"], &["--episodes"]);
    refused(
        &["eval", s(a), "--profile=nobody"],
        &["--profile", "nobody"],
    );
    let bad = root.join("bad");
    std::fs::create_dir_all(&bad).unwrap();
    let write = |name: &str, text: &str| {
        let p = bad.join(name);
        std::fs::write(&p, text).unwrap();
        p
    };
    let p = write("cut.json", "{\"profile\": {");
    refused(&["eval", s(a), "--world", s(&p)], &["cut.json"]);
    let p = write("typo.json", "{\"profle\": {}}");
    refused(&["eval", s(a), "--world", s(&p)], &["typo.json", "profle"]);
    let p = write("slow.json", "{\"substeps\": 7}");
    refused(
        &["eval", s(a), "--world", s(&p)],
        &["substeps", "--other-world"],
    );
    refused(
        &["watch", s(a), "--no-gif", "--world", s(&p)],
        &["substeps"],
    );
    refused(
        &["export", s(&empty), "--onnx", s(&root.join("x.onnx"))],
        &["is not a run folder"],
    );
    // Two runs of different worlds are not judged side by side as if on the same episodes.
    let other = root.join("other-world");
    let copy = Command::new("cp")
        .args(["-r", s(b), s(&other)])
        .status()
        .unwrap();
    assert!(copy.success());
    let cfg = other.join("config.json");
    let mut c: Value = serde_json::from_str(&std::fs::read_to_string(&cfg).unwrap()).unwrap();
    c["world"]["config"]["substeps"] = 4.into();
    std::fs::write(&cfg, c.to_string()).unwrap();
    refused(
        &["eval", s(a), s(&other), "--episodes=1"],
        &["different worlds", "substeps"],
    );
    let (ok, _, stderr) = pbrl(&["eval", s(a), s(&other), "--episodes=1", "--other-world"]);
    assert!(ok, "{stderr}");
    // With --other-world it is evaluated there, as asked.
    let (ok, _, stderr) = pbrl(&[
        "eval",
        s(a),
        "--episodes=1",
        "--world",
        s(&p),
        "--other-world",
    ]);
    assert!(ok, "{stderr}");
}

#[test]
#[cfg_attr(skip_browser, ignore = "PBRL_SKIP_BROWSER=1: needs a browser")]
fn watch_writes_a_page_that_plays_in_chromium_and_a_gif() {
    use support::poll::poll;
    use support::web::{Browser, CHROMEDRIVER, CHROMIUM};
    let (a, b, root) = runs();
    let out = root.join("watch");
    let html = out.join("a-b.html");
    let (ok, stdout, stderr) = pbrl(&[
        "watch",
        s(a),
        s(b),
        "--episodes=2",
        "--html",
        s(&html),
        "--step=4",
    ]);
    assert!(ok, "{stderr}");
    assert!(stdout.contains("a-b.gif"), "{stdout}");
    // The GIF: both episodes, every 4th step (201 frames each: 51), and it moves.
    let file = std::fs::File::open(out.join("a-b.gif")).unwrap();
    let mut opts = gif::DecodeOptions::new();
    opts.set_color_output(gif::ColorOutput::RGBA);
    let mut dec = opts.read_info(file).unwrap();
    let (mut frames, mut changed) = (0, 0);
    while let Some(f) = dec.read_next_frame().unwrap() {
        frames += 1;
        // NOTE: after the first, a frame holds only what changed (the rest transparent).
        changed += f.buffer.chunks(4).any(|p| p[3] != 0) as usize;
    }
    assert_eq!(frames, 2 * 51);
    assert!(changed > 80, "{changed} of {frames} frames change anything");
    // The page, opened from the file in a real browser, with nothing of pbrl running.
    assert!(
        Path::new(CHROMIUM).exists() && Path::new(CHROMEDRIVER).exists(),
        "this test needs {CHROMIUM} and {CHROMEDRIVER}: run deploy/setup.sh"
    );
    let browser = Browser::open(&out);
    browser.go(&format!("file://{}", html.display()));
    assert_eq!(browser.body("mode"), "watch");
    let first = poll(
        30,
        || "the first frame drawn".into(),
        || {
            let f = browser.body("frame");
            (!f.is_empty()).then_some(f)
        },
    );
    poll(
        60,
        || format!("frames to advance from {first}"),
        || {
            let f = browser.body("frame");
            (f != first && browser.body("state") == "playing").then_some(())
        },
    );
    // The arrow key steps to the other episode; the strips show its numbers.
    let q = browser.body("query");
    browser.key("\u{E014}");
    poll(
        30,
        || "the next episode".into(),
        || (browser.body("query") != q).then_some(()),
    );
    let closest = browser.exec(
        "return document.querySelector('#att-right [data-q=distance] [data-v=closest]').textContent;",
        serde_json::json!([]),
    );
    assert!(
        closest.as_str().is_some_and(|t| t.parse::<f64>().is_ok()),
        "{closest}"
    );
    std::fs::write(out.join("page.png"), browser.screenshot()).unwrap();
}

/// A random policy of `hidden` layers with a normaliser that does something (PPO's kind:
/// means, variances, a clip that bites).
fn synthetic(hidden: &[usize], seed: u64) -> pbrl_common::wire::Weights {
    use pbrl_common::wire::{Tensor, Weights};
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let sizes: Vec<usize> = std::iter::once(25)
        .chain(hidden.iter().copied())
        .chain(std::iter::once(14))
        .collect();
    let mut tensors = Vec::new();
    for (i, w) in sizes.windows(2).enumerate() {
        let scale = 1.0 / (w[0] as f32).sqrt();
        tensors.push(Tensor {
            name: format!("pi.l{i}.weight"),
            shape: vec![w[1], w[0]],
            data: (0..w[0] * w[1])
                .map(|_| rng.random_range(-scale..scale))
                .collect(),
        });
        tensors.push(Tensor {
            name: format!("pi.l{i}.bias"),
            shape: vec![w[1]],
            data: (0..w[1]).map(|_| rng.random_range(-0.1..0.1)).collect(),
        });
    }
    Weights {
        version: 1,
        env_steps: 0,
        obs_dim: 25,
        act_dim: 7,
        tensors,
        obs_mean: (0..25).map(|_| rng.random_range(-0.5..0.5)).collect(),
        obs_var: (0..25).map(|_| rng.random_range(0.01..2.0)).collect(),
        obs_clip: 2.0,
        random_actions: false,
        episodes_per_actor: 0,
        acks: Vec::new(),
    }
}

#[test]
fn the_model_normalises_and_clips_as_pbrl_does() {
    use pbrl_learner::run::export::{model, Message};
    let w = synthetic(&[32, 16], 3);
    let bytes = model(&w, "test", &[]).unwrap().write_to_bytes().unwrap();
    let n = 1000;
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
    // Observations far enough out that the clip at 2 standard deviations bites.
    let obs: Vec<f32> = (0..n * 25).map(|_| rng.random_range(-4.0..4.0)).collect();
    let policy = Policy::from_weights(&w).unwrap();
    let worst = worst_difference(&bytes, &policy, &obs);
    assert!(worst <= 1e-5, "tract and pbrl differ by up to {worst}");
    // A policy whose last layer is not twice the action wide is refused by name.
    let mut bad = synthetic(&[8], 4);
    bad.act_dim = 6;
    let e = model(&bad, "test", &[]).unwrap_err().to_string();
    assert!(e.contains("not 25 to 2 x 6"), "{e}");
}
