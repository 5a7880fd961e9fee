//! Training the ensemble on D: the Bradley-Terry loss, each member's data order, its
//! gradients by hand over chunks of whole pairs, the Adam steps, early stopping, and the
//! accuracy that stops it.

use candle_core::{Result, Tensor};
use rand::seq::SliceRandom;
use rand::Rng;

use super::*;

/// The mean over pairs of the cross-entropy between the Bradley-Terry probability
/// `P[second > first] = sigmoid(sum_second - sum_first)` and `target`, computed through
/// log-softmax: `(1 - p) softplus(d) + p softplus(-d)` with `d = sum_second - sum_first`.
pub fn bradley_terry_loss(
    sum_first: &Tensor,
    sum_second: &Tensor,
    target: &Tensor,
) -> Result<Tensor> {
    let d = (sum_second - sum_first)?;
    let p = target.reshape(d.shape())?;
    // -log softmax(...)[0] = softplus(d), -log softmax(...)[1] = softplus(-d).
    let to_first = pbrl_common::nets::softplus(&d)?;
    let to_second = pbrl_common::nets::softplus(&d.neg()?)?;
    ((p.affine(-1.0, 1.0)? * to_first)? + (p * to_second)?)?.mean_all()
}

/// log(1 + exp(x)), stable.
fn softplus(x: f64) -> f64 {
    if x > 0.0 {
        x + (-x).exp().ln_1p()
    } else {
        x.exp().ln_1p()
    }
}

/// One temporal crop of label `label` of D: both sides' steps `starts[side] .. + len`.
#[derive(Clone, Copy, Debug)]
pub(super) struct Crop {
    label: usize,
    starts: [usize; 2],
    len: usize,
}

impl Crop {
    /// The crop as a label of its own: the two sides cut out, the label's target.
    fn cut(&self, data: &[Labelled], model: &RewardModel) -> Result<Labelled> {
        let l = &data[self.label];
        let side = |s: &Segment, start: usize| -> Result<Arc<Segment>> {
            Ok(Arc::new(s.cut(start, self.len, model.steps(s)?)))
        };
        Ok(Labelled {
            first: side(&l.first, self.starts[0])?,
            second: side(&l.second, self.starts[1])?,
            target: l.target,
        })
    }
}

impl RewardModel {
    /// The mean over members of the fraction of `data`'s labels the member gets right
    /// (`P > 0.5` exactly when the second is preferred). Equal labels are left out; with
    /// none left the accuracy is 1.
    pub fn accuracy(&self, data: &[Labelled]) -> Result<f64> {
        let hard: Vec<&Labelled> = data.iter().filter(|l| !l.is_equal()).collect();
        if hard.is_empty() {
            return Ok(1.0);
        }
        let segs: Vec<&Segment> = hard.iter().flat_map(|l| [&*l.first, &*l.second]).collect();
        let sums = self.segment_returns(&segs)?;
        let q = sums.len() as f64;
        Ok(sums
            .iter()
            .map(|s| {
                let right = hard
                    .iter()
                    .zip(s.chunks_exact(2))
                    .filter(|(l, p)| (p[1] > p[0]) == (l.target > 0.5))
                    .count();
                right as f64 / hard.len() as f64
            })
            .sum::<f64>()
            / q)
    }

    /// `crops` temporal crops of each label of `data`, drawn label by label: both sides
    /// cut to one length drawn in `[crop_min, crop_max]` of the shorter side (at least one
    /// step), each at its own uniform start; the label's target goes with them. A crop is
    /// its bounds only ([`Crop`]): a training cuts the crops of each minibatch as it reaches
    /// them, so its memory does not grow with `crops` times the labels.
    pub(super) fn draw_crops(&mut self, data: &[Labelled]) -> Result<Vec<Crop>> {
        let (lo, hi) = (self.cfg.crop_min, self.cfg.crop_max);
        if !(0.0 < lo && lo <= hi && hi <= 1.0) {
            candle_core::bail!(
                "reward_crop_min {lo} and reward_crop_max {hi} must satisfy 0 < min <= max <= 1"
            );
        }
        let mut out = Vec::with_capacity(data.len() * self.cfg.crops);
        for (label, l) in data.iter().enumerate() {
            let (n0, n1) = (self.steps(&l.first)?, self.steps(&l.second)?);
            let shorter = n0.min(n1) as f64;
            let (min_len, max_len) = (
                ((lo * shorter).round() as usize).max(1),
                ((hi * shorter).round() as usize).max(1),
            );
            for _ in 0..self.cfg.crops {
                let len = self.rng.random_range(min_len..=max_len.max(min_len));
                let first = self.rng.random_range(0..=n0 - len);
                let second = self.rng.random_range(0..=n1 - len);
                out.push(Crop {
                    label,
                    starts: [first, second],
                    len,
                });
            }
        }
        Ok(out)
    }

