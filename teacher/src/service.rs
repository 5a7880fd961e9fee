//! The teacher service: answers the learner's preference queries over Zenoh.
//!
//! Delivery is label-grade. A query comes again until the learner has stored its answer,
//! so the teacher keeps every answer it gave and, asked again, sends the same answer (it
//! never judges a query twice). An answer stays unacknowledged until the learner says it
//! committed it to the label store ([`AnswerAck`]); unacknowledged answers are sent again
//! every `resend_s` seconds, so an answer given while the learner was down reaches it
//! once it is back. A scripted teacher can lose nothing by dying: the learner asks its
//! open queries again of the next one.

use std::collections::{BTreeMap, HashMap};
use std::future::Future;
use std::time::{Duration, Instant};

use anyhow::Result;
use pbrl_common::bus::{Inbox, MessagePublisher};
use pbrl_common::wire::{check_teacher_id, Answer, AnswerAck, Body, Preference, Query};
use pbrl_common::Keys;
use zenoh::qos::Priority;
use zenoh::Session;

use crate::scripted::{Scripted, ScriptedConfig, TeacherKind};

/// Whoever judges queries: a scripted teacher, or (next) a person.
pub trait Teacher: Send {
    /// The kind of teacher, as the label store records it.
    fn kind(&self) -> String;
    /// Judge a query.
    fn judge(&mut self, q: &Query) -> Preference;
}

impl Teacher for Scripted {
    fn kind(&self) -> String {
        self.config().kind.name().to_string()
    }

    fn judge(&mut self, q: &Query) -> Preference {
        self.answer(&q.first.truth, &q.second.truth)
    }
}

/// The teacher service's settings.
#[derive(Clone, Debug)]
pub struct TeacherConfig {
    pub run: String,
    /// This teacher's id (key expressions `pbrl/<run>/teacher/<id>/...`).
    pub id: String,
    /// Send unacknowledged answers again after this long.
    pub resend: Duration,
}

impl TeacherConfig {
    pub fn new(run: &str, id: &str) -> Self {
        Self {
            run: run.into(),
            id: id.into(),
            resend: Duration::from_secs(5),
        }
    }
}

/// What a teacher did.
#[derive(Clone, Debug, Default)]
pub struct TeacherSummary {
    /// Queries judged (each once).
    pub judged: u64,
    /// Answers by kind: first, second, equal, skip.
    pub by_kind: BTreeMap<&'static str, u64>,
    /// Answers sent again (asked again, or unacknowledged for a while).
    pub resent: u64,
    /// Answers the learner acknowledged.
    pub acknowledged: u64,
    /// Malformed messages, or another run's, dropped.
    pub dropped: u64,
}

/// Run a scripted teacher of `scripted`'s kind until `shutdown`.
pub async fn run(
    cfg: TeacherConfig,
    scripted: ScriptedConfig,
    session: Session,
    shutdown: impl Future<Output = ()>,
) -> Result<TeacherSummary> {
    let teacher = Scripted::new(scripted)?;
    serve(cfg, teacher, session, shutdown).await
}

/// An answer given and not yet acknowledged.
struct Given {
    answer: Answer,
    sent: Instant,
    acknowledged: bool,
}

/// Answer queries with `teacher` until `shutdown`.
pub async fn serve(
    cfg: TeacherConfig,
    mut teacher: impl Teacher,
    session: Session,
    shutdown: impl Future<Output = ()>,
) -> Result<TeacherSummary> {
    check_teacher_id("teacher id", &cfg.id)?;
    let keys = Keys::new(&cfg.run)?;
    let mut queries = Inbox::queries(&session, &keys).await?;
    let mut acks = Inbox::answer_acks(&session, &keys, &cfg.id).await?;
    let answers =
        MessagePublisher::new(&session, &keys, keys.answer(&cfg.id), Priority::DataHigh).await?;
    tracing::info!(run = %cfg.run, id = %cfg.id, kind = %teacher.kind(), "teacher ready");
    let mut given: HashMap<u64, Given> = HashMap::new();
    let mut summary = TeacherSummary::default();
    let mut tick = tokio::time::interval(Duration::from_secs(1));
    tokio::pin!(shutdown);
    loop {
        tokio::select! {
            _ = &mut shutdown => break,
            q = queries.next() => {
                let q = q?;
                let answer = match given.get_mut(&q.id) {
                    // NOTE: asked again: the learner has not stored it; the same answer.
                    Some(g) => {
                        summary.resent += 1;
                        g.sent = Instant::now();
                        g.answer.clone()
                    }
                    None => {
                        let start = Instant::now();
                        let preference = teacher.judge(&q);
                        let answer = Answer::scripted(
                            q.id,
                            preference,
                            &teacher.kind(),
                            &cfg.id,
                            start.elapsed().as_millis() as u64,
                        );
                        summary.judged += 1;
                        *summary.by_kind.entry(preference.name()).or_default() += 1;
                        given.insert(q.id, Given { answer: answer.clone(), sent: Instant::now(), acknowledged: false });
                        answer
                    }
                };
                answers.send(&Body::Answer(answer)).await?;
            }
            a = acks.next() => {
                let AnswerAck { queries: ids, .. } = a?;
                for id in ids {
                    if let Some(g) = given.get_mut(&id) {
                        if !g.acknowledged {
                            g.acknowledged = true;
                            summary.acknowledged += 1;
                        }
                    }
                }
            }
            _ = tick.tick() => {
                for g in given.values_mut() {
                    if !g.acknowledged && g.sent.elapsed() >= cfg.resend {
                        g.sent = Instant::now();
                        summary.resent += 1;
                        answers.send(&Body::Answer(g.answer.clone())).await?;
                    }
                }
            }
        }
    }
    summary.dropped = queries.dropped.get() + acks.dropped.get();
    let open = given.values().filter(|g| !g.acknowledged).count();
    if open > 0 {
        tracing::warn!(
            open,
            "stopping with answers the learner has not acknowledged (it asks those queries again)"
        );
    }
    Ok(summary)
}

