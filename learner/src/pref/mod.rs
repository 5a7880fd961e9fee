//! Preference learning: the reward ensemble (`reward_model`), choosing queries (`query`),
//! the k-NN state-entropy bonus of the pretraining (`entropy`), the label store (`labels`,
//! `label_stats`, `label_fit`), Algorithm 1's feedback schedule (`feedback`), what the policy trains on
//! (`reward`) and their settings (`config`). It uses the backbones' types, never the run's.

pub mod config;
pub mod entropy;
pub mod feedback;
pub mod label_fit;
pub mod label_stats;
pub mod labels;
pub mod prior;
pub mod query;
pub mod reward;
pub mod reward_model;
