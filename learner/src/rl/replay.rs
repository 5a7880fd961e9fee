//! SAC's replay buffer: transitions as flat f32 rows in a ring, with what a checkpoint
//! needs to save them as segments and restore them in place.

use candle_core::{Device, Result, Tensor};
use rand::Rng;

/// Transitions, flat f32 rows, overwritten oldest first once full. A row holds the task
/// reward r_task and (for diagnostics and the `truth` baseline) the ground truth, never the
/// reward trained on: that is formed per minibatch ([`Batch`]), so no transition is trained
/// on with a stale reward model.
pub struct Replay {
    pub(crate) obs_dim: usize,
    act_dim: usize,
    /// Comfort features kept per transition (0: none; see [`Replay::keep_features`]).
    feat_dim: usize,
    capacity: usize,
    len: usize,
    next: usize,
    /// Transitions pushed since the start (the buffer holds the last `len` of them).
    pub total: u64,
    obs: Vec<f32>,
    act: Vec<f32>,
    task: Vec<f32>,
    truth: Vec<f32>,
    next_obs: Vec<f32>,
    done: Vec<f32>,
    feat: Vec<f32>,
}

/// A minibatch as drawn from the replay buffer: `[n, obs]`, `[n, act]`, r_task `[n, 1]`,
/// the ground truth `[n, 1]`, `[n, obs]`, done `[n, 1]`.
pub struct Batch {
    pub obs: Tensor,
    pub act: Tensor,
    pub task: Tensor,
    pub truth: Tensor,
    pub next_obs: Tensor,
    pub done: Tensor,
    /// The transitions' comfort features `[n, FEATURES]`, where the buffer keeps them.
    pub features: Option<Tensor>,
}

impl Replay {
    pub fn new(obs_dim: usize, act_dim: usize, capacity: usize) -> Self {
        Self {
            obs_dim,
            act_dim,
            feat_dim: 0,
            capacity,
            len: 0,
            next: 0,
            total: 0,
            obs: Vec::new(),
            act: Vec::new(),
            task: Vec::new(),
            truth: Vec::new(),
            next_obs: Vec::new(),
            done: Vec::new(),
            feat: Vec::new(),
        }
    }

    /// Keep `n` comfort features per transition from now on (a reward model that reads
    /// them relabels each minibatch); set on an empty buffer, before a restore.
    pub fn keep_features(&mut self, n: usize) {
        assert!(
            self.total == 0,
            "features are kept from a buffer's first transition"
        );
        self.feat_dim = n;
    }

    pub fn len(&self) -> usize {
        self.len
    }

    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// Store one transition with its rewards `[r_task, truth]` and its comfort features
    /// (read only where the buffer keeps them: `feat_dim` numbers).
    pub fn push(
        &mut self,
        obs: &[f32],
        act: &[f32],
        rewards: [f32; 2],
        next_obs: &[f32],
        done: bool,
        features: &[f32],
    ) {
        let (o, a, f, i) = (self.obs_dim, self.act_dim, self.feat_dim, self.next);
        let features = &features[..f];
        if self.len < self.capacity {
            self.feat.extend_from_slice(features);
            self.obs.extend_from_slice(obs);
            self.act.extend_from_slice(act);
            self.task.push(rewards[0]);
            self.truth.push(rewards[1]);
            self.next_obs.extend_from_slice(next_obs);
            self.done.push(done as u8 as f32);
            self.len += 1;
        } else {
            self.obs[i * o..(i + 1) * o].copy_from_slice(obs);
            self.act[i * a..(i + 1) * a].copy_from_slice(act);
            self.task[i] = rewards[0];
            self.truth[i] = rewards[1];
            self.next_obs[i * o..(i + 1) * o].copy_from_slice(next_obs);
            self.done[i] = done as u8 as f32;
            self.feat[i * f..(i + 1) * f].copy_from_slice(features);
        }
        self.next = (self.next + 1) % self.capacity;
        self.total += 1;
    }

    /// Numbers per transition in [`Replay::rows`]: obs, act, r_task, truth, next obs, done,
    /// then the features where kept.
    pub fn row_len(&self) -> usize {
        2 * self.obs_dim + self.act_dim + 3 + self.feat_dim
    }

