//! The learner: one type whose methods are the events of the service's loop
//! (`run::service`), each a step of Algorithm 1 or its bookkeeping: a trajectory taken in
//! and trained on, new weights, a feedback session started, its queries or a trained
//! ensemble back, answers stored, an evaluation back, the second's tick, the end.

use std::collections::BTreeMap;
use std::future::Future;
use std::path::PathBuf;
use std::pin::Pin;
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::Result;
use pbrl_common::wire::{
    Answer, AnswerAck, EvalRequest, EvalResult, LearnerStatus, Stop, TrajectoryMsg, Weights,
};

use crate::pref::feedback::{Answered, Counters, Feedback, JobDone};
use crate::pref::labels::Counts;
use crate::pref::reward::{Pool, TrainReward};
use crate::pref::reward_model::RewardModel;
use crate::run::backbone::Backbone;
use crate::run::bus::LearnerBus;
use crate::run::checkpoint::{self, fresh_progress, Checkpoints, Of};
use crate::run::config::{Algo, LearnerConfig};
use crate::run::curve::{progress_bar, Clock, Curve, CurveRow};
use crate::run::evaluation::{self, rhat_tracking, Actors, EVAL_SEED_BASE};
use crate::run::progress::Progress;
use crate::run::run_folder::RunFolder;

/// What a finished run did.
#[derive(Clone, Debug, Default)]
pub struct Summary {
    pub env_steps: u64,
    pub updates: u64,
    pub policy_version: u64,
    pub rows: Vec<CurveRow>,
    /// The run's one count of messages dropped ([`Learner::dropped`]), as the curve has it.
    pub dropped_messages: u64,
    pub stale_trajectories: u64,
    /// Episodes received from each actor.
    pub episodes_by_actor: BTreeMap<u32, u64>,
    /// The policy version of each actor's first episode.
    pub first_version_by_actor: BTreeMap<u32, u64>,
    /// The policy version of each actor's last episode taken.
    pub last_version_by_actor: BTreeMap<u32, u64>,
    /// The run was stopped (a signal) before its total.
    pub stopped: bool,
    /// Preference learning: the label store's counts and the loop's counters.
    pub labels: Option<Counts>,
    pub feedback: Option<Counters>,
    /// The final policy's tensors (to compare runs).
    pub weights: Option<Weights>,
    /// Wall time the learner stood still waiting for answers (`--label-slack-steps`,
    /// `--label-slack-s`), in this process.
    pub held: Duration,
}

pub struct Learner {
    cfg: LearnerConfig,
    backbone: Backbone,
    reward: TrainReward,
    /// Preference learning (learnt rewards only).
    feedback: Option<Feedback>,
    curve: Curve,
    checkpoints: Checkpoints,
    p: Progress,
    clock: Clock,
    actors: Actors,
    /// Rows made before the checkpoint this run resumed from and not written: evaluated
    /// again at the start.
    unwritten: Vec<(CurveRow, EvalRequest)>,
    /// The newest trajectory made new weights due; and those weights, once published.
    weights_due: bool,
    published: Option<Weights>,
    /// Keeping time with the teacher: stopped since then.
    held_since: Option<Instant>,
    /// Trajectories that came while it stood still (each taken once; at most the actors'
    /// credit), trained on first once the answers are in.
    stashed: std::collections::VecDeque<TrajectoryMsg>,
    summary: Summary,
}

