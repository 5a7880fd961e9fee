//! pbrl deployed as separate processes through the stock `zenohd` router over TLS with
//! access control by role (`deploy/certs.sh`): on loopback, or across hosts that are
//! network namespaces on a virtual link. The multi-host test and the fault matrix drive it:
//! start, kill and restart any process, take the workers' link down, then check that the
//! run finished, that every answer the teacher gave is in the label store once, and that
//! every curve row has its evaluation.

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::atomic::{AtomicU32, Ordering};
use std::time::{Duration, Instant};

use super::poll::poll;
use super::proc::{pbrl, Launch, Proc, LOG};
use super::store::sql;

/// The stock router: `PBRL_ZENOHD`, else `$CARGO_HOME/bin/zenohd`, else on the PATH.
pub fn zenohd() -> PathBuf {
    if let Some(p) = std::env::var_os("PBRL_ZENOHD") {
        return PathBuf::from(p);
    }
    let home = std::env::var_os("CARGO_HOME")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(std::env::var_os("HOME").unwrap()).join(".cargo"));
    let p = home.join("bin/zenohd");
    if p.is_file() {
        return p;
    }
    let out = Command::new("sh")
        .args(["-c", "command -v zenohd"])
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "zenohd is not installed: run `bash deploy/setup.sh` (it builds the stock router)"
    );
    PathBuf::from(String::from_utf8_lossy(&out.stdout).trim())
}

/// `deploy/certs.sh --out dir --run run [--router-listen listen] hosts...`.
pub fn certs(dir: &Path, run: &str, listen: Option<&str>, hosts: &[&str]) -> PathBuf {
    let mut cmd = Command::new("bash");
    cmd.arg(Path::new(env!("CARGO_MANIFEST_DIR")).join("deploy/certs.sh"))
        .arg("--out")
        .arg(dir)
        .args(["--run", run]);
    if let Some(l) = listen {
        cmd.args(["--router-listen", l]);
    }
    let status = cmd
        .args(hosts)
        .stdout(Stdio::null())
        .status()
        .expect("bash runs");
    assert!(status.success(), "deploy/certs.sh: {status}");
    dir.join("router-tls.json5")
}

fn ip(args: &[&str]) {
    let out = Command::new("ip")
        .args(args)
        .output()
        .unwrap_or_else(|e| panic!("iproute2's `ip` does not run ({e}): this test needs it"));
    assert!(
        out.status.success(),
        "ip {}: {} (the multi-host tests make network namespaces: they need root)",
        args.join(" "),
        String::from_utf8_lossy(&out.stderr).trim()
    );
}

/// The router host's address on the link; the learner's and the workers' are .1 and .3.
pub const ROUTER_IP: &str = "10.77.0.2";

/// Three hosts on one virtual link: the learner's, the router's (a bridge) and the
/// workers'. Removed, with every process in them, when dropped.
pub struct Hosts {
    pub learner: String,
    pub router: String,
    pub workers: String,
}

impl Hosts {
    pub fn new() -> Self {
        static N: AtomicU32 = AtomicU32::new(0);
        let tag = format!(
            "pbrl{}x{}",
            std::process::id(),
            N.fetch_add(1, Ordering::Relaxed)
        );
        let h = Hosts {
            learner: format!("{tag}-l"),
            router: format!("{tag}-r"),
            workers: format!("{tag}-w"),
        };
        for n in h.all() {
            ip(&["netns", "add", n]);
            ip(&["-n", n, "link", "set", "lo", "up"]);
        }
        let r = h.router.as_str();
        ip(&["-n", r, "link", "add", "br0", "type", "bridge"]);
        ip(&[
            "-n",
            r,
            "addr",
            "add",
            &format!("{ROUTER_IP}/24"),
            "dev",
            "br0",
        ]);
        ip(&["-n", r, "link", "set", "br0", "up"]);
        for (host, dev, addr) in [
            (&h.learner, "l0", "10.77.0.1"),
            (&h.workers, "w0", "10.77.0.3"),
        ] {
            let port = format!("{dev}p");
            ip(&[
                "link", "add", dev, "netns", host, "type", "veth", "peer", "name", &port, "netns",
                r,
            ]);
            ip(&["-n", host, "addr", "add", &format!("{addr}/24"), "dev", dev]);
            ip(&["-n", host, "link", "set", dev, "up"]);
            ip(&["-n", r, "link", "set", &port, "master", "br0"]);
            ip(&["-n", r, "link", "set", &port, "up"]);
        }
        h
    }

