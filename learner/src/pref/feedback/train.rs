//! Training the reward ensemble: a copy trained on all of D (and SURF's pseudo-labels) on a
//! thread of its own at a lower priority.

use std::sync::Arc;
use std::time::Instant;

use anyhow::Result;

use super::choose::{distinct_pairs, Side};
use super::{Feedback, Job, JobDone};
use crate::pref::query::candidate_pairs;
use crate::pref::reward_model::{Labelled, RewardModel};

impl Feedback {
    /// The job of training a copy of the ensemble on all of D (and measuring it first on
    /// the labels new since the last training).
    pub(super) fn training(&mut self) -> Result<Job> {
        let mut model = self.model.snapshot()?;
        let data = self.data.clone();
        let new = data[self.counters.trained_labels..].to_vec();
        let trained_before = model.trained();
        // NOTE: pseudo-labels need an ensemble that has learnt something: from the second
        // training on.
        let unlabelled: Vec<(Side, Side)> =
            if trained_before && self.cfg.pseudo_pairs > 0 && self.buffer.len() >= 2 {
                let held = self.buffer.len();
                candidate_pairs(&mut self.rng, held, self.cfg.pseudo_pairs)?
                    .into_iter()
                    .map(|(i, j)| {
                        let (a, b) = (self.buffer.get(i).clone(), self.buffer.get(j).clone());
                        (self.side(&a), self.side(&b))
                    })
                    .collect()
            } else {
                Vec::new()
            };
        let tau = self.cfg.pseudo_tau;
        Ok(Box::new(move || {
            let start = Instant::now();
            let accuracy_new = if trained_before {
                model.accuracy(&new)?
            } else {
                f64::NAN
            };
            let labels = data.len();
            let pseudo = pseudo_labels(&model, &unlabelled, tau)?;
            let stats = model.train_with(&data, &pseudo)?;
            Ok(JobDone::Trained {
                model: Box::new(model),
                stats,
                labels,
                accuracy_new,
                took: start.elapsed(),
            })
        }))
    }
}

/// Lower the calling thread's scheduling priority by 10 nice levels (at most to 19; Linux,
/// elsewhere nothing): the feedback jobs (choosing queries, training the ensemble) then run
/// on the CPU that the learner's updates and the actors leave, instead of taking it from
/// them. A session whose job waits for CPU comes later; the env steps do not slow down.
pub(super) fn lower_priority() {
    #[cfg(target_os = "linux")]
    {
        // NOTE: relative, not nice 10: under `nice -n 19 pbrl exp run` an absolute 10 would
        // raise the job above the learner (root may lower a nice value). On Linux the nice
        // value belongs to the thread, so this leaves the learner's threads as they are.
        // SAFETY: errno and nice only read and set this thread's errno and priority; no
        // memory is shared with them.
        let rc = unsafe {
            *libc::__errno_location() = 0;
            libc::nice(10)
        };
        let err = std::io::Error::last_os_error();
        if rc == -1 && err.raw_os_error() != Some(0) {
            tracing::debug!(error = %err, "could not lower the feedback job's priority");
        }
    }
}

/// The pairs of `unlabelled` that `model` is sure of (mean P of one side at least `tau`),
/// labelled with its answer (SURF's pseudo-labels).
pub(super) fn pseudo_labels(
    model: &RewardModel,
    unlabelled: &[(Side, Side)],
    tau: f64,
) -> Result<Vec<Labelled>> {
    if unlabelled.is_empty() {
        return Ok(Vec::new());
    }
    let d = distinct_pairs(unlabelled);
    let probs = model.preference_probs(&d.pairs())?;
    let q = probs.len() as f64;
    let mut out = Vec::new();
    for (k, &(a, b)) in d.sides.iter().enumerate() {
        let p = probs.iter().map(|m| m[k] as f64).sum::<f64>() / q;
        let target = if p >= tau {
            1.0
        } else if 1.0 - p >= tau {
            0.0
        } else {
            continue;
        };
        out.push(Labelled {
            first: Arc::new(d.segs[a].clone()),
            second: Arc::new(d.segs[b].clone()),
            target,
        });
    }
    Ok(out)
}
