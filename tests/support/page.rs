//! The labelling page as a person meets it in the browser: the training run that serves
//! it, the page opened under a name, a pair playing, the next one prefetched, an answer
//! pressed, and what a person reads on it (`tests/labelling.rs`).

use std::path::{Path, PathBuf};
use std::sync::Mutex;

use pbrl_common::connect::free_local_port;
use serde_json::json;

use super::poll::poll;
use super::proc::{pbrl, tail, Proc, LOG};
use super::web::{enc, Browser};

/// `pbrl train` on the feeding task as the labelling tests run it, small enough that the
/// first queries come within seconds (1,000 env steps of pretraining) and long enough to
/// outlast the test.
pub fn train_args(out: &Path, run: &str, extra: &[&str]) -> Vec<String> {
    let mut a: Vec<String> = [
        "train",
        "--actors=1",
        "--steps=200000",
        "--unsup-steps=1000",
        "--feedback-interval=1000",
        "--queries-per-session=5",
        "--max-open-queries=10",
        "--query-retry-s=1",
        "--eval-episodes=0",
        "--log-every=5000",
        "--checkpoint-every=0",
        "--quiet",
        "--fresh",
    ]
    .iter()
    .map(|s| s.to_string())
    .collect();
    a.push(format!("--run={run}"));
    a.push(format!("--out={}", out.display()));
    a.extend(extra.iter().map(|s| s.to_string()));
    a
}

/// `pbrl train --teacher human` on a free loopback port, with `extra` flags, in `dir`: its
/// page's address, its run folder and the process.
pub fn human_train(dir: &Path, run: &str, extra: &[&str]) -> (String, PathBuf, Proc) {
    let addr = format!("127.0.0.1:{}", free_local_port().unwrap());
    let out = dir.join("run");
    let http = format!("--http={addr}");
    let mut flags = vec!["--teacher=human", http.as_str()];
    flags.extend_from_slice(extra);
    let train = pbrl(train_args(&out, run, &flags))
        .dir(dir)
        .log("train")
        .rust_log(LOG)
        .spawn();
    (addr, out, train)
}

impl Browser {
    /// Open the labelling page at `addr` as `labeller`, keeping every resource timing (see
    /// [`Browser::prefetched`]).
    pub fn label(&self, addr: &str, labeller: &str) {
        self.go(&format!("http://{addr}/?labeller={}", enc(labeller)));
        self.exec(
            "performance.setResourceTimingBufferSize(100000); return null;",
            json!([]),
        );
    }

    /// The page's "teacher unreachable" banner shows.
    pub fn unreachable(&self) -> bool {
        self.exec("return !document.getElementById('conn').hidden;", json!([]))
            .as_bool()
            .unwrap_or(false)
    }

    /// `what` with the page's state and the end of `log` (the teacher's), for failures.
    pub fn page(&self, what: &str, log: &Path) -> String {
        format!(
            "{what} (page: state {:?}, query {:?}, busy {:?}, unreachable {}, message {}){}",
            self.body("state"),
            self.body("query"),
            self.body("busy"),
            self.unreachable(),
            self.exec(
                "return document.getElementById('msg').textContent;",
                json!([])
            ),
            tail(log)
        )
    }

    /// Wait until the page reaches its teacher and plays a pair with no answer in flight;
    /// the pair's query.
    pub fn playing(&self, secs: u64, what: &str, log: &Path) -> String {
        poll(
            secs,
            || self.page(what, log),
            || {
                let q = self.body("query");
                (self.body("state") == "playing"
                    && self.body("busy").is_empty()
                    && !q.is_empty()
                    && !self.unreachable())
                .then_some(q)
            },
        )
    }

