//! The teacher service: answers the learner's preference queries over Zenoh, one loop for
//! every kind of teacher ([`teach`]).
//!
//! Delivery is label-grade. Every answer is kept in the teacher's [`Outbox`] on disk before
//! it is sent, and sent again every `resend` until the learner says it committed it to the
//! label store ([`AnswerAck`]); a query asked again (the learner has not heard) gets the
//! answer given before, never a new judgement. A teacher killed and restarted on the same
//! file sends what it had answered instead of judging again, so an answer given while the
//! learner was down, or while the teacher was, reaches it once both are back.

use std::future::Future;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use anyhow::Result;
use pbrl_common::bus::{Inbox, LabellerTokens, MessagePublisher};
use pbrl_common::wire::{check_teacher_id, Answer, AnswerAck, Body, LearnerStatus, Query};
use pbrl_common::Keys;
use zenoh::qos::Priority;
use zenoh::Session;

use crate::file::TeacherFile;
use crate::human::{Desk, HumanConfig};
use crate::outbox::Outbox;
use crate::pace::{PaceConfig, Paced};
use crate::scripted::{Scripted, ScriptedConfig, TeacherKind};
pub use crate::teacher::{AtOnce, Judge, Served, Teacher, TeacherSummary};
use crate::web::{self, HttpConfig, Web};

/// How often the loop looks for answers due (people's, and those to send again).
const TICK: Duration = Duration::from_millis(250);

/// The teacher service's settings.
#[derive(Clone, Debug)]
pub struct TeacherConfig {
    pub run: String,
    /// This teacher's id (key expressions `pbrl/<run>/teacher/<id>/...`).
    pub id: String,
    /// Send unacknowledged answers again after this long.
    pub resend: Duration,
    /// The teacher's file: its outbox, and for people their queue (`:memory:` for none:
    /// answers then live only as long as the process).
    pub state: std::path::PathBuf,
}

impl TeacherConfig {
    pub fn new(run: &str, id: &str) -> Self {
        Self {
            run: run.into(),
            id: id.into(),
            resend: Duration::from_secs(5),
            state: ":memory:".into(),
        }
    }
}

/// Run a scripted teacher of `scripted`'s kind until `shutdown`.
pub async fn run(
    cfg: TeacherConfig,
    scripted: ScriptedConfig,
    session: Session,
    shutdown: impl Future<Output = ()>,
) -> Result<TeacherSummary> {
    serve(cfg, Scripted::new(scripted)?, session, shutdown).await
}

/// Run a scripted teacher of `scripted`'s kind at a person's `pace` until `shutdown`: at
/// once when the pace says so, else one answer at a time ([`Paced`]).
pub async fn run_paced(
    cfg: TeacherConfig,
    scripted: ScriptedConfig,
    pace: PaceConfig,
    session: Session,
    shutdown: impl Future<Output = ()>,
) -> Result<TeacherSummary> {
    if !pace.paced() {
        return run(cfg, scripted, session, shutdown).await;
    }
    let seed = scripted.seed;
    let teacher = Paced::new(Scripted::new(scripted)?, &cfg.id, pace, seed)?;
    let file = TeacherFile::open(&cfg.state)?;
    teach(cfg, teacher, &file, session, shutdown).await
}

/// Answer queries with `judge`, each at once, until `shutdown`.
pub async fn serve(
    cfg: TeacherConfig,
    judge: impl Judge,
    session: Session,
    shutdown: impl Future<Output = ()>,
) -> Result<TeacherSummary> {
    let teacher = AtOnce::new(judge, &cfg.id);
    let file = TeacherFile::open(&cfg.state)?;
    teach(cfg, teacher, &file, session, shutdown).await
}

