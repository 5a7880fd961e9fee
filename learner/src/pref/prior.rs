//! A reward prior from a population of people: a reward ensemble trained on the pooled
//! answers of other people (each a run's label store), saved as one safetensors file whose
//! header says what it is and whose answers it learnt from. `pbrl train --prior FILE`
//! starts a new person's ensemble from it (its weights and its observation normaliser,
//! which then stays fixed) and that person's answers adapt it; it is the reward from the
//! end of the pretraining on, before the person's first answer.
//!
//! Most of what people want of a feeding robot is shared (food reaches the mouth, nothing
//! spills, nobody is hit); a person's own answers then move the shared reward towards their
//! taste instead of learning it from nothing.

use std::collections::HashMap;
use std::path::Path;

use anyhow::{bail, Context, Result};
use pbrl_common::wire;
use serde::{Deserialize, Serialize};

use crate::pref::reward_model::RewardModel;

/// The header's `format`: a file of another format is refused.
pub const PRIOR_FORMAT: &str = "pbrl-reward-prior-1";

/// What a prior file says of itself (the safetensors header's `__metadata__`, as JSON under
/// the key `pbrl`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PriorMeta {
    pub format: String,
    /// The reward model's shape: observation, action and comfort-feature widths, hidden
    /// layers, members.
    pub obs_dim: usize,
    pub act_dim: usize,
    pub feat_dim: usize,
    pub hidden: Vec<usize>,
    pub members: usize,
    /// The observation normaliser fitted to the pooled answers' observations.
    pub norm_mean: Vec<f32>,
    pub norm_std: Vec<f32>,
    /// The people whose answers it learnt from (their profiles' names), and the runs.
    pub people: Vec<String>,
    pub runs: Vec<String>,
    /// Labels (pairs of D) it was trained on, and its accuracy on them.
    pub labels: usize,
    pub accuracy: f64,
}

/// A prior read from its file: what it says, and each member's tensors.
#[derive(Clone, Debug)]
pub struct Prior {
    pub meta: PriorMeta,
    pub members: Vec<Vec<wire::Tensor>>,
}

/// Write `model` as a prior with `meta` (its shape and normaliser are taken from the model).
pub fn save(model: &RewardModel, mut meta: PriorMeta, path: &Path) -> Result<()> {
    let (mean, std) = model.normaliser();
    meta.format = PRIOR_FORMAT.into();
    meta.obs_dim = model.obs_dim();
    meta.act_dim = model.act_dim();
    meta.feat_dim = model.feat_dim();
    meta.hidden = model.config().hidden.clone();
    meta.members = model.networks().len();
    meta.norm_mean = mean;
    meta.norm_std = std;
    let mut tensors: Vec<(String, Vec<usize>, Vec<u8>)> = Vec::new();
    for (name, varmap) in model.networks() {
        for t in pbrl_common::nets::export(varmap)? {
            let bytes = t.data.iter().flat_map(|x| x.to_le_bytes()).collect();
            tensors.push((format!("{name}.{}", t.name), t.shape, bytes));
        }
    }
    let views = tensors
        .iter()
        .map(|(name, shape, bytes)| {
            safetensors::tensor::TensorView::new(safetensors::Dtype::F32, shape.clone(), bytes)
                .map(|v| (name.clone(), v))
        })
        .collect::<Result<Vec<_>, _>>()
        .context("laying out the prior's tensors")?;
    let header = HashMap::from([("pbrl".to_string(), serde_json::to_string(&meta)?)]);
    let tmp = path.with_extension("tmp");
    safetensors::serialize_to_file(views, Some(header), &tmp)
        .with_context(|| format!("writing {}", tmp.display()))?;
    std::fs::rename(&tmp, path).with_context(|| format!("writing {}", path.display()))?;
    Ok(())
}

