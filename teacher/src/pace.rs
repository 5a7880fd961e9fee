//! A person's pace for a scripted teacher ([`Paced`]): queries are answered one at a time,
//! in the order they came, each after the time a person would take over it (to watch both
//! attempts as the page plays them, and to decide), so that a run measures what a real
//! sitting does to learning.
//!
//! The time is wall-clock time, as a person's is. What the person is working through lives
//! in memory only: a teacher killed mid-answer has given nothing yet, and the learner asks
//! its open queries again. An answer, once given, is kept in the outbox as any other.

use std::collections::{HashSet, VecDeque};
use std::time::{Duration, Instant};

use anyhow::{bail, Result};
use pbrl_common::wire::{now_ms, Answer, LearnerStatus, Query, Shown};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, LogNormal};
use serde::{Deserialize, Serialize};

use crate::outbox::Outbox;
use crate::teacher::{judged, Judge, Teacher};
use crate::web::LEAD_IN_STEPS;

/// Frames a second at which the page plays an attempt at 1x (the world's control rate).
pub const PLAY_STEPS_PER_S: f64 = 10.0;

/// How fast a scripted teacher answers. Each default is its flag's: at once.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, clap::Args)]
pub struct PaceConfig {
    /// Scripted teachers: seconds a simulated person takes over each answer, one answer at
    /// a time in the order the queries came (0: at once, as a program). With
    /// `--answer-watch`, the seconds to decide after watching.
    #[arg(long, default_value_t = 0.0)]
    pub answer_s: f64,
    /// Scripted teachers: the spread of each answer's time, as the standard deviation of
    /// its logarithm (0: every answer takes `--answer-s`; 0.5: a person's usual spread,
    /// the mean staying `--answer-s`).
    #[arg(long, default_value_t = 0.0)]
    pub answer_spread: f64,
    /// Scripted teachers: add the time to watch both attempts as the labelling page plays
    /// them at 1x (each judged part with its lead-in, at the world's 10 steps a second).
    #[arg(long)]
    pub answer_watch: bool,
}

impl Default for PaceConfig {
    fn default() -> Self {
        pbrl_common::flags::defaults()
    }
}

impl PaceConfig {
    /// A fixed time per answer.
    pub fn fixed(answer_s: f64) -> Self {
        Self {
            answer_s,
            ..Self::default()
        }
    }

    /// Answers take time (else the teacher answers at once).
    pub fn paced(&self) -> bool {
        self.answer_s > 0.0 || self.answer_watch
    }

    pub fn validate(&self) -> Result<()> {
        if !(self.answer_s.is_finite() && self.answer_s >= 0.0) {
            bail!(
                "answer_s is {}: must be a number of seconds, 0 or more",
                self.answer_s
            );
        }
        if !(self.answer_spread.is_finite() && (0.0..=3.0).contains(&self.answer_spread)) {
            bail!(
                "answer_spread is {}: must be in [0, 3] (the standard deviation of the time's logarithm)",
                self.answer_spread
            );
        }
        if self.answer_spread > 0.0 && self.answer_s == 0.0 {
            bail!(
                "answer_spread is {}: it spreads --answer-s, which is 0",
                self.answer_spread
            );
        }
        Ok(())
    }
}

/// Seconds to watch one side of a query as the page plays it at 1x: its judged steps and
/// their lead-in.
pub fn watch_s(s: &Shown) -> f64 {
    let seg = s.segment();
    let lead = if seg.len() < s.steps() {
        seg.start.min(LEAD_IN_STEPS)
    } else {
        0
    };
    (lead + seg.len()) as f64 / PLAY_STEPS_PER_S
}

/// A query the person has yet to answer, and when it came.
struct Waiting {
    query: Query,
    came: Instant,
}

/// A judge answering at a person's pace: one query at a time, in the order they came.
pub struct Paced<J> {
    judge: J,
    id: String,
    pace: PaceConfig,
    decide: Option<LogNormal<f64>>,
    rng: ChaCha8Rng,
    queue: VecDeque<Waiting>,
    queued: HashSet<u64>,
    /// The answer at the head of the queue: when the person started it and how long it
    /// takes (None: idle).
    working: Option<(Instant, Duration)>,
    /// The learner's env steps, by its newest status (a stale query is passed over).
    learner_steps: u64,
}

