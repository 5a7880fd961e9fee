//! `pbrl prior`: a reward prior learnt from the answers of a population's tuning people,
//! for `pbrl train --prior FILE` (`pbrl_learner::pref::prior`).

use std::path::PathBuf;

use anyhow::Result;
use clap::Args;
use pbrl_learner::pref::prior;

#[derive(Args, Debug)]
pub struct PriorArgs {
    /// Run folders whose answers the prior learns from (each a run's config.json and
    /// labels.sqlite), e.g. the tuning people's runs.
    #[arg(required = true)]
    pub runs: Vec<PathBuf>,
    /// Where to write the prior (one safetensors file).
    #[arg(long)]
    pub out: PathBuf,
    /// A folder of people the prior must never see (world configs of `pbrl people
    /// sample`): a run of any of them is refused.
    #[arg(long, default_value = "results/people/held-out")]
    pub held_out: PathBuf,
    /// Seed of the ensemble's initialisation and training.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Trainings on the pooled answers (each bounded by --reward-max-pairs of the runs'
    /// settings, as a run's once a session).
    #[arg(long, default_value_t = 40)]
    pub rounds: usize,
    /// Runs of other people to judge the prior on (their answers never trained on): its
    /// accuracy on each.
    #[arg(long, num_args = 1..)]
    pub check: Vec<PathBuf>,
}

pub fn run(a: PriorArgs) -> Result<()> {
    let barred = if a.held_out.is_dir() {
        prior::people_of(&a.held_out)?
    } else {
        anyhow::bail!(
            "--held-out {}: no such folder (the people the prior must never see)",
            a.held_out.display()
        );
    };
    let (model, meta) = prior::build(&a.runs, &barred, a.seed, a.rounds)?;
    prior::save(&model, meta.clone(), &a.out)?;
    let people = match meta.people.len() {
        1 => "1 person".to_string(),
        n => format!("{n} people"),
    };
    println!(
        "prior {}: {} labels of {people} ({}) from {} runs, accuracy {:.3}; never saw {} held-out people",
        a.out.display(),
        meta.labels,
        meta.people.join(", "),
        meta.runs.len(),
        meta.accuracy,
        barred.len()
    );
    for run in &a.check {
        let labels = pbrl_learner::pref::label_fit::read_labels(&run.join("labels.sqlite"))?;
        println!(
            "  on {} ({} labels, never trained on): accuracy {:.3}",
            run.display(),
            labels.data.len(),
            model.accuracy(&labels.data)?
        );
    }
    Ok(())
}
