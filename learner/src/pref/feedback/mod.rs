//! Algorithm 1's bookkeeping, with no Zenoh inside: the annotation buffer, when a feedback
//! session is due, choosing its queries, the queries in flight, storing answers in the
//! label store (committed before they are acknowledged), the preference dataset D, the
//! budget, and training the reward ensemble.
//!
//! The learner never waits for a teacher: queries go out, training goes on with the reward
//! model it has, and answers are used at the next training of the ensemble, which starts
//! once the session's queries are all answered (or the next session is due). Choosing
//! queries (the ensemble's predictions on every candidate pair) and training run on a
//! thread of their own at a lower priority ([`Feedback::job`]), one at a time, so
//! trajectories keep flowing and the policy's updates keep their CPU; the deterministic
//! mode runs both in place instead.
//!
//! The label store is the truth about labels: query and trajectory ids come from it (never
//! reused across restarts), D is rebuilt from it on resume, and the queries open in it
//! are asked again.

mod choose;
mod open;
mod schedule;
#[cfg(test)]
mod tests;
mod train;

use std::collections::{BTreeMap, HashMap};
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{Context, Result};
use pbrl_common::wire::{self, AnswerAck, TrajectoryMsg};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use crate::pref::config::PrefConfig;
use crate::pref::labels::LabelStore;
use crate::pref::query::{AnnotationBuffer, Candidate, Sampler};
use crate::pref::reward_model::{Labelled, RewardModel, RewardModelState, Segment, TrainStats};
use crate::state::RngState;
pub use choose::Side;
pub(crate) use open::labelled;
use open::{AskedAt, InFlight};
pub use open::{Outgoing, AGREEMENT_WINDOW};

/// Counters of the feedback loop (saved with each checkpoint).
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct Counters {
    /// Feedback sessions held.
    pub sessions: u64,
    /// Env steps at which the next session is due.
    pub next_session_at: u64,
    /// Labels of D the ensemble was last trained on (D's first `trained_labels`).
    pub trained_labels: usize,
    /// Trainings of the ensemble.
    pub trainings: u64,
    /// The ensemble's accuracy on D after its last training, and on the labels new to
    /// that training before it (NaN before any).
    pub accuracy: f64,
    pub accuracy_new: f64,
    /// Answers dropped: to a query this learner never asked, or repeated.
    pub unknown_answers: u64,
    pub repeated_answers: u64,
    /// Queries asked again (unanswered for `query_retry_s`).
    pub retried_queries: u64,
    /// Queries withdrawn as stale (`query_stale_steps`). Not in a checkpoint's layout:
    /// counted since the learner started.
    #[serde(skip)]
    pub withdrawn_queries: u64,
}

/// What a checkpoint keeps of the feedback loop (D and the open queries live in the label
/// store; the ensemble's networks are saved beside the backbone's).
#[derive(Clone, Serialize, Deserialize)]
pub struct FeedbackState {
    pub counters: Counters,
    pub rng: RngState,
    pub buffer: AnnotationBuffer,
    pub model: RewardModelState,
    /// The state-entropy bonus (while pretraining).
    pub entropy: Option<crate::pref::entropy::StateEntropy>,
}

/// A background job: choosing queries or training the ensemble.
type Job = Box<dyn FnOnce() -> Result<JobDone> + Send>;

/// What a background job hands back.
pub enum JobDone {
    /// The pairs (or sets to rank) chosen for session `session`, and the session's R_avg;
    /// `quota` is what the session (or, `top_up`, what it still owed) asked for.
    Chosen {
        session: u64,
        env_steps: u64,
        sampler: Sampler,
        sets: Vec<Vec<Side>>,
        r_avg: Option<f32>,
        quota: u64,
        top_up: bool,
    },
    /// A trained ensemble, its statistics, and its accuracy on the new labels before.
    Trained {
        model: Box<RewardModel>,
        stats: TrainStats,
        labels: usize,
        accuracy_new: f64,
        /// The job's wall time.
        took: Duration,
    },
}

/// What an answer did.
pub enum Answered {
    /// Stored (or stored before): acknowledge it.
    Ack(AnswerAck),
    /// Not for this learner: dropped with a warning and counted.
    Dropped,
}

