//! The learner loop's counters: what a curve row reports and a checkpoint keeps.

use pbrl_common::bus::Receipts;
use pbrl_common::Outcome;
use serde::{Deserialize, Serialize};

use crate::run::backbone::{LastLosses, Publication};

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
    /// The newest losses.
    pub losses: LastLosses,
    /// Wall time of the run in earlier processes.
    pub wall_s: f64,
    pub rows_written: u64,
    pub stale: u64,
}

/// Episode statistics accumulated between curve rows.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct Window {
    pub episodes: u64,
    pub truth: f64,
    pub success: f64,
    pub human: f64,
    pub task: f64,
}

impl Window {
    pub fn add(&mut self, o: &Outcome) {
        self.episodes += 1;
        self.truth += o.return_truth as f64;
        self.human += o.return_human as f64;
        self.task += o.return_task as f64;
        self.success += o.success as u8 as f64;
    }
}
