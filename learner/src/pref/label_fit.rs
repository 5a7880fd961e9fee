//! How well the reward ensemble generalises from a run's labels (`pbrl labels fit`):
//! k-fold cross-validation of one training on the stored labels, beside what the task
//! prior alone (`-d` summed over each side) gets right on the same labels.
//!
//! A run trains its ensemble every session, each time from the last one's weights; here
//! each fold trains a fresh ensemble once, with the given settings, on the other folds. The
//! figures compare settings on the same labels; they are not the run's own accuracy.

use std::collections::hash_map::Entry;
use std::collections::HashMap;
use std::path::Path;
use std::sync::Arc;

use anyhow::{bail, Context, Result};
use rand::seq::SliceRandom;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

use crate::pref::feedback::labelled;
use crate::pref::labels::LabelStore;
use crate::pref::reward_model::{task_reward, Labelled, RewardModel, RewardModelConfig, Segment};

/// A store's labels (first, second and equal) as D trains on them, and the sizes of the
/// observation and action they were taken with.
pub struct StoredLabels {
    pub data: Vec<Labelled>,
    pub obs_dim: usize,
    pub act_dim: usize,
}

/// Read every label of the store at `path` (read-only, safe while its run goes).
pub fn read_labels(path: &Path) -> Result<StoredLabels> {
    let store = LabelStore::open_read_only(path)?;
    let rows = store.labels_since(0)?;
    if rows.is_empty() {
        bail!("label store {} holds no labels", path.display());
    }
    let mut whole: HashMap<u64, crate::pref::labels::StoredSteps> = HashMap::new();
    let (mut obs_dim, mut act_dim) = (0, 0);
    let mut data = Vec::with_capacity(rows.len());
    for row in rows {
        let mut side = |id: u64, (start, len): (usize, usize)| -> Result<Arc<Segment>> {
            if let Entry::Vacant(e) = whole.entry(id) {
                e.insert(store.steps(id)?);
            }
            let t = &whole[&id];
            if (obs_dim, act_dim) == (0, 0) {
                (obs_dim, act_dim) = (t.obs_dim, t.act_dim);
            } else if (obs_dim, act_dim) != (t.obs_dim, t.act_dim) {
                bail!(
                    "label store {}: trajectory {id} has obs {} and action {}, others {obs_dim} and {act_dim}",
                    path.display(),
                    t.obs_dim,
                    t.act_dim
                );
            }
            if len == 0 || start + len > t.steps {
                bail!(
                    "label store {}: segment start {start}, length {len} of trajectory {id} is not within its {} steps",
                    path.display(),
                    t.steps
                );
            }
            Ok(Arc::new(Segment::of(
                &t.obs,
                &t.actions,
                &t.features,
                (start, len),
                t.steps,
            )))
        };
        let sides = row
            .attempts()
            .into_iter()
            .map(|(id, seg)| side(id, seg))
            .collect::<Result<Vec<_>>>()?;
        data.extend(labelled(&sides, row.preference, &row.ranks));
    }
    Ok(StoredLabels {
        data,
        obs_dim,
        act_dim,
    })
}

/// What cross-validation found.
#[derive(Clone, Debug, PartialEq)]
pub struct FitReport {
    pub labels: usize,
    pub equal: usize,
    /// Each fold's accuracy on its held-out labels (equal ones left out).
    pub held_out: Vec<f64>,
    /// Each fold's accuracy on the labels it trained on.
    pub trained: Vec<f64>,
    /// The share of the hard labels the task prior alone gets right: the side with the
    /// larger sum of `-|obs[goal]|` preferred (none without a goal).
    pub task_prior: Option<f64>,
}

impl FitReport {
    pub fn mean(v: &[f64]) -> f64 {
        v.iter().sum::<f64>() / v.len().max(1) as f64
    }
}

/// The task prior's sum over a segment: `-|obs[goal]|` of each row.
fn prior_sum(seg: &Segment, obs_dim: usize, goal: [usize; 2]) -> f32 {
    seg.obs
        .chunks_exact(obs_dim)
        .map(|row| task_reward(row, goal))
        .sum()
}

/// `folds`-fold cross-validation of the ensemble `cfg` on `labels` (folds drawn by a
/// shuffle from `seed`; each fold's ensemble starts from `cfg.seed + fold`). `goal`: where
/// the observation holds the vector to the goal, for the task prior's figure.
pub fn cross_validate(
    labels: &StoredLabels,
    cfg: &RewardModelConfig,
    folds: usize,
    seed: u64,
    goal: Option<[usize; 2]>,
) -> Result<FitReport> {
    let n = labels.data.len();
    if folds < 2 || folds > n {
        bail!("folds is {folds}: must be in 2..={n} (the labels)");
    }
    let mut order: Vec<usize> = (0..n).collect();
    order.shuffle(&mut ChaCha8Rng::seed_from_u64(seed));
    let (mut held_out, mut trained) = (Vec::new(), Vec::new());
    for k in 0..folds {
        let (mut train, mut test) = (Vec::new(), Vec::new());
        for (i, &j) in order.iter().enumerate() {
            let l = labels.data[j].clone();
            if i % folds == k {
                test.push(l);
            } else {
                train.push(l);
            }
        }
        let mut cfg = cfg.clone();
        cfg.seed = cfg.seed.wrapping_add(k as u64);
        let mut model = RewardModel::new(cfg, labels.obs_dim, labels.act_dim)
            .with_context(|| format!("fold {k}: making the ensemble"))?;
        model
            .train(&train)
            .with_context(|| format!("fold {k}: training"))?;
        held_out.push(model.accuracy(&test)?);
        trained.push(model.accuracy(&train)?);
    }
    let hard: Vec<&Labelled> = labels.data.iter().filter(|l| !l.is_equal()).collect();
    let task_prior = goal.filter(|_| !hard.is_empty()).map(|g| {
        let right = hard
            .iter()
            .filter(|l| {
                let (a, b) = (
                    prior_sum(&l.first, labels.obs_dim, g),
                    prior_sum(&l.second, labels.obs_dim, g),
                );
                (b > a) == (l.target > 0.5)
            })
            .count();
        right as f64 / hard.len() as f64
    });
    Ok(FitReport {
        labels: n,
        equal: n - hard.len(),
        held_out,
        trained,
        task_prior,
    })
}

