//! The messages that cross Zenoh: one envelope (format version, run id) around one body,
//! serde + bincode. A receiver decodes with [`decode`], which refuses anything that does not
//! decode, comes from another format or run, has the wrong dimensions or holds a
//! non-finite number; the caller drops it with a warning and counts it.

mod check;
#[cfg(test)]
mod tests;

use serde::{Deserialize, Serialize};

use crate::trajectory::{Outcome, Replay, Trajectory, TrajectoryError};

/// Version of the wire format; bumped whenever a message changes (10: a query may show
/// more than two attempts to rank and an answer may rank them; the learner's status says
/// when it stopped to wait for answers).
pub const WIRE_FORMAT: u16 = 10;

/// The largest message a receiver decodes (the paper preset's weights are about 1.1 MB, a
/// feeding trajectory about 65 KB); anything larger is dropped and counted unread.
pub const MAX_MESSAGE_BYTES: usize = 16 << 20;

/// One named tensor of a network, row-major f32.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Tensor {
    pub name: String,
    pub shape: Vec<usize>,
    pub data: Vec<f32>,
}

/// Policy weights as the learner publishes them, with the observation normaliser they
/// were trained with, so that actors normalise exactly as the learner did.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Weights {
    /// Counts up over the whole run, across restarts.
    pub version: u64,
    /// Env steps the learner had consumed when it made these weights.
    pub env_steps: u64,
    pub obs_dim: u32,
    pub act_dim: u32,
    /// The policy's tensors.
    pub tensors: Vec<Tensor>,
    /// Observation normaliser: running mean and variance, and the clip applied after.
    pub obs_mean: Vec<f32>,
    pub obs_var: Vec<f32>,
    pub obs_clip: f32,
    /// Act uniformly at random instead (SAC's first steps).
    pub random_actions: bool,
    /// The learner's flow control (credit): each actor may have at most this many
    /// trajectories unacknowledged (0: no limit); acknowledgements come with each version.
    /// Actors never run far ahead of training, and what waits for the learner is bounded.
    pub episodes_per_actor: u32,
    /// Trajectories the learner holds, per actor: an actor forgets the ones acknowledged
    /// and sends the others again if it waits too long for the next version.
    pub acks: Vec<Ack>,
}

/// The learner holds every trajectory of actor `actor`'s `incarnation` below `next_seq`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Ack {
    pub actor: u32,
    pub incarnation: u64,
    pub next_seq: u64,
}

/// A trajectory from an actor, tagged with the policy version that acted.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TrajectoryMsg {
    pub actor: u32,
    /// Drawn at random when the actor starts: sequence numbers restart with it.
    pub incarnation: u64,
    /// This actor's training trajectories, numbered from 0 (a trajectory sent again keeps
    /// its number, so the learner takes it once).
    pub seq: u64,
    /// The oldest number the actor still holds for the learner: it will not send any
    /// below again (acknowledged, perhaps to a learner since restarted from a checkpoint).
    pub oldest: u64,
    pub trajectory: Trajectory,
}

/// A request to one actor for deterministic evaluation episodes (the policy's mean action)
/// of the weights it carries, so the evaluation is of exactly that snapshot.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct EvalRequest {
    /// Names the evaluation (the learner uses the env steps it was asked at).
    pub id: u64,
    /// The actor asked to run it.
    pub actor: u32,
    pub weights: Weights,
    /// Episode seeds (the same at every evaluation of a run, so rows are comparable).
    pub seeds: Vec<u64>,
    /// Also run every seed with sampled actions (the policy as it trains).
    pub sampled: bool,
    /// Also send each mean-action episode's steps ([`EvalSteps`]): a learner with a learnt
    /// reward compares it with the ground truth on them.
    pub steps: bool,
}

/// One evaluation episode's steps: what a learnt reward reads and the ground truth.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct EvalSteps {
    /// One observation per step (the one the action was taken in), flattened.
    pub obs: Vec<f32>,
    /// One action per step, flattened.
    pub actions: Vec<f32>,
    /// The ground-truth reward r of each step.
    pub truth: Vec<f32>,
    /// Its two parts the learnt reward is judged against: the person's preference reward
    /// r_H and the task reward r_task of each step.
    pub human: Vec<f32>,
    pub task: Vec<f32>,
    /// Each step's comfort features ([`crate::trajectory::StepRewards::features`]), rows
    /// of [`crate::trajectory::FEATURES`] (empty: none).
    pub features: Vec<f32>,
}

