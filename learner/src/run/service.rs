//! The learner service: Algorithm 1 of the paper (PEBBLE's, and PrefPPO's with PPO) over
//! Zenoh, as one loop over the events that come to the learner. Each event is a method of
//! [`Learner`]; the bus is [`LearnerBus`].

use std::future::Future;
use std::time::Duration;

use anyhow::Result;
use pbrl_common::wire::TrajectoryMsg;
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
        // Keeping time with the teacher: no trajectory is trained on until the answers are
        // in; those that came meanwhile are trained on first once they are.
        let holding = l.holding();
        if !holding {
            if let Some(m) = l.unstash() {
                step(&mut l, m, true, &mut bus).await?;
                continue;
            }
        }
        tokio::select! {
            _ = &mut shutdown => break true,
            // A trajectory acted by the newest policy (taken once: one sent again is not).
            m = bus.trajectories.next() => {
                if let Some(m) = l.take(m?) {
                    if holding {
                        l.stash(m);
                    } else {
                        step(&mut l, m, false, &mut bus).await?;
                    }
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

/// One trajectory through Algorithm 1's steps (`kept_for_queries`: the annotation buffer
/// has it already, from while the learner stood still).
async fn step(
    l: &mut Learner,
    m: TrajectoryMsg,
    kept_for_queries: bool,
    bus: &mut LearnerBus,
) -> Result<()> {
    l.train(m, kept_for_queries)?; // store its transitions; gradient steps
    l.publish_weights(bus).await?; // new weights, when due
    l.feedback(bus).await?; // every K env steps: choose queries
    l.curve_row(bus).await?; // a row of the curve, when due
    l.checkpoint_if_due() // at a publication, when due
}