impl<J: Judge> Paced<J> {
    pub fn new(judge: J, id: &str, pace: PaceConfig, seed: u64) -> Result<Self> {
        pace.validate()?;
        let decide = (pace.answer_spread > 0.0)
            .then(|| {
                let sigma = pace.answer_spread;
                // NOTE: the mean of the log-normal is exp(mu + sigma^2 / 2) = answer_s.
                LogNormal::new(pace.answer_s.ln() - sigma * sigma / 2.0, sigma)
            })
            .transpose()?;
        Ok(Self {
            judge,
            id: id.to_string(),
            pace,
            decide,
            rng: ChaCha8Rng::seed_from_u64(seed ^ 0x9ace_0000_0000_0001),
            queue: VecDeque::new(),
            queued: HashSet::new(),
            working: None,
            learner_steps: 0,
        })
    }

    /// How long the person takes over `q`.
    fn time(&mut self, q: &Query) -> Duration {
        let decide = match &self.decide {
            Some(d) => d.sample(&mut self.rng),
            None => self.pace.answer_s,
        };
        let watch = if self.pace.answer_watch {
            watch_s(&q.first) + watch_s(&q.second)
        } else {
            0.0
        };
        Duration::from_secs_f64((decide + watch).max(0.0))
    }

    /// Queries waiting for the person (the one being answered among them).
    pub fn waiting(&self) -> usize {
        self.queue.len()
    }

    /// `q` came at `now`: queued behind the others (a query asked again while queued is
    /// not queued twice).
    pub fn receive_at(&mut self, q: Query, now: Instant) {
        if !self.queued.insert(q.id) {
            return;
        }
        self.queue.push_back(Waiting {
            query: q,
            came: now,
        });
        self.start_next(now);
    }

    /// The person takes up the next query that is still asked, at `at`.
    fn start_next(&mut self, at: Instant) {
        if self.working.is_some() {
            return;
        }
        while let Some(head) = self.queue.front() {
            let q = &head.query;
            let gone = q.expired_at(now_ms()) || q.stale_at(self.learner_steps);
            if gone {
                tracing::debug!(query = q.id, "a withdrawn query passed over");
                let id = q.id;
                self.queue.pop_front();
                self.queued.remove(&id);
                continue;
            }
            let start = at.max(head.came);
            let q = head.query.clone();
            let took = self.time(&q);
            self.working = Some((start, took));
            return;
        }
    }

    /// The answers the person has finished by `now`, each kept in `outbox` first.
    pub fn due_at(&mut self, outbox: &mut Outbox, now: Instant) -> Result<Vec<Answer>> {
        let mut out = Vec::new();
        while let Some((start, took)) = self.working {
            let done = start + took;
            if done > now {
                break;
            }
            self.working = None;
            let Some(head) = self.queue.pop_front() else {
                break;
            };
            self.queued.remove(&head.query.id);
            let answer = judged(
                &mut self.judge,
                &head.query,
                &self.id,
                took.as_millis() as u64,
            );
            outbox.keep(&answer, head.query.asked_at_ms)?;
            out.push(answer);
            self.start_next(done);
        }
        Ok(out)
    }
}

impl<J: Judge> Teacher for Paced<J> {
    fn kind(&self) -> String {
        self.judge.kind()
    }

    fn receive(&mut self, q: Query, _outbox: &mut Outbox) -> Result<Option<Answer>> {
        self.receive_at(q, Instant::now());
        Ok(None)
    }

    fn due(&mut self, outbox: &mut Outbox) -> Result<Vec<Answer>> {
        self.due_at(outbox, Instant::now())
    }

