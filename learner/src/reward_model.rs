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

use std::cell::RefCell;
use std::collections::HashSet;
use std::sync::Arc;

use candle_core::backprop::GradStore;
use candle_core::{CpuStorage, DType, Device, InplaceOp2, Layout, Result, Tensor, D};
use candle_nn::{Linear, Module, VarBuilder, VarMap};
use pbrl_common::nets::{export, import, Owned};
use rand::seq::SliceRandom;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use crate::optim::{Adam, AdamState};
use crate::state::RngState;

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
    /// Seed of initialisation and data orders (the run's `--seed`).
    #[arg(skip)]
    pub seed: u64,
}

impl Default for RewardModelConfig {
    fn default() -> Self {
        use clap::Parser;
        #[derive(clap::Parser)]
        struct Defaults {
            #[command(flatten)]
            model: RewardModelConfig,
        }
        // NOTE: the defaults are clap's, so the two cannot drift apart (as `PrefConfig`'s);
        // parsing no arguments cannot fail.
        Defaults::parse_from(["pbrl"]).model
    }
}

impl RewardModelConfig {
    /// The authors' size: three hidden layers of 256.
    pub fn paper() -> Self {
        Self {
            hidden: vec![256, 256, 256],
            ..Self::default()
        }
    }
}

/// A trajectory as the reward model sees it: `steps` rows of raw obs and of actions (the
/// obs after the last action is not included).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Segment {
    /// `steps * obs_dim` raw observations, row-major.
    pub obs: Vec<f32>,
    /// `steps * act_dim` actions, row-major.
    pub actions: Vec<f32>,
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

/// One member: linear layers, LeakyReLU between them, tanh after the last (one output).
#[derive(Clone, Debug)]
pub struct RewardNet {
    layers: Vec<Linear>,
}

impl RewardNet {
    /// Layers `input -> hidden... -> 1`, named `l0`, `l1`, ...
    pub fn new(vb: VarBuilder, input: usize, hidden: &[usize]) -> Result<Self> {
        let sizes: Vec<usize> = std::iter::once(input)
            .chain(hidden.iter().copied())
            .chain(std::iter::once(1))
            .collect();
        let layers = sizes
            .windows(2)
            .enumerate()
            .map(|(i, w)| candle_nn::linear(w[0], w[1], vb.pp(format!("l{i}"))))
            .collect::<Result<Vec<_>>>()?;
        Ok(Self { layers })
    }

    /// Per-row rewards `[rows, 1]` in (-1, 1), with candle's ops (and its autodiff): the
    /// definition the fast path below must agree with.
    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let mut h = x.clone();
        for (i, l) in self.layers.iter().enumerate() {
            h = l.forward(&h)?;
            h = if i + 1 < self.layers.len() {
                candle_nn::ops::leaky_relu(&h, LEAKY_SLOPE)?
            } else {
                h.tanh()?
            };
        }
        Ok(h)
    }

    /// The same outputs outside candle's autodiff, each layer's bias and activation
    /// applied in place; each layer's input is pushed onto `tape` when given.
    fn run(&self, x: &Tensor, mut tape: Option<&mut Vec<Tensor>>) -> Result<Tensor> {
        let mut h = x.detach();
        for (i, l) in self.layers.iter().enumerate() {
            let z = h.matmul(&l.weight().detach().t()?)?;
            let act = if i + 1 < self.layers.len() {
                Act::Leaky
            } else {
                Act::Tanh
            };
            let b = l
                .bias()
                .ok_or_else(|| candle_core::Error::Msg("reward layer without bias".into()))?;
            z.inplace_op2(&b.detach(), &BiasAct(act))?;
            if let Some(t) = tape.as_deref_mut() {
                t.push(h);
            }
            h = z;
        }
        Ok(h)
    }

    /// Backpropagate `dz` (`[rows, 1]`, the loss's gradient with respect to the last
    /// layer's pre-tanh output) through the layers whose inputs are `tape`, adding each
    /// weight's gradient into `acc`.
    fn backward(&self, tape: &[Tensor], dz: Vec<f32>, acc: &mut Grads) -> Result<()> {
        let last = self.layers.len() - 1;
        acc.b[last][0] += dz.iter().sum::<f32>();
        let rows = dz.len();
        let mut dz = Tensor::from_vec(dz, (rows, 1), &Device::Cpu)?;
        for i in (0..self.layers.len()).rev() {
            let dw = dz.t()?.matmul(&tape[i])?;
            acc.w[i] = Some(match acc.w[i].take() {
                Some(a) => (a + dw)?,
                None => dw,
            });
            if i == 0 {
                break;
            }
            let dh = dz.matmul(&self.layers[i].weight().detach())?;
            // LeakyReLU: the layer's input h = leaky(z) has z's sign, so its slope is 1
            // where h > 0 and LEAKY_SLOPE elsewhere; the bias gradient is the column sum.
            let back = LeakyBack {
                colsum: RefCell::new(std::mem::take(&mut acc.b[i - 1])),
            };
            dh.inplace_op2(&tape[i], &back)?;
            acc.b[i - 1] = back.colsum.into_inner();
            dz = dh;
        }
        Ok(())
    }

    fn vars(&self) -> Vec<(Tensor, Option<Tensor>)> {
        self.layers
            .iter()
            .map(|l| (l.weight().clone(), l.bias().cloned()))
            .collect()
    }
}

