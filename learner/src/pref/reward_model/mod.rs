//! The reward ensemble of PEBBLE and PrefPPO (`shared/method.md` section 2): `q` MLPs over
//! (normalised observation, clipped action), each step's reward through tanh, trained on
//! the preference dataset D with a Bradley-Terry model over whole trajectories:
//!
//! `P[second > first] = softmax([sum_t r(first), sum_t r(second)])[1]`,
//!
//! cross-entropy against the label (0, 1, or 0.5 for "equal"), summed over members. The
//! reward the policy sees is the mean over members (paper Eq. 3).
//!
//! A session's training ([`RewardModel::train`]): fit the observation normaliser to D and
//! freeze it, then up to `max_epochs` passes over D, each member in its own order
//! (bootstrap or shuffle), minibatches of `batch` pairs, one Adam per member; stop early
//! once the ensemble's accuracy exceeds `stop_accuracy`.
//!
//! Speed: a 200-step trajectory is 200 network rows, so a minibatch of 256 pairs is 102,400
//! rows through each member. The gradients are taken by hand (forward with a tape, then
//! backward, as `nets::Mlp` does for SAC), a few pairs at a time so the tape stays in
//! cache, with the bias and activation work done in place in one pass.

use std::collections::HashSet;
use std::sync::Arc;

use candle_core::backprop::GradStore;
use candle_core::{DType, Device, Result, Tensor, D};
use candle_nn::{VarBuilder, VarMap};
use pbrl_common::nets::{export, import, Owned};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use pbrl_common::trajectory::FEATURES;

use crate::optim::{Adam, AdamState};
use crate::state::RngState;

mod net;
#[cfg(test)]
mod tests;
mod train;

use net::Grads;
pub use net::RewardNet;
pub use train::bradley_terry_loss;

/// Negative slope of the hidden layers' LeakyReLU (PyTorch's default).
pub const LEAKY_SLOPE: f64 = 0.01;
/// Normalised observations are clipped to [-OBS_CLIP, OBS_CLIP].
pub const OBS_CLIP: f32 = 10.0;
/// Floor of the normaliser's standard deviation (a constant observation dimension).
pub const STD_FLOOR: f64 = 1e-6;
/// Network rows per forward/backward chunk: whole pairs are grouped up to this many rows.
const CHUNK_ROWS: usize = 1024;

/// How each member draws its data order for an epoch.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "kebab-case")]
pub enum Resample {
    /// |D| pairs drawn with replacement (the paper).
    Bootstrap,
    /// A permutation of D (the authors' code).
    Shuffle,
}

