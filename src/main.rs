//! `pbrl`: the command line. It parses arguments, sets up logging and calls the crates.

use anyhow::Result;
use clap::{Parser, Subcommand};

#[derive(Parser, Debug)]
#[command(
    name = "pbrl",
    version,
    about = "Preference-based RL for personalised robot feeding"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// The feeding world: demo, bench, record, render.
    #[command(subcommand)]
    Env(pbrl_actor::cli::EnvCommand),
}

fn main() -> Result<()> {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "info".into()),
        )
        .with_writer(std::io::stderr)
        .init();
    match Cli::parse().command {
        Command::Env(cmd) => pbrl_actor::cli::run(cmd),
    }
}
