//! The state-entropy bonus of PEBBLE's unsupervised pretraining (`shared/method.md`
//! section 6; B-Pref's `compute_state_entropy`): each observation of a batch is rewarded
//! by its distance `d_k` to the k-th nearest neighbour among stored raw observations
//! (k = 5), divided by a running std of those distances: `r = d_k / running_std(d_k)`.
//!
//! Where this differs from B-Pref's `TorchRunningMeanStd` (on purpose):
//! - the statistics start empty (count 0), not at variance 1 with count 1e-4, and a batch's
//!   variance is the population one (ddof 0), not torch's unbiased `var`: the running
//!   values are then exactly the mean and variance of every distance seen;
//! - B-Pref's mean update reads `mean + delta + batch_count / tot_count` (a `+` for a
//!   `*`); here it is the parallel update's `mean + delta * batch_count / tot_count`;
//! - while the std is still 0 (every distance so far equal, or one batch of one), the
//!   distances are returned undivided instead of as infinities.

use std::collections::VecDeque;

use serde::{Deserialize, Serialize};

/// The k-th smallest Euclidean distance (k counts from 1) from each row of `batch` to the
/// rows of `pool` (both flattened, `dim` numbers a row). If `pool` has fewer than `k` rows
/// the largest distance to them is used, and 0 if it has none.
///
/// A batch row that is itself in `pool` is its own nearest neighbour at distance 0; to skip
/// it, ask for `k + 1` (as B-Pref does, whose batch is always drawn from the pool).
///
/// Cost: the pool is copied once per call into tiles of [`TILE`] rows stored column by
/// column, so that one batch row is compared with a whole tile at once (independent sums
/// the compiler keeps in vector registers), and a tile's distances then go through a
/// sorted array of the `k` smallest (no allocation per pair). 256 rows against 10,000 of
/// 25 numbers: `knn_timing` (k = 6) prints the figure.
///
/// # Panics
/// If `dim` or `k` is 0, or `batch` or `pool` is not whole rows.
pub fn knn_distances(batch: &[f32], pool: &[f32], dim: usize, k: usize) -> Vec<f32> {
    assert!(dim > 0, "knn_distances needs dim >= 1, got {dim}");
    assert!(k > 0, "knn_distances counts neighbours from 1, got k = {k}");
    assert!(
        batch.len().is_multiple_of(dim) && pool.len().is_multiple_of(dim),
        "knn_distances: batch of {} and pool of {} numbers are not whole rows of {dim}",
        batch.len(),
        pool.len()
    );
    let rows = pool.len() / dim;
    // NOTE: with fewer than k rows in the pool, the k-th neighbour is the farthest one.
    let m = k.min(rows);
    if m == 0 {
        return vec![0.0; batch.len() / dim];
    }
    let tiles = tiled(pool, dim);
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: the CPU has AVX2, checked just above.
        return unsafe { nearest_avx2(batch, &tiles, dim, m) };
    }
    nearest(batch, &tiles, dim, m)
}

/// [`nearest`] compiled for AVX2 (twice the lanes of the x86-64 baseline). No FMA: each
/// sum is rounded exactly as the baseline's, so the results are the same bits.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn nearest_avx2(batch: &[f32], tiles: &[f32], dim: usize, m: usize) -> Vec<f32> {
    nearest(batch, tiles, dim, m)
}