/// The outcome of each evaluation episode, in the order of the request's seeds.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct EvalResult {
    pub id: u64,
    pub actor: u32,
    /// The weights version that acted.
    pub version: u64,
    /// With the mean action.
    pub episodes: Vec<Outcome>,
    /// With sampled actions, the same seeds (empty unless asked for).
    pub sampled: Vec<Outcome>,
    /// The steps of each mean-action episode (empty unless asked for).
    pub steps: Vec<EvalSteps>,
}

/// The learner's word that the run is over: actors stop.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Stop {
    /// Env steps the run reached.
    pub env_steps: u64,
    /// The last weights version published.
    pub version: u64,
}

/// One trajectory of a query, with what a teacher needs to judge it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Shown {
    /// The label store's id of the trajectory.
    pub id: u64,
    /// Seed of the episode's reset (with the actions and the world config, the world
    /// replays the episode exactly).
    pub seed: u64,
    /// Version of the policy that acted.
    pub policy_version: u64,
    /// The actions, `steps` rows of `act_dim`, as the policy gave them.
    pub act_dim: u32,
    pub actions: Vec<f32>,
    /// Per-step ground-truth reward r, for scripted teachers only (the learner never
    /// trains on it; a person judges the replay instead).
    pub truth: Vec<f32>,
    /// What a person needs to watch the episode (absent for tasks with nothing to draw,
    /// or when the learner is not asked to send it).
    pub replay: Option<Replay>,
    /// The segment judged: steps `start .. start + len` of the trajectory (the whole
    /// trajectory is `0, steps`). The actions and the truth are the whole trajectory's,
    /// so that the episode replays from its seed up to the segment.
    pub start: u32,
    pub len: u32,
}

impl Shown {
    /// Env steps of the trajectory.
    pub fn steps(&self) -> usize {
        self.truth.len()
    }

    /// The steps judged (`start .. start + len`, clamped to the trajectory).
    pub fn segment(&self) -> std::ops::Range<usize> {
        let start = (self.start as usize).min(self.steps());
        start..(start + self.len as usize).min(self.steps())
    }

    /// The ground-truth reward of the segment's steps.
    pub fn segment_truth(&self) -> &[f32] {
        &self.truth[self.segment()]
    }
}

/// "Which of these two attempts was better?" (or, with more attempts, "rank these"), asked by
/// the learner of any teacher.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Query {
    /// The label store's id of the query: unique over the run, across restarts.
    pub id: u64,
    /// The feedback session that asked it (1, 2, ...).
    pub session: u64,
    /// Unix time in milliseconds when it was first asked.
    pub asked_at_ms: u64,
    /// Unix time in milliseconds after which the learner no longer waits for an answer
    /// (0: never); a teacher takes it off its queue then.
    pub expires_at_ms: u64,
    pub first: Shown,
    pub second: Shown,
    /// R_avg of the scripted teachers' thresholds: the mean ground-truth return of the
    /// newest 100 training episodes when the session was asked (whole episodes; a teacher
    /// scales it to the segment's length), fixed for the session as in the authors' code.
    /// None where the learner had no episodes (a teacher then keeps its own window).
    pub r_avg: Option<f32>,
    /// The learner's env steps at which an unanswered query grows stale and is withdrawn
    /// (0: never): a teacher offers it to nobody new once the learner's status reaches
    /// them, and a person who is judging it may still answer (the answer is stored as
    /// late).
    pub withdraw_at_steps: u64,
    /// The attempts after the first two, for a ranking of `2 + more.len()` (empty: a pair).
    /// Last, so that a query an older build stored reads as its layout.
    pub more: Vec<Shown>,
}

/// The most attempts a query shows (a ranking of four).
pub const MAX_ATTEMPTS: usize = 4;

impl Query {
    /// Every attempt shown, in order: first, second, then `more`.
    pub fn attempts(&self) -> impl Iterator<Item = &Shown> {
        [&self.first, &self.second].into_iter().chain(&self.more)
    }

    /// Attempts shown: 2 for a pair, 3 or 4 for a ranking.
    pub fn len(&self) -> usize {
        2 + self.more.len()
    }

