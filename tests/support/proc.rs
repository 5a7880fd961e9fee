//! Child processes as the tests start them: one builder ([`Launch`], [`pbrl`] for the
//! binary under test) that takes the arguments, a folder and a log name, and one [`Proc`]
//! that is killed (and reaped) when dropped, so a failed test leaves nothing running.

use std::ffi::{OsStr, OsString};
use std::io::Read;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Output, Stdio};

use super::poll::poll;

/// What a service process logs unless a test asks otherwise: pbrl's own lines at info,
/// zenoh's warnings.
pub const LOG: &str = "warn,pbrl=info,pbrl_learner=info,pbrl_teacher=info,pbrl_actor=info";

/// How to start a process: `pbrl(args).dir(dir).log("learner").spawn()`.
pub struct Launch {
    program: PathBuf,
    args: Vec<OsString>,
    dir: Option<PathBuf>,
    log: Option<PathBuf>,
    append: bool,
    stdout: Option<PathBuf>,
    stdout_to_log: bool,
    piped: bool,
    rust_log: Option<String>,
    env: Vec<(String, String)>,
    host: Option<String>,
    group: bool,
}

/// The `pbrl` binary under test (for a shell line; else [`pbrl`]).
pub const PBRL: &str = env!("CARGO_BIN_EXE_pbrl");

/// The `pbrl` binary under test with `args` (`PBRL_TOKEN` from the test's environment is
/// not passed on: a test gives its token by flag).
pub fn pbrl<S: AsRef<OsStr>>(args: impl IntoIterator<Item = S>) -> Launch {
    Launch::new(PBRL, args)
}

impl Launch {
    /// `program` with `args`; its output goes nowhere until told.
    pub fn new<S: AsRef<OsStr>>(
        program: impl Into<PathBuf>,
        args: impl IntoIterator<Item = S>,
    ) -> Self {
        Self {
            program: program.into(),
            args: args
                .into_iter()
                .map(|a| a.as_ref().to_os_string())
                .collect(),
            dir: None,
            log: None,
            append: false,
            stdout: None,
            stdout_to_log: false,
            piped: false,
            rust_log: None,
            env: Vec::new(),
            host: None,
            group: false,
        }
    }

    /// More arguments after those given.
    pub fn args<S: AsRef<OsStr>>(mut self, more: impl IntoIterator<Item = S>) -> Self {
        self.args
            .extend(more.into_iter().map(|a| a.as_ref().to_os_string()));
        self
    }

    /// Run in `dir`; a log named with [`Launch::log`] goes there too.
    pub fn dir(mut self, dir: &Path) -> Self {
        self.dir = Some(dir.to_path_buf());
        self
    }

    /// Its stderr to a fresh `DIR/NAME.log` (the folder of [`Launch::dir`]).
    pub fn log(mut self, name: &str) -> Self {
        let dir = self.dir.as_ref().expect("Launch::log after Launch::dir");
        self.log = Some(dir.join(format!("{name}.log")));
        self
    }

    /// Its stderr to a fresh file `path`.
    pub fn log_file(mut self, path: &Path) -> Self {
        self.log = Some(path.to_path_buf());
        self
    }

    /// Its stderr appended to the file `path` (a process restarted on the same log).
    pub fn append_log(mut self, path: &Path) -> Self {
        self.log = Some(path.to_path_buf());
        self.append = true;
        self
    }

    /// Its stdout to the file `path`.
    pub fn stdout(mut self, path: &Path) -> Self {
        self.stdout = Some(path.to_path_buf());
        self
    }

    /// Its stdout in its log too.
    pub fn stdout_to_log(mut self) -> Self {
        self.stdout_to_log = true;
        self
    }

    /// Its stdout kept for [`Proc::finish`].
    pub fn piped(mut self) -> Self {
        self.piped = true;
        self
    }

    /// `RUST_LOG` (else the test's own environment's).
    pub fn rust_log(mut self, filter: &str) -> Self {
        self.rust_log = Some(filter.to_string());
        self
    }

    pub fn env(mut self, key: &str, value: &str) -> Self {
        self.env.push((key.to_string(), value.to_string()));
        self
    }

    /// In the network namespace `host` (`None`: this machine), through `ip netns exec`.
    pub fn host(mut self, host: Option<String>) -> Self {
        self.host = host;
        self
    }

    /// In a process group of its own, killed whole (a driver and the browser it starts).
    pub fn group(mut self) -> Self {
        self.group = true;
        self
    }

