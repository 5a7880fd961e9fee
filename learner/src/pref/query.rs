//! Choosing queries (`shared/method.md` section 3): the annotation buffer of recent whole
//! trajectories, candidate pairs drawn uniformly from it, and the samplers that keep the
//! pairs worth asking about.
//!
//! A session reads top to bottom: [`candidate_pairs`] draws `queries_per_session *
//! candidate_factor` pairs, the reward ensemble predicts `P[second > first]` for each pair
//! and member, and [`select`] keeps `queries_per_session` of them (uniform, disagreement
//! or entropy; the first session is always uniform, which is the caller's choice).

use std::collections::VecDeque;
use std::sync::Arc;

use anyhow::{bail, Result};
use pbrl_common::wire::TrajectoryMsg;
use rand::Rng;
use serde::{Deserialize, Deserializer, Serialize, Serializer};

/// Capacity of the annotation buffer, in trajectories (B-Pref and the authors).
pub const DEFAULT_CAPACITY: usize = 10_000;

/// Identity of a trajectory across restarts: (actor, incarnation, seq) as in
/// [`pbrl_common::wire::TrajectoryMsg`].
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
pub struct TrajKey {
    pub actor: u32,
    pub incarnation: u64,
    pub seq: u64,
}

/// What the reward model and the teachers need of one trajectory: no replay data, and the
/// observations the actions were taken in (`steps` rows, not the trajectory's `steps + 1`).
///
/// One feeding trajectory (obs 25, act 7, 200 steps) costs 31,344 bytes in memory:
/// `4 * (200 * 25 + 200 * 7 + 200 + 200 * 6) = 31,200` bytes of numbers (observations,
/// actions, truth, comfort features) plus the 144-byte struct (see [`Candidate::bytes`]);
/// a full buffer of 10,000 is about 313 MB. The features are kept whether or not the
/// model reads them, so that the label store holds them for any later fit.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Candidate {
    pub key: TrajKey,
    /// Seed of the episode's reset (to replay it for a person).
    pub seed: u64,
    /// Version of the policy that acted.
    pub policy_version: u64,
    pub obs_dim: u32,
    pub act_dim: u32,
    /// `steps` raw (unnormalised) observations, flattened row-major.
    pub obs: Vec<f32>,
    /// `steps` actions as the policy gave them, flattened row-major.
    pub actions: Vec<f32>,
    /// Ground-truth reward r per step, for scripted teachers only.
    pub truth: Vec<f32>,
    /// Comfort features per step, `steps` rows of `FEATURES`. Not in the candidate's own
    /// serialised form (a checkpoint's annotation buffer keeps the layout of the builds
    /// before them): the checkpoint carries them apart ([`AnnotationBuffer::features`]).
    #[serde(skip)]
    pub features: Vec<f32>,
}

impl Candidate {
    /// The candidate of a received trajectory.
    pub fn from_msg(msg: &TrajectoryMsg) -> Self {
        let t = &msg.trajectory;
        let steps = t.steps();
        Self {
            key: TrajKey {
                actor: msg.actor,
                incarnation: msg.incarnation,
                seq: msg.seq,
            },
            seed: t.seed,
            policy_version: t.policy_version,
            obs_dim: t.obs_dim,
            act_dim: t.act_dim,
            // NOTE: the trajectory holds `steps + 1` observations; the last one (after the
            // final action) has no action and no reward, so it is left out.
            obs: t.obs[..steps * t.obs_dim as usize].to_vec(),
            actions: t.actions.clone(),
            truth: t.rewards.iter().map(|r| r.truth).collect(),
            features: t.features(),
        }
    }

    /// Env steps (rows of `obs`).
    pub fn steps(&self) -> usize {
        self.obs.len() / (self.obs_dim as usize).max(1)
    }

