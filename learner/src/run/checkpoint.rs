//! Checkpoints and resume: what the loop counts ([`Progress`]), what a checkpoint's
//! `state.bin` holds ([`Saved`]), when one is due and writing it ([`Checkpoints`]), and
//! opening a run folder, new or to resume ([`open_folder`]). The run folder's layout is
//! `run_folder`'s.

use std::io::Write;
use std::time::{Duration, Instant};

use anyhow::{Context, Result};
use pbrl_common::nets::import;
use pbrl_common::wire::{self, EvalRequest};
use serde::{Deserialize, Serialize};

use crate::pref::feedback::{Feedback, FeedbackState};
use crate::pref::reward::{TaskGuard, TrainReward};
use crate::run::backbone::{Backbone, BackboneState};
use crate::run::config::{check_resume, LearnerConfig};
use crate::run::curve::{Curve, CurveRow};
use crate::run::progress::Progress;
use crate::run::run_folder::{FileSum, RunFolder};

/// A checkpoint's `state.bin`.
#[derive(Serialize, Deserialize)]
pub struct Saved {
    /// The config as JSON (for a reader; the run folder's `config.json` is the one used).
    pub config: String,
    pub progress: Progress,
    /// Rows made but not written yet, with their evaluation requests.
    pub pending: Vec<(CurveRow, EvalRequest)>,
    pub backbone: BackboneState,
    /// Preference learning (learnt rewards only).
    pub feedback: Option<FeedbackState>,
    /// The comfort features of the annotation buffer's trajectories, oldest first (last,
    /// and apart from the buffer, so that a checkpoint of an older build, which ends
    /// before them, still decodes: [`decode_saved`]).
    pub buffer_features: Vec<Vec<f32>>,
    /// The task guard's episodes (last, so that an older build's checkpoint, which ends
    /// before it, still decodes with an empty guard).
    pub guard: TaskGuard,
}

/// A checkpoint's state as the builds before the task guard wrote it.
#[derive(Deserialize)]
#[cfg_attr(test, derive(Serialize))]
struct SavedBeforeGuard {
    config: String,
    progress: Progress,
    pending: Vec<(CurveRow, EvalRequest)>,
    backbone: BackboneState,
    feedback: Option<FeedbackState>,
    buffer_features: Vec<Vec<f32>>,
}

/// A checkpoint's state as the builds before the comfort features wrote it.
#[derive(Deserialize)]
#[cfg_attr(test, derive(Serialize))]
struct SavedBeforeFeatures {
    config: String,
    progress: Progress,
    pending: Vec<(CurveRow, EvalRequest)>,
    backbone: BackboneState,
    feedback: Option<FeedbackState>,
}

/// Decode a checkpoint's `state.bin`: this build's layout, or the one before the comfort
/// features (its trajectories then have none); the features go back to their candidates.
pub fn decode_saved(bytes: &[u8]) -> Result<Saved> {
    fn decode<T: serde::de::DeserializeOwned>(
        bytes: &[u8],
    ) -> Result<T, bincode::error::DecodeError> {
        bincode::serde::decode_from_slice(bytes, bincode::config::standard()).map(|(s, _)| s)
    }
    // NOTE: the newest layout first, then each older one, converted up the chain; the
    // newest's error is the one reported.
    let mut saved: Saved = match decode::<Saved>(bytes) {
        Ok(s) => s,
        Err(e) => match decode::<SavedBeforeGuard>(bytes) {
            Ok(old) => old.into(),
            Err(_) => {
                SavedBeforeGuard::from(decode::<SavedBeforeFeatures>(bytes).map_err(|_| e)?).into()
            }
        },
    };
    let features = std::mem::take(&mut saved.buffer_features);
    if let Some(f) = &mut saved.feedback {
        f.buffer.attach_features(features)?;
    }
    Ok(saved)
}

impl From<SavedBeforeGuard> for Saved {
    /// An empty guard: it has seen no episode yet.
    fn from(old: SavedBeforeGuard) -> Self {
        Saved {
            config: old.config,
            progress: old.progress,
            pending: old.pending,
            backbone: old.backbone,
            feedback: old.feedback,
            buffer_features: old.buffer_features,
            guard: TaskGuard::default(),
        }
    }
}

impl From<SavedBeforeFeatures> for SavedBeforeGuard {
    /// No comfort features: its trajectories had none.
    fn from(old: SavedBeforeFeatures) -> Self {
        SavedBeforeGuard {
            config: old.config,
            progress: old.progress,
            pending: old.pending,
            backbone: old.backbone,
            feedback: old.feedback,
            buffer_features: Vec::new(),
        }
    }
}

/// The start and end of a replay segment's range, from its name.
fn segment_range(s: &FileSum) -> Option<(u64, u64)> {
    let name = std::path::Path::new(&s.path).file_stem()?.to_str()?;
    let (a, b) = name.split_once('-')?;
    Some((a.parse().ok()?, b.parse().ok()?))
}

