//! The run folder (`--out DIR`): this module alone knows its layout.
//!
//! ```text
//! DIR/config.json                    the resolved learner config
//! DIR/curve.csv                      one row per evaluation, against env steps
//! DIR/train.log                      the log, appended across restarts
//! DIR/version                        the newest weights version published (high-water mark)
//! DIR/finished.json                  written once the run reached its total
//! DIR/checkpoints/<env steps>/       networks (*.safetensors), state.bin, manifest.json last
//! DIR/replay/<start>-<end>.bin       SAC's transitions, one segment appended per checkpoint
//! DIR/labels.sqlite                  the label store (preference learning): every query and
//!                                    answer, committed as it happens (`labels`); kept when
//!                                    a run starts over, moved aside by `--fresh`, never
//!                                    deleted
//! ```
//!
//! Every file is written to a temporary name, synced and renamed; a checkpoint directory is
//! complete only with its `manifest.json`, which lists every file it needs (its own and the
//! replay segments) with size and CRC-32. A checkpoint that fails those checks is reported
//! and the previous one is used. A checkpoint written again at the same env steps replaces
//! the old one by renames (the old one is `<env steps>.old` until the new one is in place).

use std::io::Write;
use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use candle_nn::VarMap;
use serde::{Deserialize, Serialize};

/// One file of a checkpoint: name (relative to the run folder), size and checksum.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FileSum {
    pub path: String,
    pub bytes: u64,
    pub crc32: u32,
}

/// What makes a checkpoint complete.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Manifest {
    pub env_steps: u64,
    pub version: u64,
    /// The checkpoint's own files.
    pub files: Vec<FileSum>,
    /// The replay segments it needs, oldest first.
    pub replay: Vec<FileSum>,
}

/// A checkpoint that passed its checks.
pub struct Checkpoint {
    pub dir: PathBuf,
    pub manifest: Manifest,
}

/// The run folder.
#[derive(Clone, Debug)]
pub struct RunFolder {
    pub root: PathBuf,
}

fn sync_dir(dir: &Path) -> Result<()> {
    std::fs::File::open(dir)
        .and_then(|f| f.sync_all())
        .with_context(|| format!("syncing {}", dir.display()))
}

impl RunFolder {
    pub fn new(root: impl Into<PathBuf>) -> Self {
        Self { root: root.into() }
    }

    pub fn config(&self) -> PathBuf {
        self.root.join("config.json")
    }

    pub fn curve(&self) -> PathBuf {
        self.root.join("curve.csv")
    }

    pub fn log(&self) -> PathBuf {
        self.root.join("train.log")
    }

    pub fn finished(&self) -> PathBuf {
        self.root.join("finished.json")
    }

    /// The env steps a finished run reached (none if it has not finished).
    pub fn finished_steps(&self) -> Result<Option<u64>> {
        let Ok(text) = std::fs::read_to_string(self.finished()) else {
            return Ok(None);
        };
        let done: serde_json::Value = serde_json::from_str(&text)
            .with_context(|| format!("parsing {}", self.finished().display()))?;
        Ok(done["env_steps"].as_u64())
    }

    fn version_mark(&self) -> PathBuf {
        self.root.join("version")
    }

    fn checkpoints(&self) -> PathBuf {
        self.root.join("checkpoints")
    }

    fn replay(&self) -> PathBuf {
        self.root.join("replay")
    }

    /// The label store (SQLite).
    pub fn labels(&self) -> PathBuf {
        self.root.join("labels.sqlite")
    }

    /// The in-process teacher's file (SQLite): its outbox of answers not yet acknowledged,
    /// and for a person (`--teacher human`) the queue of queries too.
    pub fn teacher(&self) -> PathBuf {
        self.root.join("teacher.sqlite")
    }

    /// Whether the folder holds a run (its config).
    pub fn holds_run(&self) -> bool {
        self.config().exists()
    }

    /// Create the folder and its subfolders.
    pub fn create(&self) -> Result<()> {
        for d in [self.root.clone(), self.checkpoints(), self.replay()] {
            std::fs::create_dir_all(&d).with_context(|| format!("creating {}", d.display()))?;
        }
        Ok(())
    }

