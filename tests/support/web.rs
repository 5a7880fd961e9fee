//! A browser and HTTP/1.1 for the tests that meet a page as a person does: one request
//! per connection over a `TcpStream`, the human teacher's API over it ([`Api`]), and
//! headless Chromium driven over WebDriver (chromedriver).

use std::io::{Read, Write};
use std::net::TcpStream;
use std::path::{Path, PathBuf};
use std::time::Duration;

use pbrl_common::connect::free_local_port;
use serde_json::{json, Value};

use super::poll::poll;
use super::proc::{tail, Launch, Proc};

pub const CHROMIUM: &str = "/usr/bin/chromium";
pub const CHROMEDRIVER: &str = "/usr/bin/chromedriver";

// ---------- HTTP/1.1 over a TcpStream ----------

pub struct Reply {
    pub status: u16,
    pub body: Vec<u8>,
}

impl Reply {
    pub fn text(&self) -> String {
        String::from_utf8_lossy(&self.body).into_owned()
    }

    pub fn json(&self) -> Value {
        serde_json::from_slice(&self.body).unwrap_or_else(|e| {
            panic!(
                "HTTP {}: the body is not JSON ({e}): {}",
                self.status,
                self.text()
            )
        })
    }
}

fn bad_reply(what: &str) -> std::io::Error {
    std::io::Error::new(std::io::ErrorKind::InvalidData, what.to_string())
}

/// One request on its own connection (`Connection: close`); the reply is read up to its
/// end (Content-Length, the last chunk, or EOF).
pub fn http(
    addr: &str,
    method: &str,
    path: &str,
    headers: &[(&str, &str)],
    body: Option<&[u8]>,
) -> std::io::Result<Reply> {
    let mut s = TcpStream::connect(addr)?;
    s.set_read_timeout(Some(Duration::from_secs(120)))?;
    s.set_write_timeout(Some(Duration::from_secs(30)))?;
    let mut head =
        format!("{method} {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\nAccept: */*\r\n");
    for (k, v) in headers {
        head.push_str(&format!("{k}: {v}\r\n"));
    }
    if body.is_some() || method == "POST" {
        head.push_str(&format!(
            "Content-Length: {}\r\n",
            body.map_or(0, <[u8]>::len)
        ));
    }
    head.push_str("\r\n");
    s.write_all(head.as_bytes())?;
    // NOTE: a server that refuses a large body may answer and close before reading it: a
    // failed write still leaves its reply to read.
    let wrote = body.map_or(Ok(()), |b| s.write_all(b));
    // NOTE: chromedriver keeps the connection open despite `Connection: close`: reading to
    // EOF would wait for the read timeout at every command.
    let mut raw = Vec::new();
    let mut buf = vec![0u8; 64 << 10];
    loop {
        if let Some(reply) = parse_reply(&raw, false)? {
            return Ok(reply);
        }
        match s.read(&mut buf) {
            Ok(0) => break,
            Ok(n) => raw.extend_from_slice(&buf[..n]),
            Err(e) if raw.is_empty() => {
                wrote?;
                return Err(e);
            }
            Err(_) => break,
        }
    }
    parse_reply(&raw, true)?.ok_or_else(|| bad_reply("the reply ends before its end"))
}

/// The reply in `raw`, once it is all there (`eof`: no more will come).
pub fn parse_reply(raw: &[u8], eof: bool) -> std::io::Result<Option<Reply>> {
    let Some(end) = raw.windows(4).position(|w| w == b"\r\n\r\n") else {
        return if eof {
            Err(bad_reply("no end of the headers"))
        } else {
            Ok(None)
        };
    };
    let head = String::from_utf8_lossy(&raw[..end]);
    let mut lines = head.split("\r\n");
    let status: u16 = lines
        .next()
        .and_then(|l| l.split(' ').nth(1))
        .and_then(|s| s.parse().ok())
        .ok_or_else(|| bad_reply("no status line"))?;
    let (mut length, mut chunked) = (None, false);
    for line in lines {
        if let Some((k, v)) = line.split_once(':') {
            match k.trim().to_ascii_lowercase().as_str() {
                "content-length" => length = v.trim().parse::<usize>().ok(),
                "transfer-encoding" => chunked = v.to_ascii_lowercase().contains("chunked"),
                _ => {}
            }
        }
    }
    let rest = &raw[end + 4..];
    let body = if status == 204 || status == 304 || status < 200 {
        Some(Vec::new())
    } else if chunked {
        dechunk(rest)
    } else if let Some(n) = length {
        (rest.len() >= n).then(|| rest[..n].to_vec())
    } else if eof {
        Some(rest.to_vec())
    } else {
        None
    };
    match body {
        Some(body) => Ok(Some(Reply { status, body })),
        None if eof => Err(bad_reply("the body is cut short")),
        None => Ok(None),
    }
}

