//! The networks actors and learner share (candle, CPU, f32): MLPs, the tanh-squashed
//! Gaussian policy, the value network and the twin Q critics. Each trainable network owns
//! its own `VarMap`; weights travel as named tensors ([`crate::wire::Weights`]).

use candle_core::backprop::GradStore;
use candle_core::{DType, Device, Result, Tensor, Var, D};
use candle_nn::{Linear, Module, VarBuilder, VarMap};
use rand::Rng;

use crate::par::Par;
use crate::wire;

/// Bounds of the policy's log standard deviation (CleanRL's SAC).
pub const LOG_STD_MIN: f64 = -5.0;
pub const LOG_STD_MAX: f64 = 2.0;

/// Linear layers `sizes[0] -> sizes[1] -> ... -> sizes[n-1]`, named `l0`, `l1`, ... (every
/// network pbrl trains is such a stack with its own activations).
pub fn linear_layers(vb: VarBuilder, sizes: &[usize]) -> Result<Vec<Linear>> {
    sizes
        .windows(2)
        .enumerate()
        .map(|(i, w)| candle_nn::linear(w[0], w[1], vb.pp(format!("l{i}"))))
        .collect()
}

/// A multilayer perceptron: ReLU between layers, none after the last.
#[derive(Clone, Debug)]
pub struct Mlp {
    layers: Vec<Linear>,
}

impl Mlp {
    /// Layers `sizes[0] -> sizes[1] -> ... -> sizes[n-1]`, named `l0`, `l1`, ...
    pub fn new(vb: VarBuilder, sizes: &[usize]) -> Result<Self> {
        Ok(Self {
            layers: linear_layers(vb, sizes)?,
        })
    }

    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let mut h = x.clone();
        for (i, l) in self.layers.iter().enumerate() {
            h = l.forward(&h)?;
            if i + 1 < self.layers.len() {
                h = h.relu()?;
            }
        }
        Ok(h)
    }
}

/// What [`Mlp::forward_taped`] keeps for [`Mlp::backward`]: each layer's input.
#[derive(Clone)]
pub struct MlpTape {
    inputs: Vec<Tensor>,
}

// NOTE: candle's autodiff computes the gradient of every operand of every op (the weights
// of a network that is not trained by this loss and the constant inputs included) and adds
// each into a zero-filled buffer. The SAC step takes its gradients by hand instead (the
// forward pass with a tape, then `backward`), which does only the work the step needs.
impl Mlp {
    /// The forward pass outside candle's autodiff, keeping each layer's input. The same
    /// operations as [`Mlp::forward`], so the same outputs.
    pub fn forward_taped(&self, x: &Tensor) -> Result<(Tensor, MlpTape)> {
        let mut inputs = Vec::with_capacity(self.layers.len());
        let mut h = x.detach();
        for (i, l) in self.layers.iter().enumerate() {
            let mut z = h.matmul(&l.weight().detach().t()?)?;
            if let Some(b) = l.bias() {
                z = z.broadcast_add(&b.detach())?;
            }
            inputs.push(h);
            h = if i + 1 < self.layers.len() {
                z.relu()?
            } else {
                z
            };
        }
        Ok((h, MlpTape { inputs }))
    }

    /// Backpropagate `dy`, a loss's gradient with respect to the output of
    /// [`Mlp::forward_taped`]: the weights' gradients go into `grads`, keyed by their
    /// variables (none are computed without it), and the input's gradient is returned when
    /// `want_dx`.
    pub fn backward(
        &self,
        tape: &MlpTape,
        dy: &Tensor,
        grads: Option<&mut GradStore>,
        want_dx: bool,
    ) -> Result<Option<Tensor>> {
        self.backward_on(tape, dy, grads, want_dx, &Par::default())
    }