    fn all(&self) -> [&str; 3] {
        [&self.learner, &self.router, &self.workers]
    }

    /// The workers' host's link to the router up or down (its cable pulled).
    pub fn workers_link(&self, up: bool) {
        ip(&[
            "-n",
            &self.workers,
            "link",
            "set",
            "w0",
            if up { "up" } else { "down" },
        ]);
    }
}

impl Drop for Hosts {
    fn drop(&mut self) {
        for n in self.all() {
            // NOTE: what still runs in a namespace goes with it.
            let _ = Command::new("ip")
                .args(["netns", "pids", n])
                .output()
                .map(|o| {
                    for pid in String::from_utf8_lossy(&o.stdout).split_whitespace() {
                        let _ = Command::new("kill").args(["-KILL", pid]).status();
                    }
                });
            let _ = Command::new("ip").args(["netns", "del", n]).status();
        }
    }
}

/// Env steps between curve rows.
pub const LOG_EVERY: u64 = 1_000;

/// One Decoupled PEBBLE run on the point task with the default label-efficient settings
/// (`--label-efficient`: segments, the budget's schedule, crops, comfort features, hybrid
/// replay, the task prior; what `pbrl train` runs on feeding): a learner, two actors and an
/// oracle teacher through a stock router, each with its own certificate. The budget's
/// schedule spans the first 2,400 env steps after the pretraining (five sessions), so a run
/// of several thousand steps has time to store every answer, and a fault can strike while
/// labels flow.
pub struct Deployment {
    pub dir: tempfile::TempDir,
    pub run: String,
    pub steps: u64,
    pub hosts: Option<Hosts>,
    endpoint: String,
    certs: PathBuf,
    pub router: Option<Proc>,
    pub learner: Option<Proc>,
    pub actors: Vec<Option<Proc>>,
    pub teacher: Option<Proc>,
    starts: u32,
}

/// Labels the run asks for.
pub const BUDGET: usize = 40;

impl Deployment {
    /// Certificates for `run` and, with `across_hosts`, three network namespaces; nothing
    /// started yet.
    pub fn new(run: &str, steps: u64, across_hosts: bool) -> Self {
        let dir = tempfile::tempdir().unwrap();
        let made = dir.path().join("certs");
        let (hosts, endpoint, listen) = if across_hosts {
            (
                Some(Hosts::new()),
                format!("tls/{ROUTER_IP}:7447"),
                format!("tls/{ROUTER_IP}:7447"),
            )
        } else {
            let port = pbrl_common::connect::free_local_port().unwrap();
            let e = format!("tls/127.0.0.1:{port}");
            (None, e.clone(), e)
        };
        let router_ip = if across_hosts { ROUTER_IP } else { "127.0.0.1" };
        certs(
            &made,
            run,
            Some(&listen),
            &[
                &format!("router:hub@{router_ip}"),
                "learner:server",
                "actor:lab",
                "teacher:ward",
            ],
        );
        Deployment {
            dir,
            run: run.to_string(),
            steps,
            hosts,
            endpoint,
            certs: made,
            router: None,
            learner: None,
            actors: vec![None, None],
            teacher: None,
            starts: 0,
        }
    }

    pub fn path(&self, name: &str) -> PathBuf {
        self.dir.path().join(name)
    }

    pub fn out(&self) -> PathBuf {
        self.path("run")
    }

    fn teacher_state(&self) -> PathBuf {
        self.path("teacher.sqlite")
    }

