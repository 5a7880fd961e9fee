//! Adam with its state in the open (candle's own keeps moments and step private, and a
//! checkpoint must hold them), and gradient clipping by global norm.

use candle_core::backprop::GradStore;
use candle_core::{DType, Result, Tensor, Var};

/// Adam (Kingma & Ba), the update PyTorch's `torch.optim.Adam` makes.
pub struct Adam {
    /// Parameters in a fixed order (sorted by name when built from a `VarMap`).
    pub vars: Vec<(String, Var)>,
    /// First and second moments, one per parameter.
    pub m: Vec<Tensor>,
    pub v: Vec<Tensor>,
    /// Steps taken.
    pub t: u64,
    pub lr: f64,
    pub beta1: f64,
    pub beta2: f64,
    pub eps: f64,
}

/// Adam's moments and step count, for checkpoints.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct AdamState {
    pub t: u64,
    pub m: Vec<pbrl_common::wire::Tensor>,
    pub v: Vec<pbrl_common::wire::Tensor>,
}

impl Adam {
    /// The moments and step count.
    pub fn state(&self) -> Result<AdamState> {
        let named = |ts: &[Tensor]| -> Result<Vec<_>> {
            self.vars
                .iter()
                .zip(ts)
                .map(|((name, _), t)| pbrl_common::nets::to_wire(name, t))
                .collect()
        };
        Ok(AdamState {
            t: self.t,
            m: named(&self.m)?,
            v: named(&self.v)?,
        })
    }

    /// Take the moments and step count of `s`, which must name the same variables with
    /// the same shapes.
    pub fn restore(&mut self, s: &AdamState) -> Result<()> {
        if s.m.len() != self.vars.len() || s.v.len() != self.vars.len() {
            candle_core::bail!(
                "optimiser state holds {} moments for {} variables",
                s.m.len(),
                self.vars.len()
            );
        }
        for (i, (name, var)) in self.vars.iter().enumerate() {
            for (src, dst) in [(&s.m[i], &mut self.m[i]), (&s.v[i], &mut self.v[i])] {
                if src.name != *name || src.shape != var.dims() {
                    candle_core::bail!(
                        "optimiser state has {} {:?} where {name} {:?} is expected",
                        src.name,
                        src.shape,
                        var.dims()
                    );
                }
                *dst = Tensor::from_slice(&src.data, var.shape(), var.device())?;
            }
        }
        self.t = s.t;
        Ok(())
    }

    pub fn new(vars: Vec<(String, Var)>, lr: f64) -> Result<Self> {
        let m = vars
            .iter()
            .map(|(_, v)| v.zeros_like())
            .collect::<Result<Vec<_>>>()?;
        Ok(Self {
            v: m.clone(),
            m,
            vars,
            t: 0,
            lr,
            beta1: 0.9,
            beta2: 0.999,
            eps: 1e-8,
        })
    }

    /// Adam over every variable of `varmap`, in name order.
    pub fn for_varmap(varmap: &candle_nn::VarMap, lr: f64) -> Result<Self> {
        Self::new(pbrl_common::nets::named_vars(varmap)?, lr)
    }

    pub fn step(&mut self, grads: &GradStore) -> Result<()> {
        self.t += 1;
        let t = self.t as i32;
        let (b1, b2) = (self.beta1, self.beta2);
        let (c1, c2) = (1.0 - b1.powi(t), 1.0 - b2.powi(t));
        // NOTE: one pass over each parameter's elements, where candle's tensor ops would
        // take thirteen, each into a new buffer.
        let (b1, b2, eps) = (b1 as f32, b2 as f32, self.eps as f32);
        let (step, inv_c2) = ((self.lr / c1) as f32, (1.0 / c2) as f32);
        let flat = |t: &Tensor| t.flatten_all()?.to_vec1::<f32>();
        for (i, (_, var)) in self.vars.iter().enumerate() {
            let Some(g) = grads.get(var) else { continue };
            let (g, mut p) = (flat(g)?, flat(var.as_tensor())?);
            let (mut m, mut v) = (flat(&self.m[i])?, flat(&self.v[i])?);
            for k in 0..p.len() {
                m[k] = b1 * m[k] + (1.0 - b1) * g[k];
                v[k] = b2 * v[k] + (1.0 - b2) * g[k] * g[k];
                // PyTorch: p -= lr / c1 * m / (sqrt(v / c2) + eps)
                p[k] -= step * m[k] / ((v[k] * inv_c2).sqrt() + eps);
            }
            let shape = var.shape();
            var.set(&Tensor::from_vec(p, shape, var.device())?)?;
            self.m[i] = Tensor::from_vec(m, shape, var.device())?;
            self.v[i] = Tensor::from_vec(v, shape, var.device())?;
        }
        Ok(())
    }
}