    /// Remove everything a run wrote but its label store (a run started over keeps its
    /// labels: D alone can train a reward model).
    pub fn clear(&self) -> Result<()> {
        for f in [
            self.config(),
            self.curve(),
            self.finished(),
            self.version_mark(),
        ] {
            if f.exists() {
                std::fs::remove_file(&f).with_context(|| format!("removing {}", f.display()))?;
            }
        }
        for d in [self.checkpoints(), self.replay()] {
            if d.exists() {
                std::fs::remove_dir_all(&d).with_context(|| format!("removing {}", d.display()))?;
            }
        }
        Ok(())
    }

    /// Start over entirely (`--fresh`): [`RunFolder::clear`], and the label store moved
    /// aside (labels are people's time: never deleted).
    pub fn clear_fresh(&self) -> Result<()> {
        self.clear()?;
        for labels in [self.labels(), self.teacher()] {
            if !labels.exists() {
                continue;
            }
            let ms = pbrl_common::wire::now_ms();
            for suffix in ["", "-wal", "-shm"] {
                let from = PathBuf::from(format!("{}{suffix}", labels.display()));
                let to = PathBuf::from(format!("{}.{ms}.old{suffix}", labels.display()));
                if from.exists() {
                    std::fs::rename(&from, &to).with_context(|| {
                        format!("moving {} to {}", from.display(), to.display())
                    })?;
                }
            }
            tracing::warn!(
                moved_to = %format!("{}.{ms}.old", labels.display()),
                "starting over: the store is kept aside"
            );
        }
        Ok(())
    }

    fn relative(&self, path: &Path) -> String {
        path.strip_prefix(&self.root)
            .unwrap_or(path)
            .to_string_lossy()
            .into_owned()
    }

    /// Write `bytes` to `path` atomically: a temporary file, synced, renamed.
    pub fn write_atomic(&self, path: &Path, bytes: &[u8]) -> Result<FileSum> {
        let tmp = path.with_extension("tmp");
        let mut f =
            std::fs::File::create(&tmp).with_context(|| format!("creating {}", tmp.display()))?;
        f.write_all(bytes)
            .and_then(|_| f.sync_all())
            .with_context(|| format!("writing {}", tmp.display()))?;
        std::fs::rename(&tmp, path)
            .with_context(|| format!("renaming {} to {}", tmp.display(), path.display()))?;
        // The rename itself lives in the directory: synced too, or a crash may undo it.
        if let Some(parent) = path.parent() {
            sync_dir(parent)?;
        }
        Ok(FileSum {
            path: self.relative(path),
            bytes: bytes.len() as u64,
            crc32: crc32fast::hash(bytes),
        })
    }

    /// Remember the newest weights version published (not synced: it only has to survive
    /// the process, so that a resumed learner counts on from above it).
    pub fn mark_version(&self, version: u64) -> Result<()> {
        let tmp = self.version_mark().with_extension("tmp");
        std::fs::write(&tmp, version.to_string())
            .and_then(|_| std::fs::rename(&tmp, self.version_mark()))
            .with_context(|| format!("writing {}", self.version_mark().display()))
    }

    /// The newest weights version ever published here (0 if none).
    pub fn published_version(&self) -> u64 {
        std::fs::read_to_string(self.version_mark())
            .ok()
            .and_then(|s| s.trim().parse().ok())
            .unwrap_or(0)
    }

    /// Append SAC transitions `start..end` (rows as `Replay::rows` lays them out).
    pub fn write_replay_segment(&self, start: u64, end: u64, rows: &[f32]) -> Result<FileSum> {
        let path = self.replay().join(format!("{start:012}-{end:012}.bin"));
        let bytes: Vec<u8> = rows.iter().flat_map(|x| x.to_le_bytes()).collect();
        self.write_atomic(&path, &bytes)
    }