/// The reward ensemble's settings (defaults from `shared/method.md` section 2, but the
/// members' size: see `hidden`). Each is a flag of `pbrl train` (`--reward-...`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, clap::Args)]
pub struct RewardModelConfig {
    /// Reward ensemble: members q.
    #[arg(id = "reward_members", long = "reward-members", default_value_t = 3)]
    pub members: usize,
    /// Reward ensemble: hidden layer sizes of each member (LeakyReLU between them; the
    /// authors' 3x256 is the `paper` preset, about 4x the cost of training on 2 cores).
    #[arg(id = "reward_hidden", long = "reward-hidden", value_delimiter = ',', default_values_t = [64, 64, 64])]
    pub hidden: Vec<usize>,
    /// Reward ensemble: Adam learning rate of each member.
    #[arg(id = "reward_lr", long = "reward-lr", default_value_t = 3e-4)]
    pub lr: f64,
    /// Reward ensemble: pairs per minibatch.
    #[arg(id = "reward_batch", long = "reward-batch", default_value_t = 256)]
    pub batch: usize,
    /// Reward ensemble: most passes over D per training.
    #[arg(id = "reward_epochs", long = "reward-epochs", default_value_t = 50)]
    pub max_epochs: usize,
    /// Reward ensemble: stop a training once the mean accuracy on D exceeds this.
    #[arg(
        id = "reward_stop_accuracy",
        long = "reward-stop-accuracy",
        default_value_t = 0.97
    )]
    pub stop_accuracy: f64,
    /// Reward ensemble: most pairs each member trains on in one training, over all its
    /// epochs (0: no bound). It bounds a training's cost as D grows: one pair of 200-step
    /// trajectories costs about 0.9 ms for three 3x64 members on this machine kind, so
    /// the default costs about 4 s per training, where the authors' 50 epochs over D cost
    /// 5-30 s. Measured on feeding (Decoupled PEBBLE, 3 seeds at 1M env steps): 4,096
    /// pairs give success 0.70 where 1,024 give 0.60, at the same preference return.
    /// PrefPPO's default is 1,024 (its sessions come 3 s apart at PPO's pace).
    #[arg(
        id = "reward_max_pairs",
        long = "reward-max-pairs",
        default_value_t = 4096
    )]
    #[serde(default)]
    pub max_pairs: usize,
    /// Reward ensemble: each member's data per epoch, resampled with replacement
    /// (bootstrap, the paper) or shuffled (the authors' code).
    #[arg(
        id = "reward_resample",
        long = "reward-resample",
        value_enum,
        default_value = "bootstrap"
    )]
    pub resample: Resample,
    /// Reward ensemble: each label also trains as this many temporal crops of its pair,
    /// drawn afresh at every training (QPA's and SURF's augmentation: a sub-snippet of
    /// each side, both the same length, independent starts; 0: off). With
    /// `--reward-max-pairs` the cost of a training stays the same.
    #[arg(id = "reward_crops", long = "reward-crops", default_value_t = 20)]
    #[serde(default)]
    pub crops: usize,
    /// Reward ensemble: a crop's length, as shares of the shorter side, drawn uniformly
    /// in [min, max] (QPA: 35-45 steps of 50).
    #[arg(
        id = "reward_crop_min",
        long = "reward-crop-min",
        default_value_t = 0.7
    )]
    #[serde(default = "crop_min")]
    pub crop_min: f64,
    #[arg(
        id = "reward_crop_max",
        long = "reward-crop-max",
        default_value_t = 0.9
    )]
    #[serde(default = "crop_max")]
    pub crop_max: f64,
    /// Reward ensemble: model the person's reward as `r_hat + C r_task` and learn only
    /// r_hat (task-anchored Bradley-Terry: the teacher's preference already contains the
    /// task, which the designer knows, so the labels go to what r_task does not say: the
    /// person's taste). r_task = -d, the distance to the goal read from the observation
    /// ([`RewardModelConfig::goal`]) each action is taken in: the step's own r_task is
    /// -d after it, so a segment's anchor is one step earlier than its r_task, and
    /// r_hat(s, a) carries the difference (the step's progress; the store keeps no
    /// observation after a trajectory's last action). The learnt reward the policy trains
    /// on is the whole `r_hat + C r_task`. 0: off (the authors').
    #[arg(id = "reward_anchor", long = "reward-anchor", default_value_t = 0.0)]
    #[serde(default)]
    pub anchor: f64,
    /// Reward ensemble: read each step's designer-computed comfort features beside the
    /// observation (food eaten, EE speed, force on the person, the spoon's force at or
    /// over the high-force threshold, food hits, eaten food's speed: the measurements behind the paper's preference
    /// terms, unweighted, through sign(x) ln(1 + |x|); `StepRewards::features`). What a
    /// person makes of them is still learnt, and so is any taste outside them. Off: the
    /// authors' and the presets' (observation and action only). On by default;
    /// `--reward-features=false` turns it off.
    #[arg(
        id = "reward_features",
        long = "reward-features",
        action = clap::ArgAction::Set,
        num_args = 0..=1,
        require_equals = true,
        default_value_t = true,
        default_missing_value = "true"
    )]
    #[serde(default)]
    pub features: bool,
    /// Where the observation holds the vector to the goal (first index, length): the
    /// task's, filled by the binary (feeding: spoon minus mouth; point: goal minus point).
    #[arg(skip)]
    #[serde(default)]
    pub goal: Option<[usize; 2]>,
    /// Seed of initialisation and data orders (the run's `--seed`).
    #[arg(skip)]
    pub seed: u64,
}