    /// Never: a query shows at least two attempts.
    pub fn is_empty(&self) -> bool {
        false
    }

    /// Expired at `now_ms` (Unix milliseconds): the learner no longer waits for it.
    pub fn expired_at(&self, now_ms: u64) -> bool {
        self.expires_at_ms != 0 && self.expires_at_ms <= now_ms
    }

    /// Withdrawn as stale at `env_steps` of the learner.
    pub fn stale_at(&self, env_steps: u64) -> bool {
        self.withdraw_at_steps != 0 && env_steps >= self.withdraw_at_steps
    }
}

/// A teacher's judgement of a query.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum Preference {
    /// The first trajectory was better.
    First,
    /// The second trajectory was better.
    Second,
    /// Both were as good (the soft target (0.5, 0.5)).
    Equal,
    /// The teacher cannot tell (not stored in D, but counted against the budget).
    Skip,
}

impl Preference {
    /// The name used in the label store and on the command line.
    pub fn name(self) -> &'static str {
        match self {
            Preference::First => "first",
            Preference::Second => "second",
            Preference::Equal => "equal",
            Preference::Skip => "skip",
        }
    }

    /// The inverse of [`Preference::name`].
    pub fn parse(s: &str) -> Option<Self> {
        [
            Preference::First,
            Preference::Second,
            Preference::Equal,
            Preference::Skip,
        ]
        .into_iter()
        .find(|p| p.name() == s)
    }
}

/// A teacher's answer to one query.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Answer {
    /// The query answered.
    pub query: u64,
    pub preference: Preference,
    /// The kind of teacher (`oracle`, `noisy`, ..., `human`).
    pub teacher: String,
    /// This teacher's id (1-64 characters of a-z, 0-9, '-' and '_'): where the
    /// acknowledgement goes.
    pub teacher_id: String,
    /// How long the teacher took, in milliseconds (a person's time).
    pub took_ms: u64,
    /// Who answered, for a person (empty for a scripted teacher): 1-40 characters of
    /// letters, digits, space, `_`, `.` and `-`.
    pub labeller: String,
    /// How often the person played each attempt through (first, second).
    pub replays: [u32; 2],
    /// The oracle's answer on the ground truth (`--shadow oracle`): recorded, never shown
    /// and never trained on.
    pub shadow: Option<Preference>,
    /// A query asked again to measure consistency and agreement: stored apart from D.
    pub repeat: bool,
    /// A ranking's places, one per attempt in the query's order: 0 for the best, and the
    /// same place for attempts as good as each other (empty: a pair's answer, which
    /// `preference` says). A ranking's `preference` is the order of its first two
    /// attempts, or Skip where the teacher could not rank them.
    pub ranks: Vec<u8>,
}

impl Answer {
    /// A scripted teacher's answer (no labeller, no replays, no shadow, not a repeat).
    pub fn scripted(
        query: u64,
        preference: Preference,
        teacher: &str,
        teacher_id: &str,
        took_ms: u64,
    ) -> Self {
        Self {
            query,
            preference,
            teacher: teacher.into(),
            teacher_id: teacher_id.into(),
            took_ms,
            labeller: String::new(),
            replays: [0, 0],
            shadow: None,
            repeat: false,
            ranks: Vec::new(),
        }
    }

    /// A scripted teacher's ranking of a query's attempts by `ranks` (places, 0 best).
    pub fn ranked(
        query: u64,
        ranks: Vec<u8>,
        teacher: &str,
        teacher_id: &str,
        took_ms: u64,
    ) -> Self {
        Self {
            ranks: ranks.clone(),
            ..Self::scripted(
                query,
                Preference::of_places(ranks[0], ranks[1]),
                teacher,
                teacher_id,
                took_ms,
            )
        }
    }
}

impl Preference {
    /// First, Second or Equal by two attempts' places in a ranking (0 best).
    pub fn of_places(first: u8, second: u8) -> Self {
        match first.cmp(&second) {
            std::cmp::Ordering::Less => Preference::First,
            std::cmp::Ordering::Greater => Preference::Second,
            std::cmp::Ordering::Equal => Preference::Equal,
        }
    }
}

/// Unix time in milliseconds: the clock of [`Query::expires_at_ms`] and of every time a
/// label's record keeps.
pub fn now_ms() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_millis() as u64)
}