impl Learner {
    /// A new run, or the run its folder holds, continued from its newest checkpoint.
    pub fn open(cfg: LearnerConfig) -> Result<Self> {
        let mut backbone = Backbone::new(&cfg)?;
        let folder = cfg.out.as_ref().map(RunFolder::new);
        let (file, resumed, segments) = match &folder {
            Some(f) => {
                let (file, resumed, segments) = checkpoint::open_folder(f, &cfg, &mut backbone)?;
                (Some(file), resumed, segments)
            }
            None => (None, None, Vec::new()),
        };
        let pool = match cfg.algo {
            Algo::Sac => Pool::AtOnce,
            Algo::Ppo => Pool::AfterRollout,
        };
        let mut reward =
            TrainReward::new(cfg.reward, &cfg.pref, cfg.total_steps, cfg.obs_dim, pool);
        reward.lambda_scale = cfg.sac.lambda_scale;
        let mut feedback = open_feedback(&cfg, folder.as_ref())?;
        let (p, unwritten) = match resumed {
            Some(r) => {
                reward.guard = r.saved.guard.clone();
                if let (Some(f), Some(state)) = (feedback.as_mut(), &r.saved.feedback) {
                    f.restore(state)?;
                    checkpoint::load_networks(&r.dir, f.networks())?;
                    reward.entropy = state.entropy.clone();
                    reward.model = f.model();
                }
                let mut p = r.saved.progress;
                // NOTE: versions published after the checkpoint may still be held by actors;
                // count on from above every version this run ever published.
                p.version = p
                    .version
                    .max(folder.as_ref().map_or(0, |f| f.published_version()))
                    + 1;
                (p, r.saved.pending)
            }
            None => (fresh_progress(&cfg), Vec::new()),
        };
        let bar = cfg
            .progress
            .then(|| progress_bar(cfg.total_steps, p.env_steps));
        Ok(Self {
            curve: Curve::new(file, p.rows_written, bar),
            checkpoints: Checkpoints::new(&cfg, folder, segments),
            clock: Clock::new(&p),
            cfg,
            backbone,
            reward,
            feedback,
            p,
            actors: Actors::default(),
            unwritten,
            weights_due: false,
            published: None,
            held_since: None,
            stashed: std::collections::VecDeque::new(),
            summary: Summary::default(),
        })
    }

    /// The run asks teachers (a learnt reward).
    pub fn asks_teachers(&self) -> bool {
        self.feedback.is_some()
    }

    /// The run has reached its total.
    pub fn done(&self) -> bool {
        self.p.env_steps >= self.cfg.total_steps
    }

    /// The first weights; the rows a resumed run had not written are evaluated again, and
    /// the queries open in the label store (asked before a restart) are asked again.
    pub async fn start(&mut self, bus: &LearnerBus) -> Result<()> {
        tracing::debug!(config = %serde_json::to_string(&self.cfg)?, "learner config");
        tracing::info!(
            run = %self.cfg.run,
            algo = ?self.cfg.algo,
            reward = self.cfg.reward.name(),
            steps = self.cfg.total_steps,
            from = self.p.env_steps,
            "learner starts"
        );
        bus.publish(&self.weights()?).await?;
        for (row, mut request) in std::mem::take(&mut self.unwritten) {
            request.actor = 0;
            evaluation::ask(bus, &mut self.curve, row, request).await?;
        }
        if let Some(f) = self.feedback.as_mut() {
            bus.ask(&f.retry(self.p.env_steps)?).await?;
        }
        Ok(())
    }

    /// A trajectory arrived: the one to train on, or none (taken before, or acted by a
    /// version the backbone does not train on).
    pub fn take(&mut self, msg: TrajectoryMsg) -> Option<TrajectoryMsg> {
        self.actors.last_seen.insert(msg.actor, Instant::now());
        // NOTE: a trajectory sent again (its actor waited long for weights) is taken once.
        if !self.p.receipts.take(&msg) {
            return None;
        }
        let version = msg.trajectory.policy_version;
        let s = &mut self.summary;
        *s.episodes_by_actor.entry(msg.actor).or_default() += 1;
        s.first_version_by_actor.entry(msg.actor).or_insert(version);
        s.last_version_by_actor.insert(msg.actor, version);
        if !self.backbone.takes(&self.cfg, version, self.p.version) {
            self.p.stale += 1;
            return None;
        }
        Some(msg)
    }

