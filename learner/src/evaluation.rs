//! Evaluation requests: each row of the curve asks one actor to run the row's weights on
//! fixed seeds; an evaluation unanswered in time is asked again, of another actor if there
//! is one, until answered (a row waits for its evaluation).

use std::collections::BTreeMap;
use std::time::{Duration, Instant};

use anyhow::Result;
use pbrl_common::bus::put_message;
use pbrl_common::wire::{Body, EvalRequest};
use pbrl_common::Keys;
use zenoh::qos::Priority;
use zenoh::Session;

use crate::curve::{Curve, CurveRow, Pending};

/// Seeds of the evaluation episodes: the same at every row, apart from training seeds
/// (`actor::runner::episode_seed`, below 2^63).
pub const EVAL_SEED_BASE: u64 = 1 << 63;

/// An evaluation unanswered this long is asked again, of another actor if there is one.
pub const EVAL_TIMEOUT: Duration = Duration::from_secs(60);

/// The actors that sent a trajectory recently, for evaluation requests.
#[derive(Default)]
pub struct Actors {
    pub last_seen: BTreeMap<u32, Instant>,
    turn: usize,
}

impl Actors {
    /// The next live actor in turn.
    pub fn next_live(&mut self) -> u32 {
        let live: Vec<u32> = self
            .last_seen
            .iter()
            .filter(|(_, t)| t.elapsed() < EVAL_TIMEOUT)
            .map(|(a, _)| *a)
            .collect();
        self.turn += 1;
        if live.is_empty() {
            // NOTE: nobody sent anything for a while; ask the first actor known.
            return self.last_seen.keys().next().copied().unwrap_or(0);
        }
        live[self.turn % live.len()]
    }
}

/// Ask for the evaluation of `row`'s weights; the row waits for it.
pub async fn ask(
    session: &Session,
    keys: &Keys,
    curve: &mut Curve,
    row: CurveRow,
    request: EvalRequest,
) -> Result<()> {
    send(session, keys, &request).await?;
    curve.pending.push_back(Pending {
        row,
        request,
        sent: Instant::now(),
        tries: 1,
    });
    Ok(())
}

/// Ask again (another actor, if there is one) for evaluations not answered in time;
/// returns how many were asked again.
pub async fn retry(
    session: &Session,
    keys: &Keys,
    curve: &mut Curve,
    actors: &mut Actors,
) -> Result<u64> {
    let mut asked = 0;
    for p in curve.pending.iter_mut() {
        if p.row.eval_episodes > 0 || p.sent.elapsed() < EVAL_TIMEOUT {
            continue;
        }
        p.request.actor = actors.next_live();
        p.tries += 1;
        p.sent = Instant::now();
        asked += 1;
        tracing::warn!(
            env_steps = p.row.env_steps,
            actor = p.request.actor,
            tries = p.tries,
            "an evaluation went unanswered; asking again"
        );
        send(session, keys, &p.request).await?;
    }
    Ok(asked)
}

async fn send(session: &Session, keys: &Keys, request: &EvalRequest) -> Result<()> {
    put_message(
        session,
        keys,
        keys.eval_request(request.actor),
        &Body::EvalRequest(Box::new(request.clone())),
        Priority::Data,
    )
    .await
}
