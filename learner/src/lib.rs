//! The learner: PPO and SAC backbones, the reward ensemble and query selection. Built by
//! the actor-learner issue; empty until then.