    /// [`Mlp::backward`] with each layer's weight gradients beside its input gradient on
    /// `par` (the two products share only their inputs).
    pub fn backward_on(
        &self,
        tape: &MlpTape,
        dy: &Tensor,
        mut grads: Option<&mut GradStore>,
        want_dx: bool,
        par: &Par,
    ) -> Result<Option<Tensor>> {
        let mut dz = dy.clone();
        for (i, l) in self.layers.iter().enumerate().rev() {
            let x = &tape.inputs[i];
            let wants_dx = i > 0 || want_dx;
            let weight_grads = {
                let (dz, x, with_bias) = (dz.clone(), x.clone(), l.bias().is_some());
                move || -> Result<(Tensor, Option<Tensor>)> {
                    let dw = dz.t()?.matmul(&x)?;
                    // NOTE: the column sums as a product with a row of ones: candle's
                    // reduction over the batch dimension is several times slower.
                    let db = with_bias
                        .then(|| {
                            let ones = Tensor::ones((1, dz.dim(0)?), dz.dtype(), dz.device())?;
                            ones.matmul(&dz)?.squeeze(0)
                        })
                        .transpose()?;
                    Ok((dw, db))
                }
            };
            let input_grad = || {
                wants_dx
                    .then(|| dz.matmul(&l.weight().detach()))
                    .transpose()
            };
            let dx = match grads.as_deref_mut() {
                Some(g) => {
                    // NOTE: beside each other only when there are two products to run.
                    let (dx, wg) = if wants_dx {
                        par.join(input_grad, weight_grads)
                    } else {
                        (Ok(None), weight_grads())
                    };
                    let (dw, db) = wg?;
                    g.insert(l.weight(), dw);
                    if let (Some(b), Some(db)) = (l.bias(), db) {
                        g.insert(b, db);
                    }
                    dx?
                }
                None => input_grad()?,
            };
            let Some(dx) = dx else {
                return Ok(None);
            };
            if i == 0 {
                return Ok(Some(dx));
            }
            // ReLU: this layer's input is relu(z) of the one before, positive where z was;
            // its sign is the 0/1 mask.
            dz = (dx * x.sign()?)?;
        }
        Ok(None)
    }
}

/// The layer sizes of an MLP from `input` through `hidden` to `output`.
fn sizes(input: usize, hidden: &[usize], output: usize) -> Vec<usize> {
    std::iter::once(input)
        .chain(hidden.iter().copied())
        .chain(std::iter::once(output))
        .collect()
}

/// Every variable of `varmap` with its name, in name order (a `VarMap` iterates in hash
/// order, which differs from run to run).
pub fn named_vars(varmap: &VarMap) -> Result<Vec<(String, Var)>> {
    let data = varmap
        .data()
        .lock()
        .map_err(|_| candle_core::Error::Msg("a VarMap lock was poisoned".into()))?;
    let mut vars: Vec<(String, Var)> = data.iter().map(|(k, v)| (k.clone(), v.clone())).collect();
    vars.sort_by(|a, b| a.0.cmp(&b.0));
    Ok(vars)
}

/// Re-initialise every variable of `varmap` from `rng`, in name order, as PyTorch's
/// `nn.Linear` does: weights and biases from U(-1/sqrt(fan_in), 1/sqrt(fan_in)).
/// (candle's own random generator cannot be seeded.)
pub fn init_seeded(varmap: &VarMap, rng: &mut impl Rng) -> Result<()> {
    let vars = named_vars(varmap)?;
    let fan_in_of = |name: &str, var: &Var| match name.strip_suffix(".bias") {
        Some(stem) => vars
            .iter()
            .find(|(n, _)| *n == format!("{stem}.weight"))
            .map(|(_, w)| w.dims()[1])
            .unwrap_or(1),
        None => var.dims().last().copied().unwrap_or(1),
    };
    for (name, var) in &vars {
        let b = 1.0 / (fan_in_of(name, var) as f32).sqrt();
        let vals: Vec<f32> = (0..var.elem_count())
            .map(|_| rng.random_range(-b..b))
            .collect();
        var.set(&Tensor::from_vec(vals, var.shape(), var.device())?)?;
    }
    Ok(())
}

/// Every variable of `varmap` as named tensors, in name order.
pub fn export(varmap: &VarMap) -> Result<Vec<wire::Tensor>> {
    named_vars(varmap)?
        .into_iter()
        .map(|(name, var)| to_wire(&name, var.as_tensor()))
        .collect()
}

