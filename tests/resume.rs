//! Runs that outlive their process: `pbrl train` on the point task as a child process,
//! killed, stopped, corrupted and resumed.

use std::path::Path;

use pbrl_learner::run::run_folder::RunFolder;

mod support;

use support::poll::poll;
use support::proc::{Launch, Proc};

fn pbrl(args: &[String]) -> Launch {
    support::proc::pbrl(args).rust_log("info")
}

fn train_args(out: &Path, extra: &[&str]) -> Vec<String> {
    let mut a: Vec<String> = [
        "train",
        "--task",
        "point",
        "--log-every",
        "500",
        "--checkpoint-every",
        "1000",
    ]
    .iter()
    .map(|s| s.to_string())
    .collect();
    a.push("--out".into());
    a.push(out.display().to_string());
    a.extend(extra.iter().map(|s| s.to_string()));
    a
}

fn spawn(args: &[String]) -> Proc {
    pbrl(args).piped().spawn()
}

/// Wait (polling the folder) until the run has a complete checkpoint; its env steps.
fn first_checkpoint(folder: &RunFolder, child: &mut Proc) -> u64 {
    poll(
        120,
        || "a checkpoint".into(),
        || {
            let c = folder.latest_checkpoint().unwrap();
            assert!(
                c.is_some() || !child.exited(),
                "the run ended before its first checkpoint"
            );
            c.map(|c| c.manifest.env_steps)
        },
    )
}

/// The curve's rows: (env steps, policy version).
fn curve(folder: &RunFolder) -> Vec<(u64, u64)> {
    let text = std::fs::read_to_string(folder.curve()).unwrap();
    let mut lines = text.lines();
    let header: Vec<&str> = lines.next().unwrap().split(',').collect();
    let col = |name: &str| header.iter().position(|h| *h == name).unwrap();
    let (steps, version) = (col("env_steps"), col("policy_version"));
    lines
        .map(|l| {
            let f: Vec<&str> = l.split(',').collect();
            (f[steps].parse().unwrap(), f[version].parse().unwrap())
        })
        .collect()
}

fn log(folder: &RunFolder) -> String {
    std::fs::read_to_string(folder.log()).unwrap()
}

#[test]
fn a_killed_run_resumes_from_its_checkpoint_and_its_curve_has_every_row_once() {
    let dir = tempfile::tempdir().unwrap();
    let folder = RunFolder::new(dir.path());
    let args = train_args(
        dir.path(),
        &["--steps", "20000", "--eval-episodes", "2", "--actors", "2"],
    );
    let mut child = spawn(&args);
    first_checkpoint(&folder, &mut child);
    child.kill();
    let resumed_from = folder
        .latest_checkpoint()
        .unwrap()
        .expect("a checkpoint")
        .manifest
        .env_steps;
    assert!(resumed_from < 20_000, "the run finished before the kill");

    let out = pbrl(&args).output();
    assert!(out.status.success());
    let log = log(&folder);
    assert!(
        log.lines()
            .any(|l| l.contains("resuming the run")
                && l.contains(&format!("env_steps={resumed_from} "))),
        "{log}"
    );
    assert!(folder.finished_steps().unwrap() >= Some(20_000));
    let rows = curve(&folder);
    assert_eq!(rows.len(), 40, "{rows:?}");
    for (k, (steps, _)) in rows.iter().enumerate() {
        let due = 500 * (k as u64 + 1);
        assert!((due..due + 30).contains(steps), "row {k}: {steps}");
    }
    assert!(
        rows.windows(2).all(|w| w[0].1 <= w[1].1),
        "the weights version only grows: {rows:?}"
    );
}