    /// `launch` on `host` (`None`: this machine), in the deployment's folder, its stderr to
    /// a fresh log `name-k.log`.
    fn spawn(&mut self, host: Option<String>, launch: Launch, name: &str) -> Proc {
        self.starts += 1;
        launch
            .host(host)
            .dir(self.dir.path())
            .log(&format!("{name}-{}", self.starts))
            .rust_log(LOG)
            .spawn()
    }

    fn host(&self, pick: impl Fn(&Hosts) -> &String) -> Option<String> {
        self.hosts.as_ref().map(|h| pick(h).clone())
    }

    fn connect(&self, cert: &str) -> Vec<String> {
        vec![
            format!("--connect={}", self.endpoint),
            format!("--tls-ca={}", self.certs.join("ca.pem").display()),
            format!(
                "--tls-cert={}",
                self.certs.join(format!("{cert}.pem")).display()
            ),
            format!(
                "--tls-key={}",
                self.certs.join(format!("{cert}.key")).display()
            ),
        ]
    }

    /// The router, up once it accepts connections (on loopback) or once its log is there.
    pub fn start_router(&mut self) {
        let args = vec![
            "-c".to_string(),
            self.certs.join("router-tls.json5").display().to_string(),
        ];
        let host = self.host(|h| &h.router);
        let p = self.spawn(host, Launch::new(zenohd(), args), "zenohd");
        self.router = Some(p);
    }

    pub fn start_learner(&mut self) {
        let mut args: Vec<String> = [
            "learner",
            "--task=point",
            "--algo=sac",
            "--reward=decoupled",
            "--actors=2",
            "--eval-episodes=2",
            "--label-efficient",
            "--unsup-steps=600",
            "--feedback-interval=600",
            "--feedback-span=2400",
            "--query-retry-s=1",
            // NOTE: a gradient step of a larger net every env step holds the point task
            // to tens of env steps/s, so the budget's sessions span tens of seconds of
            // the run and a fault strikes while labels flow.
            "--sac-update-every=1",
            "--sac-hidden=256,256",
            "--sac-batch=256",
            "--quiet",
        ]
        .iter()
        .map(|s| s.to_string())
        .collect();
        args.extend([
            format!("--max-feedback={BUDGET}"),
            format!("--log-every={LOG_EVERY}"),
            format!("--steps={}", self.steps),
            format!("--run={}", self.run),
            format!("--out={}", self.out().display()),
        ]);
        args.extend(self.connect("learner-server"));
        let host = self.host(|h| &h.learner);
        let p = self.spawn(host, pbrl(args), "learner");
        self.learner = Some(p);
    }

    pub fn start_actor(&mut self, id: usize) {
        let mut args: Vec<String> = vec![
            "actor".into(),
            "--task=point".into(),
            format!("--run={}", self.run),
            format!("--id={id}"),
        ];
        args.extend(self.connect("actor-lab"));
        let host = self.host(|h| &h.workers);
        let p = self.spawn(host, pbrl(args), &format!("actor{id}"));
        self.actors[id] = Some(p);
    }

    pub fn start_teacher(&mut self) {
        let mut args: Vec<String> = vec![
            "teacher".into(),
            "--task=point".into(),
            "--teacher=oracle".into(),
            "--teacher-id=oracle-ward".into(),
            format!("--run={}", self.run),
            format!("--teacher-state={}", self.teacher_state().display()),
        ];
        args.extend(self.connect("teacher-ward"));
        let host = self.host(|h| &h.workers);
        let p = self.spawn(host, pbrl(args), "teacher");
        self.teacher = Some(p);
    }

    /// Router, learner, two actors and the teacher.
    pub fn start_all(&mut self) {
        self.start_router();
        self.start_learner();
        for id in 0..2 {
            self.start_actor(id);
        }
        self.start_teacher();
    }