    /// Store the trajectory's transitions (and keep it for queries; while pretraining, its
    /// states join the entropy bonus's pool), then take the gradient steps it pays for.
    pub fn train(&mut self, msg: TrajectoryMsg, kept_for_queries: bool) -> Result<()> {
        self.published = None;
        if let Some(f) = self.feedback.as_mut().filter(|_| !kept_for_queries) {
            f.observe(&msg);
        }
        self.reward.observe(&msg.trajectory);
        if let crate::run::backbone::Backbone::Sac(sac) = &mut self.backbone {
            // NOTE: QPA's hybrid replay holds while labels are still asked.
            sac.hybrid = match &self.feedback {
                Some(f) => !f.frozen()?,
                None => false,
            };
        }
        let outcome = msg.trajectory.outcome;
        let steps = msg.trajectory.steps() as u64;
        let observed = self.backbone.observe(
            &self.cfg,
            msg.trajectory,
            &mut self.reward,
            self.p.env_steps,
            &mut self.p.publication,
        )?;
        self.p.updates += observed.updates;
        if let Some(l) = observed.losses {
            self.p.losses.record(l);
        }
        self.p.env_steps += steps;
        self.p.window.add(&outcome);
        if let Some(bar) = &self.curve.bar {
            bar.set_position(self.p.env_steps.min(self.cfg.total_steps));
        }
        self.weights_due = observed.publish;
        Ok(())
    }

    /// Keep time with the teacher: whether the learner stands still now (it trains on no
    /// trajectory, keeping those that come, and publishes no weights, so the actors idle
    /// once their credit is spent) until the answers it waits for are in and trained on.
    /// The deterministic mode waits in its own way.
    pub fn holding(&mut self) -> bool {
        let held = !self.cfg.sync
            && self
                .feedback
                .as_ref()
                .is_some_and(|f| f.holds(self.p.env_steps, Instant::now()));
        match (held, self.held_since) {
            (true, None) => {
                self.held_since = Some(Instant::now());
                let open = self.feedback.as_ref().map_or(0, |f| f.open());
                tracing::info!(
                    env_steps = self.p.env_steps,
                    open,
                    "keeping time with the teacher: stopped until the answers are in"
                );
                if let Some(bar) = &self.curve.bar {
                    bar.set_message("stopped: waiting for the teacher's answers");
                }
            }
            (false, Some(since)) => {
                self.held_since = None;
                let waited = since.elapsed();
                self.summary.held += waited;
                tracing::info!(
                    env_steps = self.p.env_steps,
                    waited_s = waited.as_secs(),
                    "the answers are in: training goes on"
                );
                if let Some(bar) = &self.curve.bar {
                    bar.set_message("");
                }
            }
            _ => {}
        }
        held
    }

    /// Keep a trajectory that came while the learner stands still, for when it goes on
    /// (taking it from the bus keeps a sender's copies sent again from piling up there).
    pub fn stash(&mut self, m: TrajectoryMsg) {
        // NOTE: kept for queries now, so that a session's queries still owed can be asked
        // of what the robot did last (not again when it is trained on).
        if let Some(f) = self.feedback.as_mut() {
            f.observe(&m);
        }
        self.stashed.push_back(m);
    }

    /// The oldest trajectory kept while the learner stood still (already kept for queries).
    pub fn unstash(&mut self) -> Option<TrajectoryMsg> {
        self.stashed.pop_front()
    }

    /// New weights, when the backbone said so.
    pub async fn publish_weights(&mut self, bus: &LearnerBus) -> Result<()> {
        if !self.weights_due {
            return Ok(());
        }
        let p = &mut self.p;
        p.version += 1;
        p.publication.since = 0;
        p.publication.episodes = 0;
        p.publication.env_steps = p.env_steps;
        let w = self.weights()?;
        bus.publish(&w).await?;
        self.published = Some(w);
        Ok(())
    }

    /// The weights of the current version, with the actors' acknowledgements (recorded as
    /// published in the run folder).
    fn weights(&self) -> Result<Weights> {
        if let Some(f) = self.checkpoints.folder() {
            f.mark_version(self.p.version)?;
        }
        let mut w = self
            .backbone
            .weights(&self.cfg, self.p.version, self.p.env_steps)?;
        w.acks = self.p.receipts.acks();
        Ok(w)
    }

    /// Preference learning after a trajectory: what is due starts (a training on new
    /// labels, or a feedback session's choice of queries), in the background; the
    /// deterministic mode does it in place and waits for the answers.
    pub async fn feedback(&mut self, bus: &mut LearnerBus) -> Result<()> {
        match self.feedback.as_mut() {
            Some(_) if self.cfg.sync => self.feedback_in_place(bus).await,
            Some(f) => f.start(self.p.env_steps, false).map(drop),
            None => Ok(()),
        }
    }