fn crop_min() -> f64 {
    0.7
}

fn crop_max() -> f64 {
    0.9
}

impl Default for RewardModelConfig {
    /// Every field at its flag's default.
    fn default() -> Self {
        pbrl_common::flags::defaults()
    }
}

impl RewardModelConfig {
    /// The defaults with the label-efficiency pieces off: no crops, no comfort features
    /// (the authors' reward model, what the presets train).
    pub fn plain() -> Self {
        Self {
            crops: 0,
            features: false,
            ..Self::default()
        }
    }

    /// The authors' size: three hidden layers of 256.
    pub fn paper() -> Self {
        Self {
            hidden: vec![256, 256, 256],
            ..Self::default()
        }
    }
}

/// The task reward `-|row[at..at + len]|` of one raw observation row whose goal vector
/// lies at `[at, len]` (what the anchor and `pbrl labels fit`'s task prior read).
pub fn task_reward(row: &[f32], [at, len]: [usize; 2]) -> f32 {
    -row[at..at + len].iter().map(|x| x * x).sum::<f32>().sqrt()
}

/// A trajectory as the reward model sees it: `steps` rows of raw obs and of actions (the
/// obs after the last action is not included), and the steps' comfort features where known.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Segment {
    /// `steps * obs_dim` raw observations, row-major.
    pub obs: Vec<f32>,
    /// `steps * act_dim` actions, row-major.
    pub actions: Vec<f32>,
    /// `steps * FEATURES` comfort features ([`pbrl_common::StepRewards::features`]),
    /// row-major; empty where unknown (read only by a model with `features` on).
    #[serde(default)]
    pub features: Vec<f32>,
}

impl Segment {
    /// Steps `start .. start + len` of `steps` (bounds checked by the caller).
    pub fn cut(&self, start: usize, len: usize, steps: usize) -> Segment {
        Segment::of(
            &self.obs,
            &self.actions,
            &self.features,
            (start, len),
            steps,
        )
    }

    /// Steps `start .. start + len` of the rows `obs`, `actions` and `features`, which
    /// hold `steps` rows each (features may be empty).
    pub fn of(
        obs: &[f32],
        actions: &[f32],
        features: &[f32],
        (start, len): (usize, usize),
        steps: usize,
    ) -> Segment {
        let rows = |xs: &[f32]| {
            let w = xs.len() / steps.max(1);
            xs[start * w..(start + len) * w].to_vec()
        };
        Segment {
            obs: rows(obs),
            actions: rows(actions),
            features: rows(features),
        }
    }
}

/// A comfort feature as the network reads it: sign(x) ln(1 + |x|) (counts, speeds and
/// forces of very different scales, most steps zero; no normaliser to fit).
fn squash(x: f32) -> f32 {
    x.signum() * x.abs().ln_1p()
}

/// One label of D: target = probability that `second` is preferred (0, 1 or 0.5).
#[derive(Clone, Debug)]
pub struct Labelled {
    pub first: Arc<Segment>,
    pub second: Arc<Segment>,
    pub target: f32,
}

impl Labelled {
    /// Whether the label says "equal" (a soft target, left out of accuracy).
    pub fn is_equal(&self) -> bool {
        (self.target - 0.5).abs() < 1e-6
    }
}

/// What a training session did.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TrainStats {
    /// Epochs run (0 when D was empty; the last may be cut short by `max_pairs`).
    pub epochs: usize,
    /// Pairs each member trained on, over all epochs.
    pub pairs: usize,
    /// Cross-entropy per pair over the last epoch, mean over members.
    pub loss: f64,
    /// Accuracy over the last epoch as the members saw it, mean over members (see
    /// [`RewardModel::train`]).
    pub accuracy: f64,
}