    /// Bytes held in memory: the struct and the numbers of its vectors (their lengths,
    /// not capacities).
    pub fn bytes(&self) -> usize {
        std::mem::size_of::<Self>()
            + std::mem::size_of::<f32>()
                * (self.obs.len() + self.actions.len() + self.truth.len() + self.features.len())
    }
}

/// FIFO of the most recent trajectories ([`DEFAULT_CAPACITY`] by default). Items are
/// shared (`Arc`), so a clone of the buffer (a snapshot for a query session or a
/// checkpoint) copies pointers, not trajectories.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct AnnotationBuffer {
    capacity: usize,
    #[serde(serialize_with = "ser_items", deserialize_with = "de_items")]
    items: VecDeque<Arc<Candidate>>,
}

// serde's `Arc` support needs its "rc" feature; the candidates are written as plain values.
fn ser_items<S: Serializer>(items: &VecDeque<Arc<Candidate>>, s: S) -> Result<S::Ok, S::Error> {
    s.collect_seq(items.iter().map(|c| &**c))
}

fn de_items<'de, D: Deserializer<'de>>(d: D) -> Result<VecDeque<Arc<Candidate>>, D::Error> {
    Ok(Vec::<Candidate>::deserialize(d)?
        .into_iter()
        .map(Arc::new)
        .collect())
}

impl Default for AnnotationBuffer {
    fn default() -> Self {
        Self::new(DEFAULT_CAPACITY)
    }
}

impl AnnotationBuffer {
    /// An empty buffer holding at most `capacity` trajectories.
    ///
    /// # Panics
    /// If `capacity` is 0.
    pub fn new(capacity: usize) -> Self {
        assert!(
            capacity > 0,
            "annotation buffer capacity must be at least 1, got {capacity}"
        );
        Self {
            capacity,
            items: VecDeque::new(),
        }
    }

    /// Store `c`, dropping the oldest trajectory once full.
    pub fn push(&mut self, c: Candidate) {
        if self.items.len() == self.capacity {
            self.items.pop_front();
        }
        self.items.push_back(Arc::new(c));
    }

    pub fn len(&self) -> usize {
        self.items.len()
    }

    pub fn is_empty(&self) -> bool {
        self.items.is_empty()
    }

    pub fn capacity(&self) -> usize {
        self.capacity
    }

    /// Item `i`, counted from the oldest held (0).
    ///
    /// # Panics
    /// If `i >= len()`.
    pub fn get(&self, i: usize) -> &Arc<Candidate> {
        match self.items.get(i) {
            Some(c) => c,
            None => panic!(
                "annotation buffer index {i} out of range (it holds {})",
                self.items.len()
            ),
        }
    }

    /// Items from the oldest to the newest.
    pub fn iter(&self) -> impl Iterator<Item = &Arc<Candidate>> {
        self.items.iter()
    }

    /// Every candidate's comfort features, oldest first (what a checkpoint keeps beside
    /// the buffer).
    pub fn features(&self) -> Vec<Vec<f32>> {
        self.items.iter().map(|c| c.features.clone()).collect()
    }

    /// Give the candidates back their comfort features ([`AnnotationBuffer::features`]);
    /// none (a checkpoint of an older build) leaves them without.
    pub fn attach_features(&mut self, features: Vec<Vec<f32>>) -> anyhow::Result<()> {
        if features.is_empty() {
            return Ok(());
        }
        if features.len() != self.items.len() {
            anyhow::bail!(
                "the checkpoint holds comfort features for {} trajectories and {} in the annotation buffer",
                features.len(),
                self.items.len()
            );
        }
        for (c, f) in self.items.iter_mut().zip(features) {
            Arc::make_mut(c).features = f;
        }
        Ok(())
    }

    /// Bytes held: each candidate's [`Candidate::bytes`] plus its `Arc` (two counters) and
    /// its slot in the queue (one pointer).
    pub fn bytes(&self) -> usize {
        let per_item = 3 * std::mem::size_of::<usize>();
        self.items.iter().map(|c| c.bytes() + per_item).sum()
    }
}

