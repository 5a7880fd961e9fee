//! Evaluation requests: each row of the curve asks one actor to run the row's weights on
//! fixed seeds; an evaluation unanswered in time is asked again, of another actor if there
//! is one, until answered (a row waits for its evaluation).

use std::collections::BTreeMap;
use std::time::{Duration, Instant};

use anyhow::Result;
use pbrl_common::wire::{EvalRequest, EvalSteps};

use crate::pref::reward_model::RewardModel;
use crate::run::bus::LearnerBus;
use crate::run::curve::correlation;
use crate::run::curve::{Curve, CurveRow, Pending, Tracking};

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
    bus: &LearnerBus,
    curve: &mut Curve,
    row: CurveRow,
    request: EvalRequest,
) -> Result<()> {
    bus.evaluate(&request).await?;
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
pub async fn retry(bus: &LearnerBus, curve: &mut Curve, actors: &mut Actors) -> Result<u64> {
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
        bus.evaluate(&p.request).await?;
    }
    Ok(asked)
}

/// How well `model` tracks the ground truth on an evaluation's episodes: the Pearson
/// correlation of r_hat with r, r_H and r_task per step, and with r per episode sum.
/// Episodes whose lengths do not agree with the model are left out (with a warning); NaN
/// when none is left.
pub fn rhat_tracking(model: &RewardModel, episodes: &[EvalSteps]) -> Result<Tracking> {
    let (mut step_hat, mut step_true, mut sum_hat, mut sum_true) =
        (Vec::new(), Vec::new(), Vec::new(), Vec::new());
    let (mut step_human, mut step_task) = (Vec::new(), Vec::new());
    for e in episodes {
        let n = e.truth.len();
        if e.obs.len() != n * model.obs_dim() || e.actions.len() != n * model.act_dim() {
            tracing::warn!(
                steps = n,
                obs = e.obs.len(),
                actions = e.actions.len(),
                "an evaluation episode's steps do not fit the reward model; left out"
            );
            continue;
        }
        if model.feat_dim() > 0 && e.features.len() != n * model.feat_dim() {
            tracing::warn!(
                steps = n,
                features = e.features.len(),
                "an evaluation episode came without the comfort features the reward model reads; left out"
            );
            continue;
        }
        let r = model.predict(&e.obs, &e.actions, &e.features)?;
        sum_hat.push(r.iter().map(|x| *x as f64).sum());
        sum_true.push(e.truth.iter().map(|x| *x as f64).sum());
        step_hat.extend(r.iter().map(|x| *x as f64));
        step_true.extend(e.truth.iter().map(|x| *x as f64));
        step_human.extend(e.human.iter().map(|x| *x as f64));
        step_task.extend(e.task.iter().map(|x| *x as f64));
    }
    // NOTE: the parts are absent from the steps of an older actor: NaN then.
    let part = |xs: &[f64]| {
        if xs.len() == step_hat.len() {
            correlation(&step_hat, xs)
        } else {
            f64::NAN
        }
    };
    Ok(Tracking {
        step: correlation(&step_hat, &step_true),
        step_human: part(&step_human),
        step_task: part(&step_task),
        sum: correlation(&sum_hat, &sum_true),
    })
}
