//! `pbrl export`: a run's policy as an ONNX model a robot stack loads, and its card
//! (`pbrl_learner::run::export` has the model and the card's fields).

use std::path::PathBuf;

use anyhow::{bail, Context, Result};
use pbrl_actor::evaluate::{evaluate_seeds, Acting};
use pbrl_learner::run::export::{
    card_path, model, Card, Message, Slot, IR_VERSION, JOINTS, OBSERVATION, OPSET,
};

use crate::eval::{open_runs, seeds, threads, Estimate, Person};

#[derive(clap::Args, Debug)]
pub struct ExportArgs {
    /// The run folder.
    pub run: PathBuf,
    /// The checkpoint at this many env steps (default: the newest).
    #[arg(long, value_name = "STEPS")]
    pub checkpoint: Option<u64>,
    /// Where the ONNX model goes.
    #[arg(long, value_name = "FILE")]
    pub onnx: PathBuf,
    /// Where the card goes (default: the model's name with .card.json).
    #[arg(long, value_name = "FILE")]
    pub card: Option<PathBuf>,
    /// Evaluation episodes for the card's figures (the run's own person, the mean action;
    /// 0: none).
    #[arg(long, default_value_t = 100)]
    pub episodes: u32,
    /// Threads of that evaluation (default: every core).
    #[arg(long)]
    pub threads: Option<usize>,
}

pub fn export(args: ExportArgs) -> Result<()> {
    let runs = open_runs(std::slice::from_ref(&args.run), args.checkpoint)?;
    let run = &runs[0];
    let p = &run.policy;
    let world = Person::own().world_for(run, false)?;
    if (p.config.obs_dim, p.config.act_dim) != (OBSERVATION.len(), JOINTS.len()) {
        bail!(
            "{}: the policy takes {} numbers and gives {}; the feeding world's are {} and {}",
            args.run.display(),
            p.config.obs_dim,
            p.config.act_dim,
            OBSERVATION.len(),
            JOINTS.len()
        );
    }
    let doc = "pbrl feeding policy: raw observation (25, robot base frame) in, mean action (7, in [-1, 1]: joint targets q + action_scale * action) out; see the card (JSON) beside this file";
    let meta = [
        ("run", run.name.clone()),
        ("env_steps", p.env_steps.to_string()),
        ("person", world.profile.name.clone()),
        ("action_scale", world.action_scale.to_string()),
    ];
    let m = model(&p.weights, doc, &meta)?;
    let bytes = m.write_to_bytes().context("encoding the ONNX model")?;
    if let Some(dir) = args.onnx.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    }
    std::fs::write(&args.onnx, &bytes)
        .with_context(|| format!("writing {}", args.onnx.display()))?;
    let evaluation = if args.episodes > 0 {
        let s = seeds(args.episodes);
        let episodes = evaluate_seeds(
            &p.weights,
            &world,
            &s,
            Acting::Mean,
            threads(args.threads),
            &|| {},
        )?;
        let figures: serde_json::Map<String, serde_json::Value> = crate::eval::summarise(&episodes)
            .into_iter()
            .map(|(k, e): (String, Estimate)| Ok((k, serde_json::to_value(e)?)))
            .collect::<Result<_>>()?;
        Some(serde_json::json!({
            "episodes": s.len(),
            "seeds": { "first": s[0], "count": s.len() },
            "acting": "mean",
            "measures": figures,
        }))
    } else {
        None
    };
    let labels = p.label_counts()?.map(|c| {
        serde_json::json!({ "asked": c.asked, "answered": c.answered, "equal": c.equal, "skipped": c.skipped })
    });
    let card = Card {
        format: "pbrl policy card".into(),
        version: 1,
        model: args.onnx.display().to_string(),
        opset: OPSET,
        ir_version: IR_VERSION,
        input: "obs".into(),
        input_shape: vec!["N".into(), OBSERVATION.len().to_string()],
        output: "action".into(),
        output_shape: vec!["N".into(), JOINTS.len().to_string()],
        observation: OBSERVATION
            .iter()
            .enumerate()
            .map(|(index, (name, unit))| Slot {
                index,
                name: name.to_string(),
                unit: unit.to_string(),
            })
            .collect(),
        action: JOINTS
            .iter()
            .enumerate()
            .map(|(index, j)| Slot {
                index,
                name: format!("joint_{j}_target_delta"),
                unit: "fraction of action_scale rad, in [-1, 1]".into(),
            })
            .collect(),
        action_meaning: "joint position targets q + action_scale * action (rad, q measured), clamped to the joint limits, held for one control step".into(),
        action_scale: world.action_scale,
        action_low: -1.0,
        action_high: 1.0,
        control_hz: 1.0 / world.control_dt(),
        obs_clip: p.weights.obs_clip,
        run: run.name.clone(),
        algo: format!("{:?}", p.config.algo).to_lowercase(),
        reward: p.config.reward.name().to_string(),
        seed: p.config.sac.seed,
        env_steps: p.env_steps,
        weights_version: p.version,
        person: serde_json::to_value(&world.profile)?,
        world: run.world.clone(),
        labels,
        evaluation,
    };
    let card_file = args.card.clone().unwrap_or_else(|| card_path(&args.onnx));
    std::fs::write(&card_file, serde_json::to_string_pretty(&card)? + "\n")
        .with_context(|| format!("writing {}", card_file.display()))?;
    println!(
        "{}: ONNX opset {OPSET}, obs [N, 25] -> action [N, 7] ({} bytes); card {}",
        args.onnx.display(),
        bytes.len(),
        card_file.display()
    );
    Ok(())
}