    /// Wait until the pair after `q` is fetched while `q` plays (answering then shows it
    /// at once).
    pub fn prefetched(&self, q: &str, log: &Path) {
        poll(
            60,
            || self.page(&format!("the pair after query {q} prefetched"), log),
            || {
                self.exec(
                    "return performance.getEntriesByType('resource').some((e) => \
                     e.name.includes('/api/v1/next?') && \
                     e.name.endsWith('exclude=' + arguments[0]) && e.responseStatus === 200);",
                    json!([q]),
                )
                .as_bool()
                .unwrap_or(false)
                .then_some(())
            },
        )
    }

    /// Answer the pair on screen with `key` (`name` in messages) and wait until its POST
    /// is through and the next pair shows; the answered query.
    pub fn press(&self, key: &str, name: &str, log: &Path) -> u64 {
        let q = self.body("query");
        self.prefetched(&q, log);
        self.key(key);
        poll(
            60,
            || {
                self.page(
                    &format!("{name} on query {q} sent and the next pair shown"),
                    log,
                )
            },
            || {
                let now = self.body("query");
                (self.body("busy").is_empty() && !now.is_empty() && now != q).then_some(now)
            },
        );
        q.parse()
            .unwrap_or_else(|e| panic!("the page's query {q:?}: {e}"))
    }
}

/// WebDriver's codes of the keys the page answers to.
pub const ARROW_LEFT: &str = "\u{E012}";
pub const ARROW_RIGHT: &str = "\u{E014}";
pub const BACKSPACE: &str = "\u{E003}";
pub const ENTER: &str = "\u{E007}";

static ONE_AT_A_TIME: Mutex<()> = Mutex::new(());

/// The page's tests run one at a time: two feeding runs beside a browser on 2 cores starve
/// one another.
pub fn one_at_a_time() -> std::sync::MutexGuard<'static, ()> {
    // NOTE: a failed test poisons the lock; the next one may still run.
    ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner())
}

/// What a person reads on the page for the pair on screen: the strips' numbers of each
/// attempt and the judged part's length, from the DOM's text (nothing the API sends but the
/// page does not show).
pub const READ_PAGE: &str = "
    const side = (id) => {
      const el = document.getElementById(id);
      const v = (q, k) => Number(el.querySelector(`.strip[data-q=${q}] [data-v=${k}]`).textContent);
      return {
        closest: v('distance', 'closest'), distance: v('distance', 'mean'),
        speed: v('speed', 'mean'), force: v('force', 'mean'),
        eaten: v('food', 'eaten'), spilled: v('food', 'spilled'), hits: v('food', 'hits'),
        seconds: Number(el.querySelector('.strips [data-v=\"judged-s\"]').textContent),
      };
    };
    return { query: document.body.dataset.query, left: side('att-left'), right: side('att-right') };";

/// Elements of a row that leave the window or overlap each other, and text cut off.
pub const LAYOUT_PROBLEMS: &str = "
    const out = [];
    const W = window.innerWidth, H = window.innerHeight;
    const groups = ['header > *:not([hidden])', '.statusrow > .chip:not([hidden])', '.controls > *',
                    '.answers > button', 'footer > span', '#att-left .strip .sl > span',
                    '#att-right .strip .sl > span', 'main > section'];
    for (const sel of groups) {
      const els = [...document.querySelectorAll(sel)].filter((e) => e.getClientRects().length);
      const rs = els.map((e) => e.getBoundingClientRect());
      rs.forEach((r, i) => {
        if (r.left < -0.5 || r.right > W + 0.5 || r.bottom > H + 0.5) out.push(sel + ' #' + i + ' leaves the window');
        if (els[i].scrollWidth > els[i].clientWidth + 1 && getComputedStyle(els[i]).overflow !== 'visible') out.push(sel + ' #' + i + ' is cut off');
        for (let j = 0; j < i; j++) {
          const o = rs[j];
          const w = Math.min(r.right, o.right) - Math.max(r.left, o.left);
          const h = Math.min(r.bottom, o.bottom) - Math.max(r.top, o.top);
          if (w > 1 && h > 1) out.push(sel + ' #' + j + ' and #' + i + ' overlap');
        }
      });
    }
    return out;";
