//! Every Zenoh key expression pbrl uses, built in one place:
//! `pbrl/<run>/<role>/<id>/<topic>`, lowercase, general to specific.

use std::fmt;

/// The key expressions of one run.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Keys {
    run: String,
}

/// A run id that cannot be part of a key expression.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
#[error("invalid run id {run:?}: {reason}")]
pub struct RunIdError {
    pub run: String,
    pub reason: &'static str,
}

impl Keys {
    /// Keys for run `run`: 1-64 characters of `a-z`, `0-9`, `-` and `_`.
    pub fn new(run: &str) -> Result<Self, RunIdError> {
        let err = |reason| RunIdError {
            run: run.to_string(),
            reason,
        };
        if run.is_empty() || run.len() > 64 {
            return Err(err("must be 1 to 64 characters long"));
        }
        if !run
            .chars()
            .all(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || c == '-' || c == '_')
        {
            return Err(err("may hold only a-z, 0-9, '-' and '_'"));
        }
        Ok(Self {
            run: run.to_string(),
        })
    }

    /// The run id.
    pub fn run(&self) -> &str {
        &self.run
    }

    /// Newest policy weights, published by the learner (also answered as a query, so an
    /// actor that joins late gets them at once).
    pub fn weights(&self) -> String {
        format!("pbrl/{}/learner/0/weights", self.run)
    }

    /// Whole trajectories published by actor `actor`.
    pub fn trajectory(&self, actor: u32) -> String {
        format!("pbrl/{}/actor/{actor}/trajectory", self.run)
    }

    /// Trajectories of every actor (a subscription).
    pub fn all_trajectories(&self) -> String {
        format!("pbrl/{}/actor/*/trajectory", self.run)
    }

    /// The learner's requests to actor `actor` for deterministic evaluation episodes.
    pub fn eval_request(&self, actor: u32) -> String {
        format!("pbrl/{}/learner/0/eval/{actor}", self.run)
    }

    /// Evaluation episodes published by actor `actor`.
    pub fn eval_result(&self, actor: u32) -> String {
        format!("pbrl/{}/actor/{actor}/eval", self.run)
    }

    /// Evaluation episodes of every actor (a subscription).
    pub fn all_eval_results(&self) -> String {
        format!("pbrl/{}/actor/*/eval", self.run)
    }

    /// Preference queries asked by the learner (of any teacher).
    pub fn queries(&self) -> String {
        format!("pbrl/{}/learner/0/query", self.run)
    }

    /// Answers published by teacher `teacher`.
    pub fn answer(&self, teacher: &str) -> String {
        format!("pbrl/{}/teacher/{teacher}/answer", self.run)
    }

    /// Answers of every teacher (a subscription).
    pub fn all_answers(&self) -> String {
        format!("pbrl/{}/teacher/*/answer", self.run)
    }

    /// The learner's acknowledgements of teacher `teacher`'s stored answers.
    pub fn answer_ack(&self, teacher: &str) -> String {
        format!("pbrl/{}/learner/0/ack/{teacher}", self.run)
    }

    /// The learner's state, every second ([`crate::wire::LearnerStatus`]).
    pub fn status(&self) -> String {
        format!("pbrl/{}/learner/0/status", self.run)
    }

    /// The liveliness token of a person labelling at teacher `teacher` (`name` with
    /// anything but a-z, A-Z, 0-9, '-' and '_' as '_').
    pub fn labeller(&self, teacher: &str, name: &str) -> String {
        let name: String = name
            .chars()
            .map(|c| {
                if c.is_ascii_alphanumeric() || c == '-' {
                    c
                } else {
                    '_'
                }
            })
            .collect();
        format!("pbrl/{}/teacher/{teacher}/labeller/{name}", self.run)
    }

    /// Every labeller's liveliness token (a liveliness subscription).
    pub fn all_labellers(&self) -> String {
        format!("pbrl/{}/teacher/*/labeller/*", self.run)
    }

    /// The learner's stop signal to the run's actors.
    pub fn stop(&self) -> String {
        format!("pbrl/{}/learner/0/stop", self.run)
    }
}

impl fmt::Display for Keys {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "pbrl/{}", self.run)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn keys_are_general_to_specific_and_run_ids_are_checked() {
        let k = Keys::new("sac-seed_1").unwrap();
        assert_eq!(k.weights(), "pbrl/sac-seed_1/learner/0/weights");
        assert_eq!(k.trajectory(3), "pbrl/sac-seed_1/actor/3/trajectory");
        assert_eq!(k.all_trajectories(), "pbrl/sac-seed_1/actor/*/trajectory");
        for bad in ["", "a/b", "A", "x*", "run$", &"x".repeat(65)] {
            assert!(Keys::new(bad).is_err(), "{bad:?} accepted");
        }
    }
}