/// Check a labeller's name.
pub fn check_labeller(field: &str, name: &str) -> Result<(), WireError> {
    let ok = name.chars().count() <= 40
        && name
            .chars()
            .all(|c| c.is_alphanumeric() || matches!(c, ' ' | '_' | '.' | '-'));
    if ok {
        Ok(())
    } else {
        Err(WireError::Invalid {
            field: field.to_string(),
            value: name.chars().take(80).collect(),
            reason: "must be at most 40 characters of letters, digits, space, '_', '.' and '-'",
        })
    }
}

/// The learner's word that it stored these answers of teacher `teacher_id` (committed to
/// the label store): the teacher may forget them.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct AnswerAck {
    pub teacher_id: String,
    pub queries: Vec<u64>,
    /// Repeated queries' answers stored (by query and labeller).
    pub repeats: Vec<(u64, String)>,
}

/// The learner's state, published every second for teachers and people: what a labelling
/// page shows and how a teacher knows that training runs.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct LearnerStatus {
    /// Env steps so far.
    pub env_steps: u64,
    /// Queries asked, answered (first, second, equal or skip), and open now.
    pub asked: u64,
    pub answered: u64,
    pub open: u64,
    /// Queries the budget still allows.
    pub budget_left: u64,
    /// A feedback session is due and waits for open queries to be answered.
    pub waiting: bool,
    /// The learner has stopped (no training, the robot idle) until the answers it keeps
    /// time with are in and trained on (`--label-slack-steps`, `--label-slack-s`).
    pub held: bool,
    /// People labelling now (by the teachers' liveliness tokens).
    pub labellers: u32,
    /// The share of the newest answers (`agreement_of` of them, up to 20) that the learnt
    /// reward already agreed with before it trained on them (None before it is trained):
    /// near 1, more answers of the same kind teach it little.
    pub agreement: Option<f32>,
    pub agreement_of: u32,
}

/// Everything that travels.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum Body {
    Weights(Weights),
    Trajectory(Box<TrajectoryMsg>),
    EvalRequest(Box<EvalRequest>),
    EvalResult(EvalResult),
    Stop(Stop),
    Query(Box<Query>),
    Answer(Answer),
    AnswerAck(AnswerAck),
    Status(LearnerStatus),
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
struct Envelope {
    format: u16,
    run: String,
    body: Body,
}

/// Why a message was refused.
#[derive(Debug, thiserror::Error)]
pub enum WireError {
    #[error("message of {bytes} bytes, more than the {MAX_MESSAGE_BYTES} any pbrl message needs")]
    TooLarge { bytes: usize },
    #[error("message does not decode: {0}")]
    Decode(String),
    #[error("message format {found}, this build speaks {expected}")]
    Format { found: u16, expected: u16 },
    #[error("message for run {found:?}, this process is in run {expected:?}")]
    Run { found: String, expected: String },
    #[error("field {field} has {found} numbers, expected {expected}")]
    Shape {
        field: String,
        found: usize,
        expected: usize,
    },
    #[error("field {field} holds a non-finite value")]
    NonFinite { field: String },
    #[error("field {field} is {value:?}: {reason}")]
    Invalid {
        field: String,
        value: String,
        reason: &'static str,
    },
    #[error(transparent)]
    Trajectory(#[from] TrajectoryError),
}

/// Check a teacher id as it appears in key expressions.
pub fn check_teacher_id(field: &str, id: &str) -> Result<(), WireError> {
    crate::keys::Keys::new(id)
        .map(|_| ())
        .map_err(|e| WireError::Invalid {
            field: field.to_string(),
            value: id.chars().take(80).collect(),
            reason: e.reason,
        })
}

/// Encode `body` for run `run`.
pub fn encode(run: &str, body: &Body) -> Vec<u8> {
    let env = EnvelopeRef {
        format: WIRE_FORMAT,
        run,
        body,
    };
    // NOTE: encoding plain data into a Vec cannot fail.
    bincode::serde::encode_to_vec(&env, bincode::config::standard())
        .expect("encoding a message into memory cannot fail")
}

#[derive(Serialize)]
struct EnvelopeRef<'a> {
    format: u16,
    run: &'a str,
    body: &'a Body,
}

/// Decode a message for run `run` and check it.
pub fn decode(run: &str, bytes: &[u8]) -> Result<Body, WireError> {
    decode_formats(run, bytes, &[WIRE_FORMAT])
}

