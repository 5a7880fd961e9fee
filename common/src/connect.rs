//! One set of Zenoh connection flags, flattened into every command that talks (as zenoh's
//! own examples do with `CommonArgs`), and the session configs built from them.
//!
//! Multicast scouting is off unless `--multicast` is given, and nothing listens unless
//! asked: pbrl never opens a port on an outside interface by itself.

use std::path::PathBuf;

use anyhow::{bail, Context, Result};

/// The role a session plays in Zenoh's routing.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum Mode {
    Peer,
    Client,
    Router,
}

impl Mode {
    fn as_str(self) -> &'static str {
        match self {
            Mode::Peer => "peer",
            Mode::Client => "client",
            Mode::Router => "router",
        }
    }
}

/// How a process joins the Zenoh network.
#[derive(clap::Args, Clone, Debug, PartialEq, Eq)]
pub struct ConnectArgs {
    /// Endpoint to connect to, e.g. tcp/127.0.0.1:7447 (repeatable).
    #[arg(long = "connect", value_name = "ENDPOINT")]
    pub connect: Vec<String>,
    /// Endpoint to listen on, e.g. tcp/127.0.0.1:7447 (repeatable; none by default).
    #[arg(long = "listen", value_name = "ENDPOINT")]
    pub listen: Vec<String>,
    /// A Zenoh config file (json5) to start from; the flags above and below override it.
    #[arg(long = "config", value_name = "FILE")]
    pub config: Option<PathBuf>,
    /// Zenoh mode (default: client when --connect is given, else peer).
    #[arg(long = "mode", value_enum)]
    pub mode: Option<Mode>,
    /// Turn multicast scouting on (it is off unless asked for, config file or not).
    #[arg(long)]
    pub multicast: bool,
    /// Seconds to keep trying the --connect endpoints before giving up (a process may
    /// start before the router or learner it joins); 0: one try.
    #[arg(long, default_value_t = 60)]
    pub connect_timeout: u64,
    /// Seconds without a word from a peer before its link is declared dead (zenoh's lease,
    /// 10 s by default; pbrl's 60 s lets a peer pause, say for a long update or a SIGSTOP,
    /// without losing its session; a peer that exits closes its links at once anyway).
    #[arg(long, default_value_t = DEFAULT_LEASE_SECS)]
    pub lease: u64,
    /// TLS: the certificate authority that signed every pbrl certificate (PEM; made by
    /// deploy/certs.sh). With --tls-cert and --tls-key, links over tls/ endpoints
    /// authenticate both ways: this process shows its certificate and accepts only peers
    /// whose certificate the CA signed.
    #[arg(long = "tls-ca", value_name = "FILE")]
    pub tls_ca: Option<PathBuf>,
    /// TLS: this process's certificate (PEM; its common name is its role for the router's
    /// access control).
    #[arg(long = "tls-cert", value_name = "FILE")]
    pub tls_cert: Option<PathBuf>,
    /// TLS: the private key of --tls-cert (PEM).
    #[arg(long = "tls-key", value_name = "FILE")]
    pub tls_key: Option<PathBuf>,
}

/// pbrl's default link lease, seconds.
pub const DEFAULT_LEASE_SECS: u64 = 60;

impl Default for ConnectArgs {
    fn default() -> Self {
        Self {
            connect: Vec::new(),
            listen: Vec::new(),
            config: None,
            mode: None,
            multicast: false,
            // NOTE: in code (tests, the in-process router) one try; the flag's default is 60.
            connect_timeout: 0,
            lease: DEFAULT_LEASE_SECS,
            tls_ca: None,
            tls_cert: None,
            tls_key: None,
        }
    }
}

fn json_list(items: &[String]) -> String {
    let quoted: Vec<String> = items.iter().map(|e| format!("{e:?}")).collect();
    format!("[{}]", quoted.join(","))
}

fn zerr(what: String) -> impl FnOnce(zenoh::Error) -> anyhow::Error {
    move |e| anyhow::anyhow!("{what}: {e}")
}

impl ConnectArgs {
    /// Flags for a session that connects to `endpoint`.
    pub fn connecting_to(endpoint: &str) -> Self {
        Self {
            connect: vec![endpoint.to_string()],
            ..Self::default()
        }
    }

    /// Flags for a router listening on `endpoint`.
    pub fn router_on(endpoint: &str) -> Self {
        Self {
            listen: vec![endpoint.to_string()],
            mode: Some(Mode::Router),
            ..Self::default()
        }
    }

