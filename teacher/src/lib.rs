//! The teachers that answer preference queries. [`scripted`]: the six B-Pref scripted
//! teachers of paper Table I, which judge from the ground-truth reward.

pub mod scripted;
