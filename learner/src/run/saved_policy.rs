//! A run's policy read back from its run folder: the weights its actors acted with at a
//! checkpoint (the policy's tensors and the observation normaliser), with the run's config,
//! what `pbrl eval`, `pbrl watch` and `pbrl export` start from.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use pbrl_common::wire::Weights;

use crate::pref::labels::{Counts, LabelStore};
use crate::run::backbone::{identity_norm, BackboneState};
use crate::run::checkpoint::decode_saved;
use crate::run::config::{Algo, LearnerConfig};
use crate::run::run_folder::RunFolder;

/// A run's policy at one of its checkpoints.
pub struct SavedPolicy {
    /// The run folder.
    pub folder: PathBuf,
    /// The run's resolved config (its `config.json`).
    pub config: LearnerConfig,
    /// The policy as an actor rebuilds it ([`Weights`]; no credit, no acknowledgements).
    pub weights: Weights,
    /// Env steps and weights version of the checkpoint.
    pub env_steps: u64,
    pub version: u64,
    /// The checkpoint's folder.
    pub checkpoint: PathBuf,
    /// Whether the run reached its total (`finished.json`).
    pub finished: bool,
}

impl SavedPolicy {
    /// The policy of the run in `dir`: its checkpoint at `env_steps`, or its newest.
    pub fn load(dir: &Path, env_steps: Option<u64>) -> Result<Self> {
        let folder = RunFolder::new(dir);
        if !dir.is_dir() {
            bail!("{}: no such folder", dir.display());
        }
        if !folder.holds_run() {
            bail!(
                "{} is not a run folder: it has no config.json (a run folder is what `pbrl train --out DIR` writes)",
                dir.display()
            );
        }
        let text = std::fs::read_to_string(folder.config())
            .with_context(|| format!("reading {}", folder.config().display()))?;
        let config: LearnerConfig = serde_json::from_str(&text).with_context(|| {
            format!(
                "parsing {} (written by another build of pbrl?)",
                folder.config().display()
            )
        })?;
        let c = match env_steps {
            Some(s) => folder.checkpoint_at(s)?,
            None => folder.latest_checkpoint()?.with_context(|| {
                format!(
                    "{} holds no complete checkpoint yet (one is written every --checkpoint-every env steps and at the end)",
                    dir.display()
                )
            })?,
        };
        let path = c.dir.join("policy.safetensors");
        folder.read(&c, "policy.safetensors")?;
        let tensors = candle_core::safetensors::load(&path, &candle_core::Device::Cpu)
            .with_context(|| format!("reading {}", path.display()))?;
        let mut tensors: Vec<pbrl_common::wire::Tensor> = tensors
            .iter()
            .map(|(name, t)| pbrl_common::nets::to_wire(name, t))
            .collect::<candle_core::Result<_>>()
            .with_context(|| format!("reading {}", path.display()))?;
        tensors.sort_by(|a, b| a.name.cmp(&b.name));
        let norm = match config.algo {
            Algo::Sac => identity_norm(config.obs_dim),
            Algo::Ppo => {
                let bytes = folder.read(&c, "state.bin")?;
                let saved = decode_saved(&bytes).with_context(|| {
                    format!(
                        "decoding {}/state.bin (written by another build of pbrl?)",
                        c.dir.display()
                    )
                })?;
                match saved.backbone {
                    BackboneState::Ppo(s) => s.norm,
                    BackboneState::Sac(_) => bail!(
                        "{}: config.json says PPO, the checkpoint holds SAC",
                        c.dir.display()
                    ),
                }
            }
        };
        let weights = Weights {
            version: c.manifest.version,
            env_steps: c.manifest.env_steps,
            obs_dim: config.obs_dim as u32,
            act_dim: config.act_dim as u32,
            tensors,
            obs_mean: norm.mean.iter().map(|x| *x as f32).collect(),
            obs_var: norm.var.iter().map(|x| *x as f32).collect(),
            obs_clip: norm.clip as f32,
            random_actions: false,
            episodes_per_actor: 0,
            acks: Vec::new(),
        };
        Ok(Self {
            folder: dir.to_path_buf(),
            finished: folder.finished().exists(),
            env_steps: c.manifest.env_steps,
            version: c.manifest.version,
            checkpoint: c.dir,
            config,
            weights,
        })
    }

    /// The run's world as its config records it (`{"task": ..., "config": {...}}`): the
    /// world config's JSON, or None for a task without one (the point task).
    pub fn world_json(&self) -> Option<&serde_json::Value> {
        self.config.world.get("config")
    }

    /// The task the run trained on (`feeding`, `point`).
    pub fn task(&self) -> &str {
        self.config
            .world
            .get("task")
            .and_then(|t| t.as_str())
            .unwrap_or("feeding")
    }

    /// The label store's counts (None when the run kept no labels).
    pub fn label_counts(&self) -> Result<Option<Counts>> {
        let path = RunFolder::new(&self.folder).labels();
        if !path.exists() {
            return Ok(None);
        }
        let store = LabelStore::open_read_only(&path)?;
        Ok(Some(store.counts()?))
    }
}