/// The ensemble's state beside its networks, for checkpoints.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct RewardModelState {
    /// Each member's Adam.
    pub opts: Vec<AdamState>,
    /// The frozen observation normaliser.
    pub obs_mean: Vec<f32>,
    pub obs_std: Vec<f32>,
    pub rng: RngState,
    pub trained: bool,
}

/// The observation normaliser: frozen between training sessions.
#[derive(Clone, Debug, PartialEq)]
struct ObsNorm {
    mean: Vec<f32>,
    std: Vec<f32>,
}

impl ObsNorm {
    fn identity(dim: usize) -> Self {
        Self {
            mean: vec![0.0; dim],
            std: vec![1.0; dim],
        }
    }

    /// Mean and standard deviation of every observation row of `segs` (f64 sums, two
    /// passes), the deviation floored at [`STD_FLOOR`].
    fn fit<'a>(segs: impl Iterator<Item = &'a Segment> + Clone, dim: usize) -> Self {
        let mut sum = vec![0f64; dim];
        let mut n = 0usize;
        for s in segs.clone() {
            for row in s.obs.chunks_exact(dim) {
                sum.iter_mut().zip(row).for_each(|(a, x)| *a += *x as f64);
                n += 1;
            }
        }
        if n == 0 {
            return Self::identity(dim);
        }
        let mean: Vec<f64> = sum.iter().map(|s| s / n as f64).collect();
        let mut sq = vec![0f64; dim];
        for s in segs {
            for row in s.obs.chunks_exact(dim) {
                for ((a, x), m) in sq.iter_mut().zip(row).zip(&mean) {
                    *a += (*x as f64 - m).powi(2);
                }
            }
        }
        Self {
            mean: mean.iter().map(|m| *m as f32).collect(),
            std: sq
                .iter()
                .map(|s| (s / n as f64).sqrt().max(STD_FLOOR) as f32)
                .collect(),
        }
    }
}

/// The ensemble, its optimisers, normaliser and generator.
pub struct RewardModel {
    cfg: RewardModelConfig,
    obs_dim: usize,
    act_dim: usize,
    /// Comfort features per step read (0: off).
    feat_dim: usize,
    nets: Vec<Owned<RewardNet>>,
    opts: Vec<Adam>,
    norm: ObsNorm,
    rng: ChaCha8Rng,
    trained: bool,
    /// The normaliser came with a prior and is kept: not refitted to D at each training.
    keep_norm: bool,
}

impl RewardModel {
    /// A fresh ensemble, members initialised in order from the config's seed.
    pub fn new(cfg: RewardModelConfig, obs_dim: usize, act_dim: usize) -> Result<Self> {
        if cfg.members == 0 || cfg.batch == 0 || obs_dim == 0 {
            candle_core::bail!(
                "reward model needs members, batch and obs_dim > 0 (got {}, {}, {obs_dim})",
                cfg.members,
                cfg.batch
            );
        }
        if !(cfg.anchor.is_finite() && cfg.anchor >= 0.0) {
            candle_core::bail!("reward_anchor must be finite and >= 0 (got {})", cfg.anchor);
        }
        if cfg.anchor > 0.0 {
            match cfg.goal {
                Some([at, len]) if len > 0 && at + len <= obs_dim => {}
                Some(g) => candle_core::bail!(
                    "reward_anchor: the goal's place in the observation {g:?} is not within obs_dim {obs_dim}"
                ),
                None => candle_core::bail!(
                    "reward_anchor {} needs a task whose observation holds the vector to the goal",
                    cfg.anchor
                ),
            }
        }
        let feat_dim = if cfg.features { FEATURES } else { 0 };
        let mut rng = ChaCha8Rng::seed_from_u64(cfg.seed);
        let nets = (0..cfg.members)
            .map(|_| {
                Owned::build(&mut rng, |vb| {
                    RewardNet::new(vb, obs_dim + feat_dim + act_dim, &cfg.hidden)
                })
            })
            .collect::<Result<Vec<_>>>()?;
        let opts = nets
            .iter()
            .map(|n| Adam::for_varmap(&n.varmap, cfg.lr))
            .collect::<Result<Vec<_>>>()?;
        Ok(Self {
            cfg,
            obs_dim,
            act_dim,
            feat_dim,
            nets,
            opts,
            norm: ObsNorm::identity(obs_dim),
            rng,
            trained: false,
            keep_norm: false,
        })
    }

