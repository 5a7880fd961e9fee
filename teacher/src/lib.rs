//! The teachers that answer preference queries. [`scripted`]: the six B-Pref scripted
//! teachers of paper Table I, which judge from the ground-truth reward. [`service`]: the
//! teacher service that answers the learner's queries over Zenoh (`pbrl teacher`, or
//! in-process under `pbrl train`). [`human`] and [`web`]: people answer from a labelling
//! page (or any client of its HTTP API), through a queue kept on disk.

pub mod human;
pub mod scripted;
pub mod service;
pub mod web;
