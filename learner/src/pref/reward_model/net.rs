//! One member of the ensemble (linear layers, LeakyReLU between them, tanh after the
//! last) with its hand-taken gradients: a forward pass that keeps a tape, a backward pass
//! over it, and the two in-place kernels (bias plus activation, the activation's
//! derivative) that do each layer's elementwise work in one pass.

use candle_core::backprop::GradStore;
use std::cell::RefCell;

use candle_core::{CpuStorage, Device, InplaceOp2, Layout, Result, Tensor};
use candle_nn::{Linear, Module, VarBuilder};

use super::LEAKY_SLOPE;

/// One member: linear layers, LeakyReLU between them, tanh after the last (one output).
#[derive(Clone, Debug)]
pub struct RewardNet {
    pub(super) layers: Vec<Linear>,
}

impl RewardNet {
    /// Layers `input -> hidden... -> 1`, named `l0`, `l1`, ...
    pub fn new(vb: VarBuilder, input: usize, hidden: &[usize]) -> Result<Self> {
        let sizes: Vec<usize> = std::iter::once(input)
            .chain(hidden.iter().copied())
            .chain(std::iter::once(1))
            .collect();
        Ok(Self {
            layers: pbrl_common::nets::linear_layers(vb, &sizes)?,
        })
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
    pub(super) fn run(&self, x: &Tensor, mut tape: Option<&mut Vec<Tensor>>) -> Result<Tensor> {
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
            z.inplace_op2(&b.detach(), &InPlace(BiasAct(act)))?;
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
    pub(super) fn backward(&self, tape: &[Tensor], dz: Vec<f32>, acc: &mut Grads) -> Result<()> {
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
            let back = InPlace(LeakyBack {
                colsum: RefCell::new(std::mem::take(&mut acc.b[i - 1])),
            });
            dh.inplace_op2(&tape[i], &back)?;
            acc.b[i - 1] = back.0.colsum.into_inner();
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
pub(super) struct Grads {
    w: Vec<Option<Tensor>>,
    b: Vec<Vec<f32>>,
}

impl Grads {
    pub(super) fn new(net: &RewardNet) -> Result<Self> {
        Ok(Self {
            w: vec![None; net.layers.len()],
            b: net
                .layers
                .iter()
                .map(|l| Ok(vec![0.0; l.weight().dim(0)?]))
                .collect::<Result<_>>()?,
        })
    }

    pub(super) fn into_store(self, net: &RewardNet) -> Result<GradStore> {
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

/// An elementwise pass over a layer's values in place: `out` is written, `input` read.
trait Kernel {
    const NAME: &'static str;
    fn apply(&self, out: &mut [f32], input: &[f32]);
}

/// A [`Kernel`] as candle's in-place op on two CPU tensors.
struct InPlace<K>(K);

impl<K: Kernel> InplaceOp2 for InPlace<K> {
    fn name(&self) -> &'static str {
        K::NAME
    }

    fn cpu_fwd(
        &self,
        s1: &mut CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> Result<()> {
        match (s1, l1.contiguous_offsets(), s2, l2.contiguous_offsets()) {
            (CpuStorage::F32(x), Some((a, b)), CpuStorage::F32(y), Some((c, d))) => {
                self.0.apply(&mut x[a..b], &y[c..d]);
                Ok(())
            }
            _ => candle_core::bail!("{}: needs contiguous f32 tensors", K::NAME),
        }
    }
}

/// `z <- act(z + b)` in place, `b` broadcast over rows.
struct BiasAct(Act);

impl Kernel for BiasAct {
    const NAME: &'static str = "reward-bias-act";

    fn apply(&self, z: &mut [f32], b: &[f32]) {
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
    }
}

/// `dh <- dh * leaky'(h)` in place, with the column sums of the result added to `colsum`.
struct LeakyBack {
    colsum: RefCell<Vec<f32>>,
}

impl Kernel for LeakyBack {
    const NAME: &'static str = "reward-leaky-backward";

    fn apply(&self, dh: &mut [f32], h: &[f32]) {
        let mut colsum = self.colsum.borrow_mut();
        let width = colsum.len();
        let slope = LEAKY_SLOPE as f32;
        for (drow, hrow) in dh.chunks_exact_mut(width).zip(h.chunks_exact(width)) {
            for ((d, h), c) in drow.iter_mut().zip(hrow).zip(colsum.iter_mut()) {
                *d *= if *h > 0.0 { 1.0 } else { slope };
                *c += *d;
            }
        }
    }
}
