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

use std::collections::{BTreeMap, HashMap};
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{Context, Result};
use pbrl_common::wire::{
    self, now_ms, Answer, AnswerAck, Body, Preference, Query, Shown, TrajectoryMsg,
};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use crate::pref::config::{PrefConfig, SegmentStart};
use crate::pref::labels::{LabelStore, Stored, StoredTrajectory};
use crate::pref::query::{candidate_pairs, select, AnnotationBuffer, Candidate, Sampler, TrajKey};
use crate::pref::reward_model::{Labelled, RewardModel, RewardModelState, Segment, TrainStats};
use crate::state::RngState;

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

/// A query asked and not answered yet.
struct InFlight {
    query: Box<Query>,
    sent: Instant,
    /// Its two trajectories (for the bound on open queries per trajectory).
    keys: [TrajKey; 2],
}

/// A background job: choosing queries or training the ensemble.
type Job = Box<dyn FnOnce() -> Result<JobDone> + Send>;

/// What a background job hands back.
pub enum JobDone {
    /// The pairs chosen for session `session`, and the session's R_avg; `quota` is what
    /// the session (or, `top_up`, what it still owed) asked for.
    Chosen {
        session: u64,
        env_steps: u64,
        sampler: Sampler,
        pairs: Vec<(Side, Side)>,
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

/// One side of a query: a segment of a trajectory in the annotation buffer.
#[derive(Clone, Debug)]
pub struct Side {
    pub trajectory: Arc<Candidate>,
    /// Steps `start .. start + len` of the trajectory.
    pub start: usize,
    pub len: usize,
}

impl Side {
    /// The segment's steps, as the reward model reads them.
    fn segment(&self) -> Segment {
        let c = &self.trajectory;
        let span = (self.start, self.len);
        Segment::of(&c.obs, &c.actions, &c.features, span, c.steps())
    }
}

/// Trajectories whose ground-truth returns make R_avg (the authors' 100 newest).
const R_AVG_EPISODES: usize = 100;

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
        let model = RewardModel::new(model_cfg, obs_dim, act_dim)?;
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
            let first = self.labelled_side(row.first, row.first_segment)?;
            let second = self.labelled_side(row.second, row.second_segment)?;
            self.data.push(Labelled {
                first,
                second,
                target: target(row.preference),
            });
        }
        self.in_flight.clear();
        for (id, _, bytes) in self.store.open_queries()? {
            match wire::decode_stored_query(&self.run, &bytes) {
                Ok(q) => {
                    let keys = [
                        self.store.trajectory_key(q.first.id)?,
                        self.store.trajectory_key(q.second.id)?,
                    ];
                    self.in_flight.insert(
                        id,
                        InFlight {
                            query: Box::new(q),
                            // NOTE: asked again at once after a restart.
                            sent: Instant::now() - Duration::from_secs(self.cfg.query_retry_s),
                            keys,
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

    fn segment(&self, id: u64) -> Result<Arc<Segment>> {
        if let Some(s) = self.segments.get(&id) {
            return Ok(s.clone());
        }
        let s = self.store.segment(id)?;
        Ok(Arc::new(Segment {
            obs: s.obs,
            actions: s.actions,
            features: s.features,
        }))
    }

    /// Steps `start .. start + len` of stored trajectory `id`, for D (the whole
    /// trajectory's segment, shared, when the query compared whole trajectories).
    fn labelled_side(&mut self, id: u64, (start, len): (usize, usize)) -> Result<Arc<Segment>> {
        let whole = self.segment(id)?;
        let a = self.model.act_dim();
        let steps = whole.actions.len() / a.max(1);
        if start == 0 && len == steps {
            // Shared by every label of this trajectory (kept while D holds it).
            self.segments.insert(id, whole.clone());
            return Ok(whole);
        }
        if len == 0 || start + len > steps {
            anyhow::bail!(
                "label store {}: segment start {start}, length {len} of trajectory {id} is not within its {steps} steps",
                self.store.path().display()
            );
        }
        Ok(Arc::new(whole.cut(start, len, steps)))
    }

    /// Trajectory `c` as one side of a query: its segment drawn as the settings say
    /// (the whole trajectory, and no draw, where the segment would be all of it).
    fn side(&mut self, c: &Arc<Candidate>) -> Side {
        let steps = c.steps();
        let len = match self.cfg.segment_len {
            0 => steps,
            n => n.min(steps),
        };
        let start = if len >= steps {
            0
        } else {
            match self.cfg.segment_start {
                SegmentStart::Uniform => self.rng.random_range(0..=steps - len),
                SegmentStart::End => steps - len,
            }
        };
        Side {
            trajectory: c.clone(),
            start,
            len,
        }
    }

    /// R_avg for a session now: the mean ground-truth return of the newest
    /// [`R_AVG_EPISODES`] trajectories in the annotation buffer (the newest training
    /// episodes); None while it is empty.
    fn r_avg(&self) -> Option<f32> {
        let n = self.buffer.len().min(R_AVG_EPISODES);
        if n == 0 {
            return None;
        }
        let sum: f64 = (self.buffer.len() - n..self.buffer.len())
            .map(|i| {
                self.buffer
                    .get(i)
                    .truth
                    .iter()
                    .map(|&r| r as f64)
                    .sum::<f64>()
            })
            .sum();
        Some((sum / n as f64) as f32)
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

    /// The newest trained ensemble, if any.
    pub fn model(&self) -> Option<Arc<RewardModel>> {
        self.model.trained().then(|| self.model.clone())
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

    /// A session is due at `env_steps`.
    fn session_due(&self, env_steps: u64) -> Result<bool> {
        Ok(env_steps >= self.counters.next_session_at
            && self.buffer.len() >= 2
            && self.room() > 0
            && !self.frozen()?)
    }

    /// Queries the bounds on open ones leave room for: `max_open_queries` in all, and
    /// `open_per_labeller` for each person at a page (as for one while nobody is, so that
    /// the first to come finds a pair).
    fn room(&self) -> u64 {
        let mut bound = match self.cfg.max_open_queries {
            0 => u64::MAX,
            n => n,
        };
        if self.cfg.open_per_labeller > 0 {
            let people = u64::from(self.labellers.max(1));
            bound = bound.min(self.cfg.open_per_labeller.saturating_mul(people));
        }
        bound.saturating_sub(self.in_flight.len() as u64)
    }

    /// Queries the budget still allows, with `spent` counted against it so far
    /// ([`crate::pref::labels::Counts::spent`]).
    pub fn budget_left(&self, spent: u64) -> u64 {
        self.cfg.max_feedback.saturating_sub(spent)
    }

    /// A session is due at `env_steps`, or queries are owed, and they wait for open queries
    /// to be answered (the bound on open queries is reached): the learner is waiting for
    /// labels.
    pub fn waiting(&self, env_steps: u64) -> Result<bool> {
        Ok(
            (env_steps >= self.counters.next_session_at || self.owed > 0)
                && self.room() == 0
                && !self.frozen()?,
        )
    }

    /// Queries are owed and there is room to ask them now (just in time, from the newest
    /// episodes), unless the last try found no pair and no trajectory came since.
    fn top_up_due(&self) -> Result<bool> {
        Ok(self.owed > 0
            && self.room() > 0
            && self.buffer.len() >= 2
            && self.top_up_stuck_at != Some(self.observed)
            && !self.frozen()?)
    }

    /// New labels wait for training, and the session that asked them is answered (or the
    /// next one is due).
    fn training_due(&self, env_steps: u64) -> bool {
        self.data.len() > self.counters.trained_labels
            && (self.in_flight.is_empty() || env_steps >= self.counters.next_session_at)
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
                lower_priority();
                // NOTE: a receiver gone means the learner is shutting down; nothing to tell.
                let _ = tx.send(work());
            })
            .context("starting the feedback job's thread")?;
        self.job = Some(rx);
        Ok(None)
    }

    /// The job of training a copy of the ensemble on all of D (and measuring it first on
    /// the labels new since the last training).
    fn training(&mut self) -> Result<Job> {
        let mut model = self.model.snapshot()?;
        let data = self.data.clone();
        let new = data[self.counters.trained_labels..].to_vec();
        let trained_before = model.trained();
        // NOTE: pseudo-labels need an ensemble that has learnt something: from the second
        // training on.
        let unlabelled: Vec<(Side, Side)> =
            if trained_before && self.cfg.pseudo_pairs > 0 && self.buffer.len() >= 2 {
                let held = self.buffer.len();
                candidate_pairs(&mut self.rng, held, self.cfg.pseudo_pairs)?
                    .into_iter()
                    .map(|(i, j)| {
                        let (a, b) = (self.buffer.get(i).clone(), self.buffer.get(j).clone());
                        (self.side(&a), self.side(&b))
                    })
                    .collect()
            } else {
                Vec::new()
            };
        let tau = self.cfg.pseudo_tau;
        Ok(Box::new(move || {
            let start = Instant::now();
            let accuracy_new = if trained_before {
                model.accuracy(&new)?
            } else {
                f64::NAN
            };
            let labels = data.len();
            let pseudo = pseudo_labels(&model, &unlabelled, tau)?;
            let stats = model.train_with(&data, &pseudo)?;
            Ok(JobDone::Trained {
                model: Box::new(model),
                stats,
                labels,
                accuracy_new,
                took: start.elapsed(),
            })
        }))
    }

    /// The job of choosing a session's queries at `env_steps` (or, `top_up`, those the
    /// current session still owes): candidate pairs drawn from the annotation buffer, the
    /// sampler keeps the best of them that the bound per trajectory allows.
    fn choosing(&mut self, env_steps: u64, top_up: bool) -> Result<Job> {
        let session = self.counters.sessions + u64::from(!top_up);
        let spent = self.store.counts()?.spent();
        let quota = if top_up {
            self.owed.min(self.budget_left(spent))
        } else {
            self.cfg.session_queries(session, spent)
        };
        let k = quota.min(self.room()) as usize;
        // NOTE: the first session is uniform: an untrained ensemble's disagreement
        // means nothing.
        let sampler = if session == 1 || !self.model.trained() {
            Sampler::Uniform
        } else {
            self.cfg.sampler
        };
        let cap = self.cfg.queries_per_trajectory;
        // NOTE: with a bound per trajectory, uniform draws more pairs than it keeps too,
        // so that the ones the bound refuses leave enough.
        let n = if sampler == Sampler::Uniform && cap == 0 {
            k
        } else {
            k * self.cfg.candidate_factor as usize
        };
        let mut open: HashMap<TrajKey, u64> = HashMap::new();
        if cap > 0 {
            for f in self.in_flight.values() {
                for key in f.keys {
                    *open.entry(key).or_default() += 1;
                }
            }
        }
        // NOTE: policy-aligned queries (QPA) draw from the newest trajectories only.
        let held = self.buffer.len();
        let recent = match self.cfg.query_recent {
            0 => held,
            r => r.clamp(2, held.max(2)).min(held),
        };
        let offset = held - recent;
        let idx = candidate_pairs(&mut self.rng, recent, n)?;
        let mut candidates: Vec<(Side, Side)> = Vec::with_capacity(idx.len());
        for (i, j) in idx {
            let (a, b) = (
                self.buffer.get(offset + i).clone(),
                self.buffer.get(offset + j).clone(),
            );
            candidates.push((self.side(&a), self.side(&b)));
        }
        if cap > 0 {
            candidates.retain(|(a, b)| {
                open.get(&a.trajectory.key).copied().unwrap_or(0) < cap
                    && open.get(&b.trajectory.key).copied().unwrap_or(0) < cap
            });
        }
        let r_avg = self.r_avg();
        let model = self.model.clone();
        Ok(Box::new(move || {
            let ranked = if sampler == Sampler::Uniform {
                (0..candidates.len()).collect()
            } else {
                let probs = model.preference_probs(&distinct_pairs(&candidates).pairs())?;
                select(sampler, &probs, candidates.len(), candidates.len())
            };
            let chosen = within_cap(&candidates, ranked, k, cap, open);
            Ok(JobDone::Chosen {
                session,
                env_steps,
                sampler,
                pairs: chosen.into_iter().map(|i| candidates[i].clone()).collect(),
                r_avg,
                quota,
                top_up,
            })
        }))
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
    ) -> Result<(Vec<Query>, Option<Arc<RewardModel>>)> {
        match done {
            JobDone::Chosen {
                session,
                env_steps,
                sampler,
                pairs,
                r_avg,
                quota,
                top_up,
            } => {
                let queries = self.ask(session, env_steps, sampler, &pairs, r_avg)?;
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
                Ok((queries, None))
            }
            JobDone::Trained {
                model,
                stats,
                labels,
                accuracy_new,
                took,
            } => {
                self.counters.trained_labels = labels;
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

    /// Record the chosen pairs in the label store (each query committed before it is sent)
    /// and return the queries.
    fn ask(
        &mut self,
        session: u64,
        env_steps: u64,
        sampler: Sampler,
        pairs: &[(Side, Side)],
        r_avg: Option<f32>,
    ) -> Result<Vec<Query>> {
        let mut out = Vec::with_capacity(pairs.len());
        let sampler_name = match sampler {
            Sampler::Uniform => "uniform",
            Sampler::Disagreement => "disagreement",
            Sampler::Entropy => "entropy",
        };
        for (a, b) in pairs {
            let asked_at_ms = now_ms();
            let mut built = None;
            let run = self.run.clone();
            let expires_at_ms = match self.cfg.query_expiry_s {
                0 => 0,
                s => asked_at_ms + s * 1000,
            };
            let withdraw_at_steps = match self.cfg.query_stale_steps {
                0 => 0,
                s => env_steps + s,
            };
            let asked = self.store.ask(
                session,
                sampler_name,
                env_steps,
                asked_at_ms,
                &stored(a),
                &stored(b),
                |id, first, second| {
                    let q = Query {
                        id,
                        session,
                        asked_at_ms,
                        expires_at_ms,
                        first: shown(a, first),
                        second: shown(b, second),
                        r_avg,
                        withdraw_at_steps,
                    };
                    let bytes = wire::encode(&run, &Body::Query(Box::new(q.clone())));
                    built = Some(q);
                    bytes
                },
            )?;
            let q = built.context("the label store did not build the query")?;
            self.segments
                .insert(asked.first, Arc::new(seg_of(&a.trajectory)));
            self.segments
                .insert(asked.second, Arc::new(seg_of(&b.trajectory)));
            self.in_flight.insert(
                asked.query,
                InFlight {
                    query: Box::new(q.clone()),
                    sent: Instant::now(),
                    keys: [a.trajectory.key, b.trajectory.key],
                },
            );
            out.push(q);
        }
        Ok(out)
    }

    /// Store a teacher's answer (committed before this returns) and say whether to
    /// acknowledge it.
    pub fn answer(&mut self, a: &Answer) -> Result<Answered> {
        if a.repeat {
            return Ok(match self.store.repeat(a, now_ms())? {
                Stored::Unknown => {
                    self.counters.unknown_answers += 1;
                    tracing::warn!(
                        query = a.query,
                        teacher = %a.teacher_id,
                        "dropped a repeated answer to a query this run never asked"
                    );
                    Answered::Dropped
                }
                _ => Answered::Ack(AnswerAck {
                    teacher_id: a.teacher_id.clone(),
                    queries: Vec::new(),
                    repeats: vec![(a.query, a.labeller.clone())],
                }),
            });
        }
        let stored = self.store.answer(a, now_ms())?;
        match stored {
            Stored::New | Stored::Late => {
                let open = self.in_flight.remove(&a.query);
                if a.preference != Preference::Skip {
                    let bounds = |s: &Shown| (s.id, (s.start as usize, s.len as usize));
                    let (first, second) = match &open {
                        Some(f) => (bounds(&f.query.first), bounds(&f.query.second)),
                        None => {
                            // NOTE: a late answer to an expired query: its ids are in D.
                            let row = self
                                .store
                                .labels_since(0)?
                                .into_iter()
                                .find(|r| r.query == a.query)
                                .context("a stored answer is not in D")?;
                            (
                                (row.first, row.first_segment),
                                (row.second, row.second_segment),
                            )
                        }
                    };
                    let (first, second) = (
                        self.labelled_side(first.0, first.1)?,
                        self.labelled_side(second.0, second.1)?,
                    );
                    self.data.push(Labelled {
                        first,
                        second,
                        target: target(a.preference),
                    });
                }
            }
            Stored::Repeated => {
                self.counters.repeated_answers += 1;
                tracing::debug!(query = a.query, teacher = %a.teacher_id, "an answer came again; the first stands");
            }
            Stored::Unknown => {
                self.counters.unknown_answers += 1;
                tracing::warn!(
                    query = a.query,
                    teacher = %a.teacher_id,
                    "dropped an answer to a query this run never asked"
                );
                return Ok(Answered::Dropped);
            }
        }
        self.prune_segments();
        Ok(Answered::Ack(AnswerAck {
            teacher_id: a.teacher_id.clone(),
            queries: vec![a.query],
            repeats: Vec::new(),
        }))
    }

    /// Forget the whole trajectories no query in flight compares and D does not share:
    /// a label of a segment holds its own cut, so keeping the whole trajectory of every
    /// query ever asked would grow the learner by two trajectories a label.
    fn prune_segments(&mut self) {
        let open: std::collections::HashSet<u64> = self
            .in_flight
            .values()
            .flat_map(|f| [f.query.first.id, f.query.second.id])
            .collect();
        self.segments
            .retain(|id, s| Arc::strong_count(s) > 1 || open.contains(id));
    }

    /// Queries to ask again (unanswered for `query_retry_s`) at `env_steps`; queries past
    /// `query_expiry_s` expire instead, and those grown stale (`query_stale_steps`) are
    /// withdrawn, a fresh one owed in each one's place.
    pub fn retry(&mut self, env_steps: u64) -> Result<Vec<Query>> {
        let retry = Duration::from_secs(self.cfg.query_retry_s);
        let now = now_ms();
        let mut again = Vec::new();
        let mut expired = Vec::new();
        let mut stale = Vec::new();
        for (id, f) in self.in_flight.iter_mut() {
            let age_ms = now.saturating_sub(f.query.asked_at_ms);
            if self.cfg.query_expiry_s > 0 && age_ms >= self.cfg.query_expiry_s * 1000 {
                expired.push(*id);
            } else if f.query.stale_at(env_steps) {
                stale.push(*id);
            } else if f.sent.elapsed() >= retry {
                f.sent = Instant::now();
                again.push((*f.query).clone());
            }
        }
        for id in expired {
            self.store.expire(id, now)?;
            self.in_flight.remove(&id);
            tracing::warn!(query = id, "a query went unanswered too long: expired");
        }
        for id in stale {
            // NOTE: the store says it was withdrawn; an answer that still comes (a person
            // held the pair) is stored as late, exactly once.
            if self.store.withdraw(id, now, env_steps)? {
                self.owed += 1;
                self.counters.withdrawn_queries += 1;
            }
            self.in_flight.remove(&id);
            tracing::debug!(
                query = id,
                env_steps,
                "a stale query withdrawn; a fresh one owed"
            );
        }
        self.counters.retried_queries += again.len() as u64;
        Ok(again)
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

/// Lower the calling thread's scheduling priority by 10 nice levels (at most to 19; Linux,
/// elsewhere nothing): the feedback jobs (choosing queries, training the ensemble) then run
/// on the CPU that the learner's updates and the actors leave, instead of taking it from
/// them. A session whose job waits for CPU comes later; the env steps do not slow down.
fn lower_priority() {
    #[cfg(target_os = "linux")]
    {
        // NOTE: relative, not nice 10: under `nice -n 19 pbrl exp run` an absolute 10 would
        // raise the job above the learner (root may lower a nice value). On Linux the nice
        // value belongs to the thread, so this leaves the learner's threads as they are.
        // SAFETY: errno and nice only read and set this thread's errno and priority; no
        // memory is shared with them.
        let rc = unsafe {
            *libc::__errno_location() = 0;
            libc::nice(10)
        };
        let err = std::io::Error::last_os_error();
        if rc == -1 && err.raw_os_error() != Some(0) {
            tracing::debug!(error = %err, "could not lower the feedback job's priority");
        }
    }
}

/// The pairs of `unlabelled` that `model` is sure of (mean P of one side at least `tau`),
/// labelled with its answer (SURF's pseudo-labels).
fn pseudo_labels(
    model: &RewardModel,
    unlabelled: &[(Side, Side)],
    tau: f64,
) -> Result<Vec<Labelled>> {
    if unlabelled.is_empty() {
        return Ok(Vec::new());
    }
    let d = distinct_pairs(unlabelled);
    let probs = model.preference_probs(&d.pairs())?;
    let q = probs.len() as f64;
    let mut out = Vec::new();
    for (k, &(a, b)) in d.sides.iter().enumerate() {
        let p = probs.iter().map(|m| m[k] as f64).sum::<f64>() / q;
        let target = if p >= tau {
            1.0
        } else if 1.0 - p >= tau {
            0.0
        } else {
            continue;
        };
        out.push(Labelled {
            first: Arc::new(d.segs[a].clone()),
            second: Arc::new(d.segs[b].clone()),
            target,
        });
    }
    Ok(out)
}

/// The candidates to keep, `k` at most, in the order `ranked`, such that no trajectory is in
/// more than `cap` open queries (0: no bound), `open` counting those open already.
fn within_cap(
    candidates: &[(Side, Side)],
    ranked: Vec<usize>,
    k: usize,
    cap: u64,
    mut open: HashMap<TrajKey, u64>,
) -> Vec<usize> {
    if cap == 0 {
        return ranked.into_iter().take(k).collect();
    }
    let mut out = Vec::with_capacity(k);
    for i in ranked {
        if out.len() >= k {
            break;
        }
        let (a, b) = (
            candidates[i].0.trajectory.key,
            candidates[i].1.trajectory.key,
        );
        let n = |key: &TrajKey| open.get(key).copied().unwrap_or(0);
        if a == b || n(&a) >= cap || n(&b) >= cap {
            continue;
        }
        *open.entry(a).or_default() += 1;
        *open.entry(b).or_default() += 1;
        out.push(i);
    }
    out
}

/// The soft target of a preference: P[second preferred].
pub(crate) fn target(p: Preference) -> f32 {
    match p {
        Preference::First => 0.0,
        Preference::Second => 1.0,
        Preference::Equal | Preference::Skip => 0.5,
    }
}

/// Candidate pairs as the ensemble judges them: one segment per distinct trajectory, and
/// each pair as two indices into them.
struct Distinct {
    segs: Vec<Segment>,
    sides: Vec<(usize, usize)>,
}

impl Distinct {
    fn pairs(&self) -> Vec<(&Segment, &Segment)> {
        self.sides
            .iter()
            .map(|&(a, b)| (&self.segs[a], &self.segs[b]))
            .collect()
    }
}

/// One segment per distinct side of `candidates`: the ensemble judges each once.
fn distinct_pairs(candidates: &[(Side, Side)]) -> Distinct {
    let mut index: HashMap<(*const Candidate, usize, usize), usize> = HashMap::new();
    let mut segs: Vec<Segment> = Vec::new();
    let mut sides = Vec::with_capacity(candidates.len());
    for (a, b) in candidates {
        let mut at = |s: &Side| {
            let key = (Arc::as_ptr(&s.trajectory), s.start, s.len);
            *index.entry(key).or_insert_with(|| {
                segs.push(s.segment());
                segs.len() - 1
            })
        };
        sides.push((at(a), at(b)));
    }
    Distinct { segs, sides }
}

fn seg_of(c: &Candidate) -> Segment {
    Segment {
        obs: c.obs.clone(),
        actions: c.actions.clone(),
        features: c.features.clone(),
    }
}

fn stored(side: &Side) -> StoredTrajectory<'_> {
    let c = &*side.trajectory;
    StoredTrajectory {
        actor: c.key.actor,
        incarnation: c.key.incarnation,
        seq: c.key.seq,
        seed: c.seed,
        policy_version: c.policy_version,
        obs_dim: c.obs_dim as usize,
        act_dim: c.act_dim as usize,
        obs: &c.obs,
        actions: &c.actions,
        features: &c.features,
        segment: (side.start, side.len),
    }
}

fn shown(side: &Side, id: u64) -> Shown {
    let c = &*side.trajectory;
    Shown {
        id,
        seed: c.seed,
        policy_version: c.policy_version,
        act_dim: c.act_dim,
        actions: c.actions.clone(),
        truth: c.truth.clone(),
        replay: None,
        start: side.start as u32,
        len: side.len as u32,
    }
}

/// A figure for a log field: a number, to three decimals (NaN stays NaN).
fn round3(x: f64) -> f64 {
    (x * 1000.0).round() / 1000.0
}

#[cfg(test)]
mod tests {
    use super::*;
    use pbrl_common::{StepRewards, Trajectory};
    use std::path::Path;

    /// This thread's nice value.
    #[cfg(target_os = "linux")]
    fn thread_nice() -> i32 {
        // SAFETY: getpriority only reads this thread's priority.
        unsafe { libc::getpriority(libc::PRIO_PROCESS, 0) }
    }

    #[cfg(target_os = "linux")]
    #[test]
    fn the_feedback_job_runs_ten_nice_levels_below_its_caller_and_never_above_it() {
        std::thread::spawn(|| {
            let before = thread_nice();
            lower_priority();
            assert_eq!(thread_nice(), (before + 10).min(19));
        })
        .join()
        .unwrap();
        // A learner run under `nice -n 15` (as `pbrl exp` grids often are): the job must
        // not come out at nice 10, above the learner.
        std::thread::spawn(|| {
            let niced = thread_nice().max(15);
            // SAFETY: setpriority only sets this thread's priority (raising a nice value
            // needs no privilege).
            assert_eq!(
                unsafe { libc::setpriority(libc::PRIO_PROCESS, 0, niced) },
                0
            );
            lower_priority();
            assert_eq!(thread_nice(), 19);
        })
        .join()
        .unwrap();
    }

    fn msg(seq: u64) -> TrajectoryMsg {
        let steps = 3;
        TrajectoryMsg {
            actor: 0,
            incarnation: 1,
            seq,
            oldest: 0,
            trajectory: Trajectory {
                format: pbrl_common::trajectory::TRAJECTORY_FORMAT,
                seed: seq,
                policy_version: 1,
                obs_dim: 2,
                act_dim: 1,
                obs: vec![seq as f32; (steps + 1) * 2],
                actions: vec![0.5; steps],
                rewards: vec![StepRewards::default(); steps],
                ..Trajectory::default()
            },
        }
    }

    #[test]
    fn open_queries_are_bounded_and_a_due_session_waits_for_answers() {
        let cfg = PrefConfig {
            unsup_steps: 0,
            queries_per_session: 30,
            feedback_interval: 100,
            max_open_queries: 50,
            ..PrefConfig::plain()
        };
        let mut f = Feedback::new(&cfg, "run", 2, 1, 0, Path::new(":memory:")).unwrap();
        for seq in 0..40 {
            f.observe(&msg(seq));
        }
        let mut asked = Vec::new();
        for env_steps in [0, 100, 200, 300] {
            if let Some(done) = f.start(env_steps, true).unwrap() {
                asked.extend(f.finish(done, env_steps).unwrap().0);
            }
            assert!(f.open() <= 50, "{} open at {env_steps}", f.open());
        }
        // 30, then the 20 the bound leaves; then the sessions wait: nobody answered.
        assert_eq!(asked.len(), 50);
        assert_eq!(f.open(), 50);
        assert!(f.waiting(400).unwrap());
        assert!(f.start(400, true).unwrap().is_none());
        // One answer makes room for one query.
        let a = Answer::scripted(asked[0].id, Preference::First, "oracle", "o-0", 1);
        assert!(matches!(f.answer(&a).unwrap(), Answered::Ack(_)));
        assert!(!f.waiting(400).unwrap());
        let mut more = Vec::new();
        for _ in 0..2 {
            // NOTE: the first job may be the training on the new label.
            if let Some(done) = f.start(400, true).unwrap() {
                more.extend(f.finish(done, 400).unwrap().0);
            }
        }
        assert_eq!(more.len(), 1);
        assert!(f.waiting(500).unwrap());
    }

    #[test]
    fn with_people_queries_are_asked_just_in_time_and_a_stale_one_is_withdrawn() {
        let cfg = PrefConfig {
            unsup_steps: 0,
            queries_per_session: 10,
            feedback_interval: 10_000,
            open_per_labeller: 2,
            query_stale_steps: 500,
            queries_per_trajectory: 1,
            ..PrefConfig::plain()
        };
        let mut f = Feedback::new(&cfg, "run", 2, 1, 0, Path::new(":memory:")).unwrap();
        for seq in 0..40 {
            f.observe(&msg(seq));
        }
        let run = |f: &mut Feedback, env_steps| {
            let mut out = Vec::new();
            for _ in 0..3 {
                if let Some(done) = f.start(env_steps, true).unwrap() {
                    out.extend(f.finish(done, env_steps).unwrap().0);
                }
            }
            out
        };
        // Nobody at a page yet: room for one person's 2; the session's other 8 are owed.
        let first = run(&mut f, 0);
        assert_eq!(first.len(), 2);
        assert!(f.waiting(0).unwrap());
        assert!(first.iter().all(|q| q.withdraw_at_steps == 500));
        // Two people: room for 4, asked at once from what is owed.
        f.set_labellers(2);
        let more = run(&mut f, 100);
        assert_eq!(more.len(), 2);
        assert_eq!(f.open(), 4);
        // No trajectory is in two open queries.
        let mut sides: Vec<u64> = first
            .iter()
            .chain(&more)
            .flat_map(|q| [q.first.seed, q.second.seed])
            .collect();
        sides.sort();
        sides.dedup();
        assert_eq!(sides.len(), 8, "a trajectory in two open queries");
        // Past 500 env steps the first two are stale: withdrawn, and fresh ones asked.
        f.retry(550).unwrap();
        assert_eq!(f.open(), 2);
        let c = f.counts().unwrap();
        assert_eq!((c.withdrawn, c.spent()), (2, 2));
        let fresh = run(&mut f, 550);
        assert_eq!(fresh.len(), 2);
        assert!(fresh.iter().all(|q| q.withdraw_at_steps == 1_050));
        // A withdrawn query's late answer is stored, once, and joins D.
        let a = Answer::scripted(first[0].id, Preference::First, "human", "h-0", 1);
        assert!(matches!(f.answer(&a).unwrap(), Answered::Ack(_)));
        assert!(matches!(f.answer(&a).unwrap(), Answered::Ack(_)));
        let c = f.counts().unwrap();
        assert_eq!((c.late, c.labels(), c.withdrawn), (1, 1, 1));
        assert_eq!(f.data.len(), 1);
    }

    /// A 200-step trajectory numbered `seq`: observation (seq, step), truth `seq` a step.
    fn long(seq: u64) -> TrajectoryMsg {
        let steps = 200;
        let mut m = msg(seq);
        let t = &mut m.trajectory;
        t.obs = (0..=steps).flat_map(|k| [seq as f32, k as f32]).collect();
        t.actions = vec![0.5; steps];
        t.rewards = vec![
            StepRewards {
                truth: seq as f32,
                ..StepRewards::default()
            };
            steps
        ];
        m
    }

    #[test]
    fn queries_compare_segments_of_the_newest_trajectories_with_the_sessions_r_avg() {
        let cfg = PrefConfig {
            unsup_steps: 0,
            queries_per_session: 20,
            feedback_interval: 100,
            segment_len: 50,
            query_recent: 10,
            ..PrefConfig::plain()
        };
        let mut f = Feedback::new(&cfg, "run", 2, 1, 3, Path::new(":memory:")).unwrap();
        for seq in 0..150 {
            f.observe(&long(seq));
        }
        let done = f.start(0, true).unwrap().unwrap();
        let queries = f.finish(done, 0).unwrap().0;
        assert_eq!(queries.len(), 20);
        let mut starts = std::collections::BTreeSet::new();
        for q in &queries {
            // R_avg: the mean return of the newest 100 (seq 50..150, 200 steps each).
            assert_eq!(q.r_avg, Some(99.5 * 200.0));
            for s in [&q.first, &q.second] {
                assert_eq!(s.len, 50);
                assert!(s.start as usize + 50 <= 200);
                starts.insert(s.start);
                // Policy-aligned: only the newest 10 (seq 140..150, seeds = seq).
                assert!(s.seed >= 140, "seed {}", s.seed);
                assert_eq!(
                    s.steps(),
                    200,
                    "the whole trajectory travels for the replay"
                );
            }
        }
        assert!(starts.len() > 20, "starts are drawn: {starts:?}");
        // The label trains on the segments: their observations carry the step numbers.
        let q = &queries[0];
        let a = Answer::scripted(q.id, Preference::Second, "oracle", "o-0", 1);
        assert!(matches!(f.answer(&a).unwrap(), Answered::Ack(_)));
        let l = f.data.last().unwrap().clone();
        assert_eq!(l.first.obs.len(), 50 * 2);
        assert_eq!(l.first.obs[1], q.first.start as f32);
        assert_eq!(l.second.obs[99], (q.second.start + 49) as f32);
        // The whole trajectories stay in memory only while a query in flight compares
        // them: once every query is answered, D holds only its segments.
        let open = |f: &Feedback, id: u64| {
            f.in_flight
                .values()
                .any(|o| o.query.first.id == id || o.query.second.id == id)
        };
        for id in [q.first.id, q.second.id] {
            assert_eq!(
                f.segments.contains_key(&id),
                open(&f, id),
                "trajectory {id}"
            );
        }
        for q in &queries[1..] {
            let a = Answer::scripted(q.id, Preference::First, "oracle", "o-0", 1);
            assert!(matches!(f.answer(&a).unwrap(), Answered::Ack(_)));
        }
        assert!(f.in_flight.is_empty());
        assert!(
            f.segments.is_empty(),
            "{} whole trajectories kept",
            f.segments.len()
        );
        // The same after a restart: D is read back from the store with its segments.
        let d = |f: &Feedback| {
            let mut d: Vec<_> = f
                .data
                .iter()
                .map(|l| (l.first.obs.clone(), l.second.obs.clone()))
                .collect();
            d.sort_by(|a, b| a.partial_cmp(b).unwrap());
            d
        };
        let before = d(&f);
        f.reload().unwrap();
        assert_eq!(f.data.len(), 20);
        assert_eq!(d(&f), before);
        assert!(f.segments.is_empty(), "a reload keeps whole trajectories");
    }

    #[test]
    fn segment_starts_are_golden_for_a_seed() {
        // The draw of segments is part of a run's determinism: the same seed, the same
        // starts (a change here changes every `--sync` curve).
        let cfg = PrefConfig {
            unsup_steps: 0,
            queries_per_session: 4,
            sampler: Sampler::Uniform,
            segment_len: 50,
            ..PrefConfig::plain()
        };
        let mut f = Feedback::new(&cfg, "run", 2, 1, 3, Path::new(":memory:")).unwrap();
        for seq in 0..20 {
            f.observe(&long(seq));
        }
        let done = f.start(0, true).unwrap().unwrap();
        let q = f.finish(done, 0).unwrap().0;
        let got: Vec<(u64, u32, u64, u32)> = q
            .iter()
            .map(|q| (q.first.seed, q.first.start, q.second.seed, q.second.start))
            .collect();
        assert_eq!(got, GOLDEN_STARTS.to_vec());
        // The end of the trajectory, on request.
        let cfg = PrefConfig {
            segment_start: SegmentStart::End,
            ..cfg
        };
        let mut f = Feedback::new(&cfg, "run", 2, 1, 3, Path::new(":memory:")).unwrap();
        for seq in 0..20 {
            f.observe(&long(seq));
        }
        let done = f.start(0, true).unwrap().unwrap();
        let q = f.finish(done, 0).unwrap().0;
        assert!(q
            .iter()
            .all(|q| q.first.start == 150 && q.second.start == 150));
    }

    #[test]
    fn pseudo_labels_are_the_ensembles_sure_answers_and_nothing_else() {
        // A reward that learnt "more obs[0] is better" (segments of constant obs).
        let seg = |v: f32, steps: usize| Segment {
            obs: vec![v; steps],
            actions: vec![0.0; steps],
            features: Vec::new(),
        };
        let cfg = crate::pref::reward_model::RewardModelConfig {
            hidden: vec![16],
            lr: 3e-3,
            seed: 1,
            ..crate::pref::reward_model::RewardModelConfig::plain()
        };
        let mut model = RewardModel::new(cfg, 1, 1).unwrap();
        let labels: Vec<Labelled> = (0..64)
            .map(|k| {
                let (a, b) = ((k % 8) as f32 / 4.0 - 1.0, ((k / 8) % 8) as f32 / 4.0 - 1.0);
                Labelled {
                    first: Arc::new(seg(a, 5)),
                    second: Arc::new(seg(b, 5)),
                    target: if b > a {
                        1.0
                    } else if a > b {
                        0.0
                    } else {
                        0.5
                    },
                }
            })
            .collect();
        model.train(&labels).unwrap();
        let side = |v: f32| Side {
            trajectory: Arc::new(Candidate {
                key: crate::pref::query::TrajKey {
                    actor: 0,
                    incarnation: 0,
                    seq: (100.0 * v) as u64,
                },
                seed: 0,
                policy_version: 0,
                obs_dim: 1,
                act_dim: 1,
                obs: vec![v; 5],
                actions: vec![0.0; 5],
                truth: vec![0.0; 5],
                features: Vec::new(),
            }),
            start: 0,
            len: 5,
        };
        // Sure: the far ends, either way round; unsure: two alike.
        let pairs = vec![
            (side(-1.0), side(1.0)),
            (side(1.0), side(-1.0)),
            (side(0.5), side(0.5)),
        ];
        let got = pseudo_labels(&model, &pairs, 0.6).unwrap();
        let targets: Vec<f32> = got.iter().map(|l| l.target).collect();
        assert_eq!(targets, vec![1.0, 0.0], "the alike pair is left out");
        assert_eq!(got[0].first.obs, vec![-1.0; 5]);
        // Nothing is sure enough at tau 1.
        assert!(pseudo_labels(&model, &pairs, 1.0).unwrap().is_empty());
    }

    const GOLDEN_STARTS: [(u64, u32, u64, u32); 4] = [
        (6, 122, 2, 122),
        (7, 80, 12, 28),
        (3, 108, 1, 58),
        (16, 30, 13, 42),
    ];
}