/// One tensor as a named, row-major f32 wire tensor.
pub fn to_wire(name: &str, t: &Tensor) -> Result<wire::Tensor> {
    Ok(wire::Tensor {
        name: name.to_string(),
        shape: t.dims().to_vec(),
        data: t.flatten_all()?.to_vec1::<f32>()?,
    })
}

/// Set the variables of `varmap` from named tensors; every variable must be given, with
/// its shape.
pub fn import(varmap: &VarMap, tensors: &[wire::Tensor]) -> Result<()> {
    let data = varmap
        .data()
        .lock()
        .map_err(|_| candle_core::Error::Msg("a VarMap lock was poisoned".into()))?;
    if tensors.len() != data.len() {
        candle_core::bail!(
            "weights hold {} tensors, the network has {}",
            tensors.len(),
            data.len()
        );
    }
    for t in tensors {
        let Some(var) = data.get(&t.name) else {
            candle_core::bail!(
                "weights hold tensor {:?}, which the network does not have",
                t.name
            );
        };
        if var.dims() != t.shape.as_slice() {
            candle_core::bail!(
                "tensor {:?} has shape {:?}, the network's is {:?}",
                t.name,
                t.shape,
                var.dims()
            );
        }
        var.set(&Tensor::from_slice(
            &t.data,
            t.shape.as_slice(),
            var.device(),
        )?)?;
    }
    Ok(())
}

/// log(1 + exp(x)), stable for large |x|.
pub fn softplus(x: &Tensor) -> Result<Tensor> {
    // max(x, 0) + log(1 + exp(-|x|))
    x.relu()? + (x.abs()?.neg()?.exp()? + 1.0)?.log()?
}

/// A tanh-squashed Gaussian policy: the MLP gives the mean and log standard deviation of a
/// Gaussian over pre-squash actions u; the action is tanh(u), in (-1, 1).
#[derive(Clone, Debug)]
pub struct GaussianPolicy {
    mlp: Mlp,
    act_dim: usize,
}

impl GaussianPolicy {
    pub fn new(vb: VarBuilder, obs_dim: usize, hidden: &[usize], act_dim: usize) -> Result<Self> {
        Ok(Self {
            mlp: Mlp::new(vb.pp("pi"), &sizes(obs_dim, hidden, 2 * act_dim))?,
            act_dim,
        })
    }

    pub fn act_dim(&self) -> usize {
        self.act_dim
    }

    /// Mean and log standard deviation, `[batch, act_dim]` each; the log-std is squashed
    /// smoothly into [LOG_STD_MIN, LOG_STD_MAX].
    pub fn dist(&self, obs: &Tensor) -> Result<(Tensor, Tensor)> {
        let out = self.mlp.forward(obs)?;
        let mean = out.narrow(D::Minus1, 0, self.act_dim)?;
        let raw = out.narrow(D::Minus1, self.act_dim, self.act_dim)?;
        // NOTE: tanh then affine, as CleanRL, rather than a hard clamp whose gradient dies.
        let log_std = raw.tanh()?.affine(
            (LOG_STD_MAX - LOG_STD_MIN) / 2.0,
            (LOG_STD_MAX + LOG_STD_MIN) / 2.0,
        )?;
        Ok((mean, log_std))
    }

    /// A reparameterised sample `tanh(mean + std * eps)` for given standard normal noise
    /// `eps`, and its log-probability (summed over action dimensions, `[batch, 1]`).
    pub fn sample(&self, obs: &Tensor, eps: &Tensor) -> Result<(Tensor, Tensor)> {
        let (mean, log_std) = self.dist(obs)?;
        let u = (&mean + (log_std.exp()? * eps)?)?;
        let logp = squashed_log_prob(&u, &mean, &log_std)?;
        Ok((u.tanh()?, logp))
    }

    /// Log-probability of actions `a` in (-1, 1) (`[batch, 1]`).
    pub fn log_prob(&self, obs: &Tensor, a: &Tensor) -> Result<Tensor> {
        let (mean, log_std) = self.dist(obs)?;
        // NOTE: atanh of an action clamped away from +-1, where the density is singular.
        let a = a.clamp(-1.0 + 1e-6, 1.0 - 1e-6)?;
        let u = (((&a + 1.0)? / (1.0 - &a)?)?.log()? * 0.5)?;
        squashed_log_prob(&u, &mean, &log_std)
    }

