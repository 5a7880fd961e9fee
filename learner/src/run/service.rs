//! The learner service: Algorithm 1 of the paper (PEBBLE's, and PrefPPO's with PPO) over
//! Zenoh, as one loop over the events that come to the learner. Each event is a method of
//! [`Learner`]; the bus is [`LearnerBus`].

use std::future::Future;
use std::time::Duration;

use anyhow::Result;
use pbrl_common::Keys;
use zenoh::Session;

pub use crate::pref::reward::RewardSource;
use crate::run::bus::LearnerBus;
pub use crate::run::config::{Algo, LearnerConfig};
pub use crate::run::evaluation::EVAL_SEED_BASE;
use crate::run::learner::Learner;
pub use crate::run::learner::Summary;

/// Train until `total_steps` env steps or `shutdown`; then write a checkpoint and tell the
/// actors to stop. With a run folder that holds a run, it continues that run.
pub async fn run(
    cfg: LearnerConfig,
    session: Session,
    shutdown: impl Future<Output = ()>,
) -> Result<Summary> {
    cfg.validate()?;
    let keys = Keys::new(&cfg.run)?;
    let mut l = Learner::open(cfg)?;
    let mut bus = LearnerBus::open(&session, keys, l.asks_teachers()).await?;
    l.start(&bus).await?;
    let mut tick = tokio::time::interval(Duration::from_secs(1));
    tokio::pin!(shutdown);
    let stopped = loop {
        if l.done() {
            break false;
        }
        tokio::select! {
            _ = &mut shutdown => break true,
            // A trajectory acted by the newest policy.
            m = bus.trajectories.next() => {
                if let Some(m) = l.take(m?) {
                    l.train(m)?;                    // store its transitions; gradient steps
                    l.publish_weights(&bus).await?; // new weights, when due
                    l.feedback(&mut bus).await?;    // every K env steps: choose queries
                    l.curve_row(&bus).await?;       // a row of the curve, when due
                    l.checkpoint_if_due()?;         // at a publication, when due
                }
            }
            // Queries chosen: asked; or r_hat trained on D: it is the reward from now on.
            d = l.feedback_job() => l.feedback_done(d?, &bus).await?,
            // A teacher's answers: stored in D (committed), then acknowledged.
            a = bus.answers.next() => l.answered(a?, &mut bus).await?,
            r = bus.eval_results.next() => l.evaluated(r?)?,
            // What went unanswered is asked again; teachers hear where the learner stands.
            _ = tick.tick() => l.tick(&bus).await?,
        }
    };
    l.finish(&mut bus, stopped, shutdown).await
}

/// Keep the process's resident memory at what it holds (glibc; elsewhere nothing): call it
/// first in `main`, before any thread starts. Two settings of glibc's allocator, both from
/// the soak (`deploy/soak.sh`, results/deploy/README.md):
/// - A fixed mmap threshold. A checkpoint encodes its state (about 18 MB on the feeding
///   world with the soak's buffers) and each replay segment (13-40 MB) into one buffer each.
///   glibc serves a block that large from mmap and returns it when freed, but the first
///   free raises the threshold to that block's size, so later checkpoints' buffers come from
///   the heap and leave it at a new high-water mark. Fixed at 4 MiB, those buffers stay in
///   mmap; the labels, trajectories and minibatches, all far smaller, stay in the heap.
/// - At most two arenas. glibc gives threads that allocate at once arenas of their own (up
///   to 8 a core), each a heap that grows on its own and hardly shrinks; the learner's
///   updates, its feedback jobs (a thread each), zenoh's and tokio's threads all allocate.
///
/// glibc's own variables, `MALLOC_MMAP_THRESHOLD_` and `MALLOC_ARENA_MAX`, where set, rule.
pub fn steady_allocator() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        const MMAP_THRESHOLD: libc::c_int = 4 << 20;
        const ARENAS: libc::c_int = 2;
        // SAFETY: mallopt only sets parameters of glibc's allocator; they change where later
        // blocks come from, never a block already handed out.
        unsafe {
            if std::env::var_os("MALLOC_MMAP_THRESHOLD_").is_none() {
                libc::mallopt(libc::M_MMAP_THRESHOLD, MMAP_THRESHOLD);
            }
            if std::env::var_os("MALLOC_ARENA_MAX").is_none() {
                libc::mallopt(libc::M_ARENA_MAX, ARENAS);
            }
        }
    }
}