/// Serve people: the labelling page on `http`, the queue on `human`'s desk, until
/// `shutdown`. Answers go to the learner once past their undo window; each person at the
/// page holds a liveliness token, so the learner knows whether anyone is labelling.
pub async fn run_human(
    cfg: TeacherConfig,
    human: HumanConfig,
    http: HttpConfig,
    world: pbrl_actor::WorldConfig,
    session: Session,
    shutdown: impl Future<Output = ()>,
) -> Result<TeacherSummary> {
    check_teacher_id("teacher id", &cfg.id)?;
    let file = TeacherFile::open(&cfg.state)?;
    let desk = Arc::new(Mutex::new(Desk::open(human, &file, &cfg.run, &cfg.id)?));
    let bound = web::bind(&http).await?;
    let addr = bound.listener.local_addr()?;
    let page = Web::new(desk.clone(), world, http.token.clone());
    let (stop_http, http_stopped) = tokio::sync::oneshot::channel::<()>();
    let server = tokio::spawn(web::serve(bound, web::router(page), async {
        let _ = http_stopped.await;
    }));
    tracing::info!(
        run = %cfg.run,
        id = %cfg.id,
        "labelling page on {}://{addr}/",
        http.scheme()
    );
    let summary = teach(cfg, desk, &file, session, shutdown).await;
    let _ = stop_http.send(());
    match server.await {
        Ok(Err(e)) => tracing::warn!(error = %e, "the labelling page failed"),
        Err(e) => tracing::warn!(error = %e, "the labelling page's task died"),
        Ok(Ok(())) => {}
    }
    summary
}

/// The teacher's side of the bus: queries and acknowledgements in, the learner's status
/// (for people's page), answers out, people's liveliness tokens.
struct TeacherBus {
    queries: Inbox<Box<Query>>,
    acks: Inbox<AnswerAck>,
    status: Inbox<LearnerStatus>,
    answers: MessagePublisher,
    labellers: LabellerTokens,
}

impl TeacherBus {
    async fn open(session: &Session, cfg: &TeacherConfig) -> Result<Self> {
        let keys = Keys::new(&cfg.run)?;
        Ok(Self {
            queries: Inbox::queries(session, &keys).await?,
            acks: Inbox::answer_acks(session, &keys, &cfg.id).await?,
            status: Inbox::status(session, &keys).await?,
            answers: MessagePublisher::new(
                session,
                &keys,
                keys.answer(&cfg.id),
                Priority::DataHigh,
            )
            .await?,
            labellers: LabellerTokens::new(session, &keys, &cfg.id),
        })
    }

    async fn send(&self, answers: impl IntoIterator<Item = Answer>) -> Result<()> {
        for a in answers {
            self.answers.send(&Body::Answer(a)).await?;
        }
        Ok(())
    }

    /// Malformed messages, or another run's, dropped.
    fn dropped(&self) -> u64 {
        self.queries.dropped.get() + self.acks.dropped.get() + self.status.dropped.get()
    }
}

/// Answer queries with `teacher` until `shutdown`: every answer kept in the outbox in the
/// teacher's `file` (`cfg.state`) before it is sent, and sent again every `cfg.resend`
/// until acknowledged.
pub async fn teach(
    cfg: TeacherConfig,
    teacher: impl Teacher,
    file: &TeacherFile,
    session: Session,
    shutdown: impl Future<Output = ()>,
) -> Result<TeacherSummary> {
    check_teacher_id("teacher id", &cfg.id)?;
    let mut served = Served::new(teacher, Outbox::open(file, &cfg.id)?);
    let mut bus = TeacherBus::open(&session, &cfg).await?;
    let kind = served.teacher.kind();
    tracing::info!(run = %cfg.run, id = %cfg.id, %kind, "teacher ready");
    let mut tick = tokio::time::interval(TICK);
    tokio::pin!(shutdown);
    loop {
        tokio::select! {
            _ = &mut shutdown => break,
            q = bus.queries.next() => bus.send(served.receive(*q?)?).await?,
            a = bus.acks.next() => {
                served.acknowledged(&a?)?;
            }
            s = bus.status.next() => served.teacher.learner_status(s?),
            _ = tick.tick() => {
                bus.send(served.due(cfg.resend)?).await?;
                bus.labellers.hold(&served.teacher.present()).await?;
            }
        }
    }
    let mut summary = served.summary.clone();
    summary.dropped = bus.dropped();
    let open = served.unacknowledged();
    if open > 0 {
        tracing::warn!(
            open,
            "stopping with answers the learner has not acknowledged (kept in the outbox: sent when the teacher is back, or given again when asked)"
        );
    }
    Ok(summary)
}

/// The default id of a teacher of `kind` with `seed`.
pub fn default_id(kind: TeacherKind, seed: u64) -> String {
    format!("{}-{seed}", kind.name())
}