/// [`decode`], accepting the envelope formats `formats` (older formats whose body of the
/// kind expected is laid out as this build's).
fn decode_formats(run: &str, bytes: &[u8], formats: &[u16]) -> Result<Body, WireError> {
    if bytes.len() > MAX_MESSAGE_BYTES {
        return Err(WireError::TooLarge { bytes: bytes.len() });
    }
    let (env, _): (Envelope, usize) =
        bincode::serde::decode_from_slice(bytes, bincode::config::standard())
            .map_err(|e| WireError::Decode(e.to_string()))?;
    if !formats.contains(&env.format) {
        return Err(WireError::Format {
            found: env.format,
            expected: WIRE_FORMAT,
        });
    }
    if env.run != run {
        return Err(WireError::Run {
            found: env.run,
            expected: run.to_string(),
        });
    }
    check::body(&env.body)?;
    Ok(env.body)
}

/// A query as a label store keeps it (the encoded message of an open query): this build's
/// format; format 9's (pairs only), read as a pair; format 7's or 8's (before the withdrawal step; format 8 changed only the
/// evaluation steps), read as never withdrawn; or format 6's (before segments), read as
/// whole-trajectory segments with no R_avg, so that a store of an older build still asks
/// its open queries.
pub fn decode_stored_query(run: &str, bytes: &[u8]) -> Result<Query, WireError> {
    // NOTE: the envelope starts with its format; an older body does not decode as this
    // build's, so the format is read first.
    let format = bincode::serde::decode_from_slice::<u16, _>(bytes, bincode::config::standard())
        .map(|(f, _)| f)
        .ok();
    let old = match format {
        Some(6) => old_query::<v6::Query>(run, bytes, 6)?.upgrade(),
        Some(f @ (7 | 8)) => old_query::<v8::Query>(run, bytes, f)?.upgrade(),
        Some(9) => old_query::<v9::Query>(run, bytes, 9)?.upgrade(),
        _ => {
            return match decode(run, bytes)? {
                Body::Query(q) => Ok(*q),
                _ => Err(WireError::Decode("the message is not a query".into())),
            }
        }
    };
    // Validated as this build validates a query it receives.
    match decode(run, &encode(run, &Body::Query(Box::new(old))))? {
        Body::Query(q) => Ok(*q),
        _ => unreachable!("a query encodes and decodes as a query"),
    }
}

/// The query of an envelope of an older `format` for `run`, in that format's layout `Q`.
fn old_query<Q: serde::de::DeserializeOwned>(
    run: &str,
    bytes: &[u8],
    format: u16,
) -> Result<Q, WireError> {
    if bytes.len() > MAX_MESSAGE_BYTES {
        return Err(WireError::TooLarge { bytes: bytes.len() });
    }
    let ((found, found_run, variant, q), _): ((u16, String, u32, Q), usize) =
        bincode::serde::decode_from_slice(bytes, bincode::config::standard())
            .map_err(|e| WireError::Decode(e.to_string()))?;
    // NOTE: formats 6 to 9 listed Query sixth in Body (index 5), as this one does.
    if found != format || variant != 5 {
        return Err(WireError::Decode(format!(
            "a format-{found} message of body {variant} is not a query"
        )));
    }
    if found_run != run {
        return Err(WireError::Run {
            found: found_run,
            expected: run.to_string(),
        });
    }
    Ok(q)
}

/// Format 9's query (pairs only), to read open queries that a store of an older build
/// holds.
pub mod v9 {
    use super::*;

    #[derive(Clone, Debug, Serialize, Deserialize)]
    pub struct Query {
        pub id: u64,
        pub session: u64,
        pub asked_at_ms: u64,
        pub expires_at_ms: u64,
        pub first: super::Shown,
        pub second: super::Shown,
        pub r_avg: Option<f32>,
        pub withdraw_at_steps: u64,
    }

    /// Format 9's answer (before rankings), as a teacher's file keeps it.
    #[derive(Clone, Debug, Serialize, Deserialize)]
    pub struct Answer {
        pub query: u64,
        pub preference: Preference,
        pub teacher: String,
        pub teacher_id: String,
        pub took_ms: u64,
        pub labeller: String,
        pub replays: [u32; 2],
        pub shadow: Option<Preference>,
        pub repeat: bool,
    }