pub struct Feedback {
    cfg: PrefConfig,
    run: String,
    buffer: AnnotationBuffer,
    store: LabelStore,
    /// D, in the order the answers were stored.
    data: Vec<Labelled>,
    segments: HashMap<u64, Arc<Segment>>,
    /// The newest trained ensemble (untrained until the first session's answers).
    model: Arc<RewardModel>,
    in_flight: BTreeMap<u64, InFlight>,
    job: Option<tokio::sync::oneshot::Receiver<Result<JobDone>>>,
    rng: ChaCha8Rng,
    pub counters: Counters,
    /// The budget was found spent ([`Feedback::frozen`]).
    frozen: std::cell::Cell<bool>,
    /// People at a labelling page now (their liveliness tokens), for the bound of open
    /// queries per person.
    labellers: u32,
    /// Queries of the current session not asked yet for want of room, or to replace a
    /// withdrawn one: asked as room appears (not saved: a restart's next session asks
    /// its own).
    owed: u64,
    /// Trajectories observed, and how many there were when a top-up found no pair the
    /// bound per trajectory allowed (none is tried again before a new one comes).
    observed: u64,
    top_up_stuck_at: Option<u64>,
    /// When the oldest answer D holds that the ensemble is not trained on yet was asked
    /// (to keep time with the teacher, [`Feedback::holds`]).
    untrained_from: Option<AskedAt>,
    /// For the newest answers, the share of each one's pairs the ensemble ordered as the
    /// teacher did before it trained on them (not saved: a restart counts afresh).
    agreement: std::collections::VecDeque<f64>,
}

impl Feedback {
    /// Open the label store at `labels` (`:memory:` for none) and start the loop: the first
    /// session comes at the end of the unsupervised pretraining.
    pub fn new(
        cfg: &PrefConfig,
        run: &str,
        obs_dim: usize,
        act_dim: usize,
        seed: u64,
        labels: &std::path::Path,
    ) -> Result<Self> {
        let store = LabelStore::open(labels, run)?;
        let mut model_cfg = cfg.model.clone();
        model_cfg.seed = seed;
        let mut model = RewardModel::new(model_cfg, obs_dim, act_dim)?;
        if let Some(path) = &cfg.prior {
            let prior = crate::pref::prior::load(path)?;
            model.start_from(&prior, path)?;
            tracing::info!(
                prior = %path.display(),
                people = prior.meta.people.len(),
                labels = prior.meta.labels,
                "the reward ensemble starts from a prior"
            );
        }
        let mut f = Self {
            cfg: cfg.clone(),
            run: run.into(),
            buffer: AnnotationBuffer::new(cfg.annotation_capacity),
            store,
            data: Vec::new(),
            segments: HashMap::new(),
            model: Arc::new(model),
            in_flight: BTreeMap::new(),
            job: None,
            frozen: std::cell::Cell::new(false),
            labellers: 0,
            owed: 0,
            observed: 0,
            top_up_stuck_at: None,
            untrained_from: None,
            agreement: std::collections::VecDeque::new(),
            // NOTE: its own stream of the run's seed, apart from the backbone's.
            rng: ChaCha8Rng::seed_from_u64(seed ^ 0x5eed_f00d_0000_0001),
            counters: Counters {
                next_session_at: cfg.unsup_steps,
                accuracy: f64::NAN,
                accuracy_new: f64::NAN,
                ..Counters::default()
            },
        };
        // A store that holds labels (a run started over without a checkpoint keeps them;
        // `--fresh` moves the store aside) is read in, and its sessions count.
        f.reload()?;
        f.catch_up()?;
        Ok(f)
    }