    fn command(&self) -> Command {
        let mut cmd = match &self.host {
            Some(h) => {
                let mut c = Command::new("ip");
                c.args(["netns", "exec", h]).arg(&self.program);
                c
            }
            None => Command::new(&self.program),
        };
        cmd.args(&self.args);
        if let Some(d) = &self.dir {
            cmd.current_dir(d);
        }
        if let Some(f) = &self.rust_log {
            cmd.env("RUST_LOG", f);
        }
        for (k, v) in &self.env {
            cmd.env(k, v);
        }
        if self.program == Path::new(PBRL) {
            cmd.env_remove("PBRL_TOKEN");
        }
        cmd
    }

    /// Started; its log and stdout as told, else nowhere.
    pub fn spawn(self) -> Proc {
        let mut cmd = self.command();
        let log = self
            .log
            .clone()
            .unwrap_or_else(|| PathBuf::from("/dev/null"));
        let file = if self.append {
            std::fs::File::options()
                .create(true)
                .append(true)
                .open(&log)
        } else {
            std::fs::File::create(&log)
        }
        .unwrap_or_else(|e| panic!("the log {}: {e}", log.display()));
        let out = match (&self.stdout, self.piped) {
            (Some(p), _) => Stdio::from(std::fs::File::create(p).unwrap()),
            (None, true) => Stdio::piped(),
            (None, false) if self.stdout_to_log => Stdio::from(file.try_clone().unwrap()),
            (None, false) => Stdio::null(),
        };
        cmd.stdout(out).stderr(file);
        if self.group {
            use std::os::unix::process::CommandExt;
            cmd.process_group(0);
        }
        let child = cmd
            .spawn()
            .unwrap_or_else(|e| panic!("{} runs: {e}", self.program.display()));
        Proc {
            child,
            log,
            group: self.group,
        }
    }

    /// Run to its end; its stdout and stderr.
    pub fn output(self) -> Output {
        self.command()
            .output()
            .unwrap_or_else(|e| panic!("{} runs: {e}", self.program.display()))
    }
}

/// A child process killed (and reaped) when dropped, with the file its stderr goes to.
/// With `group`, its whole process group goes.
pub struct Proc {
    pub child: Child,
    pub log: PathBuf,
    pub group: bool,
}

impl Proc {
    /// Its log so far.
    pub fn log(&self) -> String {
        std::fs::read_to_string(&self.log).unwrap_or_default()
    }

    /// The end of its log, for failure messages.
    pub fn tail(&self) -> String {
        tail(&self.log)
    }

    /// Send `sig` (`-STOP`, `-KILL`, ...).
    pub fn signal(&self, sig: &str) {
        let ok = Command::new("kill")
            .args([sig, &self.child.id().to_string()])
            .status()
            .unwrap()
            .success();
        assert!(ok, "kill {sig}");
    }

    /// Its exit, waited for at most `secs` (`what` names it in the failure).
    pub fn exit(&mut self, secs: u64, what: &str) -> ExitStatus {
        let child = &mut self.child;
        poll(
            secs,
            || format!("{what} to exit"),
            || child.try_wait().unwrap(),
        )
    }

    /// Its exit, waited for.
    pub fn wait(&mut self) -> ExitStatus {
        self.child.wait().unwrap()
    }

    /// Whether it has exited (reaped if so).
    pub fn exited(&mut self) -> bool {
        self.child.try_wait().unwrap().is_some()
    }

    /// Its exit and its stdout (started [`Launch::piped`]), waited for.
    pub fn finish(&mut self) -> (ExitStatus, String) {
        let mut text = String::new();
        if let Some(mut out) = self.child.stdout.take() {
            out.read_to_string(&mut text).unwrap();
        }
        (self.child.wait().unwrap(), text)
    }

    /// SIGKILL, and reaped.
    pub fn kill(&mut self) {
        if self.child.try_wait().ok().flatten().is_some() {
            return;
        }
        if self.group {
            let _ = Command::new("kill")
                .args(["-KILL", "--", &format!("-{}", self.child.id())])
                .status();
        }
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl Drop for Proc {
    fn drop(&mut self) {
        self.kill();
    }
}

/// The end of the file at `path`, for failure messages.
pub fn tail(path: &Path) -> String {
    let text = std::fs::read_to_string(path).unwrap_or_default();
    let start = text.len().saturating_sub(4000);
    let start = (start..text.len())
        .find(|i| text.is_char_boundary(*i))
        .unwrap_or(text.len());
    format!("\n--- {} (end) ---\n{}", path.display(), &text[start..])
}