/// How the queries of a session are chosen among the candidate pairs.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "kebab-case")]
pub enum Sampler {
    /// The first pairs drawn (the candidates are already uniform).
    Uniform,
    /// The pairs whose preference the ensemble members disagree on most (std across
    /// members); the default.
    #[default]
    Disagreement,
    /// The pairs whose mean predicted preference is closest to a coin flip (binary
    /// entropy of the mean).
    Entropy,
}

/// `n` candidate pairs `(i, j)`, `i != j`, drawn uniformly from `len` items (with
/// replacement across pairs). Fails if `len < 2`.
pub fn candidate_pairs(rng: &mut impl Rng, len: usize, n: usize) -> Result<Vec<(usize, usize)>> {
    if len < 2 {
        bail!(
            "candidate pairs need at least 2 trajectories in the annotation buffer, it holds {len}"
        );
    }
    Ok((0..n)
        .map(|_| {
            let i = rng.random_range(0..len);
            // NOTE: j is drawn from the other len - 1 items (shifted past i), so it is
            // uniform over them and never equals i, without rejection loops.
            let j = rng.random_range(0..len - 1);
            (i, if j >= i { j + 1 } else { j })
        })
        .collect())
}

/// `n` candidate sets of `k` distinct items each, drawn uniformly from `len` items (with
/// replacement across sets), each in the order drawn. Fails if `len < k`.
pub fn candidate_sets(
    rng: &mut impl Rng,
    len: usize,
    k: usize,
    n: usize,
) -> Result<Vec<Vec<usize>>> {
    if len < k {
        bail!("candidate sets of {k} need at least {k} trajectories in the annotation buffer, it holds {len}");
    }
    Ok((0..n)
        .map(|_| rand::seq::index::sample(rng, len, k).into_vec())
        .collect())
}

/// The score [`select`] ranks pairs by: for `Disagreement` the population std across
/// members (numpy's `std`, ddof 0) of `probs[m][p]`; for `Entropy` the binary entropy (in
/// nats) of the members' mean; all zeros for `Uniform`.
///
/// # Panics
/// For `Disagreement` and `Entropy`, if `probs` has no member or a member's row does not
/// hold `n_candidates` numbers.
pub fn scores(sampler: Sampler, probs: &[Vec<f32>], n_candidates: usize) -> Vec<f64> {
    if sampler == Sampler::Uniform {
        return vec![0.0; n_candidates];
    }
    assert!(
        !probs.is_empty(),
        "{sampler:?} sampling needs the predictions of at least one ensemble member, got none"
    );
    for (m, row) in probs.iter().enumerate() {
        assert!(
            row.len() == n_candidates,
            "ensemble member {m} predicted {} pairs, expected {n_candidates}",
            row.len()
        );
    }
    let members = probs.len() as f64;
    (0..n_candidates)
        .map(|p| {
            let mean = probs.iter().map(|row| row[p] as f64).sum::<f64>() / members;
            // NOTE: both scores are symmetric under p -> 1 - p, so it does not matter that
            // `probs` holds P[second > first] where method.md speaks of P[t0 > t1].
            match sampler {
                Sampler::Disagreement => {
                    let var = probs
                        .iter()
                        .map(|row| (row[p] as f64 - mean).powi(2))
                        .sum::<f64>()
                        / members;
                    var.sqrt()
                }
                _ => binary_entropy(mean),
            }
        })
        .collect()
}

/// `-(p ln p + (1 - p) ln(1 - p))`, with `0 ln 0 = 0`.
fn binary_entropy(p: f64) -> f64 {
    let p = p.clamp(0.0, 1.0);
    let h = |x: f64| if x > 0.0 { -x * x.ln() } else { 0.0 };
    h(p) + h(1.0 - p)
}