    /// Transitions `start..end` (counted from the start of the run; all still held), one
    /// row of [`Replay::row_len`] numbers each.
    pub fn rows(&self, start: u64, end: u64) -> Vec<f32> {
        assert!(
            start <= end && end <= self.total && start + self.len as u64 >= self.total,
            "transitions {start}..{end} are not all in the buffer"
        );
        let (o, a, f) = (self.obs_dim, self.act_dim, self.feat_dim);
        let mut out = Vec::with_capacity((end - start) as usize * self.row_len());
        for n in start..end {
            // NOTE: transition n sits at (n mod capacity): the ring fills in order.
            let i = (n % self.capacity as u64) as usize;
            out.extend_from_slice(&self.obs[i * o..(i + 1) * o]);
            out.extend_from_slice(&self.act[i * a..(i + 1) * a]);
            out.push(self.task[i]);
            out.push(self.truth[i]);
            out.extend_from_slice(&self.next_obs[i * o..(i + 1) * o]);
            out.push(self.done[i]);
            out.extend_from_slice(&self.feat[i * f..(i + 1) * f]);
        }
        out
    }

    /// Refill an empty buffer from rows of transitions `start..` (as [`Replay::rows`] lays
    /// them out), each at the place it had: the same buffer, the same minibatches.
    pub fn restore(&mut self, start: u64, rows: &[f32]) -> Result<()> {
        let n = (rows.len() / self.row_len()) as u64;
        let end = start + n;
        if self.total != 0 || !rows.len().is_multiple_of(self.row_len()) {
            candle_core::bail!("replay restore needs an empty buffer and whole rows");
        }
        if start > end.saturating_sub(self.capacity as u64) {
            candle_core::bail!(
                "replay rows {start}..{end} do not cover the buffer's last {} transitions",
                self.capacity
            );
        }
        if end <= self.capacity as u64 {
            self.push_rows(rows);
            return Ok(());
        }
        // A full ring: transition k sits at k mod capacity.
        let (o, a, c) = (self.obs_dim, self.act_dim, self.capacity);
        self.feat = vec![0.0; c * self.feat_dim];
        self.obs = vec![0.0; c * o];
        self.act = vec![0.0; c * a];
        self.task = vec![0.0; c];
        self.truth = vec![0.0; c];
        self.next_obs = vec![0.0; c * o];
        self.done = vec![0.0; c];
        self.len = c;
        let skip = (end - c as u64 - start) as usize;
        self.total = end - c as u64;
        self.next = (self.total % c as u64) as usize;
        let rows = &rows[skip * self.row_len()..];
        self.push_rows(rows);
        Ok(())
    }

    /// Push rows as [`Replay::rows`] lays them out.
    pub fn push_rows(&mut self, rows: &[f32]) {
        let (o, a) = (self.obs_dim, self.act_dim);
        for r in rows.chunks_exact(self.row_len()) {
            let (obs, rest) = r.split_at(o);
            let (act, rest) = rest.split_at(a);
            let (next_obs, rest) = rest[2..].split_at(o);
            let task_truth = [r[o + a], r[o + a + 1]];
            self.push(obs, act, task_truth, next_obs, rest[0] > 0.5, &rest[1..]);
        }
    }