    impl Answer {
        /// This build's answer: a pair's.
        pub fn upgrade(self) -> super::Answer {
            super::Answer {
                query: self.query,
                preference: self.preference,
                teacher: self.teacher,
                teacher_id: self.teacher_id,
                took_ms: self.took_ms,
                labeller: self.labeller,
                replays: self.replays,
                shadow: self.shadow,
                repeat: self.repeat,
                ranks: Vec::new(),
            }
        }
    }

    impl Query {
        /// This build's query: a pair.
        pub fn upgrade(self) -> super::Query {
            super::Query {
                id: self.id,
                session: self.session,
                asked_at_ms: self.asked_at_ms,
                expires_at_ms: self.expires_at_ms,
                first: self.first,
                second: self.second,
                r_avg: self.r_avg,
                withdraw_at_steps: self.withdraw_at_steps,
                more: Vec::new(),
            }
        }
    }
}

/// Formats 7's and 8's query (before the withdrawal step), to read open queries that a
/// store of an older build holds.
pub mod v8 {
    use super::*;

    #[derive(Clone, Debug, Serialize, Deserialize)]
    pub struct Query {
        pub id: u64,
        pub session: u64,
        pub asked_at_ms: u64,
        pub expires_at_ms: u64,
        pub first: super::Shown,
        pub second: super::Shown,
        pub r_avg: Option<f32>,
    }

    impl Query {
        /// This build's query: never withdrawn (a pair).
        pub fn upgrade(self) -> super::Query {
            super::v9::Query {
                id: self.id,
                session: self.session,
                asked_at_ms: self.asked_at_ms,
                expires_at_ms: self.expires_at_ms,
                first: self.first,
                second: self.second,
                r_avg: self.r_avg,
                withdraw_at_steps: 0,
            }
            .upgrade()
        }
    }
}

/// Format 6's query (before segments and the session's R_avg), to read open queries that
/// a label store of an older build holds.
mod v6 {
    use super::*;

    #[derive(Deserialize)]
    pub struct Shown {
        id: u64,
        seed: u64,
        policy_version: u64,
        act_dim: u32,
        actions: Vec<f32>,
        truth: Vec<f32>,
        replay: Option<Replay>,
    }

    #[derive(Deserialize)]
    pub struct Query {
        id: u64,
        session: u64,
        asked_at_ms: u64,
        expires_at_ms: u64,
        first: Shown,
        second: Shown,
    }

    impl Shown {
        fn upgrade(self) -> super::Shown {
            let len = self.truth.len() as u32;
            super::Shown {
                id: self.id,
                seed: self.seed,
                policy_version: self.policy_version,
                act_dim: self.act_dim,
                actions: self.actions,
                truth: self.truth,
                replay: self.replay,
                start: 0,
                len,
            }
        }
    }

    impl Query {
        pub fn upgrade(self) -> super::Query {
            super::v8::Query {
                id: self.id,
                session: self.session,
                asked_at_ms: self.asked_at_ms,
                expires_at_ms: self.expires_at_ms,
                first: self.first.upgrade(),
                second: self.second.upgrade(),
                r_avg: None,
            }
            .upgrade()
        }
    }
}

impl Weights {
    /// Check lengths against shapes and dimensions, and finiteness.
    pub fn validate(&self) -> Result<(), WireError> {
        let shape = |field: &str, found: usize, expected: usize| {
            if found == expected {
                Ok(())
            } else {
                Err(WireError::Shape {
                    field: field.to_string(),
                    found,
                    expected,
                })
            }
        };
        let finite = |field: &str, xs: &[f32]| {
            if xs.iter().all(|x| x.is_finite()) {
                Ok(())
            } else {
                Err(WireError::NonFinite {
                    field: field.to_string(),
                })
            }
        };
        shape("obs_mean", self.obs_mean.len(), self.obs_dim as usize)?;
        shape("obs_var", self.obs_var.len(), self.obs_dim as usize)?;
        finite("obs_mean", &self.obs_mean)?;
        finite("obs_var", &self.obs_var)?;
        finite("obs_clip", &[self.obs_clip])?;
        for t in &self.tensors {
            shape(&t.name, t.data.len(), t.shape.iter().product())?;
            finite(&t.name, &t.data)?;
        }
        Ok(())
    }
}