    /// The deterministic action tanh(mean).
    pub fn deterministic(&self, obs: &Tensor) -> Result<Tensor> {
        self.dist(obs)?.0.tanh()
    }

    /// [`GaussianPolicy::dist`] outside candle's autodiff: mean, log-std and the tape.
    fn dist_taped(&self, obs: &Tensor) -> Result<(Tensor, Tensor, DistTape)> {
        let (out, mlp) = self.mlp.forward_taped(obs)?;
        let mean = out.narrow(D::Minus1, 0, self.act_dim)?;
        let tanh_raw = out.narrow(D::Minus1, self.act_dim, self.act_dim)?.tanh()?;
        let log_std = tanh_raw.affine(
            (LOG_STD_MAX - LOG_STD_MIN) / 2.0,
            (LOG_STD_MAX + LOG_STD_MIN) / 2.0,
        )?;
        Ok((mean, log_std, DistTape { mlp, tanh_raw }))
    }

    /// The weights' gradients, into `grads`, for the gradients of a loss with respect to
    /// the mean and the log-std of [`GaussianPolicy::dist_taped`].
    fn backward_dist(
        &self,
        tape: &DistTape,
        dmean: &Tensor,
        dlog_std: &Tensor,
        grads: &mut GradStore,
        par: &Par,
    ) -> Result<()> {
        // log_std = k tanh(raw) + c: d/draw = k (1 - tanh(raw)^2).
        let k = (LOG_STD_MAX - LOG_STD_MIN) / 2.0;
        let draw = (dlog_std * tape.tanh_raw.sqr()?.affine(-k, k)?)?;
        let dout = Tensor::cat(&[dmean, &draw], D::Minus1)?;
        self.mlp
            .backward_on(&tape.mlp, &dout, Some(grads), false, par)?;
        Ok(())
    }

    /// [`GaussianPolicy::sample`] outside candle's autodiff, keeping what
    /// [`GaussianPolicy::backward_sample`] needs.
    pub fn sample_taped(&self, obs: &Tensor, eps: &Tensor) -> Result<(Tensor, Tensor, PolicyTape)> {
        let (mean, log_std, dist) = self.dist_taped(obs)?;
        let std_eps = (log_std.exp()? * eps)?;
        let u = (&mean + &std_eps)?;
        let logp = squashed_log_prob(&u, &mean, &log_std)?;
        let a = u.tanh()?;
        let tape = PolicyTape {
            dist,
            a: a.clone(),
            std_eps,
        };
        Ok((a, logp, tape))
    }

    /// [`GaussianPolicy::log_prob`] outside candle's autodiff, keeping what
    /// [`GaussianPolicy::backward_log_prob`] needs.
    pub fn log_prob_taped(&self, obs: &Tensor, a: &Tensor) -> Result<(Tensor, LogProbTape)> {
        let (mean, log_std, dist) = self.dist_taped(obs)?;
        let a = a.clamp(-1.0 + 1e-6, 1.0 - 1e-6)?;
        let u = (((&a + 1.0)? / (1.0 - &a)?)?.log()? * 0.5)?;
        let logp = squashed_log_prob(&u, &mean, &log_std)?;
        let std = log_std.exp()?;
        let z = ((&u - &mean)? / &std)?;
        let tape = LogProbTape {
            dist,
            z_over_std: (&z / &std)?,
            z,
        };
        Ok((logp, tape))
    }

    /// The weights' gradients, into `grads`, of a loss whose gradient with respect to each
    /// row's log-probability of fixed actions is `dlogp` (`[batch, 1]`): the tanh term
    /// does not move, `d logp / d mean = z / std` and `d logp / d log_std = z^2 - 1`.
    pub fn backward_log_prob(
        &self,
        tape: &LogProbTape,
        dlogp: &Tensor,
        grads: &mut GradStore,
    ) -> Result<()> {
        let dmean = tape.z_over_std.broadcast_mul(dlogp)?;
        let dlog_std = tape.z.sqr()?.affine(1.0, -1.0)?.broadcast_mul(dlogp)?;
        self.backward_dist(&tape.dist, &dmean, &dlog_std, grads, &Par::default())
    }

