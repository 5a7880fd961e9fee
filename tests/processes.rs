//! `pbrl learner` and two `pbrl actor` processes joined on loopback (the learner's session is
//! the router, as `deploy/local.sh` runs them), the learner stopped with SIGSTOP for 30 s and
//! continued: the actors keep their sessions, the run goes on, nothing is lost.

use std::path::Path;
use std::time::Duration;

mod support;

use support::poll::poll;
use support::proc::{pbrl, Proc};

fn spawn(args: &[&str], log: &Path) -> Proc {
    // NOTE: zenoh's transport at debug says when a link's lease expires or a push gives
    // up; pbrl's own lines at info.
    pbrl(args)
        .append_log(log)
        .rust_log("warn,pbrl=info,pbrl_actor=info,pbrl_learner=info,zenoh_transport=debug")
        .spawn()
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
    let mut actors: Vec<Proc> = (0..2)
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
    poll(
        120,
        || "a curve row".into(),
        || {
            assert!(!learner.exited(), "the learner exited early");
            (rows(&curve).len() >= 2).then_some(())
        },
    );
    learner.signal("-STOP");
    let stopped_at = rows(&curve).len();
    // NOTE: the pause itself is what is tested: three lease-less zenoh defaults long.
    std::thread::sleep(Duration::from_secs(30));
    for a in actors.iter_mut() {
        assert!(!a.exited(), "an actor exited while the learner was stopped");
    }
    learner.signal("-CONT");
    assert!(
        learner.exit(300, "the learner").success(),
        "the learner finishes"
    );
    for a in actors.iter_mut() {
        assert!(
            a.exit(60, "an actor").success(),
            "the actors stop when told"
        );
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
