//! The learner service, Algorithm 1 of the paper over Zenoh: trajectories arrive and the
//! backbone trains on them (publishing new weights when it says so); every
//! `feedback_interval` env steps a feedback session asks a teacher about pairs of them;
//! answers arrive, are stored and acknowledged; a trained ensemble arrives and the reward
//! uses it; a curve row and a checkpoint come when due.
//!
//! The pieces: `config` (settings), `backbone` (SAC or PPO), `reward` (what the policy
//! trains on), `feedback` (queries, answers, D and the ensemble), `curve` and
//! `evaluation` (the learning curve), `checkpoint` (resume).

use std::future::Future;
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::Result;
use pbrl_common::bus::{put_message, Inbox, Labellers, MessagePublisher, WeightsServer};
use pbrl_common::wire::{
    AnswerAck, Body, EvalRequest, EvalResult, EvalSteps, LearnerStatus, Query, Stop, Weights,
};
use pbrl_common::Keys;
use zenoh::qos::Priority;
use zenoh::Session;

use crate::backbone::{Backbone, Losses};
use crate::checkpoint::{self, Progress};
use crate::curve::{correlation, Curve, CurveRow};
use crate::entropy::StateEntropy;
pub use crate::evaluation::EVAL_SEED_BASE;
use crate::evaluation::{self, Actors};
use crate::feedback::{Answered, Counters, Feedback};
use crate::labels::Counts;
use crate::reward::TrainReward;
use crate::reward_model::RewardModel;
use crate::run_folder::RunFolder;

pub use crate::config::{Algo, LearnerConfig};
pub use crate::reward::RewardSource;

/// What a finished run did.
#[derive(Clone, Debug, Default)]
pub struct Summary {
    pub env_steps: u64,
    pub updates: u64,
    pub policy_version: u64,
    pub rows: Vec<CurveRow>,
    pub dropped_messages: u64,
    pub stale_trajectories: u64,
    /// Episodes received from each actor.
    pub episodes_by_actor: std::collections::BTreeMap<u32, u64>,
    /// The policy version of each actor's first episode.
    pub first_version_by_actor: std::collections::BTreeMap<u32, u64>,
    /// The policy version of each actor's last episode taken.
    pub last_version_by_actor: std::collections::BTreeMap<u32, u64>,
    /// The run was stopped (a signal) before its total.
    pub stopped: bool,
    /// Preference learning: the label store's counts and the loop's counters.
    pub labels: Option<Counts>,
    pub feedback: Option<Counters>,
    /// The final policy's tensors (to compare runs).
    pub weights: Option<Weights>,
}

/// How well `model` tracks the ground truth on an evaluation's episodes: the Pearson
/// correlation of r_hat with r per step and per episode sum. Episodes whose lengths do not
/// agree with the model are left out (with a warning); NaN when none is left.
fn rhat_tracking(model: &RewardModel, episodes: &[EvalSteps]) -> Result<(f64, f64)> {
    let (mut step_hat, mut step_true, mut sum_hat, mut sum_true) =
        (Vec::new(), Vec::new(), Vec::new(), Vec::new());
    for e in episodes {
        let n = e.truth.len();
        if e.obs.len() != n * model.obs_dim() || e.actions.len() != n * model.act_dim() {
            tracing::warn!(
                steps = n,
                obs = e.obs.len(),
                actions = e.actions.len(),
                "an evaluation episode's steps do not fit the reward model; left out"
            );
            continue;
        }
        let r = model.predict(&e.obs, &e.actions)?;
        sum_hat.push(r.iter().map(|x| *x as f64).sum());
        sum_true.push(e.truth.iter().map(|x| *x as f64).sum());
        step_hat.extend(r.iter().map(|x| *x as f64));
        step_true.extend(e.truth.iter().map(|x| *x as f64));
    }
    Ok((
        correlation(&step_hat, &step_true),
        correlation(&sum_hat, &sum_true),
    ))
}