/// Weight gradients summed over chunks, and bias gradients as plain sums.
struct Grads {
    w: Vec<Option<Tensor>>,
    b: Vec<Vec<f32>>,
}

impl Grads {
    fn new(net: &RewardNet) -> Result<Self> {
        Ok(Self {
            w: vec![None; net.layers.len()],
            b: net
                .layers
                .iter()
                .map(|l| Ok(vec![0.0; l.weight().dim(0)?]))
                .collect::<Result<_>>()?,
        })
    }

    fn into_store(self, net: &RewardNet) -> Result<GradStore> {
        let mut g = GradStore::default();
        for ((w, b), (gw, gb)) in net.vars().into_iter().zip(self.w.into_iter().zip(self.b)) {
            if let Some(gw) = gw {
                g.insert(&w, gw);
            }
            if let Some(b) = b {
                let n = gb.len();
                g.insert(&b, Tensor::from_vec(gb, n, &Device::Cpu)?);
            }
        }
        Ok(g)
    }
}

#[derive(Clone, Copy)]
enum Act {
    Leaky,
    Tanh,
}

/// A row-major f32 slice of a CPU tensor's storage.
fn f32_slice<'a>(s: &'a CpuStorage, l: &Layout, op: &str) -> Result<&'a [f32]> {
    match (s, l.contiguous_offsets()) {
        (CpuStorage::F32(v), Some((a, b))) => Ok(&v[a..b]),
        _ => candle_core::bail!("{op}: needs a contiguous f32 tensor"),
    }
}

fn f32_slice_mut<'a>(s: &'a mut CpuStorage, l: &Layout, op: &str) -> Result<&'a mut [f32]> {
    match (s, l.contiguous_offsets()) {
        (CpuStorage::F32(v), Some((a, b))) => Ok(&mut v[a..b]),
        _ => candle_core::bail!("{op}: needs a contiguous f32 tensor"),
    }
}

/// `z <- act(z + b)` in place, `b` broadcast over rows.
struct BiasAct(Act);

impl InplaceOp2 for BiasAct {
    fn name(&self) -> &'static str {
        "reward-bias-act"
    }

    fn cpu_fwd(
        &self,
        s1: &mut CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> Result<()> {
        let b = f32_slice(s2, l2, self.name())?;
        let z = f32_slice_mut(s1, l1, self.name())?;
        let slope = LEAKY_SLOPE as f32;
        for row in z.chunks_exact_mut(b.len()) {
            for (x, bi) in row.iter_mut().zip(b) {
                let v = *x + bi;
                *x = match self.0 {
                    // NOTE: max(v, slope v) is candle_nn's max(v, 0) + min(v, 0) slope to
                    // the bit, and without a branch the loop vectorises.
                    Act::Leaky => v.max(v * slope),
                    Act::Tanh => v.tanh(),
                };
            }
        }
        Ok(())
    }
}

/// `dh <- dh * leaky'(h)` in place, with the column sums of the result added to `colsum`.
struct LeakyBack {
    colsum: RefCell<Vec<f32>>,
}

impl InplaceOp2 for LeakyBack {
    fn name(&self) -> &'static str {
        "reward-leaky-backward"
    }

    fn cpu_fwd(
        &self,
        s1: &mut CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> Result<()> {
        let h = f32_slice(s2, l2, self.name())?;
        let dh = f32_slice_mut(s1, l1, self.name())?;
        let mut colsum = self.colsum.borrow_mut();
        let width = colsum.len();
        let slope = LEAKY_SLOPE as f32;
        for (drow, hrow) in dh.chunks_exact_mut(width).zip(h.chunks_exact(width)) {
            for ((d, h), c) in drow.iter_mut().zip(hrow).zip(colsum.iter_mut()) {
                *d *= if *h > 0.0 { 1.0 } else { slope };
                *c += *d;
            }
        }
        Ok(())
    }
}