/// Pick `k` of the `n_candidates` pairs. `probs[m][p]` is member `m`'s `P[second > first]`
/// for pair `p` (unused by `Uniform`, which takes the first `k`: the candidates are
/// already random). `Disagreement` keeps the `k` with the highest std across members,
/// `Entropy` the `k` with the highest binary entropy of the mean prediction (B-Pref's
/// entropy sampler instead averages each member's entropy; method.md asks for the entropy
/// of the mean). Ties go to the lower index. Returns indices into the candidates, best
/// first; fewer than `k` if there are fewer candidates.
///
/// # Panics
/// As [`scores`].
pub fn select(sampler: Sampler, probs: &[Vec<f32>], n_candidates: usize, k: usize) -> Vec<usize> {
    let k = k.min(n_candidates);
    if sampler == Sampler::Uniform {
        return (0..k).collect();
    }
    // NOTE: a NaN score (a member that predicted NaN) ranks last, not first as
    // `total_cmp` would put it.
    let s: Vec<f64> = scores(sampler, probs, n_candidates)
        .into_iter()
        .map(|x| if x.is_nan() { f64::NEG_INFINITY } else { x })
        .collect();
    let mut order: Vec<usize> = (0..n_candidates).collect();
    // Stable: equal scores keep the lower index first.
    order.sort_by(|&a, &b| s[b].total_cmp(&s[a]));
    order.truncate(k);
    order
}

#[cfg(test)]
mod tests {
    use super::*;
    use pbrl_common::trajectory::TRAJECTORY_FORMAT;
    use pbrl_common::{StepRewards, Trajectory};
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    fn candidate(seq: u64, steps: usize, obs_dim: usize, act_dim: usize) -> Candidate {
        Candidate {
            key: TrajKey {
                actor: 1,
                incarnation: 7,
                seq,
            },
            seed: seq,
            policy_version: 0,
            obs_dim: obs_dim as u32,
            act_dim: act_dim as u32,
            obs: vec![0.5; steps * obs_dim],
            actions: vec![0.1; steps * act_dim],
            truth: vec![-1.0; steps],
            features: vec![0.0; steps * pbrl_common::trajectory::FEATURES],
        }
    }

    /// Six pairs, three members. By hand (population std; entropy in nats of the mean):
    ///
    /// | pair | P[second > first] per member | mean     | std      | H(mean)  |
    /// |------|------------------------------|----------|----------|----------|
    /// | 0    | 0.5,  0.5,  0.5              | 0.5      | 0        | 0.693147 |
    /// | 1    | 0.9,  0.1,  0.8              | 0.6      | 0.355903 | 0.673012 |
    /// | 2    | 0.2,  0.2,  0.3              | 0.233333 | 0.047140 | 0.543273 |
    /// | 3    | 0.95, 0.95, 0.1              | 0.666667 | 0.400694 | 0.636514 |
    /// | 4    | 0.25, 0.75, 0.5              | 0.5      | 0.204124 | 0.693147 |
    /// | 5    | 0.75, 0.25, 0.5              | 0.5      | 0.204124 | 0.693147 |
    ///
    /// Reference (Python):
    ///   import numpy as np
    ///   P = np.array([[.5,.9,.2,.95,.25,.75],[.5,.1,.2,.95,.75,.25],[.5,.8,.3,.1,.5,.5]])
    ///   m = P.mean(0); P.std(0)          # [0, .355903, .047140, .400694, .204124, .204124]
    ///   -(m*np.log(m) + (1-m)*np.log(1-m))  # [.693147, .673012, .543273, .636514, .693147, .693147]
    /// e.g. pair 1: deviations .3, -.5, .2 -> (.09 + .25 + .04) / 3 = .126667 -> std .355903;
    /// H(.6) = .6 * .510826 + .4 * .916291 = .673012.
    /// Pairs 4 and 5 (binary-exact numbers) tie exactly with each other, and with pair 0
    /// in entropy.
    fn probs() -> Vec<Vec<f32>> {
        vec![
            vec![0.5, 0.9, 0.2, 0.95, 0.25, 0.75],
            vec![0.5, 0.1, 0.2, 0.95, 0.75, 0.25],
            vec![0.5, 0.8, 0.3, 0.1, 0.5, 0.5],
        ]
    }