    pub fn config(&self) -> &RewardModelConfig {
        &self.cfg
    }

    pub fn obs_dim(&self) -> usize {
        self.obs_dim
    }

    pub fn act_dim(&self) -> usize {
        self.act_dim
    }

    /// Comfort features read per step (0: the model reads none).
    pub fn feat_dim(&self) -> usize {
        self.feat_dim
    }

    /// False until the first [`RewardModel::train`] on a non-empty D (or a prior).
    pub fn trained(&self) -> bool {
        self.trained
    }

    /// The observation normaliser: mean and standard deviation per dimension.
    pub fn normaliser(&self) -> (Vec<f32>, Vec<f32>) {
        (self.norm.mean.clone(), self.norm.std.clone())
    }

    /// Normalise observations with `mean` and `std` from now on, never refitted (a prior's:
    /// the weights learnt with it read observations so scaled). The model counts as
    /// trained.
    pub fn keep_normaliser(&mut self, mean: Vec<f32>, std: Vec<f32>) -> Result<()> {
        if mean.len() != self.obs_dim || std.len() != self.obs_dim {
            candle_core::bail!(
                "a normaliser of {} / {} dimensions for a model of {}",
                mean.len(),
                std.len(),
                self.obs_dim
            );
        }
        if std.iter().chain(&mean).any(|x| !x.is_finite()) || std.iter().any(|s| *s <= 0.0) {
            candle_core::bail!("a normaliser needs finite means and positive deviations");
        }
        self.norm = ObsNorm { mean, std };
        self.keep_norm = true;
        self.trained = true;
        Ok(())
    }

    /// Keep the normaliser restored from a checkpoint (a run started from a prior).
    pub fn keep_restored_normaliser(&mut self) {
        self.keep_norm = true;
    }

    /// The members' networks by name, `reward_0`, `reward_1`, ... (for checkpoints).
    pub fn networks(&self) -> Vec<(String, &VarMap)> {
        self.nets
            .iter()
            .enumerate()
            .map(|(i, n)| (format!("reward_{i}"), &n.varmap))
            .collect()
    }

    /// Optimisers, normaliser, generator and the trained flag (for checkpoints; the
    /// networks are saved apart, see [`RewardModel::networks`]).
    pub fn state(&self) -> Result<RewardModelState> {
        Ok(RewardModelState {
            opts: self.opts.iter().map(Adam::state).collect::<Result<_>>()?,
            obs_mean: self.norm.mean.clone(),
            obs_std: self.norm.std.clone(),
            rng: RngState::of(&self.rng),
            trained: self.trained,
        })
    }

    /// Continue from `s` (the networks are restored apart).
    pub fn restore(&mut self, s: &RewardModelState) -> Result<()> {
        if s.opts.len() != self.opts.len() {
            candle_core::bail!(
                "reward model state holds {} optimisers for {} members",
                s.opts.len(),
                self.opts.len()
            );
        }
        if s.obs_mean.len() != self.obs_dim || s.obs_std.len() != self.obs_dim {
            candle_core::bail!(
                "reward model state normalises {} / {} dimensions, the model has {}",
                s.obs_mean.len(),
                s.obs_std.len(),
                self.obs_dim
            );
        }
        for (o, st) in self.opts.iter_mut().zip(&s.opts) {
            o.restore(st)?;
        }
        self.norm = ObsNorm {
            mean: s.obs_mean.clone(),
            std: s.obs_std.clone(),
        };
        self.rng = s.rng.restore();
        self.trained = s.trained;
        Ok(())
    }

