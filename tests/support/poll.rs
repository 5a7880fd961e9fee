//! Waiting for an event: one poll to a deadline, in a thread ([`poll`]) or a task
//! ([`poll_async`]). Each check comes sooner at first (10 ms) and at most every 200 ms
//! after, so a quick event is seen quickly and a slow one (a store read by a child process)
//! costs little. A deadline bounds the wait; nothing here times anything.

use std::time::{Duration, Instant};

/// The pauses between checks: 10 ms, doubling to 200 ms.
fn pauses() -> impl Iterator<Item = Duration> {
    std::iter::successors(Some(10u64), |ms| Some((ms * 2).min(200))).map(Duration::from_millis)
}

/// `f` until it gives a value, which is returned; after `secs` seconds, a panic saying
/// what was waited for (`what`, built only then: it may read logs).
pub fn poll<T>(secs: u64, what: impl Fn() -> String, mut f: impl FnMut() -> Option<T>) -> T {
    let deadline = Instant::now() + Duration::from_secs(secs);
    for pause in pauses() {
        if let Some(v) = f() {
            return v;
        }
        assert!(Instant::now() < deadline, "waited {secs} s for {}", what());
        // NOTE: polled to a deadline: waiting for an event, not a timing.
        std::thread::sleep(pause);
    }
    unreachable!("the pauses never end")
}

/// [`poll`] in a task: the same checks, the runtime's other tasks run between them.
pub async fn poll_async<T>(
    secs: u64,
    what: impl Fn() -> String,
    mut f: impl FnMut() -> Option<T>,
) -> T {
    let deadline = Instant::now() + Duration::from_secs(secs);
    for pause in pauses() {
        if let Some(v) = f() {
            return v;
        }
        assert!(Instant::now() < deadline, "waited {secs} s for {}", what());
        tokio::time::sleep(pause).await;
    }
    unreachable!("the pauses never end")
}