    /// The weights' gradients, into `grads`, of a loss `L` whose gradient with respect to
    /// the sampled actions is `da` (`[batch, act_dim]`) and with respect to each row's
    /// log-probability is the constant `dlogp`.
    ///
    /// With `u = mean + std eps` and `a = tanh(u)`, the log-probability's total derivatives
    /// are `d logp / d mean = 2a` and `d logp / d log_std = 2a std eps - 1` (the Gaussian
    /// term's `z = eps` does not move), so
    /// `dL/d mean = da (1 - a^2) + 2 dlogp a` and `dL/d log_std = dL/d mean std eps - dlogp`,
    /// then through the squash of the log-std, `(MAX - MIN) / 2 (1 - tanh(raw)^2)`. Each
    /// layer's weight and input gradients run side by side on `par`.
    pub fn backward_sample(
        &self,
        tape: &PolicyTape,
        da: &Tensor,
        dlogp: f64,
        grads: &mut GradStore,
        par: &Par,
    ) -> Result<()> {
        let a = &tape.a;
        let du = (da * a.sqr()?.affine(-1.0, 1.0)?)?;
        let dmean = (du + (a * (2.0 * dlogp))?)?;
        let dlog_std = ((&dmean * &tape.std_eps)? - dlogp)?;
        self.backward_dist(&tape.dist, &dmean, &dlog_std, grads, par)
    }

    /// The action for one observation, as the network sees it (normalised where the
    /// backbone normalises): the mean when `noise` is `None`, else the sample for that
    /// standard normal noise.
    pub fn act_one(&self, obs: Vec<f32>, noise: Option<Vec<f32>>) -> Result<Vec<f32>> {
        let obs_dim = obs.len();
        let o = Tensor::from_vec(obs, (1, obs_dim), &Device::Cpu)?;
        let a = match noise {
            None => self.deterministic(&o)?,
            Some(eps) => {
                let eps = Tensor::from_vec(eps, (1, self.act_dim), &Device::Cpu)?;
                self.sample(&o, &eps)?.0
            }
        };
        a.squeeze(0)?.to_vec1::<f32>()
    }
}

/// What [`GaussianPolicy::dist_taped`] keeps: the network's tape and the squashed raw
/// log-std.
struct DistTape {
    mlp: MlpTape,
    tanh_raw: Tensor,
}

/// What [`GaussianPolicy::sample_taped`] keeps for [`GaussianPolicy::backward_sample`].
pub struct PolicyTape {
    dist: DistTape,
    a: Tensor,
    std_eps: Tensor,
}

/// What [`GaussianPolicy::log_prob_taped`] keeps for [`GaussianPolicy::backward_log_prob`].
pub struct LogProbTape {
    dist: DistTape,
    z: Tensor,
    z_over_std: Tensor,
}

/// log N(u; mean, exp(log_std)) summed over the last dimension, minus the log-Jacobian of
/// tanh: log(1 - tanh(u)^2) = 2 (log 2 - u - softplus(-2u)).
pub fn squashed_log_prob(u: &Tensor, mean: &Tensor, log_std: &Tensor) -> Result<Tensor> {
    let z = ((u - mean)? / log_std.exp()?)?;
    let half_log_2pi = 0.5 * (2.0 * std::f64::consts::PI).ln();
    let gauss = ((z.sqr()? * -0.5)? - log_std)?.affine(1.0, -half_log_2pi)?;
    let log_jac = ((u.affine(-1.0, 2f64.ln())? - softplus(&u.affine(-2.0, 0.0)?)?)? * 2.0)?;
    (gauss - log_jac)?.sum_keepdim(D::Minus1)
}

/// A state-value network.
#[derive(Clone, Debug)]
pub struct ValueNet {
    mlp: Mlp,
}