/// The ensemble, its optimisers, normaliser and generator.
pub struct RewardModel {
    cfg: RewardModelConfig,
    obs_dim: usize,
    act_dim: usize,
    nets: Vec<Owned<RewardNet>>,
    opts: Vec<Adam>,
    norm: ObsNorm,
    rng: ChaCha8Rng,
    trained: bool,
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
        let mut rng = ChaCha8Rng::seed_from_u64(cfg.seed);
        let nets = (0..cfg.members)
            .map(|_| {
                Owned::build(&mut rng, |vb| {
                    RewardNet::new(vb, obs_dim + act_dim, &cfg.hidden)
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
            nets,
            opts,
            norm: ObsNorm::identity(obs_dim),
            rng,
            trained: false,
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

    /// False until the first [`RewardModel::train`] on a non-empty D.
    pub fn trained(&self) -> bool {
        self.trained
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
            let net = RewardNet::new(vb, self.obs_dim + self.act_dim, &self.cfg.hidden)?;
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
            nets,
            opts,
            norm: self.norm.clone(),
            rng: self.rng.clone(),
            trained: self.trained,
        })
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
        Ok(steps)
    }

    /// Append the network inputs of `steps` rows: normalised, clipped observation, then
    /// the action clipped to [-1, 1].
    fn push_inputs(&self, obs: &[f32], actions: &[f32], out: &mut Vec<f32>) {
        let (o, a) = (self.obs_dim, self.act_dim);
        for t in 0..obs.len() / o {
            let row = &obs[t * o..(t + 1) * o];
            for ((x, m), s) in row.iter().zip(&self.norm.mean).zip(&self.norm.std) {
                out.push(((x - m) / s).clamp(-OBS_CLIP, OBS_CLIP));
            }
            out.extend(
                actions[t * a..(t + 1) * a]
                    .iter()
                    .map(|x| x.clamp(-1.0, 1.0)),
            );
        }
    }

    fn input_tensor(&self, x: Vec<f32>) -> Result<Tensor> {
        let width = self.obs_dim + self.act_dim;
        let rows = x.len() / width;
        Tensor::from_vec(x, (rows, width), &Device::Cpu)
    }

    /// The mean reward over members of each of `n` rows (`obs` `n * obs_dim`, `actions`
    /// `n * act_dim`).
    pub fn predict(&self, obs: &[f32], actions: &[f32]) -> Result<Vec<f32>> {
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
        let mut out = Vec::with_capacity(n);
        let (o, a) = (self.obs_dim, self.act_dim);
        for start in (0..n).step_by(CHUNK_ROWS) {
            let end = (start + CHUNK_ROWS).min(n);
            let mut x = Vec::with_capacity((end - start) * (o + a));
            self.push_inputs(
                &obs[start * o..end * o],
                &actions[start * a..end * a],
                &mut x,
            );
            let x = self.input_tensor(x)?;
            let mut sum = vec![0f32; end - start];
            for net in &self.nets {
                let r = net.net.run(&x, None)?.flatten_all()?.to_vec1::<f32>()?;
                sum.iter_mut().zip(&r).for_each(|(s, r)| *s += r);
            }
            let q = self.nets.len() as f32;
            out.extend(sum.iter().map(|s| s / q));
        }
        Ok(out)
    }

    /// The mean reward over members, `[n, 1]`, of `obs` `[n, obs_dim]` and `act`
    /// `[n, act_dim]` (a SAC minibatch), without leaving candle.
    pub fn predict_tensor(&self, obs: &Tensor, act: &Tensor) -> Result<Tensor> {
        let dev = obs.device();
        let mean = Tensor::from_slice(&self.norm.mean, (1, self.obs_dim), dev)?;
        let std = Tensor::from_slice(&self.norm.std, (1, self.obs_dim), dev)?;
        let o = obs
            .to_dtype(DType::F32)?
            .broadcast_sub(&mean)?
            .broadcast_div(&std)?
            .clamp(-OBS_CLIP, OBS_CLIP)?;
        let a = act.to_dtype(DType::F32)?.clamp(-1f32, 1f32)?;
        let x = Tensor::cat(&[&o, &a], D::Minus1)?;
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
        sum / self.nets.len() as f64
    }

    /// `[member][segment]` sums of r_hat over each segment's steps, in chunks of whole
    /// segments.
    fn segment_returns(&self, segs: &[&Segment]) -> Result<Vec<Vec<f32>>> {
        let steps = segs
            .iter()
            .map(|s| self.steps(s))
            .collect::<Result<Vec<_>>>()?;
        let mut out = vec![Vec::with_capacity(segs.len()); self.nets.len()];
        let mut start = 0;
        while start < segs.len() {
            let mut end = start + 1;
            let mut rows = steps[start];
            while end < segs.len() && rows + steps[end] <= CHUNK_ROWS {
                rows += steps[end];
                end += 1;
            }
            let mut x = Vec::with_capacity(rows * (self.obs_dim + self.act_dim));
            for s in &segs[start..end] {
                self.push_inputs(&s.obs, &s.actions, &mut x);
            }
            let x = self.input_tensor(x)?;
            for (m, net) in self.nets.iter().enumerate() {
                let r = net.net.run(&x, None)?.flatten_all()?.to_vec1::<f32>()?;
                let mut at = 0;
                for &n in &steps[start..end] {
                    out[m].push(r[at..at + n].iter().sum());
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

    /// Each member's data order for one epoch over `n` pairs, drawn in member order.
    fn draw_orders(&mut self, n: usize) -> Vec<Vec<usize>> {
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
    fn member_gradients(
        &self,
        m: usize,
        pairs: &[&Labelled],
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
            let mut x = Vec::with_capacity(rows * (self.obs_dim + self.act_dim));
            for l in &pairs[start..end] {
                self.push_inputs(&l.first.obs, &l.first.actions, &mut x);
                self.push_inputs(&l.second.obs, &l.second.actions, &mut x);
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
            for (l, s) in pairs[start..end].iter().zip(&steps) {
                let r0 = &r[at..at + s[0]];
                let r1 = &r[at + s[0]..at + s[0] + s[1]];
                at += s[0] + s[1];
                let d = (r1.iter().sum::<f32>() - r0.iter().sum::<f32>()) as f64;
                let p = l.target as f64;
                loss += (1.0 - p) * softplus(d) + p * softplus(-d);
                if !l.is_equal() {
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

    /// One training session on D (the whole preference dataset so far).
    ///
    /// The normaliser is refitted to D's observations first and then frozen until the
    /// next session. Each epoch every member draws its own order of D (bootstrap or
    /// shuffle) and takes one Adam step per minibatch of `batch` pairs. An empty D leaves
    /// the model as it was.
    pub fn train(&mut self, data: &[Labelled]) -> Result<TrainStats> {
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
        // Every distinct trajectory once, in D's order.
        let mut seen = HashSet::new();
        let segs: Vec<&Segment> = data
            .iter()
            .flat_map(|l| [&l.first, &l.second])
            .filter(|s| seen.insert(Arc::as_ptr(s)))
            .map(|s| &**s)
            .collect();
        self.norm = ObsNorm::fit(segs.iter().copied(), self.obs_dim);

        let n = data.len();
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
                    let pairs: Vec<&Labelled> = idx.iter().map(|&i| &data[i]).collect();
                    let (grads, l, r, h) = self.member_gradients(m, &pairs, CHUNK_ROWS)?;
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

/// Seconds for one training epoch (all members) over `labels` random pairs of `steps`-step
/// feeding-sized segments (observation 25, action 7), with hidden layers `hidden` and the
/// other settings at their defaults.
pub fn bench_epoch(labels: usize, steps: usize, hidden: &[usize]) -> Result<f64> {
    const OBS: usize = 25;
    const ACT: usize = 7;
    let cfg = RewardModelConfig {
        hidden: hidden.to_vec(),
        max_epochs: 1,
        stop_accuracy: f64::INFINITY,
        max_pairs: 0,
        ..RewardModelConfig::default()
    };
    let mut model = RewardModel::new(cfg, OBS, ACT)?;
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    let mut segment = || {
        Arc::new(Segment {
            obs: (0..steps * OBS)
                .map(|_| rng.random_range(-2.0..2.0))
                .collect(),
            actions: (0..steps * ACT)
                .map(|_| rng.random_range(-1.0..1.0))
                .collect(),
        })
    };
    let data: Vec<Labelled> = (0..labels)
        .map(|i| Labelled {
            first: segment(),
            second: segment(),
            target: (i % 2) as f32,
        })
        .collect();
    let t = std::time::Instant::now();
    model.train(&data)?;
    Ok(t.elapsed().as_secs_f64())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testutil::assert_same_gradients;

    /// Draw `n` random segments of `steps` steps (test helper and bench).
    fn random_segments(
        rng: &mut impl Rng,
        n: usize,
        steps: usize,
        o: usize,
        a: usize,
    ) -> Vec<Arc<Segment>> {
        (0..n)
            .map(|_| {
                Arc::new(Segment {
                    obs: (0..steps * o)
                        .map(|_| rng.random_range(-1.0..1.0))
                        .collect(),
                    actions: (0..steps * a)
                        .map(|_| rng.random_range(-1.2..1.2))
                        .collect(),
                })
            })
            .collect()
    }

    fn col(v: &[f32]) -> Tensor {
        Tensor::from_slice(v, v.len(), &Device::Cpu).unwrap()
    }

    fn small(seed: u64, hidden: &[usize]) -> RewardModelConfig {
        RewardModelConfig {
            hidden: hidden.to_vec(),
            seed,
            ..RewardModelConfig::default()
        }
    }

    /// The members' sums and the mean reward computed with candle's ops from scratch.
    fn reference_rewards(model: &RewardModel, obs: &[f32], act: &[f32]) -> Vec<Vec<f32>> {
        let mut x = Vec::new();
        let (o, a) = (model.obs_dim, model.act_dim);
        for (orow, arow) in obs.chunks_exact(o).zip(act.chunks_exact(a)) {
            for ((v, m), s) in orow.iter().zip(&model.norm.mean).zip(&model.norm.std) {
                x.push(((v - m) / s).clamp(-10.0, 10.0));
            }
            x.extend(arow.iter().map(|v| v.clamp(-1.0, 1.0)));
        }
        let x = Tensor::from_vec(x, (obs.len() / o, o + a), &Device::Cpu).unwrap();
        model
            .nets
            .iter()
            .map(|n| {
                n.net
                    .forward(&x)
                    .unwrap()
                    .flatten_all()
                    .unwrap()
                    .to_vec1()
                    .unwrap()
            })
            .collect()
    }

    #[test]
    fn bradley_terry_loss_matches_the_reference() {
        // Reference (Python, math module only):
        //   import math
        //   def ce(s0, s1, p):   # -[(1-p) log softmax(s)[0] + p log softmax(s)[1]]
        //       l0 = s0 - math.log(math.exp(s0) + math.exp(s1))
        //       l1 = s1 - math.log(math.exp(s0) + math.exp(s1))
        //       return -((1 - p) * l0 + p * l1)
        //   s0, s1, p = [1.0, 2.0, -0.5, 30.0], [3.0, -1.0, 0.5, -30.0], [1.0, 0.0, 0.5, 1.0]
        //   [ce(*x) for x in zip(s0, s1, p)]
        //   # [0.12692801104297263, 0.04858735157374206, 0.8132616875182228, 60.0]
        //   sum(_) / 4   # 15.247194262533735
        let want = [0.126_928_01f64, 0.048_587_35, 0.813_261_7, 60.0];
        for (i, w) in want.iter().enumerate() {
            let (s0, s1, p) = (
                [1.0f32, 2.0, -0.5, 30.0][i],
                [3.0f32, -1.0, 0.5, -30.0][i],
                [1.0f32, 0.0, 0.5, 1.0][i],
            );
            let got = bradley_terry_loss(&col(&[s0]), &col(&[s1]), &col(&[p]))
                .unwrap()
                .to_scalar::<f32>()
                .unwrap() as f64;
            assert!(
                (got - w).abs() < 1e-5 * w.max(1.0),
                "pair {i}: {got} vs {w}"
            );
        }
        let all = bradley_terry_loss(
            &col(&[1.0, 2.0, -0.5, 30.0]),
            &col(&[3.0, -1.0, 0.5, -30.0]),
            &col(&[1.0, 0.0, 0.5, 1.0]),
        )
        .unwrap()
        .to_scalar::<f32>()
        .unwrap();
        assert!((all - 15.247_194).abs() < 1e-4, "{all}");
        // The equal label's gradient: d/d s1 = P - p = sigmoid(1) - 0.5 = 0.2310585786300049,
        // so a soft target pulls P toward 0.5 from either side.
        let s1 = candle_core::Var::from_slice(&[0.5f32], 1, &Device::Cpu).unwrap();
        let l = bradley_terry_loss(&col(&[-0.5]), s1.as_tensor(), &col(&[0.5])).unwrap();
        let g = l
            .backward()
            .unwrap()
            .get(&s1)
            .unwrap()
            .to_vec1::<f32>()
            .unwrap()[0];
        assert!((g - 0.231_058_58).abs() < 1e-6, "{g}");
    }

    #[test]
    fn hand_gradients_are_candle_autodiffs() {
        let mut model = RewardModel::new(small(3, &[16, 12]), 3, 2).unwrap();
        let mut rng = ChaCha8Rng::seed_from_u64(4);
        // Uneven lengths, one equal label, a target that is neither.
        let segs: Vec<Arc<Segment>> = [7, 9, 5, 11, 8, 6]
            .iter()
            .flat_map(|&s| random_segments(&mut rng, 1, s, 3, 2))
            .collect();
        let labels: Vec<Labelled> = [(0, 1, 1.0), (2, 3, 0.0), (4, 5, 0.5), (1, 4, 0.0)]
            .iter()
            .map(|&(a, b, t)| Labelled {
                first: segs[a].clone(),
                second: segs[b].clone(),
                target: t,
            })
            .collect();
        // A normaliser that is not the identity.
        model.norm = ObsNorm::fit(segs.iter().map(|s| &**s), 3);
        let pairs: Vec<&Labelled> = labels.iter().collect();
        for m in 0..2 {
            // Chunks of at most 20 rows (one pair each here) and one chunk of all.
            for chunk in [20, 10_000] {
                let (got, loss, right, hard) = model.member_gradients(m, &pairs, chunk).unwrap();
                let mut s0 = Vec::new();
                let mut s1 = Vec::new();
                for l in &labels {
                    for (seg, out) in [(&l.first, &mut s0), (&l.second, &mut s1)] {
                        let mut x = Vec::new();
                        model.push_inputs(&seg.obs, &seg.actions, &mut x);
                        let x = model.input_tensor(x).unwrap();
                        out.push(model.nets[m].net.forward(&x).unwrap().sum_all().unwrap());
                    }
                }
                let (s0, s1) = (
                    Tensor::stack(&s0, 0).unwrap(),
                    Tensor::stack(&s1, 0).unwrap(),
                );
                let t = col(&labels.iter().map(|l| l.target).collect::<Vec<_>>());
                let want = bradley_terry_loss(&s0, &s1, &t).unwrap();
                let w = want.to_scalar::<f32>().unwrap() as f64;
                assert!((loss / 4.0 - w).abs() < 1e-5, "{loss} / 4 vs {w}");
                assert_eq!(hard, 3);
                let d: Vec<f32> = (s1 - s0).unwrap().to_vec1().unwrap();
                let want_right = [0, 1, 3]
                    .iter()
                    .filter(|&&i| (d[i] > 0.0) == (labels[i].target > 0.5))
                    .count();
                assert_eq!(right, want_right);
                assert_same_gradients(&model.opts[m].vars, &got, &want.backward().unwrap());
            }
        }
    }

    #[test]
    fn r_hat_is_the_mean_of_members_in_the_open_interval() {
        let mut model = RewardModel::new(small(5, &[32, 32]), 4, 2).unwrap();
        let mut rng = ChaCha8Rng::seed_from_u64(6);
        let segs = random_segments(&mut rng, 6, 10, 4, 2);
        let data: Vec<Labelled> = (0..3)
            .map(|i| Labelled {
                first: segs[2 * i].clone(),
                second: segs[2 * i + 1].clone(),
                target: 1.0,
            })
            .collect();
        model.train(&data).unwrap();
        assert!(model.trained());
        // Large observations too: the normaliser clips them.
        let obs: Vec<f32> = (0..50 * 4)
            .map(|i| ((i * 37 % 101) as f32 - 50.0) * 0.7)
            .collect();
        let act: Vec<f32> = (0..50 * 2)
            .map(|i| ((i * 13 % 7) as f32 - 3.0) * 0.6)
            .collect();
        let members = reference_rewards(&model, &obs, &act);
        let got = model.predict(&obs, &act).unwrap();
        for (k, g) in got.iter().enumerate() {
            let mean = members.iter().map(|m| m[k]).sum::<f32>() / 3.0;
            assert!((g - mean).abs() < 1e-5, "row {k}: {g} vs {mean}");
            assert!(*g > -1.0 && *g < 1.0);
            assert!(members.iter().all(|m| m[k] > -1.0 && m[k] < 1.0));
        }
        // The tensor path gives the same.
        let ot = Tensor::from_slice(&obs, (50, 4), &Device::Cpu).unwrap();
        let at = Tensor::from_slice(&act, (50, 2), &Device::Cpu).unwrap();
        let t = model.predict_tensor(&ot, &at).unwrap();
        assert_eq!(t.dims(), &[50, 1]);
        let t = t.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        assert!(got.iter().zip(&t).all(|(a, b)| (a - b).abs() < 1e-6));
        // Returns are each member's sum; probabilities come from them.
        let seg = &segs[0];
        let per_member = reference_rewards(&model, &seg.obs, &seg.actions);
        let ret = model.returns(seg).unwrap();
        for (r, m) in ret.iter().zip(&per_member) {
            assert!((r - m.iter().sum::<f32>()).abs() < 1e-4);
        }
        let probs = model
            .preference_probs(&[(&segs[0], &segs[1]), (&segs[2], &segs[3])])
            .unwrap();
        assert_eq!((probs.len(), probs[0].len()), (3, 2));
        let r1 = model.returns(&segs[1]).unwrap();
        for m in 0..3 {
            let want = 1.0 / (1.0 + (ret[m] - r1[m]).exp());
            assert!((probs[m][0] - want).abs() < 1e-5);
        }
        // The model is Send, so it can be trained on another thread.
        fn send<T: Send>(_: &T) {}
        send(&model);
    }

    #[test]
    fn members_draw_their_own_orders_deterministically() {
        for resample in [Resample::Bootstrap, Resample::Shuffle] {
            let cfg = RewardModelConfig {
                resample,
                ..small(11, &[8])
            };
            let mut a = RewardModel::new(cfg.clone(), 2, 1).unwrap();
            let mut b = RewardModel::new(cfg.clone(), 2, 1).unwrap();
            let oa = a.draw_orders(100);
            assert_eq!(
                oa,
                b.draw_orders(100),
                "{resample:?}: same seed, same orders"
            );
            assert_ne!(
                oa,
                a.draw_orders(100),
                "{resample:?}: a new epoch, new orders"
            );
            assert!(
                oa[0] != oa[1] && oa[1] != oa[2],
                "{resample:?}: members differ"
            );
            for o in &oa {
                assert_eq!(o.len(), 100);
                let mut sorted = o.clone();
                sorted.sort();
                sorted.dedup();
                match resample {
                    Resample::Shuffle => assert_eq!(sorted, (0..100).collect::<Vec<_>>()),
                    // P[no repeat in 100 draws of 100] = 100! / 100^100, about 1e-42.
                    Resample::Bootstrap => assert!(sorted.len() < 100),
                }
            }
            let mut c = RewardModel::new(RewardModelConfig { seed: 12, ..cfg }, 2, 1).unwrap();
            assert_ne!(oa, c.draw_orders(100), "{resample:?}: another seed");
        }
        // Whole training sessions are deterministic per seed too.
        let mut rng = ChaCha8Rng::seed_from_u64(2);
        let segs = random_segments(&mut rng, 40, 5, 2, 1);
        let data: Vec<Labelled> = (0..20)
            .map(|i| Labelled {
                first: segs[2 * i].clone(),
                second: segs[2 * i + 1].clone(),
                target: (i % 3) as f32 / 2.0,
            })
            .collect();
        let cfg = RewardModelConfig {
            batch: 8,
            max_epochs: 3,
            ..small(13, &[8, 8])
        };
        let weights = |m: &RewardModel| -> Vec<_> {
            m.nets.iter().map(|n| export(&n.varmap).unwrap()).collect()
        };
        let mut a = RewardModel::new(cfg.clone(), 2, 1).unwrap();
        let mut b = RewardModel::new(cfg.clone(), 2, 1).unwrap();
        assert_eq!(a.train(&data).unwrap(), b.train(&data).unwrap());
        assert_eq!(weights(&a), weights(&b));
        let mut c = RewardModel::new(
            RewardModelConfig {
                resample: Resample::Shuffle,
                ..cfg
            },
            2,
            1,
        )
        .unwrap();
        c.train(&data).unwrap();
        assert_ne!(
            weights(&a),
            weights(&c),
            "shuffle trains otherwise than bootstrap"
        );
    }

    /// Pairs of `steps`-step segments with an oracle's labels under the true reward
    /// `-|obs0|`: each segment's observations scatter (by +-0.5) around its own centre in
    /// [-1, 1]^3, as whole trajectories differ; the action is noise.
    fn oracle_pairs(rng: &mut impl Rng, n: usize, steps: usize) -> Vec<Labelled> {
        let mut segment = || {
            let c: Vec<f32> = (0..3).map(|_| rng.random_range(-1.0..1.0)).collect();
            let obs = (0..steps * 3)
                .map(|i| c[i % 3] + rng.random_range(-0.5..0.5))
                .collect();
            let actions = (0..steps).map(|_| rng.random_range(-1.0..1.0)).collect();
            Arc::new(Segment { obs, actions })
        };
        let ret = |s: &Segment| -> f32 { s.obs.chunks_exact(3).map(|o| -o[0].abs()).sum() };
        (0..n)
            .map(|_| {
                let (first, second) = (segment(), segment());
                let target = if ret(&second) > ret(&first) { 1.0 } else { 0.0 };
                Labelled {
                    first,
                    second,
                    target,
                }
            })
            .collect()
    }

    #[test]
    fn learns_an_oracle_preference_and_generalises() {
        let mut rng = ChaCha8Rng::seed_from_u64(100);
        let train = oracle_pairs(&mut rng, 200, 20);
        let held_out = oracle_pairs(&mut rng, 200, 20);
        let cfg = RewardModelConfig {
            batch: 32,
            lr: 1e-3,
            ..small(0, &[64, 64, 64])
        };
        let mut model = RewardModel::new(cfg, 3, 1).unwrap();
        let before = model.accuracy(&held_out).unwrap();
        let stats = model.train(&train).unwrap();
        let after = model.accuracy(&held_out).unwrap();
        println!("held-out accuracy {before:.3} -> {after:.3}, {stats:?}");
        assert!(after >= 0.9, "held-out accuracy {after} ({stats:?})");
        assert!(model.accuracy(&train).unwrap() >= 0.9);
    }

    #[test]
    fn state_and_restore_continue_identically() {
        let mut rng = ChaCha8Rng::seed_from_u64(8);
        let d1 = oracle_pairs(&mut rng, 30, 6);
        let d2 = oracle_pairs(&mut rng, 45, 6);
        let cfg = RewardModelConfig {
            batch: 16,
            max_epochs: 4,
            ..small(1, &[16, 16])
        };
        let mut a = RewardModel::new(cfg.clone(), 3, 1).unwrap();
        a.train(&d1).unwrap();
        let state = a.state().unwrap();
        let mut b = RewardModel::new(RewardModelConfig { seed: 99, ..cfg }, 3, 1).unwrap();
        assert!(!b.trained());
        for ((name, from), (_, to)) in a.networks().into_iter().zip(b.networks()) {
            assert!(name.starts_with("reward_"));
            import(to, &export(from).unwrap()).unwrap();
        }
        // The state goes through serde as a checkpoint would.
        let state: RewardModelState =
            serde_json::from_str(&serde_json::to_string(&state).unwrap()).unwrap();
        b.restore(&state).unwrap();
        assert!(b.trained());
        let seg = &d2[0].first;
        assert_eq!(
            a.predict(&seg.obs, &seg.actions).unwrap(),
            b.predict(&seg.obs, &seg.actions).unwrap()
        );
        // A snapshot is the same model and trains apart.
        let mut c = a.snapshot().unwrap();
        let all: Vec<Labelled> = d1.iter().chain(&d2).cloned().collect();
        let (sa, sb, sc) = (
            a.train(&all).unwrap(),
            b.train(&all).unwrap(),
            c.train(&all).unwrap(),
        );
        assert_eq!((sa, sa), (sb, sc));
        let p = a.predict(&seg.obs, &seg.actions).unwrap();
        assert_eq!(p, b.predict(&seg.obs, &seg.actions).unwrap());
        assert_eq!(p, c.predict(&seg.obs, &seg.actions).unwrap());
        assert_eq!(a.state().unwrap(), b.state().unwrap());
        c.train(&d1).unwrap();
        assert_eq!(
            p,
            a.predict(&seg.obs, &seg.actions).unwrap(),
            "training the snapshot leaves the original"
        );
        // A state of another shape is refused.
        let mut bad = state.clone();
        bad.obs_mean.push(0.0);
        assert!(b.restore(&bad).is_err());
    }

    #[test]
    fn max_pairs_bounds_a_training_and_cuts_its_last_epoch() {
        // D of 45 pairs, a bound of 100: epochs of 45, 45 and 10 pairs. Unbounded, all 5
        // epochs of 45 (the accuracy target of 2 is never reached).
        let mut rng = ChaCha8Rng::seed_from_u64(21);
        let data = oracle_pairs(&mut rng, 45, 6);
        let cfg = |max_pairs| RewardModelConfig {
            batch: 16,
            max_epochs: 5,
            stop_accuracy: 2.0,
            max_pairs,
            ..small(2, &[8, 8])
        };
        let mut bounded = RewardModel::new(cfg(100), 3, 1).unwrap();
        let stats = bounded.train(&data).unwrap();
        assert_eq!((stats.epochs, stats.pairs), (3, 100), "{stats:?}");
        let mut free = RewardModel::new(cfg(0), 3, 1).unwrap();
        let stats = free.train(&data).unwrap();
        assert_eq!((stats.epochs, stats.pairs), (5, 225), "{stats:?}");
        // A bound of one epoch's worth: exactly one epoch.
        let mut one = RewardModel::new(cfg(45), 3, 1).unwrap();
        let stats = one.train(&data).unwrap();
        assert_eq!((stats.epochs, stats.pairs), (1, 45), "{stats:?}");
    }

    #[test]
    fn equal_labels_pull_toward_one_half() {
        let mut rng = ChaCha8Rng::seed_from_u64(17);
        let s = random_segments(&mut rng, 2, 10, 3, 1);
        let cfg = RewardModelConfig {
            batch: 1,
            lr: 1e-2,
            max_epochs: 30,
            // Never stop early: with only equal labels the accuracy is 1 from the start.
            stop_accuracy: 2.0,
            ..small(4, &[16, 16])
        };
        let mut model = RewardModel::new(cfg, 3, 1).unwrap();
        let label = |target| {
            vec![Labelled {
                first: s[0].clone(),
                second: s[1].clone(),
                target,
            }]
        };
        model.train(&label(1.0)).unwrap();
        let p = |m: &RewardModel| m.preference_probs(&[(&s[0], &s[1])]).unwrap();
        let sure = p(&model);
        assert!(sure.iter().all(|q| q[0] > 0.9), "{sure:?}");
        let stats = model.train(&label(0.5)).unwrap();
        assert_eq!(
            stats.accuracy, 1.0,
            "equal labels are left out of the accuracy"
        );
        let soft = p(&model);
        for (a, b) in sure.iter().zip(&soft) {
            assert!(
                (b[0] - 0.5).abs() < 0.5 * (a[0] - 0.5).abs(),
                "{sure:?} -> {soft:?}"
            );
        }
        assert_eq!(model.accuracy(&label(0.5)).unwrap(), 1.0);
    }

    #[test]
    fn malformed_segments_and_targets_are_refused() {
        let mut model = RewardModel::new(small(0, &[4]), 3, 1).unwrap();
        let good = Arc::new(Segment {
            obs: vec![0.0; 6],
            actions: vec![0.0; 2],
        });
        let bad = Arc::new(Segment {
            obs: vec![0.0; 6],
            actions: vec![0.0; 3],
        });
        let l = |a: &Arc<Segment>, t| {
            vec![Labelled {
                first: good.clone(),
                second: a.clone(),
                target: t,
            }]
        };
        assert!(model.train(&l(&bad, 1.0)).is_err());
        assert!(model.train(&l(&good, 1.5)).is_err());
        assert!(model.predict(&[0.0; 5], &[0.0; 2]).is_err());
        let stats = model.train(&[]).unwrap();
        assert_eq!(stats.epochs, 0);
        assert!(!model.trained());
    }

    /// `RAYON_NUM_THREADS=1 cargo test --release -p pbrl-learner --lib reward_model::tests::bench -- --ignored --nocapture`
    #[test]
    #[ignore]
    fn bench_epoch_times() {
        for hidden in [[256, 256, 256], [128, 128, 128], [64, 64, 64]] {
            let s = bench_epoch(1000, 200, &hidden).unwrap();
            println!("1000 labels x 200 steps, hidden {hidden:?}: {s:.2} s per epoch");
        }
    }
}