/// Read a prior file.
pub fn load(path: &Path) -> Result<Prior> {
    let bytes = std::fs::read(path).with_context(|| format!("reading prior {}", path.display()))?;
    let st = safetensors::SafeTensors::deserialize(&bytes)
        .with_context(|| format!("prior {} is not a safetensors file", path.display()))?;
    let (_, header) = safetensors::SafeTensors::read_metadata(&bytes)
        .with_context(|| format!("reading the header of prior {}", path.display()))?;
    let meta: PriorMeta = header
        .metadata()
        .as_ref()
        .and_then(|m| m.get("pbrl"))
        .with_context(|| {
            format!(
                "{} is not a pbrl reward prior: its header has no \"pbrl\" entry (make one with `pbrl prior`)",
                path.display()
            )
        })
        .and_then(|j| {
            serde_json::from_str(j)
                .with_context(|| format!("reading the header of prior {}", path.display()))
        })?;
    if meta.format != PRIOR_FORMAT {
        bail!(
            "prior {} is of format {:?}; this build reads {PRIOR_FORMAT:?}",
            path.display(),
            meta.format
        );
    }
    let mut members = vec![Vec::new(); meta.members];
    for (name, view) in st.tensors() {
        let (member, tensor) = name
            .strip_prefix("reward_")
            .and_then(|rest| rest.split_once('.'))
            .and_then(|(i, t)| Some((i.parse::<usize>().ok()?, t)))
            .with_context(|| {
                format!(
                    "prior {}: tensor {name:?} is not a member's",
                    path.display()
                )
            })?;
        if member >= meta.members || view.dtype() != safetensors::Dtype::F32 {
            bail!(
                "prior {}: tensor {name:?} is not one of its {} members' f32 tensors",
                path.display(),
                meta.members
            );
        }
        let data = view
            .data()
            .chunks_exact(4)
            .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
            .collect();
        members[member].push(wire::Tensor {
            name: tensor.to_string(),
            shape: view.shape().to_vec(),
            data,
        });
    }
    Ok(Prior { meta, members })
}

/// A person the prior must never see, by profile.
#[derive(Clone, Debug)]
pub struct Barred {
    pub name: String,
    pub profile: serde_json::Value,
}

/// People of a folder of world configs (`pbrl people sample`'s): each `*.json` with a
/// profile.
pub fn people_of(dir: &Path) -> Result<Vec<Barred>> {
    let mut out = Vec::new();
    let entries = std::fs::read_dir(dir).with_context(|| format!("reading {}", dir.display()))?;
    let mut paths: Vec<_> = entries.filter_map(|e| e.ok().map(|e| e.path())).collect();
    paths.sort();
    for path in paths
        .into_iter()
        .filter(|p| p.extension().is_some_and(|e| e == "json"))
    {
        let text = std::fs::read_to_string(&path)?;
        let v: serde_json::Value =
            serde_json::from_str(&text).with_context(|| format!("reading {}", path.display()))?;
        if let Some(profile) = v.get("profile") {
            out.push(Barred {
                name: profile["name"].as_str().unwrap_or_default().to_string(),
                profile: profile.clone(),
            });
        }
    }
    Ok(out)
}

/// Two profiles are one person: the same name, or the same weights and taste (a person
/// renamed is still that person).
fn same_person(a: &serde_json::Value, b: &serde_json::Value) -> bool {
    let name = |p: &serde_json::Value| p["name"].as_str().unwrap_or_default().to_string();
    let close = |x: &serde_json::Value, y: &serde_json::Value| match (x.as_f64(), y.as_f64()) {
        (Some(x), Some(y)) => (x - y).abs() <= 1e-4 * (1.0 + x.abs()),
        _ => x == y,
    };
    let same_weights = match (a["weights"].as_object(), b["weights"].as_object()) {
        (Some(x), Some(y)) => {
            x.len() == y.len() && x.iter().all(|(k, v)| y.get(k).is_some_and(|w| close(v, w)))
        }
        _ => false,
    };
    (!name(a).is_empty() && name(a) == name(b)) || (same_weights && a["taste"] == b["taste"])
}

