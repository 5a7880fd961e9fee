//! The learner's side of the bus, declared in one place: what it reads (trajectories,
//! evaluations, answers), what it publishes (weights, evaluation requests, queries, answer
//! acknowledgements, its status, the stop), the people labelling now, and the one count of
//! the messages its inboxes refused.

use std::collections::BTreeMap;

use anyhow::Result;
use pbrl_common::bus::{put_message, Inbox, Labellers, MessagePublisher, WeightsServer};
use pbrl_common::wire::{
    Answer, AnswerAck, Body, EvalRequest, EvalResult, LearnerStatus, Stop, TrajectoryMsg, Weights,
};
use pbrl_common::Keys;

use crate::pref::feedback::Outgoing;
use zenoh::qos::Priority;
use zenoh::Session;

pub struct LearnerBus {
    session: Session,
    keys: Keys,
    weights: WeightsServer,
    pub trajectories: Inbox<TrajectoryMsg>,
    pub eval_results: Inbox<EvalResult>,
    pub answers: Answers,
    queries: MessagePublisher,
    status: MessagePublisher,
    stop: MessagePublisher,
    labellers: Labellers,
}

impl LearnerBus {
    /// Declare the learner's subscriptions and publishers for run `keys`; `answers`: it
    /// asks teachers (a learnt reward).
    pub async fn open(session: &Session, keys: Keys, answers: bool) -> Result<Self> {
        let weights = WeightsServer::new(session, &keys).await?;
        let trajectories = Inbox::trajectories(session, &keys).await?;
        let eval_results = Inbox::eval_results(session, &keys).await?;
        let answers = Answers(match answers {
            true => Some(Inbox::answers(session, &keys).await?),
            false => None,
        });
        let queries =
            MessagePublisher::new(session, &keys, keys.queries(), Priority::DataHigh).await?;
        let status = MessagePublisher::new(session, &keys, keys.status(), Priority::Data).await?;
        let labellers = Labellers::watch(session, &keys).await?;
        let stop = MessagePublisher::new(session, &keys, keys.stop(), Priority::DataHigh).await?;
        Ok(Self {
            session: session.clone(),
            keys,
            weights,
            trajectories,
            eval_results,
            answers,
            queries,
            status,
            stop,
            labellers,
        })
    }

    /// Messages the inboxes refused (malformed, of another run, over their caps) in this
    /// process.
    pub fn dropped(&self) -> u64 {
        self.trajectories.dropped.get()
            + self.eval_results.dropped.get()
            + self.answers.0.as_ref().map_or(0, |a| a.dropped.get())
    }

    /// People labelling now.
    pub fn labellers(&self) -> u64 {
        self.labellers.count() as u64
    }

    pub async fn publish(&self, w: &Weights) -> Result<()> {
        self.weights.publish(w).await
    }

    /// Send queries, as the label store keeps them.
    pub async fn ask(&self, queries: &[Outgoing]) -> Result<()> {
        for q in queries {
            self.queries.send_encoded(&q.message).await?;
        }
        Ok(())
    }

    /// Acknowledge stored answers, one message per teacher.
    pub async fn acknowledge(&self, acks: BTreeMap<String, AnswerAck>) -> Result<()> {
        for (teacher_id, ack) in acks {
            let key = self.keys.answer_ack(&teacher_id);
            let body = Body::AnswerAck(ack);
            put_message(&self.session, &self.keys, key, &body, Priority::DataHigh).await?;
        }
        Ok(())
    }

    /// Tell teachers (and the people at their pages) where the learner stands.
    pub async fn status(&self, s: LearnerStatus) -> Result<()> {
        self.status.send(&Body::Status(s)).await
    }

    /// Ask the request's actor for an evaluation.
    pub async fn evaluate(&self, request: &EvalRequest) -> Result<()> {
        let key = self.keys.eval_request(request.actor);
        let body = Body::EvalRequest(Box::new(request.clone()));
        put_message(&self.session, &self.keys, key, &body, Priority::Data).await
    }

    /// Tell the actors to stop.
    pub async fn stop(&self, s: Stop) -> Result<()> {
        self.stop.send(&Body::Stop(s)).await
    }
}

/// Teachers' answers (learnt rewards only; without one, none ever comes).
pub struct Answers(Option<Inbox<Answer>>);

impl Answers {
    /// The next answer (cancel-safe).
    pub async fn next(&mut self) -> Result<Answer> {
        match &mut self.0 {
            Some(i) => i.next().await,
            None => std::future::pending().await,
        }
    }

    /// An answer already received, if any.
    pub fn waiting(&mut self) -> Option<Answer> {
        self.0.as_mut().and_then(|i| i.try_next())
    }
}