    fn assert_close(got: &[f64], want: &[f64]) {
        assert_eq!(got.len(), want.len());
        for (g, w) in got.iter().zip(want) {
            assert!((g - w).abs() < 1e-5, "got {got:?}, want {want:?}");
        }
    }

    #[test]
    fn disagreement_keeps_the_pairs_the_members_disagree_on() {
        let s = scores(Sampler::Disagreement, &probs(), 6);
        assert_close(&s, &[0.0, 0.355903, 0.047140, 0.400694, 0.204124, 0.204124]);
        // std order: 3 (.4007), 1 (.3559), 4 = 5 (.2041, lower index first), 2, 0.
        assert_eq!(select(Sampler::Disagreement, &probs(), 6, 4), [3, 1, 4, 5]);
        assert_eq!(select(Sampler::Disagreement, &probs(), 6, 1), [3]);
    }

    #[test]
    fn entropy_keeps_the_pairs_closest_to_a_coin_flip() {
        let s = scores(Sampler::Entropy, &probs(), 6);
        let ln2 = std::f64::consts::LN_2;
        assert_close(&s, &[ln2, 0.673012, 0.543273, 0.636514, ln2, ln2]);
        // entropy order: 0 = 4 = 5 (ln 2, by index), 1 (.6730), 3 (.6365), 2 (.5433).
        assert_eq!(select(Sampler::Entropy, &probs(), 6, 4), [0, 4, 5, 1]);
        assert_eq!(select(Sampler::Entropy, &probs(), 6, 6), [0, 4, 5, 1, 3, 2]);
    }

    #[test]
    fn uniform_takes_the_first_k() {
        assert_eq!(select(Sampler::Uniform, &probs(), 6, 4), [0, 1, 2, 3]);
        // No predictions needed, and never more than there are candidates.
        assert_eq!(select(Sampler::Uniform, &[], 3, 5), [0, 1, 2]);
        assert_eq!(select(Sampler::Disagreement, &probs(), 6, 10).len(), 6);
    }

    #[test]
    fn a_nan_prediction_ranks_last() {
        let mut p = probs();
        p[0][3] = f32::NAN;
        assert_eq!(select(Sampler::Disagreement, &p, 6, 2), [1, 4]);
    }

    #[test]
    fn candidate_pairs_are_distinct_items_and_repeat_per_seed() {
        let draw = |seed: u64, len: usize| {
            candidate_pairs(&mut ChaCha8Rng::seed_from_u64(seed), len, 2000).unwrap()
        };
        let pairs = draw(3, 5);
        assert_eq!(pairs.len(), 2000);
        assert!(pairs.iter().all(|&(i, j)| i != j && i < 5 && j < 5));
        // Every ordered pair of distinct items turns up (20 of them, 100 draws each expected).
        for i in 0..5 {
            for j in (0..5).filter(|&j| j != i) {
                assert!(pairs.contains(&(i, j)), "({i}, {j}) never drawn");
            }
        }
        assert_eq!(pairs, draw(3, 5));
        assert_ne!(pairs, draw(4, 5));
        // Two items: only (0, 1) and (1, 0).
        let two = draw(5, 2);
        assert!(two.contains(&(0, 1)) && two.contains(&(1, 0)));
        assert!(two.iter().all(|&p| p == (0, 1) || p == (1, 0)));
    }

    #[test]
    fn candidate_pairs_need_two_items() {
        let mut rng = ChaCha8Rng::seed_from_u64(0);
        for len in [0, 1] {
            let err = candidate_pairs(&mut rng, len, 3).unwrap_err().to_string();
            assert!(err.contains(&format!("it holds {len}")), "{err}");
        }
        assert!(candidate_pairs(&mut rng, 2, 0).unwrap().is_empty());
    }