/// The m-th smallest distance from each batch row to the tiled pool (m >= 1). Plain loops
/// throughout: a closure or iterator adaptor compiled apart would not get AVX2.
#[inline(always)]
fn nearest(batch: &[f32], tiles: &[f32], dim: usize, m: usize) -> Vec<f32> {
    let mut out = Vec::with_capacity(batch.len() / dim);
    // The m smallest squared distances so far, ascending.
    let mut best = vec![f32::INFINITY; m];
    for q in batch.chunks_exact(dim) {
        best.fill(f32::INFINITY);
        for tile in tiles.chunks_exact(dim * TILE) {
            let mut acc = [0.0f32; TILE];
            for c in 0..dim {
                let x = q[c];
                let col = &tile[c * TILE..c * TILE + TILE];
                for j in 0..TILE {
                    let d = x - col[j];
                    acc[j] += d * d;
                }
            }
            // NOTE: most tiles hold no new neighbour once `best` has settled; their
            // minimum tells at once.
            let mut low = acc[0];
            for &d in &acc[1..] {
                low = if d < low { d } else { low };
            }
            if low >= best[m - 1] {
                continue;
            }
            for d in acc {
                if d < best[m - 1] {
                    let mut i = m - 1;
                    while i > 0 && best[i - 1] > d {
                        best[i] = best[i - 1];
                        i -= 1;
                    }
                    best[i] = d;
                }
            }
        }
        out.push(best[m - 1].sqrt());
    }
    out
}

/// Pool rows compared with one batch row at once.
const TILE: usize = 16;

/// The pool's rows in tiles of [`TILE`], each stored column by column (`dim` columns of
/// `TILE` numbers). The last tile is padded with infinities, which are never among the
/// nearest: a finite batch row is infinitely far from them.
fn tiled(pool: &[f32], dim: usize) -> Vec<f32> {
    let rows = pool.len() / dim;
    let mut out = vec![f32::INFINITY; rows.div_ceil(TILE) * TILE * dim];
    for (r, row) in pool.chunks_exact(dim).enumerate() {
        let tile = &mut out[(r / TILE) * TILE * dim..][..TILE * dim];
        for (c, &x) in row.iter().enumerate() {
            tile[c * TILE + r % TILE] = x;
        }
    }
    out
}

/// Running mean and (population) variance of a stream of numbers, merged batch by batch
/// (Chan et al.'s parallel update, as B-Pref's `RunningMeanStd`; see the module doc for
/// where it differs).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct RunningStd {
    pub mean: f64,
    pub var: f64,
    /// Numbers seen.
    pub count: f64,
}

impl RunningStd {
    /// Fold in a batch (an empty one changes nothing).
    pub fn update(&mut self, xs: &[f32]) {
        if xs.is_empty() {
            return;
        }
        let nb = xs.len() as f64;
        let mean = xs.iter().map(|&x| x as f64).sum::<f64>() / nb;
        let var = xs.iter().map(|&x| (x as f64 - mean).powi(2)).sum::<f64>() / nb;
        let (na, total) = (self.count, self.count + xs.len() as f64);
        let delta = mean - self.mean;
        let m2 = self.var * na + var * nb + delta * delta * na * nb / total;
        self.mean += delta * nb / total;
        self.var = m2 / total;
        self.count = total;
    }

    pub fn std(&self) -> f64 {
        self.var.sqrt()
    }
}

/// The state-entropy bonus: a FIFO pool of raw observations, `k`, and the running std of
/// the distances it has handed out.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct StateEntropy {
    /// Which nearest neighbour's distance is the bonus (5 in PEBBLE).
    pub k: usize,
    capacity: usize,
    dim: usize,
    /// Up to `capacity` rows of `dim` numbers, oldest first.
    pool: VecDeque<f32>,
    stats: RunningStd,
}

impl StateEntropy {
    /// An empty pool of at most `capacity` observations of `dim` numbers.
    ///
    /// # Panics
    /// If `dim`, `k` or `capacity` is 0.
    pub fn new(dim: usize, k: usize, capacity: usize) -> Self {
        assert!(dim > 0, "state entropy needs dim >= 1, got {dim}");
        assert!(k > 0, "state entropy counts neighbours from 1, got k = {k}");
        assert!(
            capacity > 0,
            "state entropy pool capacity must be at least 1, got {capacity}"
        );
        Self {
            k,
            capacity,
            dim,
            pool: VecDeque::new(),
            stats: RunningStd::default(),
        }
    }

