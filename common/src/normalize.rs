//! Observation normalisation by running mean and variance (the learner updates it; the
//! weights message carries it to the actors, which normalise exactly as the learner did).

use serde::{Deserialize, Serialize};

/// Running mean and variance over observations (parallel Welford updates, as
/// stable-baselines3's `RunningMeanStd`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct RunningNorm {
    pub mean: Vec<f64>,
    pub var: Vec<f64>,
    /// Observations seen (starts at a tiny epsilon, as SB3, so the first update is exact
    /// to within it).
    pub count: f64,
    /// Normalised values are clipped to [-clip, clip].
    pub clip: f64,
}

impl RunningNorm {
    pub fn new(dim: usize, clip: f64) -> Self {
        Self {
            mean: vec![0.0; dim],
            var: vec![1.0; dim],
            count: 1e-4,
            clip,
        }
    }

    pub fn dim(&self) -> usize {
        self.mean.len()
    }

    /// Fold in a batch of observations, `rows` of `dim` numbers, flattened.
    pub fn update(&mut self, rows: &[f32]) {
        let d = self.dim();
        let n = rows.len() / d;
        if n == 0 {
            return;
        }
        let mut mean = vec![0.0; d];
        for row in rows.chunks_exact(d) {
            for (m, x) in mean.iter_mut().zip(row) {
                *m += *x as f64;
            }
        }
        mean.iter_mut().for_each(|m| *m /= n as f64);
        let mut var = vec![0.0; d];
        for row in rows.chunks_exact(d) {
            for ((v, m), x) in var.iter_mut().zip(&mean).zip(row) {
                *v += (*x as f64 - m).powi(2);
            }
        }
        var.iter_mut().for_each(|v| *v /= n as f64);
        let (na, nb) = (self.count, n as f64);
        let total = na + nb;
        for i in 0..d {
            let delta = mean[i] - self.mean[i];
            let m2 = self.var[i] * na + var[i] * nb + delta * delta * na * nb / total;
            self.mean[i] += delta * nb / total;
            self.var[i] = m2 / total;
        }
        self.count = total;
    }

    /// Normalise one observation in place.
    pub fn apply(&self, obs: &mut [f32]) {
        for ((x, m), v) in obs.iter_mut().zip(&self.mean).zip(&self.var) {
            let z = (*x as f64 - m) / (v + 1e-8).sqrt();
            *x = z.clamp(-self.clip, self.clip) as f32;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn batches_give_the_mean_and_variance_of_all_rows() {
        // Reference: numpy.mean / numpy.var over all five rows of column 0: [1, 2, 3, 4, 10]
        // mean 4.0, var 10.0; column 1: [0, 0, 0, 0, 5] mean 1.0, var 4.0.
        let mut n = RunningNorm::new(2, 10.0);
        n.update(&[1.0, 0.0, 2.0, 0.0]);
        n.update(&[3.0, 0.0, 4.0, 0.0, 10.0, 5.0]);
        assert!((n.mean[0] - 4.0).abs() < 1e-3, "{:?}", n.mean);
        assert!((n.var[0] - 10.0).abs() < 1e-2, "{:?}", n.var);
        assert!((n.mean[1] - 1.0).abs() < 1e-3);
        assert!((n.var[1] - 4.0).abs() < 1e-2);
        let mut x = [4.0f32, 1001.0];
        n.apply(&mut x);
        assert!(x[0].abs() < 1e-3);
        assert_eq!(x[1], 10.0, "clipped");
    }
}
