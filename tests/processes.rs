//! `pbrl learner` and two `pbrl actor` processes joined on loopback (the learner's session is
//! the router, as `deploy/local.sh` runs them), the learner stopped with SIGSTOP for 30 s and
//! continued: the actors keep their sessions, the run goes on, nothing is lost.

use std::path::Path;
use std::process::Child;
use std::time::{Duration, Instant};

mod support;

use support::signal;

fn spawn(args: &[&str], log: &Path) -> Child {
    // NOTE: zenoh's transport at debug says when a link's lease expires or a push gives
    // up; pbrl's own lines at info.
    support::spawn_pbrl(
        args,
        log,
        "warn,pbrl=info,pbrl_actor=info,pbrl_learner=info,zenoh_transport=debug",
    )
}

/// Wait for `child` to exit, at most `secs` seconds; true if it exited 0.
fn exited_ok(child: &mut Child, secs: u64) -> bool {
    let start = Instant::now();
    loop {
        if let Some(status) = child.try_wait().unwrap() {
            return status.success();
        }
        if start.elapsed() > Duration::from_secs(secs) {
            let _ = child.kill();
            panic!("a process did not exit within {secs} s");
        }
        std::thread::sleep(Duration::from_millis(50));
    }
}

fn rows(curve: &Path) -> Vec<Vec<String>> {
    std::fs::read_to_string(curve)
        .unwrap_or_default()
        .lines()
        .map(|l| l.split(',').map(str::to_string).collect())
        .collect()
}

#[test]
fn a_learner_stopped_for_30_s_keeps_its_actors_and_loses_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let port = pbrl_common::connect::free_local_port().unwrap();
    let endpoint = format!("tcp/127.0.0.1:{port}");
    let out = dir.path().join("run");
    let curve = out.join("curve.csv");
    let mut learner = spawn(
        &[
            "learner",
            "--mode",
            "router",
            "--listen",
            &endpoint,
            "--run",
            "sigstop",
            "--actors",
            "2",
            "--task",
            "point",
            "--reward",
            "truth",
            "--steps",
            "120000",
            "--log-every",
            "4000",
            "--eval-episodes",
            "4",
            "--quiet",
            "--out",
            out.to_str().unwrap(),
        ],
        &dir.path().join("learner.log"),
    );
    let mut actors: Vec<Child> = (0..2)
        .map(|id| {
            spawn(
                &[
                    "actor",
                    "--connect",
                    &endpoint,
                    "--run",
                    "sigstop",
                    "--id",
                    &id.to_string(),
                    "--task",
                    "point",
                ],
                &dir.path().join(format!("actor{id}.log")),
            )
        })
        .collect();
    // Training is under way: a row of the curve is written.
    let start = Instant::now();
    while rows(&curve).len() < 2 {
        assert!(start.elapsed() < Duration::from_secs(120), "no curve row");
        assert!(
            learner.try_wait().unwrap().is_none(),
            "the learner exited early"
        );
        std::thread::sleep(Duration::from_millis(20));
    }
    signal(&learner, "-STOP");
    let stopped_at = rows(&curve).len();
    // NOTE: the pause itself is what is tested: three lease-less zenoh defaults long.
    std::thread::sleep(Duration::from_secs(30));
    for a in actors.iter_mut() {
        assert!(
            a.try_wait().unwrap().is_none(),
            "an actor exited while the learner was stopped"
        );
    }
    signal(&learner, "-CONT");
    assert!(exited_ok(&mut learner, 300), "the learner finishes");
    for a in actors.iter_mut() {
        assert!(exited_ok(a, 60), "the actors stop when told");
    }

    let rows = rows(&curve);
    let header = &rows[0];
    let col = |name: &str| header.iter().position(|h| h == name).unwrap();
    assert!(
        rows.len() > stopped_at + 5,
        "the run went on after the pause"
    );
    for r in &rows[1..] {
        assert_eq!(r[col("eval_episodes")], "4", "every row evaluated: {r:?}");
    }
    let last = rows.last().unwrap();
    assert_eq!(last[col("lost_messages")], "0", "no trajectory missing");
    assert_eq!(last[col("dropped_messages")], "0");
    for id in 0..2 {
        let log = std::fs::read_to_string(dir.path().join(format!("actor{id}.log"))).unwrap();
        for sign in ["expired", "Unable to push", "Closing transport"] {
            let seen: Vec<&str> = log
                .lines()
                .filter(|l| l.contains(sign) && !l.contains("the learner says stop"))
                .collect();
            // NOTE: the end closes the actor's transport too, and says "Closing transport"
            // once or twice (the learner's exit and the actor's own close, as they race);
            // none may come from the pause.
            let allowed = if sign == "Closing transport" { 2 } else { 0 };
            assert!(seen.len() <= allowed, "actor {id}: {seen:#?}");
        }
        assert!(
            log.contains("the learner says stop"),
            "actor {id} was stopped by the learner"
        );
    }
}