    /// The deterministic mode's feedback: what is due runs in place, and a session waits
    /// for its answers (asking again as it goes), so a run is a function of its seed and
    /// teacher.
    async fn feedback_in_place(&mut self, bus: &mut LearnerBus) -> Result<()> {
        let env_steps = self.p.env_steps;
        let mut tick = tokio::time::interval(Duration::from_secs(1));
        loop {
            let Some(f) = self.feedback.as_mut() else {
                return Ok(());
            };
            let Some(done) = tokio::task::block_in_place(|| f.start(env_steps, true))? else {
                return Ok(());
            };
            let (queries, model) = f.finish(done, env_steps)?;
            bus.ask(&queries).await?;
            if let Some(m) = model {
                self.install(m)?;
            }
            while self.feedback.as_ref().is_some_and(|f| f.open() > 0) {
                tokio::select! {
                    a = bus.answers.next() => self.store_answers(a?, bus).await?,
                    _ = tick.tick() => self.ask_again(bus).await?,
                }
            }
        }
    }

    /// The background feedback job's result (pending while none runs; cancel-safe).
    pub async fn feedback_job(&mut self) -> Result<JobDone> {
        match self.feedback.as_mut() {
            Some(f) if f.busy() => f.job().await,
            _ => std::future::pending().await,
        }
    }

    /// A feedback job is done: a session's queries are asked, or the trained ensemble
    /// becomes the reward; then whatever is due next starts.
    pub async fn feedback_done(&mut self, done: JobDone, bus: &LearnerBus) -> Result<()> {
        let Some(f) = self.feedback.as_mut() else {
            return Ok(());
        };
        let (queries, model) = f.finish(done, self.p.env_steps)?;
        bus.ask(&queries).await?;
        if let Some(m) = model {
            self.install(m)?;
        }
        self.start_due()
    }

    /// Start what preference learning has due, in the background.
    fn start_due(&mut self) -> Result<()> {
        if let Some(f) = self.feedback.as_mut() {
            f.start(self.p.env_steps, false)?;
        }
        Ok(())
    }

    /// The learnt reward takes over: the first trained ensemble ends the pretraining.
    fn install(&mut self, model: Arc<RewardModel>) -> Result<()> {
        if self.reward.install(model) {
            self.backbone.reset_after_pretraining()?;
            tracing::info!("pretraining over: the learnt reward takes over");
        }
        Ok(())
    }

    /// Answers came: stored (committed) and acknowledged; the session may be answered now,
    /// so training can start.
    pub async fn answered(&mut self, first: Answer, bus: &mut LearnerBus) -> Result<()> {
        self.store_answers(first, bus).await?;
        self.start_due()
    }

    /// Store `first` and every answer already waiting (each committed before any is
    /// acknowledged), then acknowledge them, one message per teacher.
    async fn store_answers(&mut self, first: Answer, bus: &mut LearnerBus) -> Result<()> {
        let Some(f) = self.feedback.as_mut() else {
            return Ok(());
        };
        let mut acks: BTreeMap<String, AnswerAck> = BTreeMap::new();
        let mut next = Some(first);
        while let Some(a) = next {
            // NOTE: `answer` commits the label before it returns; only then the acknowledgement.
            if let Answered::Ack(ack) = f.answer(&a)? {
                let all = acks
                    .entry(ack.teacher_id.clone())
                    .or_insert_with(|| AnswerAck {
                        teacher_id: ack.teacher_id,
                        queries: Vec::new(),
                        repeats: Vec::new(),
                    });
                all.queries.extend(ack.queries);
                all.repeats.extend(ack.repeats);
            }
            next = bus.answers.waiting();
        }
        bus.acknowledge(acks).await
    }

    /// Queries unanswered for a while are asked again (or expire).
    async fn ask_again(&mut self, bus: &LearnerBus) -> Result<()> {
        if let Some(f) = self.feedback.as_mut() {
            bus.ask(&f.retry(self.p.env_steps)?).await?;
        }
        Ok(())
    }

    /// An evaluation came back: its row gets the evaluation and, with a learnt reward, how
    /// well that reward tracks the truth on the evaluation's episodes.
    pub fn evaluated(&mut self, r: EvalResult) -> Result<()> {
        let tracking = match &self.reward.model {
            Some(m) if !r.steps.is_empty() => {
                Some(tokio::task::block_in_place(|| rhat_tracking(m, &r.steps))?)
            }
            _ => None,
        };
        self.curve.complete(r, tracking)
    }

