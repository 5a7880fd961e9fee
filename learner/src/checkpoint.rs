//! Checkpoints and resume: what the loop counts ([`Progress`]), what a checkpoint's
//! `state.bin` holds ([`Saved`]), writing one ([`write`]) and opening a run folder, new or
//! to resume ([`open_folder`]). The run folder's layout is `run_folder`'s.

use std::io::Write;
use std::time::Instant;

use anyhow::{Context, Result};
use pbrl_common::bus::Receipts;
use pbrl_common::nets::import;
use pbrl_common::wire::{self, EvalRequest};
use serde::{Deserialize, Serialize};

use crate::backbone::{Backbone, BackboneState, Publication};
use crate::config::{check_resume, LearnerConfig};
use crate::curve::{Curve, CurveRow, Window};
use crate::entropy::StateEntropy;
use crate::feedback::{Feedback, FeedbackState};
use crate::run_folder::{FileSum, RunFolder};

/// The learner loop's counters and bookkeeping: with the networks, optimisers, generators,
/// replay buffer and preference learning's state, everything a resumed run needs.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct Progress {
    pub version: u64,
    pub env_steps: u64,
    pub updates: u64,
    pub publication: Publication,
    pub next_row: u64,
    pub next_checkpoint: u64,
    pub window: Window,
    /// Numbered trajectories received, per actor (each taken once).
    pub receipts: Receipts,
    /// Evaluations asked again.
    pub eval_retries: u64,
    /// The newest losses: SAC critic, actor, alpha; PPO value, policy, approx KL.
    pub losses: [f64; 6],
    /// Wall time of the run in earlier processes.
    pub wall_s: f64,
    pub rows_written: u64,
    pub stale: u64,
}

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
}

/// The start and end of a replay segment's range, from its name.
fn segment_range(s: &FileSum) -> Option<(u64, u64)> {
    let name = std::path::Path::new(&s.path).file_stem()?.to_str()?;
    let (a, b) = name.split_once('-')?;
    Some((a.parse().ok()?, b.parse().ok()?))
}