/// When checkpoints are due and writing them: each at a weights publication (PPO: no
/// rollout half-collected; the deterministic mode: the point a resumed run starts from),
/// once `checkpoint_every` env steps have passed since the last mark or `checkpoint_secs`
/// seconds since the last checkpoint. Without a run folder, nothing is written.
pub struct Checkpoints {
    folder: Option<RunFolder>,
    /// The replay segments the newest checkpoint lists (SAC).
    segments: Vec<FileSum>,
    every: u64,
    secs: u64,
    keep: usize,
    last: Instant,
}

impl Checkpoints {
    pub fn new(cfg: &LearnerConfig, folder: Option<RunFolder>, segments: Vec<FileSum>) -> Self {
        Self {
            folder,
            segments,
            every: every(cfg.checkpoint_every),
            secs: cfg.checkpoint_secs,
            keep: cfg.keep_checkpoints,
            last: Instant::now(),
        }
    }

    pub fn folder(&self) -> Option<&RunFolder> {
        self.folder.as_ref()
    }

    /// Whether a checkpoint is due now, `published` telling whether weights were just
    /// published; when it is, the next mark moves past `p.env_steps`.
    pub fn due(&mut self, p: &mut Progress, published: bool) -> bool {
        let late = self.secs > 0 && self.last.elapsed() >= Duration::from_secs(self.secs);
        if !(published && (p.env_steps >= p.next_checkpoint || late)) {
            return false;
        }
        self.last = Instant::now();
        while p.next_checkpoint <= p.env_steps {
            p.next_checkpoint = p.next_checkpoint.saturating_add(self.every);
        }
        true
    }

    /// Write a checkpoint: the SAC transitions since the last one as a new replay segment,
    /// then networks, state and manifest.
    pub fn write(&mut self, cfg: &LearnerConfig, of: Of<'_>, progress: &Progress) -> Result<()> {
        let Some(folder) = &self.folder else {
            return Ok(());
        };
        let start = Instant::now();
        if let Some((held_from, total)) = of.backbone.replay_span() {
            let from = self
                .segments
                .last()
                .and_then(segment_range)
                .map_or(0, |(_, end)| end)
                .max(held_from);
            if total > from {
                let rows = of.backbone.replay_rows(from, total);
                self.segments
                    .push(folder.write_replay_segment(from, total, &rows)?);
            }
            // Segments wholly out of the buffer are no longer needed.
            self.segments
                .retain(|s| segment_range(s).is_some_and(|(_, end)| end > held_from));
        }
        let bytes = saved(cfg, &of, progress)?;
        // The checkpoint counts the curve's rows: they must be on disk before it is.
        if let Some(f) = &of.curve.file {
            f.sync_data().context("syncing the curve")?;
        }
        let mut networks: Vec<(String, &candle_nn::VarMap)> = of
            .backbone
            .networks()
            .into_iter()
            .map(|(n, v)| (n.to_string(), v))
            .collect();
        if let Some(f) = of.feedback {
            networks.extend(f.networks());
        }
        let networks: Vec<(&str, &candle_nn::VarMap)> =
            networks.iter().map(|(n, v)| (n.as_str(), *v)).collect();
        folder.write_checkpoint(
            progress.env_steps,
            progress.version,
            &networks,
            &bytes,
            self.segments.clone(),
            self.keep,
        )?;
        let replay_bytes: u64 = self.segments.iter().map(|s| s.bytes).sum();
        tracing::info!(
            env_steps = progress.env_steps,
            version = progress.version,
            ms = start.elapsed().as_millis() as u64,
            state_bytes = bytes.len(),
            replay_bytes,
            "checkpoint written"
        );
        Ok(())
    }

    /// The replay segments the newest checkpoint lists, with their sizes.
    pub fn segments(&self) -> &[FileSum] {
        &self.segments
    }
}

/// What a checkpoint is of, beside the loop's [`Progress`].
pub struct Of<'a> {
    pub backbone: &'a Backbone,
    pub feedback: Option<&'a Feedback>,
    pub reward: &'a TrainReward,
    pub curve: &'a Curve,
}

/// `n`, or never for 0.
fn every(n: u64) -> u64 {
    if n == 0 {
        u64::MAX
    } else {
        n
    }
}

/// A fresh run's progress: version 1, the first row and checkpoint marks ahead.
pub fn fresh_progress(cfg: &LearnerConfig) -> Progress {
    Progress {
        version: 1,
        next_row: cfg.log_every,
        next_checkpoint: every(cfg.checkpoint_every),
        ..Progress::default()
    }
}