    /// The Zenoh config these flags describe.
    pub fn zenoh_config(&self) -> Result<zenoh::Config> {
        for e in self.connect.iter().chain(&self.listen) {
            if !e.contains('/') {
                bail!("endpoint {e:?} is not of the form PROTOCOL/ADDRESS:PORT (e.g. tcp/127.0.0.1:7447)");
            }
        }
        let mut cfg = match &self.config {
            Some(path) => zenoh::Config::from_file(path)
                .map_err(zerr(format!("reading Zenoh config {}", path.display())))?,
            None => zenoh::Config::default(),
        };
        let mode = self.mode.unwrap_or(if self.connect.is_empty() {
            Mode::Peer
        } else {
            Mode::Client
        });
        let set = |cfg: &mut zenoh::Config, key: &str, value: String| {
            cfg.insert_json5(key, &value)
                .map_err(zerr(format!("setting Zenoh config {key} = {value}")))
        };
        set(&mut cfg, "mode", format!("{:?}", mode.as_str()))?;
        set(
            &mut cfg,
            "scouting/multicast/enabled",
            self.multicast.to_string(),
        )?;
        if self.config.is_none() || !self.listen.is_empty() {
            set(&mut cfg, "listen/endpoints", json_list(&self.listen))?;
        }
        if self.config.is_none() || !self.connect.is_empty() {
            set(&mut cfg, "connect/endpoints", json_list(&self.connect))?;
        }
        if self.lease > 0 {
            set(
                &mut cfg,
                "transport/link/tx/lease",
                (self.lease * 1000).to_string(),
            )?;
        }
        self.set_tls(&mut cfg)?;
        if !self.connect.is_empty() && self.connect_timeout > 0 {
            set(
                &mut cfg,
                "connect/timeout_ms",
                (self.connect_timeout * 1000).to_string(),
            )?;
        }
        Ok(cfg)
    }

    /// The TLS flags into `cfg`: all three or none; each file must be there. A tls/
    /// endpoint without them (and without a config file) is refused by name.
    fn set_tls(&self, cfg: &mut zenoh::Config) -> Result<()> {
        let files = [
            ("--tls-ca", &self.tls_ca),
            ("--tls-cert", &self.tls_cert),
            ("--tls-key", &self.tls_key),
        ];
        if files.iter().all(|(_, f)| f.is_none()) {
            let tls = self
                .connect
                .iter()
                .chain(&self.listen)
                .find(|e| e.starts_with("tls/"));
            if let (Some(e), None) = (tls, &self.config) {
                bail!(
                    "endpoint {e} is TLS: give --tls-ca, --tls-cert and --tls-key \
                     (deploy/certs.sh makes them), or a --config that sets transport/link/tls"
                );
            }
            return Ok(());
        }
        let mut paths = Vec::new();
        for (flag, file) in files {
            let Some(path) = file else {
                bail!("{flag} is missing: TLS needs --tls-ca, --tls-cert and --tls-key together");
            };
            if !path.is_file() {
                bail!("{flag} {}: no such file", path.display());
            }
            let path = path
                .canonicalize()
                .with_context(|| format!("{flag} {}", path.display()))?;
            paths.push(format!("{:?}", path.display().to_string()));
        }
        let (ca, cert, key) = (&paths[0], &paths[1], &paths[2]);
        for (k, v) in [
            ("root_ca_certificate", ca),
            ("connect_certificate", cert),
            ("connect_private_key", key),
            ("listen_certificate", cert),
            ("listen_private_key", key),
            ("enable_mtls", &"true".to_string()),
        ] {
            let key = format!("transport/link/tls/{k}");
            cfg.insert_json5(&key, v)
                .map_err(zerr(format!("setting Zenoh config {key} = {v}")))?;
        }
        Ok(())
    }

    /// Open a session with these flags.
    pub async fn open(&self) -> Result<zenoh::Session> {
        let cfg = self.zenoh_config()?;
        zenoh::open(cfg)
            .await
            .map_err(zerr(format!("opening a Zenoh session ({self:?})")))
    }
}

/// A free TCP port on 127.0.0.1 (for an in-process router or a test).
pub fn free_local_port() -> Result<u16> {
    let l =
        std::net::TcpListener::bind("127.0.0.1:0").context("finding a free port on 127.0.0.1")?;
    Ok(l.local_addr().context("reading the bound port")?.port())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn multicast_is_off_and_nothing_listens_unless_asked() {
        let cfg = ConnectArgs::connecting_to("tcp/127.0.0.1:7447")
            .zenoh_config()
            .unwrap();
        assert_eq!(cfg.get_json("scouting/multicast/enabled").unwrap(), "false");
        assert_eq!(cfg.get_json("listen/endpoints").unwrap(), "[]");
        assert_eq!(cfg.get_json("mode").unwrap(), "\"client\"");
        assert_eq!(cfg.get_json("transport/link/tx/lease").unwrap(), "60000");
        let args = ConnectArgs {
            multicast: true,
            ..ConnectArgs::router_on("tcp/127.0.0.1:7447")
        };
        let cfg = args.zenoh_config().unwrap();
        assert_eq!(cfg.get_json("scouting/multicast/enabled").unwrap(), "true");
        assert_eq!(cfg.get_json("mode").unwrap(), "\"router\"");
        assert!(cfg
            .get_json("listen/endpoints")
            .unwrap()
            .contains("127.0.0.1:7447"));
        let e = ConnectArgs::connecting_to("127.0.0.1:7447")
            .zenoh_config()
            .unwrap_err();
        assert!(e.to_string().contains("\"127.0.0.1:7447\""), "{e}");
    }
}
