//! The policy an actor runs, rebuilt from the learner's weights message.

use anyhow::{bail, Context, Result};
use pbrl_common::nets::{import, GaussianPolicy, Owned};
use pbrl_common::wire::Weights;
use pbrl_common::RunningNorm;
use rand::Rng;
use rand_distr::StandardNormal;

/// A policy with the observation normaliser it was trained with.
pub struct Policy {
    pub version: u64,
    /// Env steps the learner had consumed when it made these weights.
    pub made_at: u64,
    net: Owned<GaussianPolicy>,
    norm: RunningNorm,
    act_dim: usize,
    random_actions: bool,
    /// Episodes this version may run (0: no limit).
    pub episodes_allowed: u32,
}

impl Policy {
    /// Rebuild the learner's policy: the hidden sizes follow from the tensors' shapes.
    pub fn from_weights(w: &Weights) -> Result<Self> {
        let (obs_dim, act_dim) = (w.obs_dim as usize, w.act_dim as usize);
        let mut layers: Vec<(usize, &[usize])> = w
            .tensors
            .iter()
            .filter_map(|t| {
                let i = t
                    .name
                    .strip_prefix("pi.l")?
                    .strip_suffix(".weight")?
                    .parse()
                    .ok()?;
                Some((i, t.shape.as_slice()))
            })
            .collect();
        layers.sort_by_key(|(i, _)| *i);
        if layers.is_empty() || layers.iter().any(|(_, s)| s.len() != 2) {
            bail!(
                "weights version {} hold no policy layers pi.l<i>.weight",
                w.version
            );
        }
        let hidden: Vec<usize> = layers[..layers.len() - 1]
            .iter()
            .map(|(_, s)| s[0])
            .collect();
        if layers[0].1[1] != obs_dim || layers[layers.len() - 1].1[0] != 2 * act_dim {
            bail!(
                "weights version {}: policy maps {} to {}, expected {obs_dim} to {}",
                w.version,
                layers[0].1[1],
                layers[layers.len() - 1].1[0],
                2 * act_dim
            );
        }
        let mut rng = rand::rng();
        let net = Owned::build(&mut rng, |vb| {
            GaussianPolicy::new(vb, obs_dim, &hidden, act_dim)
        })?;
        import(&net.varmap, &w.tensors)
            .with_context(|| format!("loading weights version {}", w.version))?;
        let mut norm = RunningNorm::new(obs_dim, w.obs_clip as f64);
        norm.mean = w.obs_mean.iter().map(|x| *x as f64).collect();
        norm.var = w.obs_var.iter().map(|x| *x as f64).collect();
        Ok(Self {
            version: w.version,
            made_at: w.env_steps,
            net,
            norm,
            act_dim,
            random_actions: w.random_actions,
            episodes_allowed: w.episodes_per_actor,
        })
    }

    /// An action for a raw observation: uniform when the learner asks for random actions,
    /// else sampled (or the mean, when `deterministic`).
    pub fn act(&self, obs: &[f32], rng: &mut impl Rng, deterministic: bool) -> Result<Vec<f32>> {
        if self.random_actions && !deterministic {
            return Ok((0..self.act_dim)
                .map(|_| rng.random_range(-1.0..1.0))
                .collect());
        }
        let mut o = obs.to_vec();
        self.norm.apply(&mut o);
        let noise = (!deterministic).then(|| {
            (0..self.act_dim)
                .map(|_| rng.sample(StandardNormal))
                .collect()
        });
        Ok(self.net.net.act_one(o, noise)?)
    }
}