    fn learner_status(&mut self, status: LearnerStatus) {
        self.learner_steps = status.env_steps;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::file::TeacherFile;
    use crate::scripted::{Scripted, ScriptedConfig, TeacherKind};

    fn paced(pace: PaceConfig) -> (Paced<Scripted>, Outbox) {
        let oracle = Scripted::new(ScriptedConfig::of(TeacherKind::Oracle, 0)).unwrap();
        let file = TeacherFile::open(std::path::Path::new(":memory:")).unwrap();
        (
            Paced::new(oracle, "oracle-0", pace, 0).unwrap(),
            Outbox::open(&file, "oracle-0").unwrap(),
        )
    }

    fn query(id: u64) -> Query {
        crate::human::tests::query(id, id as f32, 1.5)
    }

    #[test]
    fn answers_come_one_at_a_time_each_after_the_persons_time() {
        let (mut p, mut outbox) = paced(PaceConfig::fixed(12.0));
        let t0 = Instant::now();
        for id in 1..=3 {
            p.receive_at(query(id), t0);
        }
        p.receive_at(query(2), t0 + Duration::from_secs(5));
        assert_eq!(p.waiting(), 3, "a query asked again is not queued twice");
        let at = |s: f64| t0 + Duration::from_secs_f64(s);
        assert!(p.due_at(&mut outbox, at(11.9)).unwrap().is_empty());
        let first = p.due_at(&mut outbox, at(12.0)).unwrap();
        assert_eq!(first.iter().map(|a| a.query).collect::<Vec<_>>(), [1]);
        assert_eq!(first[0].took_ms, 12_000);
        assert!(p.due_at(&mut outbox, at(23.9)).unwrap().is_empty());
        // Late to look: both that are done by then come together, in order.
        let rest = p.due_at(&mut outbox, at(40.0)).unwrap();
        assert_eq!(rest.iter().map(|a| a.query).collect::<Vec<_>>(), [2, 3]);
        assert_eq!(
            outbox.unacknowledged(),
            3,
            "each answer kept before it goes"
        );
        // Idle, a query that comes later starts when it comes, not when the last ended.
        p.receive_at(query(4), at(100.0));
        assert!(p.due_at(&mut outbox, at(111.0)).unwrap().is_empty());
        assert_eq!(p.due_at(&mut outbox, at(112.0)).unwrap().len(), 1);
    }

    #[test]
    fn watching_adds_each_sides_clip_and_a_stale_query_is_passed_over() {
        let pace = PaceConfig {
            answer_watch: true,
            ..PaceConfig::fixed(2.0)
        };
        let (mut p, mut outbox) = paced(pace);
        // Two sides of 100 steps, each judged on its last 50 after 10 of lead-in: 6 s each.
        let mut q = query(1);
        for s in [&mut q.first, &mut q.second] {
            s.truth = vec![s.truth[0]; 100];
            s.actions = vec![0.0; 100];
            s.start = 50;
            s.len = 50;
        }
        assert_eq!(watch_s(&q.first), 6.0);
        let t0 = Instant::now();
        let mut stale = query(2);
        stale.withdraw_at_steps = 100;
        p.receive_at(q, t0);
        p.receive_at(stale, t0);
        p.receive_at(query(3), t0);
        p.learner_status(LearnerStatus {
            env_steps: 500,
            ..LearnerStatus::default()
        });
        let at = |s: f64| t0 + Duration::from_secs_f64(s);
        assert!(p.due_at(&mut outbox, at(13.9)).unwrap().is_empty());
        assert_eq!(p.due_at(&mut outbox, at(14.0)).unwrap().len(), 1);
        let next = p
            .due_at(&mut outbox, at(14.0 + 2.0 + 2.0 * watch_s(&query(3).first)))
            .unwrap();
        assert_eq!(next.iter().map(|a| a.query).collect::<Vec<_>>(), [3]);
        assert_eq!(p.waiting(), 0);
    }

    #[test]
    fn a_spread_keeps_the_mean_and_bad_settings_name_their_field() {
        let pace = PaceConfig {
            answer_spread: 0.5,
            ..PaceConfig::fixed(12.0)
        };
        let (mut p, _) = paced(pace);
        let q = query(1);
        let n = 4000;
        let mean = (0..n).map(|_| p.time(&q).as_secs_f64()).sum::<f64>() / n as f64;
        assert!((mean - 12.0).abs() < 0.5, "mean {mean}");
        let err = |c: PaceConfig| c.validate().unwrap_err().to_string();
        assert!(err(PaceConfig::fixed(-1.0)).contains("answer_s is -1"));
        assert!(err(PaceConfig {
            answer_spread: 0.5,
            ..PaceConfig::default()
        })
        .contains("answer_spread is 0.5"));
        assert!(!PaceConfig::default().paced());
    }
}