    /// `data` and, after it, its crops ([`Self::draw_crops`]) cut out.
    #[cfg(test)]
    pub(super) fn with_crops(&mut self, data: &[Labelled]) -> Result<Vec<Labelled>> {
        let crops = self.draw_crops(data)?;
        let mut out = data.to_vec();
        for c in &crops {
            out.push(c.cut(data, self)?);
        }
        Ok(out)
    }

    /// Each member's data order for one epoch over `n` pairs, drawn in member order.
    pub(super) fn draw_orders(&mut self, n: usize) -> Vec<Vec<usize>> {
        (0..self.nets.len())
            .map(|_| match self.cfg.resample {
                Resample::Bootstrap => (0..n).map(|_| self.rng.random_range(0..n)).collect(),
                Resample::Shuffle => {
                    let mut v: Vec<usize> = (0..n).collect();
                    v.shuffle(&mut self.rng);
                    v
                }
            })
            .collect()
    }

    /// Member `m`'s gradients of the mean cross-entropy over `pairs`, by hand, in chunks
    /// of whole pairs of up to `chunk_rows` rows (each pair's loss depends on its own two
    /// sums only, so the chunks' gradients add up to the minibatch's). Also the summed
    /// loss, and the right answers among the hard labels and their count, before the step.
    #[cfg(test)]
    pub(super) fn member_gradients(
        &self,
        m: usize,
        pairs: &[&Labelled],
        chunk_rows: usize,
    ) -> Result<(GradStore, f64, usize, usize)> {
        self.member_gradients_counting(m, pairs, None, chunk_rows)
    }

    /// [`Self::member_gradients`], the right answers counted only over the pairs that
    /// `counted` marks (all when `None`).
    fn member_gradients_counting(
        &self,
        m: usize,
        pairs: &[&Labelled],
        counted: Option<&[bool]>,
        chunk_rows: usize,
    ) -> Result<(GradStore, f64, usize, usize)> {
        let net = &self.nets[m].net;
        let inv_b = 1.0 / pairs.len() as f64;
        let mut acc = Grads::new(net)?;
        let (mut loss, mut right, mut hard) = (0f64, 0usize, 0usize);
        let mut start = 0;
        while start < pairs.len() {
            // Whole pairs up to chunk_rows rows, at least one.
            let pair_rows = |l: &Labelled| -> Result<[usize; 2]> {
                Ok([self.steps(&l.first)?, self.steps(&l.second)?])
            };
            let mut steps = vec![pair_rows(pairs[start])?];
            let mut rows: usize = steps[0].iter().sum();
            let mut end = start + 1;
            while end < pairs.len() {
                let s = pair_rows(pairs[end])?;
                if rows + s[0] + s[1] > chunk_rows {
                    break;
                }
                rows += s[0] + s[1];
                steps.push(s);
                end += 1;
            }
            let mut x = Vec::with_capacity(rows * self.width());
            for l in &pairs[start..end] {
                self.push_segment(&l.first, &mut x);
                self.push_segment(&l.second, &mut x);
            }
            let mut tape = Vec::with_capacity(net.layers.len());
            let r = net
                .run(&self.input_tensor(x)?, Some(&mut tape))?
                .flatten_all()?
                .to_vec1::<f32>()?;

            // The Bradley-Terry loss of each pair and its gradient with respect to the two
            // sums: dCE/d sum_second = P - p = -dCE/d sum_first.
            let mut dz = Vec::with_capacity(rows);
            let mut at = 0;
            for (k, (l, s)) in pairs[start..end].iter().zip(&steps).enumerate() {
                let counts = counted.is_none_or(|c| c[start + k]);
                let r0 = &r[at..at + s[0]];
                let r1 = &r[at + s[0]..at + s[0] + s[1]];
                at += s[0] + s[1];
                // The anchor's sums are constants of the pair: they move the logit, not the
                // gradient's path.
                let d = (r1.iter().sum::<f32>() - r0.iter().sum::<f32>()
                    + self.anchor_sum(&l.second)
                    - self.anchor_sum(&l.first)) as f64;
                let p = l.target as f64;
                loss += (1.0 - p) * softplus(d) + p * softplus(-d);
                if counts && !l.is_equal() {
                    hard += 1;
                    right += usize::from((d > 0.0) == (p > 0.5));
                }
                let g = ((1.0 / (1.0 + (-d).exp()) - p) * inv_b) as f32;
                // Through tanh: d r / d z = 1 - r^2.
                dz.extend(r0.iter().map(|r| -g * (1.0 - r * r)));
                dz.extend(r1.iter().map(|r| g * (1.0 - r * r)));
            }
            net.backward(&tape, dz, &mut acc)?;
            start = end;
        }
        Ok((acc.into_store(net)?, loss, right, hard))
    }