    /// Every second: evaluations and queries unanswered for a while are asked again, and
    /// teachers hear where the learner stands.
    pub async fn tick(&mut self, bus: &LearnerBus) -> Result<()> {
        self.p.eval_retries += evaluation::retry(bus, &mut self.curve, &mut self.actors).await?;
        if let Some(f) = self.feedback.as_mut() {
            f.set_labellers(bus.labellers() as u32);
        }
        self.ask_again(bus).await?;
        // NOTE: a query withdrawn lets an owed one go now (the deterministic mode does
        // its feedback in place).
        if !self.cfg.sync {
            self.start_due()?;
        }
        if let Some(s) = self.status(bus)? {
            bus.status(s).await?;
        }
        Ok(())
    }

    /// Where the learner stands, for teachers (learnt rewards only).
    fn status(&self, bus: &LearnerBus) -> Result<Option<LearnerStatus>> {
        let Some(f) = &self.feedback else {
            return Ok(None);
        };
        let c = f.counts()?;
        Ok(Some(LearnerStatus {
            env_steps: self.p.env_steps,
            asked: c.asked,
            answered: c.answered,
            open: c.open,
            budget_left: f.budget_left(c.spent()),
            waiting: f.waiting(self.p.env_steps)?,
            held: self.held_since.is_some(),
            labellers: bus.labellers() as u32,
            agreement: f.agreement().map(|(a, _)| a as f32),
            agreement_of: f.agreement().map_or(0, |(_, n)| n as u32),
        }))
    }

    /// The run's one count of messages dropped: refused by the bus's inboxes, evaluations
    /// of the wrong size, answers to queries this run never asked. The curve and the
    /// summary both read it here.
    pub fn dropped(&self, bus: &LearnerBus) -> u64 {
        bus.dropped()
            + self.curve.dropped
            + self
                .feedback
                .as_ref()
                .map_or(0, |f| f.counters.unknown_answers)
    }

    /// A row of the curve, when due: written at once, or once its evaluation is in.
    pub async fn curve_row(&mut self, bus: &LearnerBus) -> Result<()> {
        let p = &mut self.p;
        if p.env_steps < p.next_row && p.env_steps < self.cfg.total_steps {
            return Ok(());
        }
        while p.next_row <= p.env_steps {
            p.next_row += self.cfg.log_every.max(1);
        }
        let window = std::mem::take(&mut p.window);
        let row = CurveRow::at(
            &self.p,
            window,
            &self.clock,
            &self.reward,
            self.feedback.as_ref(),
            self.dropped(bus),
            bus.labellers(),
        )?;
        if self.cfg.eval_episodes == 0 {
            return self.curve.write(row);
        }
        let request = EvalRequest {
            id: self.p.env_steps,
            actor: self.actors.next_live(),
            weights: match self.published.take() {
                Some(w) => w,
                None => self
                    .backbone
                    .weights(&self.cfg, self.p.version, self.p.env_steps)?,
            },
            seeds: (0..self.cfg.eval_episodes as u64)
                .map(|k| EVAL_SEED_BASE + k)
                .collect(),
            sampled: self.cfg.eval_sampled,
            // NOTE: only a learnt reward reads them (not while pretraining).
            steps: self.reward.model.is_some(),
        };
        evaluation::ask(bus, &mut self.curve, row, request).await
    }

    /// A checkpoint, when due (at a weights publication).
    pub fn checkpoint_if_due(&mut self) -> Result<()> {
        if self.checkpoints.due(&mut self.p, self.weights_due) {
            self.checkpoint()?;
        }
        Ok(())
    }

    /// Write a checkpoint of where the run stands (nothing without a run folder).
    fn checkpoint(&mut self) -> Result<()> {
        let mut p = self.p.clone();
        p.wall_s = self.clock.wall_s(&self.p);
        let of = Of {
            backbone: &self.backbone,
            feedback: self.feedback.as_ref(),
            reward: &self.reward,
            curve: &self.curve,
        };
        tokio::task::block_in_place(|| self.checkpoints.write(&self.cfg, of, &p))
    }