    /// Store rows of raw observations (flattened), dropping the oldest past the capacity.
    ///
    /// # Panics
    /// If `obs` is not whole rows.
    pub fn add(&mut self, obs: &[f32]) {
        assert!(
            obs.len().is_multiple_of(self.dim),
            "state entropy: {} numbers are not whole observations of {}",
            obs.len(),
            self.dim
        );
        // Only the last `capacity` rows can stay.
        let keep = obs.len().min(self.capacity * self.dim);
        self.pool.extend(&obs[obs.len() - keep..]);
        let excess = self.pool.len().saturating_sub(self.capacity * self.dim);
        self.pool.drain(..excess);
    }

    /// The bonus `d_k / running_std(d_k)` of each row of `batch` (raw observations). The
    /// running std is updated with this batch's distances first, so the first batch is
    /// divided by its own std. With `batch_in_pool` (the batch was drawn from the pool)
    /// each row's own copy is skipped by taking the (k+1)-th neighbour.
    pub fn reward(&mut self, batch: &[f32], batch_in_pool: bool) -> Vec<f32> {
        // NOTE: a row drawn from the pool is its own nearest neighbour at distance 0.
        let k = self.k + batch_in_pool as usize;
        // The pool as one slice (a no-op unless it wrapped since the last call).
        let pool = self.pool.make_contiguous();
        let mut d = knn_distances(batch, pool, self.dim, k);
        self.stats.update(&d);
        let std = self.stats.std();
        // NOTE: std is 0 until two different distances were seen; divide by 1 then, not
        // by 0.
        if std > 0.0 {
            d.iter_mut().for_each(|x| *x = (*x as f64 / std) as f32);
        }
        d
    }

    /// Observations in the pool.
    pub fn pool_len(&self) -> usize {
        self.pool.len() / self.dim
    }