    #[test]
    fn the_buffer_drops_the_oldest() {
        let mut b = AnnotationBuffer::new(3);
        assert!(b.is_empty());
        for seq in 0..5 {
            b.push(candidate(seq, 2, 3, 1));
        }
        assert_eq!(b.len(), 3);
        let seqs: Vec<u64> = b.iter().map(|c| c.key.seq).collect();
        assert_eq!(seqs, [2, 3, 4]);
        assert_eq!(b.get(0).key.seq, 2);
        assert_eq!(b.get(2).key.seq, 4);
        assert_eq!(AnnotationBuffer::default().capacity(), 10_000);
    }

    #[test]
    fn a_snapshot_shares_the_trajectories_and_serde_round_trips() {
        let mut b = AnnotationBuffer::new(4);
        b.push(candidate(0, 3, 2, 1));
        b.push(candidate(1, 3, 2, 1));
        let snap = b.clone();
        assert!(Arc::ptr_eq(snap.get(1), b.get(1)));
        let json = serde_json::to_string(&b).unwrap();
        let mut back: AnnotationBuffer = serde_json::from_str(&json).unwrap();
        assert_eq!(back.capacity(), 4);
        // The features travel apart (a checkpoint keeps them beside the buffer).
        assert!(back.iter().all(|c| c.features.is_empty()));
        back.attach_features(b.features()).unwrap();
        let (x, y): (Vec<_>, Vec<_>) = (back.iter().collect(), b.iter().collect());
        assert_eq!(x, y);
    }

    #[test]
    fn a_feeding_candidate_costs_31344_bytes() {
        // By hand, obs 25, act 7, 6 features, 200 steps:
        //   numbers: 200 * 25 + 200 * 7 + 200 + 200 * 6 = 5000 + 1400 + 200 + 1200 = 7800 f32
        //            = 31,200 bytes
        //   struct:  key 24 (u32 + u64 + u64, padded) + seed 8 + policy_version 8
        //            + obs_dim 4 + act_dim 4 + four Vecs 4 * 24 = 144 bytes (64-bit target)
        //   total:   31,344 bytes; in the buffer + 24 (Arc counters, queue pointer) = 31,368
        let c = candidate(0, 200, 25, 7);
        assert_eq!(c.steps(), 200);
        assert_eq!(std::mem::size_of::<Candidate>(), 144);
        assert_eq!(c.bytes(), 31_344);
        let mut b = AnnotationBuffer::new(10);
        b.push(c.clone());
        b.push(c);
        assert_eq!(b.bytes(), 2 * 31_368);
    }

    #[test]
    fn a_candidate_keeps_the_observations_the_actions_were_taken_in() {
        let steps = 3;
        let msg = TrajectoryMsg {
            actor: 2,
            incarnation: 9,
            seq: 4,
            oldest: 0,
            trajectory: Trajectory {
                format: TRAJECTORY_FORMAT,
                seed: 11,
                policy_version: 5,
                obs_dim: 2,
                act_dim: 1,
                obs: (0..(steps + 1) * 2).map(|x| x as f32).collect(),
                actions: vec![0.1, 0.2, 0.3],
                rewards: (0..steps)
                    .map(|k| StepRewards {
                        truth: -(k as f32),
                        ..StepRewards::default()
                    })
                    .collect(),
                ..Trajectory::default()
            },
        };
        let c = Candidate::from_msg(&msg);
        assert_eq!(
            c.key,
            TrajKey {
                actor: 2,
                incarnation: 9,
                seq: 4
            }
        );
        assert_eq!((c.seed, c.policy_version, c.steps()), (11, 5, 3));
        assert_eq!(c.obs, [0.0, 1.0, 2.0, 3.0, 4.0, 5.0]);
        assert_eq!(c.actions, [0.1, 0.2, 0.3]);
        assert_eq!(c.truth, [0.0, -1.0, -2.0]);
    }
}