/// Scale the gradients of `vars` so that their global norm is at most `max_norm`; returns
/// the norm before clipping.
pub fn clip_grad_norm(vars: &[(String, Var)], grads: &mut GradStore, max_norm: f64) -> Result<f64> {
    let mut sq = 0f64;
    for (_, v) in vars {
        if let Some(g) = grads.get(v) {
            sq += g
                .sqr()?
                .sum_all()?
                .to_dtype(DType::F64)?
                .to_scalar::<f64>()?;
        }
    }
    let norm = sq.sqrt();
    if norm > max_norm {
        let s = max_norm / (norm + 1e-6);
        for (_, v) in vars {
            if let Some(g) = grads.remove(v) {
                grads.insert(v, (g * s)?);
            }
        }
    }
    Ok(norm)
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::Device;

    #[test]
    fn adam_matches_pytorch() {
        // Reference: the update of torch.optim.Adam's documentation (defaults betas 0.9,
        // 0.999, eps 1e-8), written out in Python:
        //   p, m, v = [1.0, -2.0], [0, 0], [0, 0]
        //   for t in range(1, 4):
        //       for i in range(2):
        //           g = 2 * p[i]  # d/dp of sum(p ** 2)
        //           m[i] = 0.9 * m[i] + 0.1 * g; v[i] = 0.999 * v[i] + 0.001 * g * g
        //           mh, vh = m[i] / (1 - 0.9 ** t), v[i] / (1 - 0.999 ** t)
        //           p[i] -= 0.1 * mh / (math.sqrt(vh) + 1e-8)
        //   print(p)  # [0.7015862729460303, -1.7006233920464653]
        let p = Var::from_slice(&[1.0f32, -2.0], 2, &Device::Cpu).unwrap();
        let mut opt = Adam::new(vec![("p".into(), p.clone())], 0.1).unwrap();
        for _ in 0..3 {
            let loss = p.as_tensor().sqr().unwrap().sum_all().unwrap();
            opt.step(&loss.backward().unwrap()).unwrap();
        }
        let v = p.as_tensor().to_vec1::<f32>().unwrap();
        assert!(
            (v[0] - 0.701_586_3).abs() < 1e-5 && (v[1] + 1.700_623_4).abs() < 1e-5,
            "{v:?}"
        );
        assert_eq!(opt.t, 3);
    }

    #[test]
    fn clipping_scales_to_the_norm() {
        let p = Var::from_slice(&[3.0f32, 4.0], 2, &Device::Cpu).unwrap();
        let vars = vec![("p".to_string(), p.clone())];
        // d/dp of sum(p^2)/2 is p: norm 5.
        let loss = (p.as_tensor().sqr().unwrap().sum_all().unwrap() * 0.5).unwrap();
        let mut grads = loss.backward().unwrap();
        let norm = clip_grad_norm(&vars, &mut grads, 0.5).unwrap();
        assert!((norm - 5.0).abs() < 1e-5);
        let g = grads.get(&p).unwrap().to_vec1::<f32>().unwrap();
        assert!(
            (g[0] - 0.3).abs() < 1e-4 && (g[1] - 0.4).abs() < 1e-4,
            "{g:?}"
        );
    }
}
