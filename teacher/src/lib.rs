//! The teachers that answer preference queries. [`scripted`]: the six B-Pref scripted
//! teachers of paper Table I, which judge from the ground-truth reward. [`teacher`]: the one
//! trait both kinds implement. [`outbox`]: every answer kept on disk until the learner
//! acknowledges it, in the teacher's [`file`]. [`service`]: the one loop that answers the learner's queries over Zenoh
//! (`pbrl teacher`, or in-process under `pbrl train`). [`human`] and [`web`]: people answer
//! from a labelling page (or any client of its HTTP API), through a queue kept on disk.

pub mod file;
pub mod human;
pub mod outbox;
pub mod pace;
pub mod scripted;
pub mod service;
pub mod teacher;
pub mod web;