    /// Every log so far, for a failure's message.
    pub fn logs(&self) -> String {
        let mut names: Vec<PathBuf> = std::fs::read_dir(self.dir.path())
            .unwrap()
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| p.extension().is_some_and(|e| e == "log"))
            .collect();
        names.sort();
        names
            .iter()
            .map(|p| {
                let text = std::fs::read_to_string(p).unwrap_or_default();
                let tail: Vec<&str> = text.lines().rev().take(40).collect();
                let tail: Vec<&str> = tail.into_iter().rev().collect();
                format!("--- {}\n{}", p.display(), tail.join("\n"))
            })
            .collect::<Vec<_>>()
            .join("\n")
    }

    /// The curve's rows as (env steps, evaluation episodes).
    pub fn curve(&self) -> Vec<(u64, u64)> {
        let text = std::fs::read_to_string(self.out().join("curve.csv")).unwrap_or_default();
        let mut lines = text.lines();
        let Some(header) = lines.next() else {
            return Vec::new();
        };
        let col = |name: &str| header.split(',').position(|c| c == name).unwrap();
        let (steps, eval) = (col("env_steps"), col("eval_episodes"));
        lines
            .filter_map(|l| {
                let f: Vec<&str> = l.split(',').collect();
                Some((f.get(steps)?.parse().ok()?, f.get(eval)?.parse().ok()?))
            })
            .collect()
    }

    /// The answers in the label store.
    pub fn stored(&self) -> BTreeSet<u64> {
        let db = self.out().join("labels.sqlite");
        if !db.is_file() {
            return BTreeSet::new();
        }
        sql(
            &db,
            "SELECT id FROM queries WHERE answer IN ('first', 'second', 'equal', 'skip')",
        )
        .unwrap()
        .iter()
        .map(|r| r["id"].as_u64().unwrap())
        .collect()
    }

    /// The answers the teacher gave (its outbox, first answers only).
    pub fn given(&self) -> BTreeSet<u64> {
        if !self.teacher_state().is_file() {
            return BTreeSet::new();
        }
        sql(
            &self.teacher_state(),
            "SELECT query FROM outbox WHERE repeat = 0",
        )
        .unwrap()
        .iter()
        .map(|r| r["query"].as_u64().unwrap())
        .collect()
    }

    /// Poll until `ready` (up to `secs`), or panic with every log; the time it took.
    pub fn until(&self, what: &str, secs: u64, ready: impl Fn(&Self) -> bool) -> Duration {
        let t0 = Instant::now();
        poll(
            secs,
            || format!("{what}\n{}", self.logs()),
            || ready(self).then_some(()),
        );
        t0.elapsed()
    }

    /// The curve's rows so far.
    pub fn rows(&self) -> usize {
        self.curve().len()
    }

    /// Wait for the learner's end and check the run: it exited 0, the curve has a row
    /// every `LOG_EVERY` env steps to the end, each with its evaluation, and the label
    /// store holds exactly the answers the teacher gave, the whole budget.
    pub fn finish(&mut self, secs: u64) {
        let mut learner = self.learner.take().expect("the learner runs");
        let status = poll(
            secs,
            || format!("the run to finish\n{}", self.logs()),
            || learner.child.try_wait().unwrap(),
        );
        assert!(status.success(), "the learner: {status}\n{}", self.logs());
        let curve = self.curve();
        let due = (self.steps / LOG_EVERY) as usize;
        assert_eq!(curve.len(), due, "curve rows {curve:?}\n{}", self.logs());
        for (k, (steps, eval)) in curve.iter().enumerate() {
            assert!(*steps >= LOG_EVERY * (k as u64 + 1), "row {k}: {curve:?}");
            assert_eq!(*eval, 2, "row {k} lacks its evaluation: {curve:?}");
        }
        let (stored, given) = (self.stored(), self.given());
        assert_eq!(stored.len(), BUDGET, "stored {stored:?}\n{}", self.logs());
        assert_eq!(
            stored,
            given,
            "the store and the teacher's answers differ\n{}",
            self.logs()
        );
    }
}