    /// A minibatch of `n`: `recent.0` of them uniform over the newest `recent.1`
    /// transitions (QPA's hybrid replay; `(0, _)`: none), the rest uniform over the buffer.
    pub(crate) fn sample(
        &self,
        rng: &mut impl Rng,
        n: usize,
        recent: (usize, usize),
    ) -> Result<Batch> {
        let (k, window) = (recent.0.min(n), recent.1.clamp(1, self.len.max(1)));
        let mut idx: Vec<usize> = (0..n - k).map(|_| rng.random_range(0..self.len)).collect();
        // NOTE: the newest transition sits just before `next` in the ring.
        let cap = self.capacity;
        idx.extend((0..k).map(|_| (self.next + cap - 1 - rng.random_range(0..window)) % cap));
        let rows = |src: &[f32], w: usize| -> Result<Tensor> {
            let mut out = Vec::with_capacity(n * w);
            for &i in &idx {
                out.extend_from_slice(&src[i * w..(i + 1) * w]);
            }
            Tensor::from_vec(out, (n, w), &Device::Cpu)
        };
        Ok(Batch {
            obs: rows(&self.obs, self.obs_dim)?,
            act: rows(&self.act, self.act_dim)?,
            task: rows(&self.task, 1)?,
            truth: rows(&self.truth, 1)?,
            next_obs: rows(&self.next_obs, self.obs_dim)?,
            done: rows(&self.done, 1)?,
            features: match self.feat_dim {
                0 => None,
                f => Some(rows(&self.feat, f)?),
            },
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_hybrid_minibatch_takes_its_share_from_the_newest_transitions() {
        use rand::SeedableRng;
        let mut r = Replay::new(1, 1, 50);
        // 130 transitions through a ring of 50: it holds 80..130, the newest 10 are 120..130.
        for k in 0..130 {
            r.push(&[k as f32], &[0.0], [0.0, 0.0], &[0.0], false, &[]);
        }
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
        let b = r.sample(&mut rng, 64, (16, 10)).unwrap();
        let obs = b.obs.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        assert!(obs.iter().all(|&x| (80.0..130.0).contains(&x)));
        // The last 16 rows are the hybrid share: all among the newest 10.
        assert!(obs[48..].iter().all(|&x| x >= 120.0), "{:?}", &obs[48..]);
        let old = obs[..48].iter().filter(|&&x| x < 120.0).count();
        assert!(
            old > 30,
            "the uniform part spans the buffer: {old} of 48 older"
        );
        // Not full yet: the newest are just below `len`.
        let mut r = Replay::new(1, 1, 50);
        for k in 0..20 {
            r.push(&[k as f32], &[0.0], [0.0, 0.0], &[0.0], false, &[]);
        }
        let b = r.sample(&mut rng, 8, (8, 5)).unwrap();
        let obs = b.obs.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        assert!(obs.iter().all(|&x| (15.0..20.0).contains(&x)), "{obs:?}");
    }

    #[test]
    fn a_replay_buffer_restored_from_its_rows_is_the_same_buffer() {
        let mut a = Replay::new(2, 1, 5);
        for k in 0..13 {
            let x = k as f32;
            a.push(
                &[x, -x],
                &[0.5 * x],
                [x * 10.0, -x],
                &[x + 1.0, 0.0],
                k % 4 == 0,
                &[],
            );
        }
        // The last 5 transitions (8..13), the ring wrapped twice.
        let mut b = Replay::new(2, 1, 5);
        b.restore(8, &a.rows(8, 13)).unwrap();
        assert_eq!((b.len, b.next, b.total), (a.len, a.next, a.total));
        assert_eq!((&b.obs, &b.act, &b.task), (&a.obs, &a.act, &a.task));
        assert_eq!(&b.truth, &a.truth);
        assert_eq!((&b.next_obs, &b.done), (&a.next_obs, &a.done));
        // Not full yet: rows from the start.
        let mut d = Replay::new(2, 1, 50);
        for k in 0..13 {
            d.push(
                &[k as f32, 1.0],
                &[0.0],
                [1.0, 2.0],
                &[0.0, 2.0],
                false,
                &[],
            );
        }
        let mut c = Replay::new(2, 1, 50);
        c.restore(0, &d.rows(0, 13)).unwrap();
        assert_eq!(
            (c.len, c.next, c.total, &c.obs),
            (d.len, d.next, d.total, &d.obs)
        );
        // Rows that do not reach back far enough are refused.
        assert!(Replay::new(2, 1, 5).restore(9, &a.rows(9, 13)).is_err());
    }

    #[test]
    fn a_replay_that_keeps_features_saves_restores_and_samples_them() {
        use rand::SeedableRng;
        let filled = |capacity| {
            let mut r = Replay::new(1, 1, capacity);
            r.keep_features(2);
            for k in 0..13 {
                let x = k as f32;
                r.push(
                    &[x],
                    &[0.0],
                    [x, -x],
                    &[x + 1.0],
                    false,
                    &[x, 10.0 * x, 99.0],
                );
            }
            r
        };
        let a = filled(5);
        assert_eq!(a.row_len(), 8);
        assert_eq!(&a.rows(12, 13)[6..], &[12.0, 120.0]);
        for (start, capacity) in [(8, 5), (0, 50)] {
            let mut b = Replay::new(1, 1, capacity);
            b.keep_features(2);
            let src = filled(capacity);
            b.restore(start, &src.rows(start, 13)).unwrap();
            assert_eq!((&b.feat, &b.obs, b.next), (&src.feat, &src.obs, src.next));
        }
        // Each sampled row's features are its transition's.
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(2);
        let batch = a.sample(&mut rng, 16, (0, 0)).unwrap();
        let obs = batch.obs.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        let f = batch.features.unwrap().to_vec2::<f32>().unwrap();
        for (o, f) in obs.iter().zip(&f) {
            assert_eq!(f, &vec![*o, 10.0 * o]);
        }
        // A buffer that keeps none gives none.
        let mut r = Replay::new(1, 1, 4);
        r.push(&[0.0], &[0.0], [0.0, 0.0], &[0.0], false, &[1.0; 6]);
        assert!(r.sample(&mut rng, 2, (0, 0)).unwrap().features.is_none());
        assert_eq!(r.row_len(), 6);
    }
}