impl ValueNet {
    pub fn new(vb: VarBuilder, obs_dim: usize, hidden: &[usize]) -> Result<Self> {
        Ok(Self {
            mlp: Mlp::new(vb.pp("v"), &sizes(obs_dim, hidden, 1))?,
        })
    }

    /// Values, `[batch, 1]`.
    pub fn forward(&self, obs: &Tensor) -> Result<Tensor> {
        self.mlp.forward(obs)
    }

    /// [`ValueNet::forward`] outside candle's autodiff, with its tape.
    pub fn forward_taped(&self, obs: &Tensor) -> Result<(Tensor, MlpTape)> {
        self.mlp.forward_taped(obs)
    }

    /// The weights' gradients, into `grads`, for the gradient `dv` of the values.
    pub fn backward(&self, tape: &MlpTape, dv: &Tensor, grads: &mut GradStore) -> Result<()> {
        self.mlp.backward(tape, dv, Some(grads), false)?;
        Ok(())
    }
}

/// Two Q networks over (observation, action).
#[derive(Clone, Debug)]
pub struct TwinQ {
    q1: Mlp,
    q2: Mlp,
    act_dim: usize,
}

impl TwinQ {
    pub fn new(vb: VarBuilder, obs_dim: usize, act_dim: usize, hidden: &[usize]) -> Result<Self> {
        let s = sizes(obs_dim + act_dim, hidden, 1);
        Ok(Self {
            q1: Mlp::new(vb.pp("q1"), &s)?,
            q2: Mlp::new(vb.pp("q2"), &s)?,
            act_dim,
        })
    }

    /// Both Q values, `[batch, 1]` each (the two networks side by side on `par`).
    pub fn forward(&self, obs: &Tensor, act: &Tensor, par: &Par) -> Result<(Tensor, Tensor)> {
        let x = Tensor::cat(&[obs, act], D::Minus1)?;
        let (q2, x2) = (self.q2.clone(), x.clone());
        let (q1, q2) = par.join(|| self.q1.forward(&x), move || q2.forward(&x2));
        Ok((q1?, q2?))
    }

    /// [`TwinQ::forward`] outside candle's autodiff, with each network's tape.
    pub fn forward_taped(
        &self,
        obs: &Tensor,
        act: &Tensor,
        par: &Par,
    ) -> Result<((Tensor, Tensor), [MlpTape; 2])> {
        let x = Tensor::cat(&[obs, act], D::Minus1)?;
        let (q2, x2) = (self.q2.clone(), x.clone());
        let (r1, r2) = par.join(|| self.q1.forward_taped(&x), move || q2.forward_taped(&x2));
        let ((q1, t1), (q2, t2)) = (r1?, r2?);
        Ok(((q1, q2), [t1, t2]))
    }

    /// Backpropagate the gradients `dq` of both outputs (the two networks side by side on
    /// `par`): into the weights' gradients when `grads` is given, and to the action
    /// (`[batch, act_dim]`, the sum over both networks) when `want_da`.
    pub fn backward(
        &self,
        tapes: &[MlpTape; 2],
        dq: [&Tensor; 2],
        mut grads: Option<&mut GradStore>,
        want_da: bool,
        par: &Par,
    ) -> Result<Option<Tensor>> {
        let want_grads = grads.is_some();
        let (q2, tape2, dq2) = (self.q2.clone(), tapes[1].clone(), dq[1].clone());
        let (r1, r2) = par.join(
            || {
                self.q1
                    .backward(&tapes[0], dq[0], grads.as_deref_mut(), want_da)
            },
            move || {
                let mut g2 = GradStore::default();
                let dx2 = q2.backward(&tape2, &dq2, want_grads.then_some(&mut g2), want_da)?;
                Ok::<_, candle_core::Error>((dx2, g2))
            },
        );
        let (dx1, (dx2, g2)) = (r1?, r2?);
        if let Some(g) = grads {
            g.extend(g2)?;
        }
        let (Some(dx1), Some(dx2)) = (dx1, dx2) else {
            return Ok(None);
        };
        let dx = (dx1 + dx2)?;
        let width = dx.dim(D::Minus1)?;
        Ok(Some(dx.narrow(
            D::Minus1,
            width - self.act_dim,
            self.act_dim,
        )?))
    }
}

