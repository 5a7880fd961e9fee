//! The fault matrix: a Decoupled PEBBLE run on the point task, with the default
//! label-efficient settings, as separate processes (a learner, two actors, an oracle teacher) through the stock `zenohd` router over TLS with
//! access control by role, struck by one fault while labels flow. After each the run
//! finishes, the label store holds exactly the answers the teacher gave (the whole budget,
//! none lost, none twice) and every curve row has its evaluation. Each prints the time it
//! took to recover (`cargo test --test faults -- --nocapture`).
//!
//! The learner killed and restarted is `tests/label_crash.rs` and `tests/processes.rs`.

mod support;

use std::time::{Duration, Instant};

use support::deploy::{Deployment, BUDGET};

const STEPS: u64 = 5_000;
/// Seconds a run may take, faults included (a debug build on two busy cores).
const RUN_S: u64 = 900;

/// Labels are flowing: some stored, not yet all, and a curve row is written.
fn labels_flowing(d: &Deployment) -> Duration {
    d.until("labels flowing", RUN_S, |d| {
        let n = d.stored().len();
        n >= 1 && d.rows() >= 1
    })
}

fn report(fault: &str, recovered: Duration) {
    eprintln!(
        "fault matrix: {fault}: recovered in {:.1} s",
        recovered.as_secs_f64()
    );
}

#[test]
fn a_teacher_killed_mid_run_and_restarted_loses_no_label() {
    let mut d = Deployment::new("fault-teacher", STEPS, false);
    d.start_all();
    labels_flowing(&d);
    d.teacher.take().unwrap().kill();
    // The run goes on without it: the learner asks again what is unanswered.
    let rows = d.rows();
    d.until("a curve row without the teacher", RUN_S, |d| {
        d.rows() > rows
    });
    let before = d.stored().len();
    assert!(
        before < BUDGET,
        "the budget was all stored before the fault"
    );
    d.start_teacher();
    let t = d.until("a label stored after the restart", RUN_S, |d| {
        d.stored().len() > before
    });
    report("teacher SIGKILL, restarted", t);
    d.finish(RUN_S);
}

#[test]
fn an_actor_killed_leaves_the_run_to_the_other_and_a_replacement_joins() {
    // NOTE: longer, so that the run is still going when the replacement joins.
    let mut d = Deployment::new("fault-actor", 2 * STEPS, false);
    d.start_all();
    labels_flowing(&d);
    let mut actor = d.actors[1].take().unwrap();
    actor.kill();
    let rows = d.rows();
    d.until("two curve rows from one actor", RUN_S, |d| {
        d.rows() >= rows + 2
    });
    d.start_actor(1);
    let t0 = Instant::now();
    d.until("the replacement has weights", RUN_S, |d| {
        d.actors[1]
            .as_ref()
            .unwrap()
            .log()
            .contains("actor has weights")
    });
    let rows = d.rows();
    d.until("a curve row with the replacement", RUN_S, |d| {
        d.rows() > rows
    });
    report("one actor SIGKILL, a replacement with its id", t0.elapsed());
    d.finish(RUN_S);
    let log = d.actors[1].as_ref().unwrap().log();
    let line = log
        .lines()
        .find(|l| l.contains("the learner says stop"))
        .unwrap_or_else(|| panic!("the replacement was not told to stop: {log}"));
    assert!(
        !line.contains("episodes=0 ") && !line.contains("episodes\u{1b}[0m\u{1b}[2m=\u{1b}[0m0 "),
        "the replacement ran no episode: {line}"
    );
}

#[test]
fn the_router_killed_and_restarted_every_session_reconnects_by_itself() {
    let mut d = Deployment::new("fault-router", STEPS, false);
    d.start_all();
    labels_flowing(&d);
    let before = d.stored().len();
    assert!(
        before < BUDGET,
        "the budget was all stored before the fault"
    );
    d.router.take().unwrap().kill();
    let rows = d.rows();
    d.start_router();
    let t = d.until("a curve row after the restart", RUN_S, |d| d.rows() > rows);
    report("router SIGKILL, restarted", t);
    d.finish(RUN_S);
}

#[test]
fn the_link_between_two_hosts_down_for_30_s_and_up_again() {
    let mut d = Deployment::new("fault-link", STEPS, true);
    d.start_all();
    labels_flowing(&d);
    assert!(
        d.stored().len() < BUDGET,
        "the budget was all stored before the fault"
    );
    let hosts = d.hosts.as_ref().unwrap();
    hosts.workers_link(false);
    // NOTE: the fault itself lasts 30 s (the cable pulled), not a wait for an event.
    std::thread::sleep(Duration::from_secs(30));
    hosts.workers_link(true);
    let rows = d.rows();
    let t = d.until("a curve row after the link is back", RUN_S, |d| {
        d.rows() > rows
    });
    report("the workers' link down 30 s", t);
    d.finish(RUN_S);
}