    /// A deep copy (own variables, optimiser moments and generator), to train apart, e.g.
    /// on a thread of its own, and swap in.
    pub fn snapshot(&self) -> Result<Self> {
        let mut nets = Vec::with_capacity(self.nets.len());
        let mut opts = Vec::with_capacity(self.nets.len());
        for (n, o) in self.nets.iter().zip(&self.opts) {
            let varmap = VarMap::new();
            let vb = VarBuilder::from_varmap(&varmap, DType::F32, &Device::Cpu);
            let net = RewardNet::new(vb, self.width(), &self.cfg.hidden)?;
            import(&varmap, &export(&n.varmap)?)?;
            let mut opt = Adam::for_varmap(&varmap, self.cfg.lr)?;
            opt.restore(&o.state()?)?;
            nets.push(Owned { varmap, net });
            opts.push(opt);
        }
        Ok(Self {
            cfg: self.cfg.clone(),
            obs_dim: self.obs_dim,
            act_dim: self.act_dim,
            feat_dim: self.feat_dim,
            nets,
            opts,
            norm: self.norm.clone(),
            rng: self.rng.clone(),
            trained: self.trained,
            keep_norm: self.keep_norm,
        })
    }

    /// The anchor `C r_task` of each row of raw `obs` (none when the anchor is off).
    fn anchor_rows(&self, obs: &[f32]) -> Option<Vec<f32>> {
        let goal = self.cfg.goal.filter(|_| self.cfg.anchor > 0.0)?;
        let c = self.cfg.anchor as f32;
        Some(
            obs.chunks_exact(self.obs_dim)
                .map(|row| c * task_reward(row, goal))
                .collect(),
        )
    }

    /// The anchor's sum over `seg`'s steps (0 when off).
    pub(super) fn anchor_sum(&self, seg: &Segment) -> f32 {
        self.anchor_rows(&seg.obs).map_or(0.0, |a| a.iter().sum())
    }

    /// Numbers per network input row: observation, features, action.
    fn width(&self) -> usize {
        self.obs_dim + self.feat_dim + self.act_dim
    }

    /// Steps of `seg`, checked against the model's dimensions.
    fn steps(&self, seg: &Segment) -> Result<usize> {
        let steps = seg.obs.len() / self.obs_dim;
        if steps == 0
            || seg.obs.len() != steps * self.obs_dim
            || seg.actions.len() != steps * self.act_dim
        {
            candle_core::bail!(
                "segment of {} obs and {} action numbers is not whole steps of obs {} and action {}",
                seg.obs.len(),
                seg.actions.len(),
                self.obs_dim,
                self.act_dim
            );
        }
        self.check_features(steps, seg.features.len())?;
        Ok(steps)
    }

    /// A model that reads features needs `steps` rows of them.
    fn check_features(&self, steps: usize, found: usize) -> Result<()> {
        if self.feat_dim > 0 && found != steps * self.feat_dim {
            candle_core::bail!(
                "reward_features: the reward model reads {} comfort features per step, and {steps} steps came with {found} numbers{}",
                self.feat_dim,
                if found == 0 {
                    " (trajectories stored by an older build, or a task without them)"
                } else {
                    ""
                }
            );
        }
        Ok(())
    }

    /// Append the network inputs of `steps` rows: normalised, clipped observation, the
    /// squashed comfort features (when read), then the action clipped to [-1, 1].
    fn push_inputs(&self, obs: &[f32], actions: &[f32], features: &[f32], out: &mut Vec<f32>) {
        let (o, a, f) = (self.obs_dim, self.act_dim, self.feat_dim);
        for t in 0..obs.len() / o {
            let row = &obs[t * o..(t + 1) * o];
            for ((x, m), s) in row.iter().zip(&self.norm.mean).zip(&self.norm.std) {
                out.push(((x - m) / s).clamp(-OBS_CLIP, OBS_CLIP));
            }
            out.extend(features[t * f..(t + 1) * f].iter().map(|x| squash(*x)));
            out.extend(
                actions[t * a..(t + 1) * a]
                    .iter()
                    .map(|x| x.clamp(-1.0, 1.0)),
            );
        }
    }