    /// The running statistics of the distances (for logging).
    pub fn stats(&self) -> &RunningStd {
        &self.stats
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    fn assert_close(got: &[f32], want: &[f32]) {
        assert_eq!(got.len(), want.len(), "{got:?} vs {want:?}");
        for (g, w) in got.iter().zip(want) {
            assert!((g - w).abs() < 1e-5, "got {got:?}, want {want:?}");
        }
    }

    /// 1-D pool {0, 1, 3, 7, 8}. Distances by hand, sorted:
    ///   from 2:   1, 1, 2, 5, 6
    ///   from 6.5: 0.5, 1.5, 3.5, 5.5, 6.5
    ///   from 0:   0, 1, 3, 7, 8      (0 is in the pool)
    const POOL_1D: [f32; 5] = [0.0, 1.0, 3.0, 7.0, 8.0];

    #[test]
    fn knn_in_one_dimension() {
        let batch = [2.0, 6.5, 0.0];
        assert_close(&knn_distances(&batch, &POOL_1D, 1, 1), &[1.0, 0.5, 0.0]);
        assert_close(&knn_distances(&batch, &POOL_1D, 1, 2), &[1.0, 1.5, 1.0]);
        assert_close(&knn_distances(&batch, &POOL_1D, 1, 3), &[2.0, 3.5, 3.0]);
    }

    #[test]
    fn knn_skips_the_point_itself_with_k_plus_one() {
        // The pool against itself. Sorted distances from each point:
        //   0: 0 1 3 7 8 | 1: 0 1 2 6 7 | 3: 0 2 3 4 5 | 7: 0 1 4 6 7 | 8: 0 1 5 7 8
        // k = 1 skipping itself is the 2nd value, k = 2 the 3rd.
        assert_close(&knn_distances(&POOL_1D, &POOL_1D, 1, 1), &[0.0; 5]);
        assert_close(
            &knn_distances(&POOL_1D, &POOL_1D, 1, 2),
            &[1.0, 1.0, 2.0, 1.0, 1.0],
        );
        assert_close(
            &knn_distances(&POOL_1D, &POOL_1D, 1, 3),
            &[3.0, 2.0, 3.0, 4.0, 5.0],
        );
        // The same through StateEntropy's flag (the std division is checked elsewhere).
        let mut se = StateEntropy::new(1, 1, 10);
        se.add(&POOL_1D);
        let r = se.reward(&POOL_1D, true);
        let std = se.stats().std() as f32;
        assert_close(&r, &[1.0 / std, 1.0 / std, 2.0 / std, 1.0 / std, 1.0 / std]);
    }

    #[test]
    fn knn_in_two_dimensions() {
        // Pool (0,0), (3,4), (1,1), (-2,0). Distances by hand:
        //   from (2,1): sqrt5 = 2.236068, sqrt10 = 3.162278, 1, sqrt17 = 4.123106
        //               sorted 1, 2.236068, 3.162278, 4.123106
        //   from (0,0): 0, 5, sqrt2 = 1.414214, 2 -> sorted 0, 1.414214, 2, 5
        let pool = [0.0, 0.0, 3.0, 4.0, 1.0, 1.0, -2.0, 0.0];
        let batch = [2.0, 1.0, 0.0, 0.0];
        assert_close(&knn_distances(&batch, &pool, 2, 1), &[1.0, 0.0]);
        assert_close(
            &knn_distances(&batch, &pool, 2, 2),
            &[2.236068, std::f32::consts::SQRT_2],
        );
        // (0,0) is in the pool: skipping itself, its 2nd neighbour is the 3rd value.
        assert_close(&knn_distances(&batch, &pool, 2, 3), &[3.162278, 2.0]);
    }

    #[test]
    fn knn_with_fewer_pool_rows_than_k_takes_the_farthest() {
        assert_close(&knn_distances(&[3.0, -1.0], &[0.0, 1.0], 1, 5), &[3.0, 2.0]);
        assert_close(&knn_distances(&[3.0, -1.0], &[], 1, 5), &[0.0, 0.0]);
        assert!(knn_distances(&[], &POOL_1D, 1, 2).is_empty());
    }

    #[test]
    fn knn_matches_a_full_sort_at_every_width() {
        // The tiled kernel against sorting every distance, for pools below, at and past a
        // whole tile and widths from 1 to 25 (the feeding observation).
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        for dim in [1, 7, 8, 9, 16, 25] {
            for pool_rows in [5, 16, 41] {
                let mut rows = |n: usize| -> Vec<f32> {
                    (0..n * dim).map(|_| rng.random_range(-2.0..2.0)).collect()
                };
                let (batch, pool) = (rows(13), rows(pool_rows));
                for k in [1, 2, 5] {
                    let want: Vec<f32> = batch
                        .chunks_exact(dim)
                        .map(|q| {
                            let mut d: Vec<f64> = pool
                                .chunks_exact(dim)
                                .map(|p| {
                                    q.iter()
                                        .zip(p)
                                        .map(|(a, b)| ((a - b) as f64).powi(2))
                                        .sum::<f64>()
                                        .sqrt()
                                })
                                .collect();
                            d.sort_by(f64::total_cmp);
                            d[k - 1] as f32
                        })
                        .collect();
                    assert_close(&knn_distances(&batch, &pool, dim, k), &want);
                }
            }
        }
    }

    #[test]
    fn running_std_merges_batches_as_one_two_pass_computation() {
        // Batches [1,2,3,4], [10,20], [5]; all seven: sum 45, sum of squares 555.
        //   mean = 45/7 = 6.428571;  var = 555/7 - (45/7)^2 = 79.285714 - 41.326531
        //        = 37.959184;        std = 6.161102
        let batches: [&[f32]; 3] = [&[1.0, 2.0, 3.0, 4.0], &[10.0, 20.0], &[5.0]];
        let mut s = RunningStd::default();
        for b in batches {
            s.update(b);
        }
        s.update(&[]);
        let all: Vec<f64> = batches.concat().iter().map(|&x| x as f64).collect();
        let mean = all.iter().sum::<f64>() / 7.0;
        let var = all.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / 7.0;
        assert!(
            (s.mean - mean).abs() < 1e-12 && (s.var - var).abs() < 1e-12,
            "{s:?}"
        );
        assert!((s.mean - 6.428571).abs() < 1e-6 && (s.var - 37.959184).abs() < 1e-6);
        assert!((s.std() - 6.161102).abs() < 1e-6);
        assert_eq!(s.count, 7.0);
    }

    #[test]
    fn reward_is_the_distance_over_the_running_std() {
        // Pool {0, 1, 3, 7, 8}, k = 1.
        // Batch [2, 6.5] (not in the pool): d = [1, 0.5]; stats over {1, 0.5}:
        //   mean 0.75, var (0.25^2 + 0.25^2)/2 = 0.0625, std 0.25 -> reward [4, 2].
        // Batch [0, 3] (in the pool, so the 2nd neighbour): d = [1, 2]; stats over
        //   {1, 0.5, 1, 2}: mean 1.125, var (0.125^2 + 0.625^2 + 0.125^2 + 0.875^2)/4
        //   = 1.1875/4 = 0.296875, std 0.544862 -> reward [1.835326, 3.670652].
        let mut se = StateEntropy::new(1, 1, 10);
        se.add(&POOL_1D);
        assert_close(&se.reward(&[2.0, 6.5], false), &[4.0, 2.0]);
        assert_close(&se.reward(&[0.0, 3.0], true), &[1.835326, 3.670652]);
        assert_eq!(se.stats().count, 4.0);
        // Equal distances so far: std 0, the distances come back undivided.
        let mut flat = StateEntropy::new(1, 1, 10);
        flat.add(&[0.0, 10.0]);
        assert_eq!(flat.reward(&[5.0], false), [5.0]);
    }

    #[test]
    fn the_pool_keeps_the_newest_observations() {
        let mut se = StateEntropy::new(1, 1, 3);
        se.add(&[0.0, 1.0]);
        se.add(&[2.0, 3.0, 4.0]);
        assert_eq!(se.pool_len(), 3);
        // 0 and 1 are gone: from 0 the nearest is 2, the farthest (3rd) is 4.
        assert_eq!(
            knn_distances(&[0.0], se.pool.make_contiguous(), 1, 1),
            [2.0]
        );
        assert_eq!(
            knn_distances(&[0.0], se.pool.make_contiguous(), 1, 3),
            [4.0]
        );
        // More rows than the capacity at once: the last three stay.
        se.add(&[10.0, 11.0, 12.0, 13.0, 14.0]);
        assert_eq!(
            se.pool.iter().copied().collect::<Vec<_>>(),
            [12.0, 13.0, 14.0]
        );
        let mut two_d = StateEntropy::new(2, 5, 2);
        two_d.add(&[0.0, 0.0, 1.0, 1.0, 2.0, 2.0]);
        assert_eq!(two_d.pool_len(), 2);
        assert_eq!(
            two_d.pool.iter().copied().collect::<Vec<_>>(),
            [1.0, 1.0, 2.0, 2.0]
        );
    }

    /// `cargo test --release -p pbrl-learner --lib knn_timing -- --ignored --nocapture`
    #[test]
    #[ignore = "timing, run by hand in release"]
    fn knn_timing() {
        let (dim, n, rows) = (25, 256, 10_000);
        let mut rng = ChaCha8Rng::seed_from_u64(0);
        let pool: Vec<f32> = (0..rows * dim)
            .map(|_| rng.random_range(-1.0..1.0))
            .collect();
        let batch: Vec<f32> = (0..n * dim).map(|_| rng.random_range(-1.0..1.0)).collect();
        let mut sum = 0.0;
        let reps = 100;
        let start = std::time::Instant::now();
        for _ in 0..reps {
            sum += knn_distances(&batch, &pool, dim, 6).iter().sum::<f32>();
        }
        let ms = start.elapsed().as_secs_f64() * 1e3 / reps as f64;
        println!(
            "knn_distances: {n} x {rows} rows of {dim}, k 6: {ms:.2} ms per call (checksum {sum})"
        );
    }
}