    /// Fit the normaliser to D's observations, every distinct trajectory once (unless it
    /// came with a prior and is kept).
    fn refit_normaliser(&mut self, data: &[Labelled]) {
        if self.keep_norm {
            return;
        }
        let mut seen = HashSet::new();
        let segs: Vec<&Segment> = data
            .iter()
            .flat_map(|l| [&l.first, &l.second])
            .filter(|s| seen.insert(Arc::as_ptr(s)))
            .map(|s| &**s)
            .collect();
        self.norm = ObsNorm::fit(segs.iter().copied(), self.obs_dim);
    }

    /// One training session on D (the whole preference dataset so far).
    ///
    /// The normaliser is refitted to D's observations first and then frozen until the
    /// next session. Each epoch every member draws its own order of D (bootstrap or
    /// shuffle) and takes one Adam step per minibatch of `batch` pairs. An empty D leaves
    /// the model as it was.
    pub fn train(&mut self, data: &[Labelled]) -> Result<TrainStats> {
        self.train_with(data, &[])
    }

    /// [`Self::train`] on the labels and, beside them, `pseudo`: pairs labelled by the
    /// ensemble itself (SURF). They train like labels, but the accuracy (what stops the
    /// training and what it reports) counts the labels and their crops only: the pseudo
    /// ones are right by construction.
    pub fn train_with(&mut self, labels: &[Labelled], pseudo: &[Labelled]) -> Result<TrainStats> {
        let real = labels.len();
        let joined;
        let data = if pseudo.is_empty() {
            labels
        } else {
            joined = [labels, pseudo].concat();
            &joined[..]
        };
        for (i, l) in data.iter().enumerate() {
            self.steps(&l.first)?;
            self.steps(&l.second)?;
            if !(0.0..=1.0).contains(&l.target) {
                candle_core::bail!("label {i} has target {}, outside [0, 1]", l.target);
            }
        }
        if data.is_empty() {
            return Ok(TrainStats {
                epochs: 0,
                pairs: 0,
                loss: 0.0,
                accuracy: 1.0,
            });
        }
        self.refit_normaliser(data);
        let crops = if self.cfg.crops > 0 {
            self.draw_crops(data)?
        } else {
            Vec::new()
        };

        let n = data.len() + crops.len();
        // Crops follow D, each label's `crops` in D's order: a crop counts as its label.
        let base = labels.len() + pseudo.len();
        let counted: Vec<bool> = (0..n)
            .map(|i| {
                if i < base {
                    i < real
                } else {
                    (i - base) / self.cfg.crops.max(1) < real
                }
            })
            .collect();
        let q = self.nets.len() as f64;
        let mut stats = TrainStats {
            epochs: 0,
            pairs: 0,
            loss: 0.0,
            accuracy: 0.0,
        };
        // Pairs each member may still train on in this training.
        let mut left = match self.cfg.max_pairs {
            0 => usize::MAX,
            cap => cap,
        };
        for epoch in 1..=self.cfg.max_epochs {
            if left == 0 {
                break;
            }
            let mut orders = self.draw_orders(n);
            // NOTE: the last epoch within the bound is cut short, each member keeping the
            // start of its own order (a bootstrap draw or a shuffle either way).
            for order in &mut orders {
                order.truncate(left);
            }
            left -= orders[0].len();
            let (mut loss, mut accuracy) = (0.0, 0.0);
            for (m, order) in orders.iter().enumerate() {
                let (mut member_loss, mut right, mut hard) = (0.0, 0, 0);
                for idx in order.chunks(self.cfg.batch) {
                    // Pair i is D's i-th (its Arcs shared), or past D, crop i - |D| cut now.
                    let batch: Vec<Labelled> = idx
                        .iter()
                        .map(|&i| match data.get(i) {
                            Some(l) => Ok(l.clone()),
                            None => crops[i - data.len()].cut(data, self),
                        })
                        .collect::<Result<_>>()?;
                    let pairs: Vec<&Labelled> = batch.iter().collect();
                    let mask: Vec<bool> = idx.iter().map(|&i| counted[i]).collect();
                    let (grads, l, r, h) =
                        self.member_gradients_counting(m, &pairs, Some(&mask), CHUNK_ROWS)?;
                    self.opts[m].step(&grads)?;
                    member_loss += l;
                    right += r;
                    hard += h;
                }
                loss += member_loss / order.len() as f64;
                accuracy += if hard == 0 {
                    1.0
                } else {
                    right as f64 / hard as f64
                };
            }
            stats = TrainStats {
                epochs: epoch,
                pairs: stats.pairs + orders[0].len(),
                loss: loss / q,
                accuracy: accuracy / q,
            };
            // NOTE: the accuracy is counted as B-Pref counts it: over the pairs each member
            // drew this epoch (bootstrap draws included), each minibatch judged just before
            // its own step. An extra pass over D for the exact figure would cost a third
            // more than the epoch's training; `accuracy` gives it when wanted.
            if stats.accuracy > self.cfg.stop_accuracy {
                break;
            }
        }
        self.trained = true;
        Ok(stats)
    }
}