/// Write a checkpoint: the SAC transitions since the last one as a new replay segment,
/// then networks, state and manifest.
#[allow(clippy::too_many_arguments)]
pub fn write(
    folder: &RunFolder,
    cfg: &LearnerConfig,
    backbone: &Backbone,
    feedback: Option<&Feedback>,
    entropy: Option<&StateEntropy>,
    progress: &Progress,
    curve: &Curve,
    segments: &mut Vec<FileSum>,
) -> Result<()> {
    let start = Instant::now();
    if let Backbone::Sac(sac) = backbone {
        let total = sac.replay.total;
        let held_from = total - sac.replay.len() as u64;
        let from = segments
            .last()
            .and_then(segment_range)
            .map_or(0, |(_, end)| end)
            .max(held_from);
        if total > from {
            let rows = sac.replay.rows(from, total);
            segments.push(folder.write_replay_segment(from, total, &rows)?);
        }
        // Segments wholly out of the buffer are no longer needed.
        segments.retain(|s| segment_range(s).is_some_and(|(_, end)| end > held_from));
    }
    let saved = Saved {
        config: serde_json::to_string(cfg)?,
        progress: Progress {
            rows_written: curve.written,
            ..progress.clone()
        },
        pending: curve
            .pending
            .iter()
            .map(|p| (p.row.clone(), p.request.clone()))
            .collect(),
        backbone: backbone.state()?,
        feedback: feedback
            .map(|f| {
                f.state().map(|mut s| {
                    s.entropy = entropy.cloned();
                    s
                })
            })
            .transpose()?,
    };
    let bytes = bincode::serde::encode_to_vec(&saved, bincode::config::standard())?;
    // The checkpoint counts the curve's rows: they must be on disk before it is.
    if let Some(f) = &curve.file {
        f.sync_data().context("syncing the curve")?;
    }
    let mut networks: Vec<(String, &candle_nn::VarMap)> = backbone
        .networks()
        .into_iter()
        .map(|(n, v)| (n.to_string(), v))
        .collect();
    if let Some(f) = feedback {
        networks.extend(f.networks());
    }
    let networks: Vec<(&str, &candle_nn::VarMap)> =
        networks.iter().map(|(n, v)| (n.as_str(), *v)).collect();
    folder.write_checkpoint(
        progress.env_steps,
        progress.version,
        &networks,
        &bytes,
        segments.clone(),
        cfg.keep_checkpoints,
    )?;
    let replay_bytes: u64 = segments.iter().map(|s| s.bytes).sum();
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
                let (saved, _): (Saved, usize) =
                    bincode::serde::decode_from_slice(&bytes, bincode::config::standard())
                        .with_context(|| format!("decoding {}/state.bin", c.dir.display()))?;
                load_networks(
                    &c.dir,
                    backbone
                        .networks()
                        .into_iter()
                        .map(|(n, v)| (n.to_string(), v)),
                )?;
                match (&mut *backbone, &saved.backbone) {
                    (Backbone::Sac(sac), BackboneState::Sac(s)) => {
                        sac.restore(s)?;
                        let rows = folder.read_replay(&c.manifest.replay)?;
                        let from = c
                            .manifest
                            .replay
                            .first()
                            .and_then(segment_range)
                            .map_or(0, |r| r.0);
                        sac.replay.restore(from, &rows)?;
                    }
                    (Backbone::Ppo(ppo, _), BackboneState::Ppo(s)) => ppo.restore(s)?,
                    _ => anyhow::bail!("checkpoint {} is of another algorithm", c.dir.display()),
                }
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

/// What checkpoints cost with a full replay buffer (`pbrl bench checkpoint`).
#[derive(Clone, Debug)]
pub struct CheckpointCost {
    pub transitions: u64,
    /// The first checkpoint: the whole buffer as one segment.
    pub full_ms: f64,
    pub full_bytes: u64,
    /// A checkpoint after `increment` more transitions: only they are written.
    pub increment: u64,
    pub increment_ms: f64,
    pub increment_bytes: u64,
    /// Reading the newest checkpoint back (checks, networks, replay buffer).
    pub restore_ms: f64,
}

/// Fill a feeding-sized SAC (obs 25, action 7, 256x256) replay buffer with `transitions`
/// random transitions, checkpoint it into `dir`, add `increment`, checkpoint again, and
/// restore.
pub fn bench(dir: &std::path::Path, transitions: u64, increment: u64) -> Result<CheckpointCost> {
    use rand::{Rng, SeedableRng};
    let mut cfg = LearnerConfig::new(
        "bench",
        crate::config::Algo::Sac,
        crate::reward::RewardSource::Truth,
        25,
        7,
    );
    cfg.total_steps = transitions + increment;
    cfg.sac.replay_capacity = transitions as usize;
    cfg.out = Some(dir.to_path_buf());
    let folder = RunFolder::new(dir);
    let mut backbone = Backbone::new(&cfg)?;
    let (file, _, mut segments) = open_folder(&folder, &cfg, &mut backbone)?;
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(0);
    let mut fill = |backbone: &mut Backbone, n: u64| {
        if let Backbone::Sac(sac) = backbone {
            for _ in 0..n {
                let obs: Vec<f32> = (0..25).map(|_| rng.random()).collect();
                let act: Vec<f32> = (0..7).map(|_| rng.random()).collect();
                sac.replay
                    .push(&obs, &act, [rng.random(), rng.random()], &obs, false);
            }
        }
    };
    let curve = Curve::new(Some(file), 0, None);
    let mut p = Progress {
        version: 1,
        ..Progress::default()
    };
    let timed =
        |backbone: &Backbone, p: &Progress, segments: &mut Vec<FileSum>| -> Result<(f64, u64)> {
            let before: u64 = segments.iter().map(|s| s.bytes).sum();
            let start = Instant::now();
            write(&folder, &cfg, backbone, None, None, p, &curve, segments)?;
            let ms = start.elapsed().as_secs_f64() * 1e3;
            let after: u64 = segments.iter().map(|s| s.bytes).sum();
            let nets: u64 = folder
                .latest_checkpoint()?
                .map_or(0, |c| c.manifest.files.iter().map(|f| f.bytes).sum());
            Ok((ms, after.saturating_sub(before) + nets))
        };
    fill(&mut backbone, transitions);
    p.env_steps = transitions;
    let (full_ms, full_bytes) = timed(&backbone, &p, &mut segments)?;
    fill(&mut backbone, increment);
    p.env_steps += increment;
    let (increment_ms, increment_bytes) = timed(&backbone, &p, &mut segments)?;
    let start = Instant::now();
    let mut fresh = Backbone::new(&cfg)?;
    open_folder(&folder, &cfg, &mut fresh)?;
    Ok(CheckpointCost {
        transitions,
        full_ms,
        full_bytes,
        increment,
        increment_ms,
        increment_bytes,
        restore_ms: start.elapsed().as_secs_f64() * 1e3,
    })
}
