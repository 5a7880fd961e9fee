//! The run: the learner service and its loop (`service`), the backbone behind one enum
//! (`backbone`), the learning curve (`curve`, `evaluation`), the loop's counters
//! (`progress`), checkpoints (`checkpoint`),
//! the run folder's layout (`run_folder`) and the settings of a whole run (`config`).

pub mod backbone;
pub mod bus;
pub mod checkpoint;
pub mod config;
pub mod curve;
pub mod evaluation;
pub mod export;
pub mod learner;
pub mod progress;
pub mod run_folder;
pub mod saved_policy;
pub mod service;