/// A network and the `VarMap` that owns its variables.
pub struct Owned<M> {
    pub varmap: VarMap,
    pub net: M,
}

impl<M> Owned<M> {
    /// Build a network in a fresh `VarMap` and initialise it from `rng`.
    pub fn build(rng: &mut impl Rng, f: impl FnOnce(VarBuilder) -> Result<M>) -> Result<Self> {
        let varmap = VarMap::new();
        let vb = VarBuilder::from_varmap(&varmap, DType::F32, &Device::Cpu);
        let net = f(vb)?;
        init_seeded(&varmap, rng)?;
        Ok(Self { varmap, net })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    fn t2(rows: &[&[f32]]) -> Tensor {
        let flat: Vec<f32> = rows.iter().flat_map(|r| r.iter().copied()).collect();
        Tensor::from_vec(flat, (rows.len(), rows[0].len()), &Device::Cpu).unwrap()
    }

    #[test]
    fn tanh_gaussian_log_prob_matches_the_reference() {
        // Reference (Python, math module only):
        //   import math
        //   def lp(u, m, s):
        //       z = (u - m) / math.exp(s)
        //       g = -0.5 * z * z - s - 0.5 * math.log(2 * math.pi)
        //       return g - math.log(1 - math.tanh(u) ** 2)
        //   mean, log_std, eps = [0.1, -0.2], [-0.5, 0.3], [0.3, -1.2]
        //   u = [m + math.exp(s) * e for m, s, e in zip(mean, log_std, eps)]
        //   print(sum(lp(*x) for x in zip(u, mean, log_std)))   # -0.0191962
        let mean = t2(&[&[0.1, -0.2]]);
        let log_std = t2(&[&[-0.5, 0.3]]);
        let eps = t2(&[&[0.3, -1.2]]);
        let u = (&mean + (log_std.exp().unwrap() * &eps).unwrap()).unwrap();
        let lp = squashed_log_prob(&u, &mean, &log_std).unwrap();
        let v = lp.flatten_all().unwrap().to_vec1::<f32>().unwrap()[0];
        assert!((v - (-0.0191962)).abs() < 1e-4, "{v}");
    }

    #[test]
    fn policy_log_prob_of_its_own_sample_agrees_and_weights_round_trip() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(0);
        let p = Owned::build(&mut rng, |vb| GaussianPolicy::new(vb, 3, &[16, 16], 2)).unwrap();
        let obs = t2(&[&[0.5, -1.0, 0.2], &[0.0, 0.3, -0.7]]);
        let eps = t2(&[&[0.1, -0.4], &[1.2, 0.0]]);
        let (a, lp) = p.net.sample(&obs, &eps).unwrap();
        let lp2 = p.net.log_prob(&obs, &a).unwrap();
        let d = (lp - lp2).unwrap().abs().unwrap().max_keepdim(0).unwrap();
        assert!(d.flatten_all().unwrap().to_vec1::<f32>().unwrap()[0] < 1e-3);
        // Same seed, same weights; export then import gives the same actions.
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(0);
        let q = Owned::build(&mut rng, |vb| GaussianPolicy::new(vb, 3, &[16, 16], 2)).unwrap();
        assert_eq!(export(&p.varmap).unwrap(), export(&q.varmap).unwrap());
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
        let r = Owned::build(&mut rng, |vb| GaussianPolicy::new(vb, 3, &[16, 16], 2)).unwrap();
        assert_ne!(export(&p.varmap).unwrap(), export(&r.varmap).unwrap());
        import(&r.varmap, &export(&p.varmap).unwrap()).unwrap();
        let (ra, _) = r.net.sample(&obs, &eps).unwrap();
        assert_eq!(a.to_vec2::<f32>().unwrap(), ra.to_vec2::<f32>().unwrap());
        // A tensor of the wrong shape is refused with its name.
        let mut bad = export(&p.varmap).unwrap();
        bad[0].shape = vec![1, bad[0].data.len()];
        let e = import(&r.varmap, &bad).unwrap_err();
        assert!(e.to_string().contains(&bad[0].name), "{e}");
    }
}