/// An evaluation came back: its row gets the evaluation and, with a learnt reward, how well
/// that reward tracks the truth on the evaluation's episodes.
fn evaluated(curve: &mut Curve, reward: &TrainReward, r: EvalResult) -> Result<()> {
    let tracking = match &reward.model {
        Some(m) if !r.steps.is_empty() => {
            Some(tokio::task::block_in_place(|| rhat_tracking(m, &r.steps))?)
        }
        _ => None,
    };
    curve.complete(r, tracking)
}

/// The learnt reward takes over: the first trained ensemble ends the pretraining.
fn install(
    model: Arc<RewardModel>,
    reward: &mut TrainReward,
    backbone: &mut Backbone,
) -> Result<()> {
    if reward.model.is_none() {
        backbone.reset_after_pretraining()?;
        reward.entropy = None;
        tracing::info!("pretraining over: the learnt reward takes over");
    }
    reward.model = Some(model);
    Ok(())
}

/// The next message of an inbox that may not exist (pending forever then).
async fn next_of<T: Send + 'static>(inbox: &mut Option<Inbox<T>>) -> Result<T> {
    match inbox {
        Some(i) => i.next().await,
        None => std::future::pending().await,
    }
}

/// The Zenoh side of preference learning.
struct Teachers {
    queries: MessagePublisher,
    status: MessagePublisher,
}

/// Where the learner stands (built before any await: the feedback loop is not `Sync`).
fn status_of(f: &Feedback, env_steps: u64, labellers: &Labellers) -> Result<LearnerStatus> {
    let c = f.counts()?;
    Ok(LearnerStatus {
        env_steps,
        asked: c.asked,
        answered: c.answered,
        open: c.open,
        budget_left: f.budget_left(c.asked),
        waiting: f.waiting(env_steps)?,
        labellers: labellers.count() as u32,
    })
}

impl Teachers {
    /// Tell teachers (and the people at their pages) where the learner stands.
    async fn status(&self, s: LearnerStatus) -> Result<()> {
        self.status.send(&Body::Status(s)).await
    }

    async fn ask(&self, queries: &[Query]) -> Result<()> {
        for q in queries {
            self.queries.send(&Body::Query(Box::new(q.clone()))).await?;
        }
        Ok(())
    }
}

/// Store `first` and every answer already waiting (each committed before any is
/// acknowledged), then acknowledge them, one message per teacher.
async fn take_answers(
    session: &Session,
    keys: &Keys,
    f: &mut Feedback,
    first: pbrl_common::wire::Answer,
    inbox: &mut Option<Inbox<pbrl_common::wire::Answer>>,
) -> Result<()> {
    let mut acks: std::collections::BTreeMap<String, AnswerAck> = Default::default();
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
        next = inbox.as_mut().and_then(|i| i.try_next());
    }
    for (teacher_id, ack) in acks {
        let key = keys.answer_ack(&teacher_id);
        put_message(
            session,
            keys,
            key,
            &Body::AnswerAck(ack),
            Priority::DataHigh,
        )
        .await?;
    }
    Ok(())
}