/// A checkpoint's `state.bin`, encoded.
fn saved(cfg: &LearnerConfig, of: &Of<'_>, progress: &Progress) -> Result<Vec<u8>> {
    let saved = Saved {
        config: serde_json::to_string(cfg)?,
        progress: Progress {
            rows_written: of.curve.written,
            ..progress.clone()
        },
        pending: of
            .curve
            .pending
            .iter()
            .map(|p| (p.row.clone(), p.request.clone()))
            .collect(),
        backbone: of.backbone.state()?,
        feedback: of
            .feedback
            .map(|f| {
                f.state().map(|mut s| {
                    s.entropy = of.reward.entropy.clone();
                    s
                })
            })
            .transpose()?,
        buffer_features: of.feedback.map(|f| f.buffer_features()).unwrap_or_default(),
        guard: of.reward.guard.clone(),
    };
    Ok(bincode::serde::encode_to_vec(
        &saved,
        bincode::config::standard(),
    )?)
}

/// Load the named networks of the checkpoint in `dir` into `varmap`s.
pub fn load_networks<'a>(
    dir: &std::path::Path,
    networks: impl IntoIterator<Item = (String, &'a candle_nn::VarMap)>,
) -> Result<()> {
    for (name, varmap) in networks {
        let path = dir.join(format!("{name}.safetensors"));
        let tensors = candle_core::safetensors::load(&path, &candle_core::Device::Cpu)
            .with_context(|| format!("reading {}", path.display()))?;
        let tensors: Vec<wire::Tensor> = tensors
            .iter()
            .map(|(name, t)| pbrl_common::nets::to_wire(name, t))
            .collect::<candle_core::Result<_>>()?;
        import(varmap, &tensors).with_context(|| format!("loading {}", path.display()))?;
    }
    Ok(())
}

/// What a resumed run starts from: the saved state and the checkpoint's folder (for the
/// networks the backbone does not hold).
pub struct Resumed {
    pub saved: Saved,
    pub dir: std::path::PathBuf,
}