/// The default id of a teacher of `kind` with `seed`.
pub fn default_id(kind: TeacherKind, seed: u64) -> String {
    format!("{}-{seed}", kind.name())
}

/// Serve people: the labelling page on `http`, the queue on `human`'s desk, until
/// `shutdown`. Answers go to the learner once past their undo window, again every
/// `cfg.resend` until acknowledged; each person at the page holds a liveliness token, so
/// the learner knows whether anyone is labelling.
pub async fn run_human(
    cfg: TeacherConfig,
    human: crate::human::HumanConfig,
    http: crate::web::HttpConfig,
    world: pbrl_actor::WorldConfig,
    session: Session,
    shutdown: impl Future<Output = ()>,
) -> Result<TeacherSummary> {
    use std::sync::{Arc, Mutex};
    check_teacher_id("teacher id", &cfg.id)?;
    let keys = Keys::new(&cfg.run)?;
    let desk = Arc::new(Mutex::new(crate::human::Desk::open(
        human, &cfg.run, &cfg.id,
    )?));
    let listener = crate::web::bind(&http).await?;
    let addr = listener.local_addr()?;
    let web = crate::web::Web::new(desk.clone(), world, http.token.clone());
    let (stop_http, http_stopped) = tokio::sync::oneshot::channel::<()>();
    let server = tokio::spawn(async move {
        axum::serve(listener, crate::web::router(web))
            .with_graceful_shutdown(async {
                let _ = http_stopped.await;
            })
            .await
    });
    let mut queries = Inbox::queries(&session, &keys).await?;
    let mut acks = Inbox::answer_acks(&session, &keys, &cfg.id).await?;
    let mut status = Inbox::status(&session, &keys).await?;
    let answers =
        MessagePublisher::new(&session, &keys, keys.answer(&cfg.id), Priority::DataHigh).await?;
    let lock = || crate::web::lock(&desk);
    tracing::info!(run = %cfg.run, id = %cfg.id, "labelling page on http://{addr}/");
    let mut summary = TeacherSummary::default();
    let mut tokens: HashMap<String, zenoh::liveliness::LivelinessToken> = HashMap::new();
    let mut tick = tokio::time::interval(Duration::from_millis(250));
    let resend_ms = cfg.resend.as_millis() as u64;
    tokio::pin!(shutdown);
    loop {
        tokio::select! {
            _ = &mut shutdown => break,
            q = queries.next() => {
                let again = lock().receive(*q?)?;
                if let Some(a) = again {
                    summary.resent += 1;
                    answers.send(&Body::Answer(a)).await?;
                }
            }
            a = acks.next() => {
                let a = a?;
                summary.acknowledged += lock().acknowledged(&a.queries, &a.repeats)?;
            }
            s = status.next() => lock().learner_status(s?),
            _ = tick.tick() => {
                let due = lock().due(resend_ms)?;
                for a in due {
                    summary.judged += 1;
                    *summary.by_kind.entry(a.preference.name()).or_default() += 1;
                    answers.send(&Body::Answer(a)).await?;
                }
                let present = lock().present();
                tokens.retain(|name, _| present.contains(name));
                for name in present {
                    if let std::collections::hash_map::Entry::Vacant(e) = tokens.entry(name) {
                        let key = keys.labeller(&cfg.id, e.key());
                        let token = session
                            .liveliness()
                            .declare_token(key)
                            .await
                            .map_err(|err| anyhow::anyhow!("declaring {}'s liveliness: {err}", e.key()))?;
                        e.insert(token);
                    }
                }
            }
        }
    }
    let _ = stop_http.send(());
    match server.await {
        Ok(Err(e)) => tracing::warn!(error = %e, "the labelling page failed"),
        Err(e) => tracing::warn!(error = %e, "the labelling page's task died"),
        Ok(Ok(())) => {}
    }
    summary.dropped = queries.dropped.get() + acks.dropped.get() + status.dropped.get();
    let open = lock().unacknowledged();
    if open > 0 {
        tracing::warn!(
            open,
            "stopping with answers the learner has not acknowledged (kept on disk; sent when the teacher is back)"
        );
    }
    Ok(summary)
}