/// The report for a person: one paragraph, rounded.
pub fn report(r: &FitReport) -> String {
    let folds: Vec<String> = r.held_out.iter().map(|a| format!("{a:.2}")).collect();
    let mut s = format!(
        "{} labels ({} equal, left out of the accuracies), {} folds\n\
         held-out accuracy {:.3} (folds {})\n\
         accuracy on the labels trained on {:.3}\n",
        r.labels,
        r.equal,
        r.held_out.len(),
        FitReport::mean(&r.held_out),
        folds.join(", "),
        FitReport::mean(&r.trained),
    );
    if let Some(p) = r.task_prior {
        s.push_str(&format!(
            "the task prior alone (-d summed over each side) {p:.3}\n"
        ));
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pref::labels::StoredTrajectory;
    use pbrl_common::wire::Answer;
    use pbrl_common::wire::Preference;
    use rand::Rng;

    fn stored(
        t: &(Vec<f32>, Vec<f32>),
        seq: u64,
        segment: (usize, usize),
        (obs_dim, act_dim): (usize, usize),
    ) -> StoredTrajectory<'_> {
        StoredTrajectory {
            actor: (seq % 2) as u32,
            incarnation: 1,
            seq,
            seed: seq,
            policy_version: 1,
            obs_dim,
            act_dim,
            obs: &t.0,
            actions: &t.1,
            features: &[],
            segment,
        }
    }

    /// A store of oracle labels on 10-step segments of 30-step trajectories under the
    /// reward `-|obs[1..3]|`: cross-validation reads each label's segments back (the task
    /// prior, which is that reward, gets every one right: a segment read off by a step or
    /// a side swapped would not), and a trained ensemble generalises above chance.
    #[test]
    fn cross_validation_reads_a_stores_segments_and_tells_a_learnt_preference() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("labels.sqlite");
        let mut store = LabelStore::open(&path, "run").unwrap();
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let (o, a, steps, len) = (3usize, 1usize, 30usize, 10usize);
        let reward = |row: &[f32]| -(row[1] * row[1] + row[2] * row[2]).sqrt();
        let trajectory = |rng: &mut ChaCha8Rng| -> (Vec<f32>, Vec<f32>) {
            let c: Vec<f32> = (0..o).map(|_| rng.random_range(-1.0..1.0)).collect();
            let obs = (0..steps * o)
                .map(|i| c[i % o] + rng.random_range(-0.3..0.3))
                .collect();
            let actions = (0..steps * a)
                .map(|_| rng.random_range(-1.0..1.0))
                .collect();
            (obs, actions)
        };
        for q in 0..60u64 {
            let (t0, t1) = (trajectory(&mut rng), trajectory(&mut rng));
            let (s0, s1) = (
                rng.random_range(0..=steps - len),
                rng.random_range(0..=steps - len),
            );
            let sum = |t: &(Vec<f32>, Vec<f32>), s: usize| -> f32 {
                t.0[s * o..(s + len) * o].chunks_exact(o).map(reward).sum()
            };
            let p = if sum(&t1, s1) > sum(&t0, s0) {
                Preference::Second
            } else {
                Preference::First
            };
            let asked = store
                .ask(
                    1,
                    "uniform",
                    0,
                    0,
                    &stored(&t0, 2 * q, (s0, len), (o, a)),
                    &stored(&t1, 2 * q + 1, (s1, len), (o, a)),
                    |_, _, _| Vec::new(),
                )
                .unwrap();
            store
                .answer(&Answer::scripted(asked.query, p, "oracle", "o-1", 1), 1)
                .unwrap();
        }
        drop(store);
        let labels = read_labels(&path).unwrap();
        assert_eq!(
            (labels.data.len(), labels.obs_dim, labels.act_dim),
            (60, 3, 1)
        );
        assert!(labels.data.iter().all(|l| l.first.obs.len() == len * o));
        let cfg = RewardModelConfig {
            hidden: vec![32, 32],
            batch: 16,
            lr: 1e-3,
            ..RewardModelConfig::plain()
        };
        let r = cross_validate(&labels, &cfg, 5, 1, Some([1, 2])).unwrap();
        println!("{}", report(&r));
        assert_eq!(r.task_prior, Some(1.0));
        assert_eq!(r.held_out.len(), 5);
        assert!(FitReport::mean(&r.held_out) > 0.7, "{r:?}");
        assert!(cross_validate(&labels, &cfg, 1, 1, None).is_err());
    }
}