/// Open the run folder: a new run writes its config and curve header; a folder that holds
/// a run resumes from its newest complete checkpoint (the backbone is restored in place).
/// Returns the curve file, the saved state (if resuming) and the replay segments.
pub fn open_folder(
    folder: &RunFolder,
    cfg: &LearnerConfig,
    backbone: &mut Backbone,
) -> Result<(std::fs::File, Option<Resumed>, Vec<FileSum>)> {
    let config = serde_json::to_value(cfg)?;
    if folder.holds_run() {
        let text = std::fs::read_to_string(folder.config())
            .with_context(|| format!("reading {}", folder.config().display()))?;
        let stored: serde_json::Value = serde_json::from_str(&text)
            .with_context(|| format!("parsing {}", folder.config().display()))?;
        check_resume(&stored, &config)?;
        match folder.latest_checkpoint()? {
            Some(c) => {
                let bytes = folder.read(&c, "state.bin")?;
                let saved = decode_saved(&bytes).with_context(|| {
                            format!(
                                "decoding {}/state.bin (written by another build of pbrl? resume it with that build, or start over with --fresh)",
                                c.dir.display()
                            )
                        })?;
                load_networks(
                    &c.dir,
                    backbone
                        .networks()
                        .into_iter()
                        .map(|(n, v)| (n.to_string(), v)),
                )?;
                backbone
                    .restore(&saved.backbone, || {
                        let rows = folder.read_replay(&c.manifest.replay)?;
                        let from = c
                            .manifest
                            .replay
                            .first()
                            .and_then(segment_range)
                            .map_or(0, |r| r.0);
                        Ok((from, rows))
                    })
                    .with_context(|| format!("restoring {}", c.dir.display()))?;
                // The curve keeps the rows written before the checkpoint; later ones are
                // made again.
                let curve = std::fs::read_to_string(folder.curve())
                    .with_context(|| format!("reading {}", folder.curve().display()))?;
                let keep: Vec<&str> = curve
                    .lines()
                    .take(1 + saved.progress.rows_written as usize)
                    .collect();
                if keep.len() != 1 + saved.progress.rows_written as usize {
                    anyhow::bail!(
                        "{} has {} rows, the checkpoint counts {}",
                        folder.curve().display(),
                        keep.len().saturating_sub(1),
                        saved.progress.rows_written
                    );
                }
                let mut text = keep.join("\n");
                text.push('\n');
                folder.write_atomic(&folder.curve(), text.as_bytes())?;
                folder.write_atomic(
                    &folder.config(),
                    serde_json::to_string_pretty(cfg)?.as_bytes(),
                )?;
                let file = std::fs::OpenOptions::new()
                    .append(true)
                    .open(folder.curve())
                    .with_context(|| format!("opening {}", folder.curve().display()))?;
                tracing::info!(
                    checkpoint = %c.dir.display(),
                    env_steps = saved.progress.env_steps,
                    version = saved.progress.version,
                    rows = saved.progress.rows_written,
                    "resuming the run"
                );
                return Ok((
                    file,
                    Some(Resumed {
                        saved,
                        dir: c.dir.clone(),
                    }),
                    c.manifest.replay,
                ));
            }
            None => tracing::warn!(
                folder = %folder.root.display(),
                "the folder holds a run but no complete checkpoint; starting it over"
            ),
        }
    }
    folder.clear()?;
    folder.create()?;
    folder.write_atomic(
        &folder.config(),
        serde_json::to_string_pretty(cfg)?.as_bytes(),
    )?;
    let path = folder.curve();
    let mut f =
        std::fs::File::create(&path).with_context(|| format!("creating {}", path.display()))?;
    writeln!(f, "{}", CurveRow::header())?;
    Ok((f, None, Vec::new()))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pref::query::{AnnotationBuffer, Candidate, TrajKey};
    use crate::pref::reward_model::{RewardModel, RewardModelConfig};
    use crate::rl::sac::{Sac, SacConfig};
    use crate::state::RngState;

    fn candidate(seq: u64) -> Candidate {
        Candidate {
            key: TrajKey {
                actor: 0,
                incarnation: 1,
                seq,
            },
            seed: seq,
            policy_version: 1,
            obs_dim: 2,
            act_dim: 1,
            obs: vec![0.5; 6],
            actions: vec![0.1; 3],
            truth: vec![-1.0; 3],
            features: vec![seq as f32; 3 * pbrl_common::trajectory::FEATURES],
        }
    }

    /// A checkpoint keeps the annotation buffer's comfort features apart from it, and one
    /// written before them (its state ends at the feedback loop's) still decodes, its
    /// trajectories without features.
    #[test]
    fn checkpoints_keep_the_features_and_older_ones_still_decode() {
        let mut buffer = AnnotationBuffer::new(4);
        buffer.push(candidate(3));
        buffer.push(candidate(4));
        let rng = <rand_chacha::ChaCha8Rng as rand::SeedableRng>::seed_from_u64(1);
        let feedback = FeedbackState {
            counters: Default::default(),
            rng: RngState::of(&rng),
            buffer: buffer.clone(),
            model: RewardModel::new(RewardModelConfig::plain(), 2, 1)
                .unwrap()
                .state()
                .unwrap(),
            entropy: None,
        };
        let backbone = || {
            let sac = Sac::new(SacConfig::default(), 2, 1).unwrap();
            BackboneState::Sac(sac.state().unwrap())
        };
        let config = bincode::config::standard();
        let now = Saved {
            config: "{}".into(),
            progress: Progress::default(),
            pending: Vec::new(),
            backbone: backbone(),
            feedback: Some(feedback.clone()),
            buffer_features: buffer.features(),
            guard: {
                let mut g = TaskGuard::default();
                (0..150).for_each(|i| g.add(i % 3 == 0));
                g
            },
        };
        let back = decode_saved(&bincode::serde::encode_to_vec(&now, config).unwrap()).unwrap();
        assert_eq!(back.guard, now.guard);
        assert!(back.guard.best() > 0.3);
        // The layout before the task guard: an empty guard, everything else kept.
        let before_guard = SavedBeforeGuard {
            config: "{}".into(),
            progress: Progress::default(),
            pending: Vec::new(),
            backbone: backbone(),
            feedback: Some(feedback.clone()),
            buffer_features: buffer.features(),
        };
        let old =
            decode_saved(&bincode::serde::encode_to_vec(&before_guard, config).unwrap()).unwrap();
        assert_eq!(old.guard, TaskGuard::default());
        assert_eq!(
            old.feedback.unwrap().buffer.get(1).features,
            candidate(4).features
        );
        let b = &back.feedback.unwrap().buffer;
        assert_eq!(b.get(0).features, candidate(3).features);
        assert_eq!(b.get(1).features, candidate(4).features);
        let before = SavedBeforeFeatures {
            config: "{}".into(),
            progress: Progress::default(),
            pending: Vec::new(),
            backbone: backbone(),
            feedback: Some(feedback),
        };
        let old = decode_saved(&bincode::serde::encode_to_vec(&before, config).unwrap()).unwrap();
        let b = &old.feedback.unwrap().buffer;
        assert_eq!(b.len(), 2);
        assert!(b.iter().all(|c| c.features.is_empty()));
        assert_eq!(b.get(1).truth, candidate(4).truth);
        // Features for another number of trajectories than the buffer holds: refused.
        let wrong = Saved {
            buffer_features: vec![Vec::new()],
            ..now
        };
        let e = decode_saved(&bincode::serde::encode_to_vec(&wrong, config).unwrap())
            .err()
            .expect("refused");
        assert!(e.to_string().contains("comfort features"), "{e}");
    }
}
