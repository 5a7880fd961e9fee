//! What a person sees: `pbrl train` on a terminal (a tmux pane, read back as a screen),
//! the bar, one line per curve row and the closing lines, and nothing else; no stale
//! copies of the bar in the scrollback.

use std::process::Command;

mod support;

fn tmux(socket: &str, args: &[&str]) -> String {
    let out = Command::new("tmux")
        .arg("-L")
        .arg(socket)
        .args(args)
        .output()
        .expect("tmux runs (deploy/setup.sh installs it)");
    assert!(
        out.status.success(),
        "tmux {args:?}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8_lossy(&out.stdout).into_owned()
}

#[test]
fn a_training_run_shows_the_bar_and_its_rows_and_no_chatter() {
    let dir = tempfile::tempdir().unwrap();
    let socket = format!("pbrl-test-{}", std::process::id());
    let out = dir.path().join("run");
    // The default method (learnt reward, feedback sessions) on the point task, small;
    // `--sync` trains the ensemble in place, so its line is in the log before the end.
    let train = format!(
        "{} train --task=point --steps=6000 --log-every=1000 --unsup-steps=1000 \
         --feedback-interval=1000 --eval-episodes=5 --actors=1 --sync --run=term --out={} \
         2>&1; tmux -L {socket} wait-for -S done",
        support::proc::PBRL,
        out.display()
    );
    tmux(
        &socket,
        &[
            "new-session",
            "-d",
            "-x",
            "240",
            "-y",
            "50",
            "sh",
            "-c",
            &train,
        ],
    );
    tmux(&socket, &["set-option", "-g", "remain-on-exit", "on"]);
    // Blocks until the run's shell says it is done.
    tmux(&socket, &["wait-for", "done"]);
    let screen = tmux(&socket, &["capture-pane", "-p", "-S", "-", "-E", "-"]);
    let _ = Command::new("tmux")
        .args(["-L", &socket, "kill-server"])
        .status();
    let lines: Vec<&str> = screen.lines().filter(|l| !l.trim().is_empty()).collect();
    let rows: Vec<&&str> = lines
        .iter()
        .filter(|l| l.contains(" env steps: eval return"))
        .collect();
    assert_eq!(rows.len(), 6, "one line per curve row:\n{screen}");
    let bars = lines.iter().filter(|l| l.contains("] ")).count();
    assert_eq!(bars, 1, "one bar, at the end, no stale copies:\n{screen}");
    assert!(
        lines.iter().any(|l| l.starts_with("done: 6000 env steps")),
        "{screen}"
    );
    for l in &lines {
        assert!(
            !l.contains(" INFO ") && !l.contains(" DEBUG "),
            "chatter on the terminal: {l}\n{screen}"
        );
    }
    // The feedback detail is in the run's log, its figures as numbers.
    let log = std::fs::read_to_string(out.join("train.log")).unwrap();
    let trained = log
        .lines()
        .find(|l| l.contains("reward ensemble trained"))
        .unwrap_or_else(|| panic!("no training of the ensemble in the log:\n{log}"));
    assert!(
        trained.contains("accuracy=") && !trained.contains("accuracy=\""),
        "{trained}"
    );
}