/// Train a prior on the pooled answers of the runs in `runs` (each a run folder with its
/// config and label store), refusing any run of a person in `barred`. The reward model's
/// settings are the first run's (every run must share them), with `seed`; it trains
/// `rounds` times on the pooled answers, as a run trains once a session (each training
/// bounded by `reward_max_pairs`).
pub fn build(
    runs: &[std::path::PathBuf],
    barred: &[Barred],
    seed: u64,
    rounds: usize,
) -> Result<(RewardModel, PriorMeta)> {
    if runs.is_empty() {
        bail!("a prior needs at least one run's answers");
    }
    let mut model_cfg = None;
    let mut data = Vec::new();
    let (mut people, mut names) = (Vec::new(), Vec::new());
    let mut dims = None;
    for dir in runs {
        let config_path = dir.join("config.json");
        let text = std::fs::read_to_string(&config_path)
            .with_context(|| format!("reading {}", config_path.display()))?;
        let config: serde_json::Value = serde_json::from_str(&text)
            .with_context(|| format!("reading {}", config_path.display()))?;
        let profile = config["world"]["config"]["profile"].clone();
        if let Some(b) = barred.iter().find(|b| same_person(&b.profile, &profile)) {
            bail!(
                "{} is a run of {:?}, a person the prior must never see (held out)",
                dir.display(),
                b.name
            );
        }
        let model: crate::pref::reward_model::RewardModelConfig =
            serde_json::from_value(config["pref"]["model"].clone()).with_context(|| {
                format!(
                    "{}: pref.model is not a reward model's settings",
                    config_path.display()
                )
            })?;
        match &model_cfg {
            None => model_cfg = Some(model),
            Some(m) if (m.hidden.clone(), m.members, m.features) == (model.hidden.clone(), model.members, model.features) => {}
            Some(m) => bail!(
                "{}: its reward model (hidden {:?}, {} members, features {}) differs from the first run's (hidden {:?}, {} members, features {})",
                dir.display(),
                model.hidden,
                model.members,
                model.features,
                m.hidden,
                m.members,
                m.features
            ),
        }
        let labels = crate::pref::label_fit::read_labels(&dir.join("labels.sqlite"))?;
        match dims {
            None => dims = Some((labels.obs_dim, labels.act_dim)),
            Some(d) if d == (labels.obs_dim, labels.act_dim) => {}
            Some(d) => bail!(
                "{}: observations and actions of {:?}, the first run's {d:?}",
                dir.display(),
                (labels.obs_dim, labels.act_dim)
            ),
        }
        tracing::info!(run = %dir.display(), labels = labels.data.len(), "answers read for the prior");
        data.extend(labels.data);
        let name = profile["name"]
            .as_str()
            .unwrap_or("the paper's person")
            .to_string();
        if !people.contains(&name) {
            people.push(name);
        }
        names.push(dir.display().to_string());
    }
    let mut cfg = model_cfg.expect("at least one run");
    cfg.seed = seed;
    let (obs_dim, act_dim) = dims.expect("at least one run");
    let mut model = RewardModel::new(cfg, obs_dim, act_dim)?;
    for round in 1..=rounds.max(1) {
        let stats = model.train(&data)?;
        if round % 10 == 0 {
            tracing::info!(round, accuracy = stats.accuracy, "training the prior");
        }
    }
    let accuracy = model.accuracy(&data)?;
    let meta = PriorMeta {
        format: PRIOR_FORMAT.into(),
        obs_dim,
        act_dim,
        feat_dim: model.feat_dim(),
        hidden: model.config().hidden.clone(),
        members: model.networks().len(),
        norm_mean: Vec::new(),
        norm_std: Vec::new(),
        people,
        runs: names,
        labels: data.len(),
        accuracy,
    };
    Ok((model, meta))
}