    /// The end of the run (its total, or `stopped`): the last evaluations and answers
    /// come in, the final checkpoint, the actors told to stop, and what the run did.
    pub async fn finish(
        mut self,
        bus: &mut LearnerBus,
        stopped: bool,
        shutdown: Pin<&mut impl Future<Output = ()>>,
    ) -> Result<Summary> {
        if !stopped {
            self.drain(bus, shutdown).await?;
        }
        // Answers already received are stored (the teacher forgets them once acknowledged;
        // the queries still open are asked again by a resumed run).
        if let Some(first) = bus.answers.waiting() {
            self.store_answers(first, bus).await?;
        }
        self.final_checkpoint(stopped)?;
        self.curve.end_bar(stopped.then_some(self.p.env_steps));
        let word = Stop {
            env_steps: self.p.env_steps,
            version: self.p.version,
        };
        if let Err(e) = bus.stop(word).await {
            tracing::warn!(error = %e, "could not tell the actors to stop");
        }
        self.summary(bus, stopped)
    }

    /// The last evaluations: the actors answer while they wait for weights that will not
    /// come; their last trajectories are drained so nothing blocks. Answers still coming
    /// are stored meanwhile.
    async fn drain(
        &mut self,
        bus: &mut LearnerBus,
        mut shutdown: Pin<&mut impl Future<Output = ()>>,
    ) -> Result<()> {
        let mut tick = tokio::time::interval(Duration::from_secs(1));
        while !self.curve.pending.is_empty() {
            tokio::select! {
                _ = &mut shutdown => break,
                r = bus.eval_results.next() => self.evaluated(r?)?,
                a = bus.answers.next() => self.store_answers(a?, bus).await?,
                _ = tick.tick() => {
                    self.p.eval_retries +=
                        evaluation::retry(bus, &mut self.curve, &mut self.actors).await?;
                }
                m = bus.trajectories.next() => { m?; }
            }
        }
        Ok(())
    }

    /// The final checkpoint (a stop, or the end): pending rows stay pending in it when
    /// stopped, so a resumed run writes them, evaluated; a finished run writes them now.
    fn final_checkpoint(&mut self, stopped: bool) -> Result<()> {
        if self.checkpoints.folder().is_none() {
            return self.curve.flush();
        }
        if stopped {
            tracing::info!(
                env_steps = self.p.env_steps,
                "stopping: writing a checkpoint"
            );
        } else {
            self.curve.flush()?;
        }
        self.checkpoint()?;
        if let (false, Some(f)) = (stopped, self.checkpoints.folder()) {
            let p = &self.p;
            let text = serde_json::json!({ "env_steps": p.env_steps, "version": p.version, "updates": p.updates });
            f.write_atomic(&f.finished(), text.to_string().as_bytes())?;
        }
        Ok(())
    }

    fn summary(mut self, bus: &LearnerBus, stopped: bool) -> Result<Summary> {
        let mut s = std::mem::take(&mut self.summary);
        s.env_steps = self.p.env_steps;
        s.updates = self.p.updates;
        s.policy_version = self.p.version;
        s.stale_trajectories = self.p.stale;
        s.stopped = stopped;
        s.dropped_messages = self.dropped(bus);
        s.rows = std::mem::take(&mut self.curve.rows);
        if let Some(f) = &self.feedback {
            s.labels = Some(f.counts()?);
            s.feedback = Some(f.counters.clone());
        }
        s.weights = Some(
            self.backbone
                .weights(&self.cfg, self.p.version, self.p.env_steps)?,
        );
        Ok(s)
    }
}

/// Preference learning's loop over the run's label store (in memory without a run
/// folder), for learnt rewards.
fn open_feedback(cfg: &LearnerConfig, folder: Option<&RunFolder>) -> Result<Option<Feedback>> {
    if !cfg.reward.learnt() {
        return Ok(None);
    }
    let labels = folder.map_or_else(|| PathBuf::from(":memory:"), |f| f.labels());
    let seed = match cfg.algo {
        Algo::Sac => cfg.sac.seed,
        Algo::Ppo => cfg.ppo.seed,
    };
    let f = Feedback::new(&cfg.pref, &cfg.run, cfg.obs_dim, cfg.act_dim, seed, &labels)?;
    Ok(Some(f))
}