/// Train until `total_steps` env steps or `shutdown`; then write a checkpoint and tell the
/// actors to stop. With a run folder that holds a run, it continues that run.
pub async fn run(
    cfg: LearnerConfig,
    session: Session,
    shutdown: impl Future<Output = ()>,
) -> Result<Summary> {
    cfg.validate()?;
    let keys = Keys::new(&cfg.run)?;
    let mut backbone = Backbone::new(&cfg)?;
    let folder = cfg.out.as_ref().map(RunFolder::new);
    let (file, resumed, mut segments) = match &folder {
        Some(f) => {
            let (file, resumed, segments) = checkpoint::open_folder(f, &cfg, &mut backbone)?;
            (Some(file), resumed, segments)
        }
        None => (None, None, Vec::new()),
    };
    let mut reward = TrainReward {
        source: cfg.reward,
        schedule: cfg.pref.lambda_schedule,
        lambda0: cfg.pref.lambda0,
        rho: cfg.pref.rho,
        total_steps: cfg.total_steps,
        model: None,
        entropy: cfg
            .reward
            .learnt()
            .then(|| StateEntropy::new(cfg.obs_dim, cfg.pref.knn_k, cfg.pref.knn_pool)),
        lambda_scale: cfg.sac.lambda_scale,
    };
    let mut feedback = if cfg.reward.learnt() {
        let labels = folder
            .as_ref()
            .map_or_else(|| std::path::PathBuf::from(":memory:"), |f| f.labels());
        let seed = match cfg.algo {
            Algo::Sac => cfg.sac.seed,
            Algo::Ppo => cfg.ppo.seed,
        };
        Some(Feedback::new(
            &cfg.pref,
            &cfg.run,
            cfg.obs_dim,
            cfg.act_dim,
            seed,
            &labels,
        )?)
    } else {
        None
    };
    if let (Some(f), Some(r)) = (feedback.as_mut(), resumed.as_ref()) {
        if let Some(state) = &r.saved.feedback {
            f.restore(state)?;
            checkpoint::load_networks(&r.dir, f.networks())?;
            reward.entropy = state.entropy.clone();
            reward.model = f.model();
        }
    }
    let every = |n: u64| if n == 0 { u64::MAX } else { n };
    let (mut p, pending) = match resumed {
        Some(r) => {
            let mut p = r.saved.progress;
            // NOTE: versions published after the checkpoint may still be held by actors;
            // count on from above every version this run ever published.
            p.version = p
                .version
                .max(folder.as_ref().map_or(0, |f| f.published_version()))
                + 1;
            (p, r.saved.pending)
        }
        None => (
            Progress {
                version: 1,
                next_row: cfg.log_every,
                next_checkpoint: every(cfg.checkpoint_every),
                losses: [f64::NAN; 6],
                ..Progress::default()
            },
            Vec::new(),
        ),
    };
    let (resumed_at, updates_at) = (p.env_steps, p.updates);

    let server = WeightsServer::new(&session, &keys).await?;
    let mut trajectories = Inbox::trajectories(&session, &keys).await?;
    let mut eval_results = Inbox::eval_results(&session, &keys).await?;
    let mut answers = match &feedback {
        Some(_) => Some(Inbox::answers(&session, &keys).await?),
        None => None,
    };
    let teachers = Teachers {
        queries: MessagePublisher::new(&session, &keys, keys.queries(), Priority::DataHigh).await?,
        status: MessagePublisher::new(&session, &keys, keys.status(), Priority::Data).await?,
    };
    let labellers = Labellers::watch(&session, &keys).await?;
    let stop = MessagePublisher::new(&session, &keys, keys.stop(), Priority::DataHigh).await?;
    tracing::debug!(config = %serde_json::to_string(&cfg)?, "learner config");
    tracing::info!(
        run = %cfg.run,
        algo = ?cfg.algo,
        reward = cfg.reward.name(),
        steps = cfg.total_steps,
        from = p.env_steps,
        "learner starts"
    );
    let bar = cfg.progress.then(|| {
        let bar = indicatif::ProgressBar::new(cfg.total_steps);
        bar.set_style(
            indicatif::ProgressStyle::with_template(
                "{elapsed_precise} [{bar:30}] {human_pos}/{human_len} env steps, {per_sec}, {eta} left, {msg}",
            )
            .expect("the progress template is valid")
            .progress_chars("=> "),
        );
        bar.set_position(p.env_steps.min(cfg.total_steps));
        bar.reset_eta();
        bar
    });
    let mut curve = Curve::new(file, p.rows_written, bar);
    let mut actors = Actors::default();
    let seeds: Vec<u64> = (0..cfg.eval_episodes as u64)
        .map(|k| EVAL_SEED_BASE + k)
        .collect();
    let publish = |backbone: &Backbone, p: &Progress| -> Result<Weights> {
        if let Some(f) = &folder {
            f.mark_version(p.version)?;
        }
        let mut w = backbone.weights(&cfg, p.version, p.env_steps)?;
        w.acks = p.receipts.acks();
        Ok(w)
    };
    server.publish(&publish(&backbone, &p)?).await?;
    // Rows made before the checkpoint and not written: evaluated again.
    for (row, mut request) in pending {
        request.actor = 0;
        evaluation::ask(&session, &keys, &mut curve, row, request).await?;
    }
    // Queries open in the label store (asked before a restart): asked again at once.
    if let Some(f) = feedback.as_mut() {
        teachers.ask(&f.retry()?).await?;
    }

    let mut summary = Summary::default();
    let start = Instant::now();
    let wall = |p: &Progress| p.wall_s + start.elapsed().as_secs_f64();
    let mut tick = tokio::time::interval(Duration::from_secs(1));
    let mut last_checkpoint = Instant::now();
    tokio::pin!(shutdown);
    let mut stopped = false;
    while p.env_steps < cfg.total_steps {
        let msg = tokio::select! {
            _ = &mut shutdown => { stopped = true; break }
            r = eval_results.next() => {
                evaluated(&mut curve, &reward, r?)?;
                continue;
            }
            a = next_of(&mut answers) => {
                if let Some(f) = feedback.as_mut() {
                    take_answers(&session, &keys, f, a?, &mut answers).await?;
                    // NOTE: the session may be answered now: training can start.
                    f.start(p.env_steps, false)?;
                }
                continue;
            }
            done = async {
                match feedback.as_mut() {
                    Some(f) if f.busy() => f.job().await,
                    _ => std::future::pending().await,
                }
            } => {
                if let Some(f) = feedback.as_mut() {
                    let (queries, model) = f.finish(done?, p.env_steps)?;
                    teachers.ask(&queries).await?;
                    if let Some(m) = model {
                        install(m, &mut reward, &mut backbone)?;
                    }
                    f.start(p.env_steps, false)?;
                }
                continue;
            }
            _ = tick.tick() => {
                p.eval_retries += evaluation::retry(&session, &keys, &mut curve, &mut actors).await?;
                if let Some(f) = feedback.as_mut() {
                    teachers.ask(&f.retry()?).await?;
                    let s = status_of(f, p.env_steps, &labellers)?;
                    teachers.status(s).await?;
                }
                continue;
            }
            m = trajectories.next() => m?,
        };
        actors.last_seen.insert(msg.actor, Instant::now());
        // NOTE: a trajectory sent again (its actor waited long for weights) is taken once.
        if !p.receipts.take(&msg) {
            continue;
        }
        let version = msg.trajectory.policy_version;
        *summary.episodes_by_actor.entry(msg.actor).or_default() += 1;
        summary
            .first_version_by_actor
            .entry(msg.actor)
            .or_insert(version);
        summary.last_version_by_actor.insert(msg.actor, version);
        if !backbone.takes(&cfg, version, p.version) {
            p.stale += 1;
            continue;
        }
        // 1. The trajectory: kept for queries, trained on.
        if let Some(f) = feedback.as_mut() {
            f.observe(&msg);
        }
        let outcome = msg.trajectory.outcome;
        let steps = msg.trajectory.steps() as u64;
        let observed = backbone.observe(
            &cfg,
            msg.trajectory,
            &mut reward,
            p.env_steps,
            &mut p.publication,
        )?;
        p.updates += observed.updates;
        match observed.losses {
            Some(Losses::Sac(l)) => {
                p.losses[..3].copy_from_slice(&[l.critic as f64, l.actor as f64, l.alpha as f64])
            }
            Some(Losses::Ppo(s)) => p.losses[3..].copy_from_slice(&[
                s.value_loss as f64,
                s.policy_loss as f64,
                s.approx_kl as f64,
            ]),
            None => {}
        }
        p.env_steps += steps;
        p.window.add(&outcome);
        if let Some(bar) = &curve.bar {
            bar.set_position(p.env_steps.min(cfg.total_steps));
        }
        // 2. New weights, when the backbone says so.
        let mut published = None;
        if observed.publish {
            p.version += 1;
            p.publication.since = 0;
            p.publication.episodes = 0;
            p.publication.env_steps = p.env_steps;
            let w = publish(&backbone, &p)?;
            server.publish(&w).await?;
            published = Some(w);
        }
        // 3. Preference learning: a feedback session or a training, when due.
        if let Some(f) = feedback.as_mut() {
            if cfg.sync {
                sync_feedback(
                    f,
                    &mut reward,
                    &mut backbone,
                    &teachers,
                    &mut answers,
                    &session,
                    &keys,
                    p.env_steps,
                )
                .await?;
            } else {
                f.start(p.env_steps, false)?;
            }
        }
        // 4. A row of the curve.
        if p.env_steps >= p.next_row || p.env_steps >= cfg.total_steps {
            while p.next_row <= p.env_steps {
                p.next_row += cfg.log_every.max(1);
            }
            let here = start.elapsed().as_secs_f64().max(1e-9);
            let w = std::mem::take(&mut p.window);
            let n = w.episodes.max(1) as f64;
            let mut row = CurveRow {
                wall_s: wall(&p).max(1e-9),
                episodes: w.episodes,
                return_truth: w.truth / n,
                success_rate: w.success / n,
                return_human: w.human / n,
                return_task: w.task / n,
                loss_critic: p.losses[0],
                loss_actor: p.losses[1],
                alpha: p.losses[2],
                loss_value: p.losses[3],
                loss_policy: p.losses[4],
                approx_kl: p.losses[5],
                env_steps_per_s: (p.env_steps - resumed_at) as f64 / here,
                updates_per_s: (p.updates - updates_at) as f64 / here,
                updates: p.updates,
                policy_version: p.version,
                dropped_messages: trajectories.dropped.get()
                    + eval_results.dropped.get()
                    + answers.as_ref().map_or(0, |a| a.dropped.get())
                    + curve.dropped,
                stale_trajectories: p.stale,
                retried_messages: p.receipts.repeated + p.eval_retries,
                lost_messages: p.receipts.missing(),
                lambda: reward.lambda(p.env_steps),
                pretraining: reward.pretraining() as u8,
                ..CurveRow::empty(p.env_steps)
            };
            if let Some(f) = &feedback {
                let c = f.counts()?;
                row.labels_asked = c.asked;
                row.labels_answered = c.answered;
                row.labels_equal = c.equal;
                row.labels_skipped = c.skipped;
                row.labels_expired = c.expired;
                row.sessions = f.counters.sessions;
                row.reward_accuracy = f.counters.accuracy;
                row.reward_accuracy_new = f.counters.accuracy_new;
                row.retried_messages += f.counters.retried_queries;
                row.dropped_messages += f.counters.unknown_answers;
                row.labels_open = c.open;
                row.waiting_labels = f.waiting(p.env_steps)? as u8;
                row.labellers = labellers.count() as u64;
            }
            if cfg.eval_episodes == 0 {
                curve.write(row)?;
            } else {
                let request = EvalRequest {
                    id: p.env_steps,
                    actor: actors.next_live(),
                    weights: match published.take() {
                        Some(w) => w,
                        None => backbone.weights(&cfg, p.version, p.env_steps)?,
                    },
                    seeds: seeds.clone(),
                    sampled: cfg.eval_sampled,
                    // NOTE: only a learnt reward reads them (not while pretraining).
                    steps: reward.model.is_some(),
                };
                evaluation::ask(&session, &keys, &mut curve, row, request).await?;
            }
        }
        // 5. Checkpoints at a publication (PPO: no rollout half-collected; the
        // deterministic mode: the point a resumed run starts from), once the mark is passed.
        let late = cfg.checkpoint_secs > 0
            && last_checkpoint.elapsed() >= Duration::from_secs(cfg.checkpoint_secs);
        if observed.publish && (p.env_steps >= p.next_checkpoint || late) {
            last_checkpoint = Instant::now();
            while p.next_checkpoint <= p.env_steps {
                p.next_checkpoint = p
                    .next_checkpoint
                    .saturating_add(every(cfg.checkpoint_every));
            }
            if let Some(f) = &folder {
                let mut q = p.clone();
                q.wall_s = wall(&p);
                tokio::task::block_in_place(|| {
                    checkpoint::write(
                        f,
                        &cfg,
                        &backbone,
                        feedback.as_ref(),
                        reward.entropy.as_ref(),
                        &q,
                        &curve,
                        &mut segments,
                    )
                })?;
            }
        }
    }
    // The last evaluations: the actors answer while they wait for weights that will not
    // come; their last trajectories are drained so nothing blocks. Answers still coming
    // are stored meanwhile.
    while !stopped && !curve.pending.is_empty() {
        tokio::select! {
            _ = &mut shutdown => break,
            r = eval_results.next() => evaluated(&mut curve, &reward, r?)?,
            a = next_of(&mut answers) => {
                if let Some(f) = feedback.as_mut() {
                    take_answers(&session, &keys, f, a?, &mut answers).await?;
                }
            }
            _ = tick.tick() => {
                p.eval_retries += evaluation::retry(&session, &keys, &mut curve, &mut actors).await?;
            }
            m = trajectories.next() => { m?; }
        }
    }
    // Answers already received are stored (the teacher forgets them once acknowledged;
    // the queries still open are asked again by a resumed run).
    if let (Some(f), Some(first)) = (
        feedback.as_mut(),
        answers.as_mut().and_then(|i| i.try_next()),
    ) {
        take_answers(&session, &keys, f, first, &mut answers).await?;
    }
    // The final checkpoint (a stop, or the end): pending rows stay pending in it when
    // stopped, so a resumed run writes them.
    if let Some(f) = &folder {
        let mut q = p.clone();
        q.wall_s = wall(&p);
        if stopped {
            tracing::info!(env_steps = p.env_steps, "stopping: writing a checkpoint");
        } else {
            curve.flush()?;
        }
        tokio::task::block_in_place(|| {
            checkpoint::write(
                f,
                &cfg,
                &backbone,
                feedback.as_ref(),
                reward.entropy.as_ref(),
                &q,
                &curve,
                &mut segments,
            )
        })?;
        if !stopped {
            folder_finished(f, &p)?;
        }
    }
    // NOTE: a stopped run's rows that still wait for their evaluation stay in its
    // checkpoint (the resumed run writes them, evaluated), not in the curve.
    if !(stopped && folder.is_some()) {
        curve.flush()?;
    }
    if let Some(bar) = &curve.bar {
        bar.finish();
    }
    let word = Body::Stop(Stop {
        env_steps: p.env_steps,
        version: p.version,
    });
    if let Err(e) = stop.send(&word).await {
        tracing::warn!(error = %e, "could not tell the actors to stop");
    }
    summary.env_steps = p.env_steps;
    summary.updates = p.updates;
    summary.policy_version = p.version;
    summary.stale_trajectories = p.stale;
    summary.stopped = stopped;
    summary.dropped_messages += trajectories.dropped.get()
        + eval_results.dropped.get()
        + answers.as_ref().map_or(0, |a| a.dropped.get())
        + curve.dropped;
    summary.rows = std::mem::take(&mut curve.rows);
    if let Some(f) = &feedback {
        summary.labels = Some(f.counts()?);
        summary.feedback = Some(f.counters.clone());
    }
    summary.weights = Some(backbone.weights(&cfg, p.version, p.env_steps)?);
    Ok(summary)
}