/// A chunked body, once its last chunk is in.
fn dechunk(mut rest: &[u8]) -> Option<Vec<u8>> {
    let mut out = Vec::new();
    loop {
        let eol = rest.windows(2).position(|w| w == b"\r\n")?;
        let line = String::from_utf8_lossy(&rest[..eol]).into_owned();
        let hex = line.split(';').next().unwrap_or("").trim();
        let size = usize::from_str_radix(hex, 16).ok()?;
        rest = &rest[eol + 2..];
        if size == 0 {
            return Some(out);
        }
        if rest.len() < size + 2 {
            return None;
        }
        out.extend_from_slice(&rest[..size]);
        rest = &rest[size + 2..];
    }
}

// ---------- the human teacher's API ----------

/// Percent-encoding of a query-string value.
pub fn enc(s: &str) -> String {
    s.bytes()
        .map(|b| match b {
            b'A'..=b'Z' | b'a'..=b'z' | b'0'..=b'9' | b'-' | b'_' | b'.' | b'~' => {
                (b as char).to_string()
            }
            _ => format!("%{b:02X}"),
        })
        .collect()
}

/// The human teacher's API at `addr` (with `token`, every call carries it); `log` is the
/// serving process's, for failure messages.
pub struct Api {
    pub addr: String,
    pub token: Option<String>,
    pub log: PathBuf,
}

impl Api {
    pub fn try_call(
        &self,
        method: &str,
        path: &str,
        body: Option<&Value>,
    ) -> std::io::Result<Reply> {
        let bearer = self.token.as_ref().map(|t| format!("Bearer {t}"));
        let mut headers = vec![("Content-Type", "application/json")];
        if let Some(b) = &bearer {
            headers.push(("Authorization", b.as_str()));
        }
        let bytes = body.map(|b| serde_json::to_vec(b).unwrap());
        http(&self.addr, method, path, &headers, bytes.as_deref())
    }

    pub fn call(&self, method: &str, path: &str, body: Option<&Value>) -> Reply {
        self.try_call(method, path, body).unwrap_or_else(|e| {
            panic!(
                "{method} http://{}{path}: {e}{}",
                self.addr,
                tail(&self.log)
            )
        })
    }

    pub fn answer(&self, labeller: &str, query: u64, choice: &str) -> Reply {
        self.call(
            "POST",
            "/api/v1/answer",
            Some(&json!({
                "labeller": labeller,
                "query": query,
                "choice": choice,
                "took_ms": 1500,
                "replays": [1, 0],
            })),
        )
    }

    /// The learner's env steps as the teacher last heard them (waits for a fresh status).
    pub fn env_steps(&self, secs: u64) -> u64 {
        poll(
            secs,
            || {
                format!(
                    "the learner's env steps in /api/v1/status{}",
                    tail(&self.log)
                )
            },
            || {
                let r = self.try_call("GET", "/api/v1/status", None).ok()?;
                (r.status == 200).then(|| r.json()["env_steps"].as_u64())?
            },
        )
    }

    /// A pair for `labeller` (not `exclude`), waiting for the server and the learner's
    /// first queries.
    pub fn pair(&self, labeller: &str, exclude: Option<u64>, secs: u64) -> Value {
        let path = format!(
            "/api/v1/next?labeller={}{}",
            enc(labeller),
            exclude.map_or(String::new(), |q| format!("&exclude={q}"))
        );
        poll(
            secs,
            || format!("a pair for {labeller}{}", tail(&self.log)),
            || {
                let r = self.try_call("GET", &path, None).ok()?;
                assert!(
                    r.status == 200 || r.status == 204,
                    "GET {path}: HTTP {}: {}",
                    r.status,
                    r.text()
                );
                (r.status == 200).then(|| r.json())
            },
        )
    }
}

// ---------- a browser over WebDriver ----------

/// A headless Chromium session through chromedriver; closed (and chromedriver killed with
/// its process group) when dropped.
pub struct Browser {
    addr: String,
    session: String,
    driver: Proc,
}

/// Whether the browser can run: panics when it is not installed, unless
/// `PBRL_SKIP_BROWSER=1` (then `part` is skipped, and says so). A test that is all browser
/// is marked `#[cfg_attr(skip_browser, ignore)]` instead (`build.rs`), so that it counts as
/// skipped, not passed.
pub fn browser_wanted(part: &str) -> bool {
    if Path::new(CHROMIUM).exists() && Path::new(CHROMEDRIVER).exists() {
        return true;
    }
    if std::env::var("PBRL_SKIP_BROWSER").as_deref() == Ok("1") {
        eprintln!("PBRL_SKIP_BROWSER=1: no {CHROMIUM} or {CHROMEDRIVER}; {part} is skipped");
        return false;
    }
    panic!(
        "the browser test needs {CHROMIUM} and {CHROMEDRIVER}: run deploy/setup.sh \
         (Debian: apt-get install chromium chromium-driver), or set PBRL_SKIP_BROWSER=1 to skip it"
    );
}