    /// Read replay segments (checked against their sums) as one run of rows.
    pub fn read_replay(&self, segments: &[FileSum]) -> Result<Vec<f32>> {
        let mut rows = Vec::new();
        for s in segments {
            let bytes = self.read_checked(s)?;
            rows.extend(
                bytes
                    .chunks_exact(4)
                    .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])),
            );
        }
        Ok(rows)
    }

    fn read_checked(&self, s: &FileSum) -> Result<Vec<u8>> {
        let path = self.root.join(&s.path);
        let bytes = std::fs::read(&path).with_context(|| format!("reading {}", path.display()))?;
        if bytes.len() as u64 != s.bytes {
            bail!(
                "{} has {} bytes, its manifest says {}",
                path.display(),
                bytes.len(),
                s.bytes
            );
        }
        let crc = crc32fast::hash(&bytes);
        if crc != s.crc32 {
            bail!(
                "{} has checksum {crc:08x}, its manifest says {:08x}",
                path.display(),
                s.crc32
            );
        }
        Ok(bytes)
    }

    /// Write a checkpoint at `env_steps`: the networks, `state` (serialised learner state)
    /// and, last, the manifest naming them and the replay segments it needs. Then keep only
    /// the newest `keep` checkpoints and the segments they need.
    pub fn write_checkpoint(
        &self,
        env_steps: u64,
        version: u64,
        networks: &[(&str, &VarMap)],
        state: &[u8],
        replay: Vec<FileSum>,
        keep: usize,
    ) -> Result<Manifest> {
        let dir = self.checkpoints().join(format!("{env_steps:012}"));
        let tmp = self.checkpoints().join(format!("{env_steps:012}.tmp"));
        if tmp.exists() {
            std::fs::remove_dir_all(&tmp).with_context(|| format!("removing {}", tmp.display()))?;
        }
        std::fs::create_dir_all(&tmp).with_context(|| format!("creating {}", tmp.display()))?;
        let mut files = Vec::new();
        for (name, varmap) in networks {
            let path = tmp.join(format!("{name}.safetensors"));
            varmap
                .save(&path)
                .with_context(|| format!("writing {}", path.display()))?;
            let bytes =
                std::fs::read(&path).with_context(|| format!("reading {}", path.display()))?;
            std::fs::File::open(&path)
                .and_then(|f| f.sync_all())
                .with_context(|| format!("syncing {}", path.display()))?;
            files.push(self.sum_in(&dir, name, "safetensors", &bytes));
        }
        self.write_atomic(&tmp.join("state.bin"), state)?;
        files.push(self.sum_in(&dir, "state", "bin", state));
        let manifest = Manifest {
            env_steps,
            version,
            files,
            replay,
        };
        self.write_atomic(
            &tmp.join("manifest.json"),
            serde_json::to_string_pretty(&manifest)?.as_bytes(),
        )?;
        // (`write_atomic` synced `tmp` itself, with the network files' entries in it.)
        // NOTE: a checkpoint at the same step (a run's end right after a periodic one) is
        // replaced by renames alone: until the new one is in place, the old one stays
        // readable as `<steps>.old`, which `checkpoint_dirs` lists too.
        let old = dir.with_extension("old");
        if dir.exists() {
            if old.exists() {
                std::fs::remove_dir_all(&old)
                    .with_context(|| format!("removing {}", old.display()))?;
            }
            std::fs::rename(&dir, &old)
                .with_context(|| format!("renaming {} to {}", dir.display(), old.display()))?;
        }
        std::fs::rename(&tmp, &dir)
            .with_context(|| format!("renaming {} to {}", tmp.display(), dir.display()))?;
        sync_dir(&self.checkpoints())?;
        if old.exists() {
            std::fs::remove_dir_all(&old).with_context(|| format!("removing {}", old.display()))?;
        }
        self.prune(keep)?;
        Ok(manifest)
    }

    fn sum_in(&self, dir: &Path, name: &str, ext: &str, bytes: &[u8]) -> FileSum {
        FileSum {
            path: self.relative(&dir.join(format!("{name}.{ext}"))),
            bytes: bytes.len() as u64,
            crc32: crc32fast::hash(bytes),
        }
    }

    /// Checkpoint directories (renamed into place, so complete unless torn), newest first;
    /// a `<steps>.old` left by a replacement comes after its `<steps>`.
    fn checkpoint_dirs(&self) -> Result<Vec<PathBuf>> {
        let Ok(entries) = std::fs::read_dir(self.checkpoints()) else {
            return Ok(Vec::new());
        };
        let mut dirs: Vec<(u64, bool, PathBuf)> = entries
            .filter_map(|e| e.ok())
            .filter_map(|e| {
                let name = e.file_name().to_str()?.to_string();
                let (steps, old) = match name.strip_suffix(".old") {
                    Some(steps) => (steps.to_string(), true),
                    None => (name, false),
                };
                Some((steps.parse::<u64>().ok()?, old, e.path()))
            })
            .collect();
        dirs.sort_by_key(|d| (std::cmp::Reverse(d.0), d.1));
        Ok(dirs.into_iter().map(|(_, _, p)| p).collect())
    }

    fn load(&self, dir: &Path) -> Result<Checkpoint> {
        let text = std::fs::read_to_string(dir.join("manifest.json"))
            .with_context(|| format!("reading {}/manifest.json", dir.display()))?;
        let mut manifest: Manifest = serde_json::from_str(&text)
            .with_context(|| format!("parsing {}/manifest.json", dir.display()))?;
        // NOTE: its own files are in the directory it is in now (`<steps>.old` after an
        // interrupted replacement), whatever name it was written under.
        for s in &mut manifest.files {
            let name = Path::new(&s.path)
                .file_name()
                .with_context(|| format!("{}/manifest.json names {:?}", dir.display(), s.path))?;
            s.path = self.relative(&dir.join(name));
        }
        for s in manifest.files.iter().chain(&manifest.replay) {
            self.read_checked(s)?;
        }
        Ok(Checkpoint {
            dir: dir.to_path_buf(),
            manifest,
        })
    }

    /// The newest checkpoint that passes its checks; each one that does not is reported
    /// with the reason and skipped.
    pub fn latest_checkpoint(&self) -> Result<Option<Checkpoint>> {
        for dir in self.checkpoint_dirs()? {
            match self.load(&dir) {
                Ok(c) => return Ok(Some(c)),
                Err(e) => tracing::warn!(
                    checkpoint = %dir.display(),
                    error = format!("{e:#}"),
                    "checkpoint is torn or corrupt; trying the one before"
                ),
            }
        }
        Ok(None)
    }

    /// The checkpoint at `env_steps` (checked); the error lists the steps there are.
    pub fn checkpoint_at(&self, env_steps: u64) -> Result<Checkpoint> {
        let dirs = self.checkpoint_dirs()?;
        let steps_of = |d: &PathBuf| -> Option<u64> {
            let name = d.file_name()?.to_str()?;
            name.strip_suffix(".old").unwrap_or(name).parse().ok()
        };
        match dirs.iter().find(|d| steps_of(d) == Some(env_steps)) {
            Some(dir) => self.load(dir),
            None => {
                let have: Vec<String> = dirs
                    .iter()
                    .filter_map(steps_of)
                    .map(|s| s.to_string())
                    .collect();
                bail!(
                    "{} has no checkpoint at {env_steps} env steps (it has: {})",
                    self.root.display(),
                    if have.is_empty() {
                        "none".to_string()
                    } else {
                        have.join(", ")
                    }
                )
            }
        }
    }

    /// A checked file of a checkpoint.
    pub fn read(&self, c: &Checkpoint, name: &str) -> Result<Vec<u8>> {
        let s = c
            .manifest
            .files
            .iter()
            .find(|s| Path::new(&s.path).file_name().and_then(|n| n.to_str()) == Some(name))
            .with_context(|| format!("checkpoint {} has no {name}", c.dir.display()))?;
        self.read_checked(s)
    }

    /// Keep the newest `keep` checkpoints and the replay segments they need; remove what
    /// an interrupted write left.
    fn prune(&self, keep: usize) -> Result<()> {
        if let Ok(entries) = std::fs::read_dir(self.checkpoints()) {
            for e in entries.filter_map(|e| e.ok()) {
                if e.file_name().to_string_lossy().ends_with(".tmp") {
                    std::fs::remove_dir_all(e.path())
                        .with_context(|| format!("removing {}", e.path().display()))?;
                }
            }
        }
        let dirs = self.checkpoint_dirs()?;
        for old in dirs.iter().skip(keep.max(1)) {
            std::fs::remove_dir_all(old).with_context(|| format!("removing {}", old.display()))?;
        }
        let mut needed = std::collections::BTreeSet::new();
        for dir in dirs.iter().take(keep.max(1)) {
            if let Ok(text) = std::fs::read_to_string(dir.join("manifest.json")) {
                if let Ok(m) = serde_json::from_str::<Manifest>(&text) {
                    needed.extend(m.replay.into_iter().map(|s| s.path));
                }
            }
        }
        if let Ok(entries) = std::fs::read_dir(self.replay()) {
            for e in entries.filter_map(|e| e.ok()) {
                let rel = self.relative(&e.path());
                if !needed.contains(&rel) {
                    std::fs::remove_file(e.path())
                        .with_context(|| format!("removing {}", e.path().display()))?;
                }
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn checkpoints_are_kept_pruned_checked_and_skipped_when_torn() {
        let dir = tempfile::tempdir().unwrap();
        let f = RunFolder::new(dir.path());
        f.create().unwrap();
        let vm = VarMap::new();
        vm.get(
            (2, 3),
            "w",
            candle_nn::Init::Const(1.0),
            candle_core::DType::F32,
            &candle_core::Device::Cpu,
        )
        .unwrap();
        // A write interrupted before its rename leaves a .tmp directory behind.
        std::fs::create_dir_all(f.checkpoints().join("000000000050.tmp")).unwrap();
        let mut replay = Vec::new();
        for (k, steps) in [100u64, 200, 300, 400].into_iter().enumerate() {
            replay.push(
                f.write_replay_segment(steps - 100, steps, &[k as f32; 4])
                    .unwrap(),
            );
            // The newest checkpoints need only the last two segments.
            let need = replay[replay.len().saturating_sub(2)..].to_vec();
            f.write_checkpoint(steps, k as u64, &[("policy", &vm)], b"state", need, 2)
                .unwrap();
        }
        let names = |d: PathBuf| {
            let mut v: Vec<String> = std::fs::read_dir(d)
                .unwrap()
                .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
                .collect();
            v.sort();
            v
        };
        assert_eq!(names(f.checkpoints()), ["000000000300", "000000000400"]);
        assert_eq!(
            names(f.replay()),
            [
                "000000000100-000000000200.bin",
                "000000000200-000000000300.bin",
                "000000000300-000000000400.bin"
            ]
        );
        let c = f.latest_checkpoint().unwrap().unwrap();
        assert_eq!(c.manifest.env_steps, 400);
        assert_eq!(f.read(&c, "state.bin").unwrap(), b"state");
        assert_eq!(
            f.read_replay(&c.manifest.replay).unwrap(),
            [2.0; 4]
                .iter()
                .chain(&[3.0; 4])
                .copied()
                .collect::<Vec<f32>>()
        );
        // A flipped byte in a segment the newest needs: the one before is used.
        let seg = f.root.join(&c.manifest.replay[1].path);
        let mut bytes = std::fs::read(&seg).unwrap();
        bytes[0] ^= 1;
        std::fs::write(&seg, bytes).unwrap();
        assert_eq!(
            f.latest_checkpoint().unwrap().unwrap().manifest.env_steps,
            300
        );
        // A second checkpoint at the newest step replaces it and leaves no `.old`.
        let need = replay[1..3].to_vec();
        f.write_checkpoint(300, 9, &[("policy", &vm)], b"again", need, 2)
            .unwrap();
        assert_eq!(names(f.checkpoints()), ["000000000300", "000000000400"]);
        let c = f.latest_checkpoint().unwrap().unwrap();
        assert_eq!((c.manifest.env_steps, c.manifest.version), (300, 9));
        // Killed between the replacement's two renames: the old one is still found.
        std::fs::rename(
            f.checkpoints().join("000000000300"),
            f.checkpoints().join("000000000300.old"),
        )
        .unwrap();
        let c = f.latest_checkpoint().unwrap().unwrap();
        assert_eq!(f.read(&c, "state.bin").unwrap(), b"again");
    }
}