/// The deterministic mode's feedback: what is due runs in place, and a session waits for
/// its answers (asking again as it goes), so a run is a function of its seed and teacher.
#[allow(clippy::too_many_arguments)]
async fn sync_feedback(
    f: &mut Feedback,
    reward: &mut TrainReward,
    backbone: &mut Backbone,
    teachers: &Teachers,
    answers: &mut Option<Inbox<pbrl_common::wire::Answer>>,
    session: &Session,
    keys: &Keys,
    env_steps: u64,
) -> Result<()> {
    let mut tick = tokio::time::interval(Duration::from_secs(1));
    while let Some(done) = tokio::task::block_in_place(|| f.start(env_steps, true))? {
        let (queries, model) = f.finish(done, env_steps)?;
        teachers.ask(&queries).await?;
        if let Some(m) = model {
            install(m, reward, backbone)?;
        }
        while f.open() > 0 {
            tokio::select! {
                a = next_of(answers) => {
                    let a = a?;
                    take_answers(session, keys, f, a, answers).await?
                }
                _ = tick.tick() => teachers.ask(&f.retry()?).await?,
            }
        }
    }
    Ok(())
}

fn folder_finished(f: &RunFolder, p: &Progress) -> Result<()> {
    let text =
        serde_json::json!({ "env_steps": p.env_steps, "version": p.version, "updates": p.updates });
    f.write_atomic(&f.finished(), text.to_string().as_bytes())?;
    Ok(())
}