    /// The inputs of a segment's steps ([`RewardModel::push_inputs`]).
    fn push_segment(&self, s: &Segment, out: &mut Vec<f32>) {
        self.push_inputs(&s.obs, &s.actions, &s.features, out);
    }

    fn input_tensor(&self, x: Vec<f32>) -> Result<Tensor> {
        let width = self.width();
        let rows = x.len() / width;
        Tensor::from_vec(x, (rows, width), &Device::Cpu)
    }

    /// The mean reward over members of each of `n` rows (`obs` `n * obs_dim`, `actions`
    /// `n * act_dim`, `features` `n * FEATURES` for a model that reads them, else ignored).
    pub fn predict(&self, obs: &[f32], actions: &[f32], features: &[f32]) -> Result<Vec<f32>> {
        let n = obs.len() / self.obs_dim;
        if obs.len() != n * self.obs_dim || actions.len() != n * self.act_dim {
            candle_core::bail!(
                "predict: {} obs and {} action numbers are not whole rows of {} and {}",
                obs.len(),
                actions.len(),
                self.obs_dim,
                self.act_dim
            );
        }
        self.check_features(n, features.len())?;
        let mut out = Vec::with_capacity(n);
        let (o, a, f) = (self.obs_dim, self.act_dim, self.feat_dim);
        for start in (0..n).step_by(CHUNK_ROWS) {
            let end = (start + CHUNK_ROWS).min(n);
            let mut x = Vec::with_capacity((end - start) * self.width());
            self.push_inputs(
                &obs[start * o..end * o],
                &actions[start * a..end * a],
                &features[start * f..end * f],
                &mut x,
            );
            let x = self.input_tensor(x)?;
            let mut sum = vec![0f32; end - start];
            for net in &self.nets {
                let r = net.net.run(&x, None)?.flatten_all()?.to_vec1::<f32>()?;
                sum.iter_mut().zip(&r).for_each(|(s, r)| *s += r);
            }
            let q = self.nets.len() as f32;
            match self.anchor_rows(&obs[start * o..end * o]) {
                Some(anchor) => out.extend(sum.iter().zip(anchor).map(|(s, c)| s / q + c)),
                None => out.extend(sum.iter().map(|s| s / q)),
            }
        }
        Ok(out)
    }

    /// The mean reward over members, `[n, 1]`, of `obs` `[n, obs_dim]`, `act`
    /// `[n, act_dim]` and, for a model that reads them, the raw comfort features `[n,
    /// FEATURES]` (a SAC minibatch), without leaving candle.
    pub fn predict_tensor(
        &self,
        obs: &Tensor,
        act: &Tensor,
        features: Option<&Tensor>,
    ) -> Result<Tensor> {
        let dev = obs.device();
        let mean = Tensor::from_slice(&self.norm.mean, (1, self.obs_dim), dev)?;
        let std = Tensor::from_slice(&self.norm.std, (1, self.obs_dim), dev)?;
        let o = obs
            .to_dtype(DType::F32)?
            .broadcast_sub(&mean)?
            .broadcast_div(&std)?
            .clamp(-OBS_CLIP, OBS_CLIP)?;
        let a = act.to_dtype(DType::F32)?.clamp(-1f32, 1f32)?;
        let x = match (self.feat_dim, features) {
            (0, _) => Tensor::cat(&[&o, &a], D::Minus1)?,
            (_, Some(f)) => {
                let f = f.to_dtype(DType::F32)?;
                let f = (f.sign()? * f.abs()?.affine(1.0, 1.0)?.log()?)?;
                Tensor::cat(&[&o, &f, &a], D::Minus1)?
            }
            (_, None) => candle_core::bail!(
                "reward_features: the reward model reads comfort features and the minibatch has none"
            ),
        };
        let mut sum: Option<Tensor> = None;
        for net in &self.nets {
            let r = net.net.run(&x, None)?;
            sum = Some(match sum {
                Some(s) => (s + r)?,
                None => r,
            });
        }
        // The constructor refuses an empty ensemble, so there is a first member.
        let sum = sum.ok_or_else(|| candle_core::Error::Msg("empty ensemble".into()))?;
        let mean = (sum / self.nets.len() as f64)?;
        match self.cfg.goal.filter(|_| self.cfg.anchor > 0.0) {
            Some([at, len]) => {
                let d = obs
                    .to_dtype(DType::F32)?
                    .narrow(1, at, len)?
                    .sqr()?
                    .sum_keepdim(1)?
                    .sqrt()?;
                mean + d.affine(-self.cfg.anchor, 0.0)?
            }
            None => Ok(mean),
        }
    }