impl RewardModel {
    /// Start from `prior`: its members' weights and its normaliser, kept from now on. The
    /// model must have the prior's shape; each mismatch is named.
    pub fn start_from(&mut self, prior: &Prior, path: &Path) -> Result<()> {
        let m = &prior.meta;
        let mine = (
            self.obs_dim(),
            self.act_dim(),
            self.feat_dim(),
            self.config().hidden.clone(),
            self.networks().len(),
        );
        let theirs = (
            m.obs_dim,
            m.act_dim,
            m.feat_dim,
            m.hidden.clone(),
            m.members,
        );
        if mine != theirs {
            bail!(
                "prior {}: its reward model (observation, action, feature widths, hidden layers, members) is {theirs:?}, this run's is {mine:?}",
                path.display()
            );
        }
        for ((name, varmap), tensors) in self.networks().into_iter().zip(&prior.members) {
            pbrl_common::nets::import(varmap, tensors)
                .with_context(|| format!("prior {}: member {name}", path.display()))?;
        }
        self.keep_normaliser(m.norm_mean.clone(), m.norm_std.clone())?;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pref::reward_model::{Labelled, RewardModelConfig, Segment};
    use std::sync::Arc;

    fn seg(v: f32) -> Arc<Segment> {
        Arc::new(Segment {
            obs: vec![v, -v, 0.5 * v, 1.0, v, -v, 0.5 * v, 1.0],
            actions: vec![0.0, 0.0],
            features: Vec::new(),
        })
    }

    #[test]
    fn a_prior_saved_loads_into_a_fresh_model_that_then_predicts_as_it_did() {
        let cfg = RewardModelConfig {
            members: 2,
            hidden: vec![8, 8],
            features: false,
            crops: 0,
            ..RewardModelConfig::default()
        };
        let mut model = RewardModel::new(cfg.clone(), 4, 1).unwrap();
        let data: Vec<Labelled> = (0..20)
            .map(|k| Labelled {
                first: seg(k as f32),
                second: seg(k as f32 + 0.5),
                target: 1.0,
            })
            .collect();
        model.train(&data).unwrap();
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("prior.safetensors");
        let meta = PriorMeta {
            format: String::new(),
            obs_dim: 0,
            act_dim: 0,
            feat_dim: 0,
            hidden: Vec::new(),
            members: 0,
            norm_mean: Vec::new(),
            norm_std: Vec::new(),
            people: vec!["tune-03".into()],
            runs: vec!["a".into()],
            labels: data.len(),
            accuracy: 1.0,
        };
        save(&model, meta, &path).unwrap();
        let prior = load(&path).unwrap();
        assert_eq!(prior.meta.people, ["tune-03"]);
        assert_eq!((prior.meta.obs_dim, prior.meta.members), (4, 2));
        let mut fresh = RewardModel::new(
            RewardModelConfig {
                seed: 9,
                ..cfg.clone()
            },
            4,
            1,
        )
        .unwrap();
        let pairs = [(&*seg(1.0), &*seg(7.0)), (&*seg(3.0), &*seg(2.0))];
        assert_ne!(
            fresh.preference_probs(&pairs).unwrap(),
            model.preference_probs(&pairs).unwrap()
        );
        fresh.start_from(&prior, &path).unwrap();
        assert_eq!(
            fresh.preference_probs(&pairs).unwrap(),
            model.preference_probs(&pairs).unwrap()
        );
        // The normaliser stays the prior's through a training on a person's few answers.
        fresh.train(&data[..2]).unwrap();
        assert_eq!(fresh.normaliser(), model.normaliser());
        // Another shape is refused, naming both.
        let mut other = RewardModel::new(
            RewardModelConfig {
                hidden: vec![4],
                ..cfg
            },
            4,
            1,
        )
        .unwrap();
        let e = other.start_from(&prior, &path).unwrap_err().to_string();
        assert!(e.contains("[8, 8]") && e.contains("[4]"), "{e}");
        // A file that is not a prior is refused.
        std::fs::write(dir.path().join("x"), b"not a prior").unwrap();
        assert!(load(&dir.path().join("x")).is_err());
    }
}

#[cfg(test)]
mod build_tests {
    use super::*;
    use crate::pref::labels::{LabelStore, StoredTrajectory};
    use crate::pref::reward_model::RewardModelConfig;
    use pbrl_common::wire::{Answer, Preference};