#[test]
fn a_run_stopped_and_resumed_half_way_ends_bit_identical_to_one_never_stopped() {
    // Deterministic mode, one actor. SAC on the point task publishes after the 600 random
    // steps and then every 17 episodes (510 steps): 1620 and 3150 are publication points.
    // On the ground truth (the backbone alone) and learnt from preferences (the whole
    // loop: the ensemble and its optimiser, the annotation buffer, the label store, the
    // counters; the first session at 1,200 env steps, the second at 2,700). And with the
    // label-efficiency pieces, each of which draws from a generator the checkpoint keeps:
    // segments, policy-aligned queries, crops, pseudo-labels and hybrid replay (with the
    // anchor and the comfort features: the replay's saved rows then carry them, all zero
    // on the point task; their values are checked by the replay's own unit test).
    let pref_nets = &[
        "policy",
        "critic",
        "target_critic",
        "reward_0",
        "reward_1",
        "reward_2",
    ][..];
    let efficient = &[
        "--segment-len=10",
        "--query-recent=20",
        "--reward-crops=5",
        "--pseudo-pairs=20",
        "--sac-hybrid-share=0.5",
        "--sac-hybrid-steps=300",
        "--reward-features",
        "--reward-anchor=1",
    ][..];
    for (reward, nets, extra) in [
        ("truth", &["policy", "critic", "target_critic"][..], &[][..]),
        ("pref", pref_nets, &[][..]),
        ("pref", pref_nets, efficient),
    ] {
        let whole = tempfile::tempdir().unwrap();
        let halves = tempfile::tempdir().unwrap();
        let other = tempfile::tempdir().unwrap();
        let run = |dir: &Path, seed: &str, steps: &str| {
            let mut flags = vec![
                "--sync",
                "--actors",
                "1",
                "--eval-episodes",
                "0",
                "--reward",
                reward,
                "--seed",
                seed,
                "--steps",
                steps,
            ];
            flags.extend_from_slice(extra);
            let a = train_args(dir, &flags);
            let out = pbrl(&a).output();
            assert!(
                out.status.success(),
                "{}",
                String::from_utf8_lossy(&out.stderr)
            );
            RunFolder::new(dir).latest_checkpoint().unwrap().unwrap()
        };
        let a = run(whole.path(), "5", "3150");
        run(halves.path(), "5", "1620");
        let b = run(halves.path(), "5", "3150");
        assert_eq!(a.manifest.env_steps, 3150);
        assert_eq!(b.manifest.env_steps, 3150);
        assert!(log(&RunFolder::new(halves.path())).contains("resuming the run"));
        for net in nets {
            let file = format!("{net}.safetensors");
            let (x, y) = (
                std::fs::read(a.dir.join(&file)).unwrap(),
                std::fs::read(b.dir.join(&file)).unwrap(),
            );
            assert!(x == y, "{reward} {extra:?}: {net} differs after the resume");
        }
        if reward == "pref" {
            let labels = |d: &Path| {
                let store = pbrl_learner::pref::labels::LabelStore::open(
                    &d.join("labels.sqlite"),
                    "sac-pref-s5",
                )
                .unwrap();
                let rows = store.labels_since(0).unwrap();
                let segments: Vec<_> = rows
                    .iter()
                    .map(|r| (r.first_segment, r.second_segment))
                    .collect();
                (store.counts().unwrap(), rows.len(), segments)
            };
            let (ca, na, sa) = labels(whole.path());
            assert_eq!(ca.asked, 80, "two sessions of 40: {ca:?}");
            if !extra.is_empty() {
                assert!(sa.iter().all(|(a, b)| a.1 == 10 && b.1 == 10), "{sa:?}");
            }
            assert_eq!((ca, na, sa), labels(halves.path()));
        }
        // The check can fail: another seed gives other weights.
        let c = run(other.path(), "6", "3150");
        assert_ne!(
            std::fs::read(c.dir.join("policy.safetensors")).unwrap(),
            std::fs::read(a.dir.join("policy.safetensors")).unwrap()
        );
    }
}

#[test]
fn sigterm_checkpoints_and_exits_0_a_torn_checkpoint_falls_back_a_contradiction_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let folder = RunFolder::new(dir.path());
    let args = train_args(dir.path(), &["--steps", "400000", "--actors", "1"]);
    let mut child = spawn(&args);
    let first = first_checkpoint(&folder, &mut child);
    // Wait for a second checkpoint, so that there is one to fall back to.
    poll(
        120,
        || "a second checkpoint".into(),
        || {
            let c = folder.latest_checkpoint().unwrap().unwrap();
            (c.manifest.env_steps != first).then_some(())
        },
    );
    child.signal("-TERM");
    let (status, stdout) = child.finish();
    assert_eq!(status.code(), Some(0));
    assert!(stdout.contains("stopped at"));
    let stopped = folder.latest_checkpoint().unwrap().unwrap();
    assert!(stopped.manifest.env_steps < 400_000);
    assert!(folder.finished_steps().unwrap().is_none());

    // Another algorithm on the same folder is refused, naming the field and both values.
    let mut ppo = args.clone();
    ppo.extend(["--algo".to_string(), "ppo".to_string()]);
    let out = pbrl(&ppo).output();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("algo") && err.contains("\"sac\"") && err.contains("\"ppo\""),
        "{err}"
    );

    // Tear the newest checkpoint: the run goes on from the one before, with a warning.
    let torn = stopped.dir.join("state.bin");
    let bytes = std::fs::read(&torn).unwrap();
    std::fs::write(&torn, &bytes[..bytes.len() / 2]).unwrap();
    let previous = folder.latest_checkpoint().unwrap().unwrap();
    assert!(previous.manifest.env_steps < stopped.manifest.env_steps);
    let mut short = args.clone();
    let total = (previous.manifest.env_steps + 600).to_string();
    *short
        .iter_mut()
        .skip_while(|s| *s != "--steps")
        .nth(1)
        .unwrap() = total;
    let out = pbrl(&short).output();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let log = log(&folder);
    assert!(log.contains("torn or corrupt"), "{log}");
    assert!(
        log.lines().any(|l| l.contains("resuming the run")
            && l.contains(&format!("env_steps={} ", previous.manifest.env_steps))),
        "{log}"
    );
}