    /// `[member][segment]` sums of r_hat (and the anchor) over each segment's steps, in
    /// chunks of whole segments.
    fn segment_returns(&self, segs: &[&Segment]) -> Result<Vec<Vec<f32>>> {
        let steps = segs
            .iter()
            .map(|s| self.steps(s))
            .collect::<Result<Vec<_>>>()?;
        let anchor: Vec<f32> = segs.iter().map(|s| self.anchor_sum(s)).collect();
        let mut out = vec![Vec::with_capacity(segs.len()); self.nets.len()];
        let mut start = 0;
        while start < segs.len() {
            let mut end = start + 1;
            let mut rows = steps[start];
            while end < segs.len() && rows + steps[end] <= CHUNK_ROWS {
                rows += steps[end];
                end += 1;
            }
            let mut x = Vec::with_capacity(rows * self.width());
            for s in &segs[start..end] {
                self.push_segment(s, &mut x);
            }
            let x = self.input_tensor(x)?;
            for (m, net) in self.nets.iter().enumerate() {
                let r = net.net.run(&x, None)?.flatten_all()?.to_vec1::<f32>()?;
                let mut at = 0;
                for (&n, c) in steps[start..end].iter().zip(&anchor[start..end]) {
                    out[m].push(r[at..at + n].iter().sum::<f32>() + c);
                    at += n;
                }
            }
            start = end;
        }
        Ok(out)
    }

    /// Each member's sum of r_hat over `seg`.
    pub fn returns(&self, seg: &Segment) -> Result<Vec<f32>> {
        Ok(self
            .segment_returns(&[seg])?
            .into_iter()
            .map(|r| r[0])
            .collect())
    }

    /// `[member][pair]` P[second > first], all pairs through each member in batches.
    /// A segment in several pairs (the same reference) goes through the members once.
    pub fn preference_probs(&self, pairs: &[(&Segment, &Segment)]) -> Result<Vec<Vec<f32>>> {
        // NOTE: candidates are drawn with replacement from the annotation buffer: most
        // trajectories come up in several pairs, and their returns are what costs.
        let mut index: std::collections::HashMap<*const Segment, usize> = Default::default();
        let mut unique: Vec<&Segment> = Vec::new();
        let mut sides: Vec<(usize, usize)> = Vec::with_capacity(pairs.len());
        for &(a, b) in pairs {
            let mut side = [0usize; 2];
            for (k, seg) in [a, b].into_iter().enumerate() {
                side[k] = *index.entry(seg as *const Segment).or_insert_with(|| {
                    unique.push(seg);
                    unique.len() - 1
                });
            }
            sides.push((side[0], side[1]));
        }
        let sums = self.segment_returns(&unique)?;
        Ok(sums
            .iter()
            .map(|s| {
                sides
                    .iter()
                    .map(|&(a, b)| (1.0 / (1.0 + ((s[a] - s[b]) as f64).exp())) as f32)
                    .collect()
            })
            .collect())
    }
}