    /// The repository's people (tests run in the crate's folder).
    fn people(set: &str) -> std::path::PathBuf {
        Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../results/people")
            .join(set)
    }

    /// A run folder of `person` (a world config's file) holding `n` answered pairs.
    fn run_of(dir: &Path, person: &Path, n: u64) -> std::path::PathBuf {
        let world: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(person).unwrap()).unwrap();
        let model = RewardModelConfig {
            features: false,
            crops: 0,
            members: 2,
            hidden: vec![8],
            ..RewardModelConfig::default()
        };
        let out = dir.join(person.file_stem().unwrap());
        std::fs::create_dir_all(&out).unwrap();
        let config = serde_json::json!({
            "run": "r",
            "world": {"config": {"profile": world["profile"]}},
            "pref": {"model": model},
        });
        std::fs::write(out.join("config.json"), config.to_string()).unwrap();
        let mut store = LabelStore::open(&out.join("labels.sqlite"), "r").unwrap();
        let obs: Vec<Vec<f32>> = (0..2 * n).map(|k| vec![k as f32; 3 * 2]).collect();
        let actions = vec![0.0f32; 3];
        let side = |k: usize| StoredTrajectory {
            actor: 0,
            incarnation: 1,
            seq: k as u64,
            seed: k as u64,
            policy_version: 1,
            obs_dim: 2,
            act_dim: 1,
            obs: &obs[k],
            actions: &actions,
            features: &[],
            segment: (0, 3),
        };
        for k in 0..n as usize {
            let asked = store
                .ask(
                    1,
                    "uniform",
                    0,
                    0,
                    &side(2 * k),
                    &side(2 * k + 1),
                    |_, _, _| vec![1],
                )
                .unwrap();
            let a = Answer::scripted(asked.query, Preference::Second, "oracle", "o-0", 1);
            store.answer(&a, 1).unwrap();
        }
        out
    }

    #[test]
    fn a_prior_learns_from_tuning_people_and_refuses_a_held_out_one() {
        let dir = tempfile::tempdir().unwrap();
        let barred = people_of(&people("held-out")).unwrap();
        assert_eq!(barred.len(), 6);
        let tune = run_of(dir.path(), &people("tuning").join("tune-03.json"), 6);
        let held = run_of(dir.path(), &people("held-out").join("held-02.json"), 6);
        let (model, meta) = build(std::slice::from_ref(&tune), &barred, 1, 2).unwrap();
        assert_eq!(meta.people, ["tune-03"]);
        assert_eq!(meta.labels, 6);
        assert!(model.trained());
        let path = dir.path().join("prior.safetensors");
        save(&model, meta, &path).unwrap();
        let read = load(&path).unwrap();
        assert!(barred.iter().all(|b| !read.meta.people.contains(&b.name)));
        let e = build(&[tune.clone(), held], &barred, 1, 2)
            .err()
            .unwrap()
            .to_string();
        assert!(e.contains("held-02") && e.contains("never see"), "{e}");
        // A held-out person renamed is still refused: the same weights and taste.
        let renamed = dir.path().join("renamed.json");
        let mut w: serde_json::Value = serde_json::from_str(
            &std::fs::read_to_string(people("held-out").join("held-05.json")).unwrap(),
        )
        .unwrap();
        w["profile"]["name"] = "someone".into();
        std::fs::write(&renamed, w.to_string()).unwrap();
        let sneaked = run_of(dir.path(), &renamed, 3);
        let e = build(&[sneaked], &barred, 1, 2).err().unwrap().to_string();
        assert!(e.contains("held-05"), "{e}");
    }
}