    /// Read D and the open queries from the label store.
    fn reload(&mut self) -> Result<()> {
        self.data.clear();
        for row in self.store.labels_since(0)? {
            let labels = self.labelled(&row.attempts(), row.preference, &row.ranks)?;
            self.data.extend(labels);
        }
        self.in_flight.clear();
        for (id, _, bytes) in self.store.open_queries()? {
            match wire::decode_stored_query(&self.run, &bytes) {
                Ok(q) => {
                    let keys = q
                        .attempts()
                        .map(|s| self.store.trajectory_key(s.id))
                        .collect::<Result<Vec<_>>>()?;
                    self.in_flight.insert(
                        id,
                        InFlight {
                            query: Outgoing::encode(&self.run, q),
                            // NOTE: asked again at once after a restart.
                            sent: Instant::now() - Duration::from_secs(self.cfg.query_retry_s),
                            keys,
                            // NOTE: counted from the last session (and from now in
                            // seconds): a restart does not keep the wall clock.
                            asked: (self.last_session_at(), Instant::now()),
                        },
                    );
                }
                Err(e) => anyhow::bail!(
                    "open query {id} in {} does not decode as a query: {e}",
                    self.store.path().display(),
                ),
            }
        }
        if !self.data.is_empty() || !self.in_flight.is_empty() {
            tracing::info!(
                labels = self.data.len(),
                open = self.in_flight.len(),
                "label store read"
            );
        }
        Ok(())
    }

    /// Keep a trajectory for queries.
    pub fn observe(&mut self, msg: &TrajectoryMsg) {
        self.buffer.push(Candidate::from_msg(msg));
        self.observed += 1;
    }

    /// People at a labelling page now.
    pub fn set_labellers(&mut self, n: u32) {
        self.labellers = n;
    }

    /// The reward ensemble, once it is the reward: trained on answers, or a prior from the
    /// first session on (before it, the pretraining's bonus is).
    pub fn model(&self) -> Option<Arc<RewardModel>> {
        let installed = self.counters.trainings > 0 || self.counters.sessions > 0;
        (self.model.trained() && installed).then(|| self.model.clone())
    }

    /// The budget is spent: the ensemble is frozen. (Asked queries never leave the store,
    /// so once true it stays true, and the store is not counted again.)
    pub fn frozen(&self) -> Result<bool> {
        if !self.frozen.get() {
            self.frozen
                .set(self.store.counts()?.spent() >= self.cfg.max_feedback);
        }
        Ok(self.frozen.get())
    }

    /// Whether a background job is running.
    pub fn busy(&self) -> bool {
        self.job.is_some()
    }

    /// Open queries.
    pub fn open(&self) -> usize {
        self.in_flight.len()
    }

    /// The label store's counts.
    pub fn counts(&self) -> Result<crate::pref::labels::Counts> {
        self.store.counts()
    }

    /// Start what is due at `env_steps`, if nothing runs: training on new labels first,
    /// else a session's query selection. In the background unless `inline`; inline, the
    /// work is done here and its result returned.
    pub fn start(&mut self, env_steps: u64, inline: bool) -> Result<Option<JobDone>> {
        if self.job.is_some() {
            return Ok(None);
        }
        let work = if self.training_due(env_steps) {
            self.training()?
        } else if self.session_due(env_steps)? {
            self.choosing(env_steps, false)?
        } else if self.top_up_due()? {
            self.choosing(env_steps, true)?
        } else {
            return Ok(None);
        };
        if inline {
            return Ok(Some(work()?));
        }
        let (tx, rx) = tokio::sync::oneshot::channel();
        std::thread::Builder::new()
            .name("pbrl-feedback".into())
            .spawn(move || {
                train::lower_priority();
                // NOTE: a receiver gone means the learner is shutting down; nothing to tell.
                let _ = tx.send(work());
            })
            .context("starting the feedback job's thread")?;
        self.job = Some(rx);
        Ok(None)
    }

    /// Wait for the background job (cancel-safe; only while [`Feedback::busy`]).
    pub async fn job(&mut self) -> Result<JobDone> {
        let Some(rx) = self.job.as_mut() else {
            return std::future::pending().await;
        };
        let done = rx.await.context("the feedback job died")?;
        self.job = None;
        done
    }