impl Browser {
    pub fn open(dir: &Path) -> Self {
        let port = free_local_port().unwrap();
        let log = dir.join("chromedriver.log");
        let driver = Launch::new(CHROMEDRIVER, [format!("--port={port}")])
            .log_file(&log)
            .stdout_to_log()
            .group()
            .spawn();
        let addr = format!("127.0.0.1:{port}");
        poll(
            30,
            || format!("chromedriver to be ready{}", driver.tail()),
            || {
                let r = http(&addr, "GET", "/status", &[], None).ok()?;
                (r.status == 200 && r.json()["value"]["ready"] == json!(true)).then_some(())
            },
        );
        let caps = json!({"capabilities": {"alwaysMatch": {
            "browserName": "chrome",
            "goog:chromeOptions": {
                "binary": CHROMIUM,
                "args": ["--headless=new", "--no-sandbox", "--disable-gpu",
                         "--disable-dev-shm-usage", "--window-size=1400,900"],
            },
        }}});
        let r = http(
            &addr,
            "POST",
            "/session",
            &[("Content-Type", "application/json")],
            Some(&serde_json::to_vec(&caps).unwrap()),
        )
        .unwrap_or_else(|e| panic!("POST /session: {e}{}", driver.tail()));
        let v = r.json();
        let session = v["value"]["sessionId"]
            .as_str()
            .unwrap_or_else(|| {
                panic!(
                    "chromedriver opened no session: HTTP {}: {v}{}",
                    r.status,
                    driver.tail()
                )
            })
            .to_string();
        Self {
            addr,
            session,
            driver,
        }
    }

    pub fn cmd(&self, method: &str, path: &str, body: Option<Value>) -> Value {
        let path = format!("/session/{}{path}", self.session);
        let bytes = body.map(|b| serde_json::to_vec(&b).unwrap());
        let r = http(
            &self.addr,
            method,
            &path,
            &[("Content-Type", "application/json")],
            bytes.as_deref(),
        )
        .unwrap_or_else(|e| panic!("WebDriver {method} {path}: {e}{}", self.driver.tail()));
        let v = r.json();
        assert_eq!(r.status, 200, "WebDriver {method} {path}: {v}");
        v["value"].clone()
    }

    pub fn go(&self, url: &str) {
        self.cmd("POST", "/url", Some(json!({ "url": url })));
    }

    pub fn exec(&self, script: &str, args: Value) -> Value {
        self.cmd(
            "POST",
            "/execute/sync",
            Some(json!({ "script": script, "args": args })),
        )
    }

    pub fn body(&self, field: &str) -> String {
        self.exec(
            "return document.body.dataset[arguments[0]] || '';",
            json!([field]),
        )
        .as_str()
        .unwrap_or_default()
        .to_string()
    }

    /// Press and release one key (a character, or WebDriver's code such as `\u{E014}`).
    pub fn key(&self, value: &str) {
        self.cmd(
            "POST",
            "/actions",
            Some(json!({"actions": [{"type": "key", "id": "kb", "actions": [
                {"type": "keyDown", "value": value},
                {"type": "keyUp", "value": value},
            ]}]})),
        );
    }

    pub fn screenshot(&self) -> Vec<u8> {
        base64(self.cmd("GET", "/screenshot", None).as_str().unwrap())
    }
}

impl Drop for Browser {
    fn drop(&mut self) {
        // The browser quits with its session; `driver` (dropped next) kills the rest.
        let _ = http(
            &self.addr,
            "DELETE",
            &format!("/session/{}", self.session),
            &[],
            None,
        );
    }
}

/// Standard base64 (RFC 4648), padding and line breaks ignored.
pub fn base64(text: &str) -> Vec<u8> {
    let mut out = Vec::with_capacity(text.len() / 4 * 3);
    let (mut acc, mut bits) = (0u32, 0u32);
    for c in text.bytes() {
        let v = match c {
            b'A'..=b'Z' => c - b'A',
            b'a'..=b'z' => c - b'a' + 26,
            b'0'..=b'9' => c - b'0' + 52,
            b'+' => 62,
            b'/' => 63,
            b'=' | b'\r' | b'\n' => continue,
            _ => panic!("{:?} is not base64", c as char),
        };
        acc = (acc << 6) | u32::from(v);
        bits += 6;
        if bits >= 8 {
            bits -= 8;
            out.push((acc >> bits) as u8);
            acc &= (1 << bits) - 1;
        }
    }
    out
}
