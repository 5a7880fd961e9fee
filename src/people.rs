//! `pbrl people sample`: a population of simulated people as world configs
//! (`docs/people.md`), one file per person, for `pbrl train --world`, `pbrl eval --people`
//! and `pbrl exp` grids (`people = DIR`).

use std::path::PathBuf;

use anyhow::{bail, Context, Result};
use clap::{Args, Subcommand};
use pbrl_actor::people::{sample, CSV_HEADER};

#[derive(Subcommand, Debug)]
pub enum PeopleCommand {
    /// Draw N people and write one world config per person (`NAME.json`, holding only the
    /// person's profile) and `people.csv`, what each was drawn with.
    Sample(SampleArgs),
}

#[derive(Args, Debug)]
pub struct SampleArgs {
    /// How many people.
    #[arg(long)]
    pub n: usize,
    /// Seed of the draws (the same seed and n give the same people).
    #[arg(long)]
    pub seed: u64,
    /// Folder to write into (created; files of the same names are replaced).
    #[arg(long)]
    pub out: PathBuf,
    /// Names are this prefix and a number from 01 (default: `person-s<seed>-`).
    #[arg(long)]
    pub prefix: Option<String>,
}

pub fn run(cmd: PeopleCommand) -> Result<()> {
    match cmd {
        PeopleCommand::Sample(a) => sample_people(a),
    }
}

fn sample_people(a: SampleArgs) -> Result<()> {
    if a.n == 0 || a.n > 10_000 {
        bail!("--n = {}: must be in 1..=10000", a.n);
    }
    let prefix = a.prefix.unwrap_or_else(|| format!("person-s{}-", a.seed));
    if prefix.contains(['/', '\\']) || prefix.contains("..") {
        bail!("--prefix = {prefix:?}: names are file names, so no '/', '\\' or '..'");
    }
    std::fs::create_dir_all(&a.out).with_context(|| format!("creating {}", a.out.display()))?;
    let people = sample(a.n, a.seed, &prefix);
    let mut csv = format!("{CSV_HEADER}\n");
    for p in &people {
        let path = a.out.join(format!("{}.json", p.profile.name));
        #[derive(serde::Serialize)]
        struct File<'a> {
            profile: &'a pbrl_actor::Profile,
        }
        let text = serde_json::to_string_pretty(&File {
            profile: &p.profile,
        })?;
        std::fs::write(&path, text + "\n")
            .with_context(|| format!("writing {}", path.display()))?;
        csv.push_str(&p.csv_row());
        csv.push('\n');
    }
    let path = a.out.join("people.csv");
    std::fs::write(&path, csv).with_context(|| format!("writing {}", path.display()))?;
    println!(
        "{} people (seed {}) in {}: one world config each, and people.csv",
        people.len(),
        a.seed,
        a.out.display()
    );
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use pbrl_actor::WorldConfig;

    #[test]
    fn every_file_written_is_a_world_config_of_its_person() {
        let dir = tempfile::tempdir().unwrap();
        let args = |n| SampleArgs {
            n,
            seed: 5,
            out: dir.path().join("people"),
            prefix: None,
        };
        sample_people(args(3)).unwrap();
        let people = sample(3, 5, "person-s5-");
        for p in &people {
            let file = dir
                .path()
                .join("people")
                .join(format!("{}.json", p.profile.name));
            let cfg = WorldConfig::from_json(&std::fs::read_to_string(file).unwrap()).unwrap();
            assert_eq!(cfg.profile, p.profile);
            // Only the person: the rest of the world is the default's.
            assert_eq!(
                WorldConfig {
                    profile: WorldConfig::default().profile,
                    ..cfg
                },
                WorldConfig::default()
            );
        }
        let csv = std::fs::read_to_string(dir.path().join("people/people.csv")).unwrap();
        assert_eq!(csv.lines().count(), 4);
        assert!(csv.starts_with(CSV_HEADER));
        let e = sample_people(args(0)).unwrap_err().to_string();
        assert!(e.contains("--n = 0"), "{e}");
        let e = sample_people(SampleArgs {
            prefix: Some("../x".into()),
            ..args(2)
        })
        .unwrap_err()
        .to_string();
        assert!(e.contains("--prefix"), "{e}");
    }
}