    /// Take a job's result at `now` env steps: a session's queries to send, or a trained
    /// ensemble (returned for the reward; the first one ends the pretraining).
    pub fn finish(
        &mut self,
        done: JobDone,
        now: u64,
    ) -> Result<(Vec<Outgoing>, Option<Arc<RewardModel>>)> {
        match done {
            JobDone::Chosen {
                session,
                env_steps,
                sampler,
                sets,
                r_avg,
                quota,
                top_up,
            } => {
                let queries = self.ask(session, env_steps, sampler, &sets, r_avg)?;
                let asked = queries.len() as u64;
                if top_up {
                    self.owed = self.owed.saturating_sub(asked);
                    self.top_up_stuck_at = (asked == 0).then_some(self.observed);
                    tracing::debug!(
                        session,
                        env_steps,
                        queries = asked,
                        owed = self.owed,
                        "owed queries asked"
                    );
                    return Ok((queries, None));
                }
                self.counters.sessions = session;
                // NOTE: with people, what found no room is asked as room appears (until
                // the next session, whose own quota takes over).
                self.owed = if self.cfg.open_per_labeller > 0 {
                    quota.saturating_sub(asked)
                } else {
                    0
                };
                self.top_up_stuck_at = None;
                // NOTE: a prior is the reward from the first session on, before any answer.
                let prior = (self.cfg.prior.is_some() && self.counters.trainings == 0)
                    .then(|| self.model.clone());
                // NOTE: a session that waited for a training comes late; the next one is
                // an interval after it, not at once.
                while self.counters.next_session_at <= env_steps.max(now) {
                    self.counters.next_session_at += self.cfg.feedback_interval;
                }
                tracing::info!(
                    session,
                    env_steps,
                    queries = asked,
                    owed = self.owed,
                    sampler = ?sampler,
                    "feedback session: queries asked"
                );
                Ok((queries, prior))
            }
            JobDone::Trained {
                model,
                stats,
                labels,
                accuracy_new,
                took,
            } => {
                self.counters.trained_labels = labels;
                if labels >= self.data.len() {
                    self.untrained_from = None;
                }
                self.counters.trainings += 1;
                self.counters.accuracy = stats.accuracy;
                self.counters.accuracy_new = accuracy_new;
                tracing::info!(
                    labels,
                    epochs = stats.epochs,
                    pairs = stats.pairs,
                    accuracy = round3(stats.accuracy),
                    accuracy_on_new = round3(accuracy_new),
                    ms = took.as_millis() as u64,
                    "reward ensemble trained"
                );
                self.model = Arc::from(model);
                Ok((Vec::new(), Some(self.model.clone())))
            }
        }
    }

    /// The ensemble's networks (for checkpoints).
    pub fn networks(&self) -> Vec<(String, &candle_nn::VarMap)> {
        self.model.networks()
    }

    /// The annotation buffer's comfort features, which a checkpoint keeps apart
    /// ([`crate::run::checkpoint::Saved::buffer_features`]).
    pub fn buffer_features(&self) -> Vec<Vec<f32>> {
        self.buffer.features()
    }

    pub fn state(&self) -> Result<FeedbackState> {
        Ok(FeedbackState {
            counters: self.counters.clone(),
            rng: RngState::of(&self.rng),
            buffer: self.buffer.clone(),
            model: self.model.state()?,
            entropy: None,
        })
    }

    /// Continue from a checkpoint's state (the networks are loaded apart, into
    /// [`Feedback::networks`]). Sessions asked after the checkpoint are in the label store:
    /// they count, so the budget is not spent twice.
    pub fn restore(&mut self, s: &FeedbackState) -> Result<()> {
        self.counters = s.counters.clone();
        self.rng = s.rng.restore();
        self.buffer = s.buffer.clone();
        let mut model = self.model.snapshot()?;
        model.restore(&s.model)?;
        if self.cfg.prior.is_some() {
            model.keep_restored_normaliser();
        }
        self.model = Arc::new(model);
        self.catch_up()?;
        self.reload()
    }

    /// Sessions asked after the state this loop started from are in the label store: they
    /// count (the budget is not spent twice, session numbers stay unique).
    fn catch_up(&mut self) -> Result<()> {
        let last = self.store.last_session()?;
        while self.counters.sessions < last {
            self.counters.sessions += 1;
            self.counters.next_session_at += self.cfg.feedback_interval;
        }
        Ok(())
    }
}

/// A figure for a log field: a number, to three decimals (NaN stays NaN).
fn round3(x: f64) -> f64 {
    (x * 1000.0).round() / 1000.0
}
