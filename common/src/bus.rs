//! Weights, trajectories, evaluations and the stop over Zenoh, with the quality of service
//! each needs.
//!
//! - Weights: `CongestionControl::Block` at `Priority::DataHigh`, never dropped; the learner
//!   also answers queries with the newest weights, so an actor that joins late, or one that
//!   waited too long for the next version, gets the current one at once.
//! - Trajectories: `Block` at `Priority::Data` (whole episodes, 60-70 KB each; a plain put
//!   uses `Drop`, and large messages sent that way are known to be lost), numbered per actor
//!   and kept by the actor until the learner acknowledges them in a weights message.
//!
//! The receive path never waits on the service's work. Zenoh calls a subscriber's handler
//! on the thread that read the message from the network; a bounded channel there (zenoh's
//! default `FifoChannelHandler`, 256 samples) blocks that thread once the service falls
//! behind, the sender's queue towards it fills, and after `wait_before_close` zenoh closes
//! the transport and drops what was queued. Worse, in one process every session shares
//! zenoh's two receive threads: two of them blocked pushing towards a session whose reader
//! is waiting for a thread is a deadlock only that close breaks. So every receiver here is
//! an [`Inbox`]: its callback decodes and checks the message (bounded work) and hands it to
//! an unbounded queue, never waiting. What the queue holds is bounded by the application's
//! flow control (each weights message's episode share; one evaluation per curve row; the
//! newest weights only), and a hard cap far above that drops and counts what a sender that
//! ignores flow control (a foreign client) sends beyond it.
//!
//! Receivers decode with [`crate::wire::decode`]; a message that does not decode, is too
//! large, comes from another run or format, or holds bad numbers is dropped with a warning
//! and counted.

use std::collections::{BTreeMap, BTreeSet, VecDeque};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use anyhow::{anyhow, Result};
use serde::{Deserialize, Serialize};
use tokio::sync::{mpsc, watch};
use zenoh::pubsub::{Publisher, Subscriber};
use zenoh::qos::{CongestionControl, Priority};
use zenoh::query::Query;
use zenoh::sample::Sample;
use zenoh::Session;

use crate::keys::Keys;
use crate::trajectory::Trajectory;
use crate::wire::{self, Ack, Body, EvalRequest, EvalResult, Stop, TrajectoryMsg, Weights};

fn zerr(what: &'static str) -> impl FnOnce(zenoh::Error) -> anyhow::Error {
    move |e| anyhow!("{what}: {e}")
}

/// Count of messages a receiver refused.
#[derive(Clone, Debug, Default)]
pub struct Dropped(Arc<std::sync::atomic::AtomicU64>);

impl Dropped {
    pub fn get(&self) -> u64 {
        self.0.load(std::sync::atomic::Ordering::Relaxed)
    }
    fn add(&self) {
        self.0.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    }
}

/// Decode one sample for `run`, expecting a body `pick` accepts; anything else is dropped
/// with a warning and counted.
fn accept<T>(
    run: &str,
    sample: &Sample,
    dropped: &Dropped,
    pick: impl Fn(Body) -> Option<T>,
) -> Option<T> {
    let len = sample.payload().len();
    if len > wire::MAX_MESSAGE_BYTES {
        dropped.add();
        tracing::warn!(key = %sample.key_expr(), bytes = len, "dropped a message too large to be pbrl's");
        return None;
    }
    let bytes = sample.payload().to_bytes();
    match wire::decode(run, &bytes).map(&pick) {
        Ok(Some(t)) => Some(t),
        Ok(None) => {
            dropped.add();
            tracing::warn!(key = %sample.key_expr(), "dropped a message of the wrong kind");
            None
        }
        Err(e) => {
            dropped.add();
            tracing::warn!(key = %sample.key_expr(), error = %e, "dropped a message");
            None
        }
    }
}

/// Weights queries waiting for their answer at most (a flood beyond goes unanswered).
const QUERIES_HELD: usize = 64;

/// The learner's side of the weights: publish, and answer queries for the newest.
pub struct WeightsServer {
    run: String,
    publisher: Publisher<'static>,
    latest: Arc<Mutex<Option<Vec<u8>>>>,
    task: tokio::task::JoinHandle<()>,
}

impl WeightsServer {
    pub async fn new(session: &Session, keys: &Keys) -> Result<Self> {
        let publisher = session
            .declare_publisher(keys.weights())
            .congestion_control(CongestionControl::Block)
            .priority(Priority::DataHigh)
            .await
            .map_err(zerr("declaring the weights publisher"))?;
        // NOTE: the callback only queues the query (at most QUERIES_HELD; a flood beyond
        // goes unanswered); a task replies, so the receive path never waits on a reply.
        let (tx, mut rx) = mpsc::unbounded_channel::<Query>();
        let held = Arc::new(AtomicUsize::new(0));
        let in_callback = held.clone();
        let queryable = session
            .declare_queryable(keys.weights())
            .callback(move |query| {
                if in_callback.fetch_add(1, Ordering::Relaxed) >= QUERIES_HELD
                    || tx.send(query).is_err()
                {
                    in_callback.fetch_sub(1, Ordering::Relaxed);
                }
            })
            .await
            .map_err(zerr("declaring the weights queryable"))?;
        let latest: Arc<Mutex<Option<Vec<u8>>>> = Arc::default();
        let shared = latest.clone();
        let task = tokio::spawn(async move {
            let _queryable = queryable;
            while let Some(query) = rx.recv().await {
                held.fetch_sub(1, Ordering::Relaxed);
                let bytes = shared.lock().ok().and_then(|l| l.clone());
                if let Some(bytes) = bytes {
                    if let Err(e) = query.reply(query.key_expr().clone(), bytes).await {
                        tracing::warn!(error = %e, "could not answer a weights query");
                    }
                }
            }
        });
        Ok(Self {
            run: keys.run().to_string(),
            publisher,
            latest,
            task,
        })
    }

    /// Publish `w` and keep it as the answer to queries.
    pub async fn publish(&self, w: &Weights) -> Result<()> {
        let bytes = wire::encode(&self.run, &Body::Weights(w.clone()));
        if let Ok(mut l) = self.latest.lock() {
            *l = Some(bytes.clone());
        }
        self.publisher
            .put(bytes)
            .await
            .map_err(zerr("publishing weights"))
    }

    /// Whether any subscriber for weights is known (declarations travel asynchronously).
    pub async fn has_subscribers(&self) -> Result<bool> {
        has_subscribers(&self.publisher).await
    }
}

impl Drop for WeightsServer {
    fn drop(&mut self) {
        self.task.abort();
    }
}

/// A subscription whose messages wait in an unbounded queue for the service: the callback
/// decodes, checks and queues, and never waits (see the module's note). Holds at most `cap`
/// messages; beyond that a message is dropped with a warning and counted.
pub struct Inbox<T> {
    key: String,
    rx: mpsc::UnboundedReceiver<T>,
    held: Arc<AtomicUsize>,
    pub dropped: Dropped,
    _subscriber: Subscriber<()>,
}

impl<T: Send + 'static> Inbox<T> {
    /// Subscribe to `key` (of run `keys`), keeping the messages `pick` accepts.
    pub async fn new(
        session: &Session,
        keys: &Keys,
        key: String,
        cap: usize,
        pick: impl Fn(Body) -> Option<T> + Send + Sync + 'static,
    ) -> Result<Self> {
        let (tx, rx) = mpsc::unbounded_channel();
        let held = Arc::new(AtomicUsize::new(0));
        let dropped = Dropped::default();
        let (run, h, d) = (keys.run().to_string(), held.clone(), dropped.clone());
        let subscriber = session
            .declare_subscriber(key.as_str())
            .callback(move |sample| {
                // NOTE: this runs on zenoh's receive thread (or, for a session's own put, the
                // sender's): it must never wait on the service.
                let Some(t) = accept(&run, &sample, &d, &pick) else {
                    return;
                };
                if h.fetch_add(1, Ordering::Relaxed) >= cap {
                    h.fetch_sub(1, Ordering::Relaxed);
                    d.add();
                    tracing::warn!(key = %sample.key_expr(), cap, "dropped a message: the receiver holds as many as flow control allows (a sender that ignores it?)");
                    return;
                }
                if tx.send(t).is_err() {
                    h.fetch_sub(1, Ordering::Relaxed);
                }
            })
            .await
            .map_err(|e| anyhow!("subscribing to {key}: {e}"))?;
        Ok(Self {
            key,
            rx,
            held,
            dropped,
            _subscriber: subscriber,
        })
    }

    /// The next message (cancel-safe: a message is taken only when this returns).
    pub async fn next(&mut self) -> Result<T> {
        match self.rx.recv().await {
            Some(t) => {
                self.held.fetch_sub(1, Ordering::Relaxed);
                Ok(t)
            }
            None => Err(anyhow!("the subscription to {} closed", self.key)),
        }
    }

    /// A message already received, if any.
    pub fn try_next(&mut self) -> Option<T> {
        let t = self.rx.try_recv().ok()?;
        self.held.fetch_sub(1, Ordering::Relaxed);
        Some(t)
    }

    /// Messages waiting.
    pub fn held(&self) -> usize {
        self.held.load(Ordering::Relaxed)
    }
}

/// Caps on what an inbox holds, each far above what flow control lets through.
pub mod caps {
    /// Trajectories: flow control lets each actor run its share (plus one) per version.
    pub const TRAJECTORIES: usize = 4096;
    /// Evaluation results: one per pending curve row, and a repeat or two.
    pub const EVAL_RESULTS: usize = 256;
    /// Evaluation requests to one actor: one per pending curve row.
    pub const EVAL_REQUESTS: usize = 256;
    /// Stops.
    pub const STOPS: usize = 16;
    /// Queries at a teacher: a session's worth, asked again while unanswered.
    pub const QUERIES: usize = 16_384;
    /// Answers at the learner: one per open query, and repeats.
    pub const ANSWERS: usize = 16_384;
    /// Acknowledgements at a teacher.
    pub const ANSWER_ACKS: usize = 4096;
}

impl Inbox<Box<wire::Query>> {
    /// A teacher's subscription to the learner's queries.
    pub async fn queries(session: &Session, keys: &Keys) -> Result<Self> {
        Self::new(session, keys, keys.queries(), caps::QUERIES, |b| match b {
            Body::Query(q) => Some(q),
            _ => None,
        })
        .await
    }
}

impl Inbox<wire::Answer> {
    /// The learner's subscription to every teacher's answers.
    pub async fn answers(session: &Session, keys: &Keys) -> Result<Self> {
        Self::new(
            session,
            keys,
            keys.all_answers(),
            caps::ANSWERS,
            |b| match b {
                Body::Answer(a) => Some(a),
                _ => None,
            },
        )
        .await
    }
}

impl Inbox<wire::AnswerAck> {
    /// Teacher `teacher`'s acknowledgements from the learner.
    pub async fn answer_acks(session: &Session, keys: &Keys, teacher: &str) -> Result<Self> {
        Self::new(
            session,
            keys,
            keys.answer_ack(teacher),
            caps::ANSWER_ACKS,
            |b| match b {
                Body::AnswerAck(a) => Some(a),
                _ => None,
            },
        )
        .await
    }
}

impl Inbox<wire::LearnerStatus> {
    /// A teacher's subscription to the learner's status.
    pub async fn status(session: &Session, keys: &Keys) -> Result<Self> {
        Self::new(session, keys, keys.status(), caps::STOPS, |b| match b {
            Body::Status(s) => Some(s),
            _ => None,
        })
        .await
    }
}

impl Inbox<TrajectoryMsg> {
    /// The learner's subscription to every actor's trajectories.
    pub async fn trajectories(session: &Session, keys: &Keys) -> Result<Self> {
        Self::new(
            session,
            keys,
            keys.all_trajectories(),
            caps::TRAJECTORIES,
            |b| match b {
                Body::Trajectory(t) => Some(*t),
                _ => None,
            },
        )
        .await
    }
}

impl Inbox<EvalResult> {
    /// The learner's subscription to every actor's evaluation results.
    pub async fn eval_results(session: &Session, keys: &Keys) -> Result<Self> {
        Self::new(
            session,
            keys,
            keys.all_eval_results(),
            caps::EVAL_RESULTS,
            |b| match b {
                Body::EvalResult(r) => Some(r),
                _ => None,
            },
        )
        .await
    }
}

impl Inbox<Box<EvalRequest>> {
    /// Actor `actor`'s evaluation requests.
    pub async fn eval_requests(session: &Session, keys: &Keys, actor: u32) -> Result<Self> {
        Self::new(
            session,
            keys,
            keys.eval_request(actor),
            caps::EVAL_REQUESTS,
            |b| match b {
                Body::EvalRequest(r) => Some(r),
                _ => None,
            },
        )
        .await
    }
}

impl Inbox<Stop> {
    /// The learner's stop, as an actor receives it.
    pub async fn stops(session: &Session, keys: &Keys) -> Result<Self> {
        Self::new(session, keys, keys.stop(), caps::STOPS, |b| match b {
            Body::Stop(s) => Some(s),
            _ => None,
        })
        .await
    }
}

/// The actor's side of the weights: the callback keeps only the newest version received.
pub struct WeightsClient {
    run: String,
    key: String,
    newest: watch::Receiver<Option<Weights>>,
    pub dropped: Dropped,
    _subscriber: Subscriber<()>,
}

impl WeightsClient {
    pub async fn new(session: &Session, keys: &Keys) -> Result<Self> {
        let (tx, newest) = watch::channel::<Option<Weights>>(None);
        let dropped = Dropped::default();
        let (run, d) = (keys.run().to_string(), dropped.clone());
        let subscriber = session
            .declare_subscriber(keys.weights())
            .callback(move |sample| {
                // NOTE: on zenoh's receive thread; keeping the newest never waits.
                let Some(w) = accept(&run, &sample, &d, weights_body) else {
                    return;
                };
                tx.send_if_modified(|held| {
                    let newer = held.as_ref().is_none_or(|h| w.version > h.version);
                    if newer {
                        *held = Some(w);
                    }
                    newer
                });
            })
            .await
            .map_err(zerr("declaring the weights subscriber"))?;
        Ok(Self {
            run: keys.run().to_string(),
            key: keys.weights(),
            newest,
            dropped,
            _subscriber: subscriber,
        })
    }

    /// Ask the learner for its newest weights (an actor that joins late, or that waited
    /// too long for the next version); `None` when no learner answered within `timeout`.
    pub async fn fetch(&self, session: &Session, timeout: Duration) -> Result<Option<Weights>> {
        let replies = session
            .get(self.key.as_str())
            .timeout(timeout)
            .await
            .map_err(zerr("querying the newest weights"))?;
        let mut best: Option<Weights> = None;
        while let Ok(reply) = replies.recv_async().await {
            let Ok(sample) = reply.result() else { continue };
            if let Some(w) = accept(&self.run, sample, &self.dropped, weights_body) {
                keep_newest(&mut best, w);
            }
        }
        Ok(best)
    }

    /// The newest weights that arrived since the last call, without waiting.
    pub fn newest(&mut self) -> Option<Weights> {
        if self.newest.has_changed().unwrap_or(false) {
            self.newest.borrow_and_update().clone()
        } else {
            None
        }
    }

    /// Wait for weights newer than the last ones taken (cancel-safe).
    pub async fn next(&mut self) -> Result<Weights> {
        loop {
            self.newest
                .changed()
                .await
                .map_err(|_| anyhow!("the weights subscription closed"))?;
            if let Some(w) = self.newest.borrow_and_update().clone() {
                return Ok(w);
            }
        }
    }
}

/// The weights a message holds, if it is weights.
fn weights_body(b: Body) -> Option<Weights> {
    match b {
        Body::Weights(w) => Some(w),
        _ => None,
    }
}

/// Keep `w` in `best` if it is a newer version.
fn keep_newest(best: &mut Option<Weights>, w: Weights) {
    if best.as_ref().is_none_or(|b| w.version > b.version) {
        *best = Some(w);
    }
}

/// Trajectories an actor keeps for sending again at least (flow control keeps it at its
/// share of one or two versions; [`TrajectoryPublisher::hold_at_most`] raises it).
const UNACKED_HELD: usize = 64;

/// An actor's trajectory publisher: numbers each trajectory and keeps it until the learner
/// acknowledges it, so that one lost on the way (a closed transport, a learner restarted)
/// is sent again.
pub struct TrajectoryPublisher {
    run: String,
    actor: u32,
    incarnation: u64,
    next_seq: u64,
    unacked: VecDeque<(u64, Vec<u8>)>,
    held_at_most: usize,
    publisher: Publisher<'static>,
    /// Trajectories sent again.
    pub resent: u64,
    /// Trajectories forgotten unacknowledged (the learner acknowledged nothing for long).
    pub forgotten: u64,
}

impl TrajectoryPublisher {
    pub async fn new(session: &Session, keys: &Keys, actor: u32) -> Result<Self> {
        let publisher = session
            .declare_publisher(keys.trajectory(actor))
            .congestion_control(CongestionControl::Block)
            .priority(Priority::Data)
            .await
            .map_err(zerr("declaring the trajectory publisher"))?;
        Ok(Self {
            run: keys.run().to_string(),
            actor,
            incarnation: incarnation(actor),
            next_seq: 0,
            unacked: VecDeque::new(),
            held_at_most: UNACKED_HELD,
            publisher,
            resent: 0,
            forgotten: 0,
        })
    }

    /// Publish a training trajectory.
    pub async fn publish(&mut self, trajectory: Trajectory) -> Result<()> {
        if self.unacked.len() >= self.held_at_most {
            self.unacked.pop_front();
            if self.forgotten == 0 {
                tracing::warn!(
                    actor = self.actor,
                    held = self.held_at_most,
                    "the learner acknowledges nothing; forgetting the oldest trajectories kept for it"
                );
            }
            self.forgotten += 1;
        }
        let msg = TrajectoryMsg {
            actor: self.actor,
            incarnation: self.incarnation,
            seq: self.next_seq,
            oldest: self.unacked.front().map_or(self.next_seq, |(s, _)| *s),
            trajectory,
        };
        let bytes = wire::encode(&self.run, &Body::Trajectory(Box::new(msg)));
        self.unacked.push_back((self.next_seq, bytes.clone()));
        self.next_seq += 1;
        self.publisher
            .put(bytes)
            .await
            .map_err(zerr("publishing a trajectory"))
    }

    /// Keep at most `n` unacknowledged trajectories (never fewer than a floor of 64): the
    /// actor's share of two versions.
    pub fn hold_at_most(&mut self, n: usize) {
        self.held_at_most = n.max(UNACKED_HELD);
    }

    /// Forget the trajectories `acks` says the learner holds.
    pub fn acknowledge(&mut self, acks: &[Ack]) {
        let Some(a) = acks
            .iter()
            .find(|a| a.actor == self.actor && a.incarnation == self.incarnation)
        else {
            return;
        };
        while self.unacked.front().is_some_and(|(s, _)| *s < a.next_seq) {
            self.unacked.pop_front();
        }
    }

    /// Trajectories sent and not acknowledged yet.
    pub fn unacknowledged(&self) -> usize {
        self.unacked.len()
    }

    /// Send every unacknowledged trajectory again (the learner takes each once).
    pub async fn resend(&mut self) -> Result<usize> {
        for (_, bytes) in &self.unacked {
            self.publisher
                .put(bytes.clone())
                .await
                .map_err(zerr("publishing a trajectory again"))?;
        }
        self.resent += self.unacked.len() as u64;
        Ok(self.unacked.len())
    }

    /// Whether the learner's subscription is known yet.
    pub async fn has_subscribers(&self) -> Result<bool> {
        has_subscribers(&self.publisher).await
    }
}

/// A number for this start of actor `actor`, distinct from its earlier starts.
fn incarnation(actor: u32) -> u64 {
    let nanos = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_nanos() as u64);
    let mut z = nanos ^ ((std::process::id() as u64) << 32) ^ actor as u64;
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

/// What the learner has received of each actor's numbered trajectories: it takes each once
/// and knows which are missing.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Receipts {
    actors: BTreeMap<u32, Receipt>,
    /// Trajectories received twice (sent again) and not taken again.
    pub repeated: u64,
}

#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
struct Receipt {
    incarnation: u64,
    /// Every number below this is received.
    next: u64,
    /// Numbers received above `next`.
    ahead: BTreeSet<u64>,
}

impl Receipts {
    /// Record `msg`; false when it was taken before.
    pub fn take(&mut self, msg: &TrajectoryMsg) -> bool {
        let r = self.actors.entry(msg.actor).or_default();
        if r.incarnation != msg.incarnation {
            // NOTE: the actor started again; its numbers start again.
            *r = Receipt {
                incarnation: msg.incarnation,
                ..Receipt::default()
            };
        }
        if msg.oldest > r.next {
            // NOTE: the actor holds nothing below `oldest` any more (acknowledged to this
            // learner before it restarted from a checkpoint, or given up): none will come.
            r.ahead = r.ahead.split_off(&msg.oldest);
            r.next = msg.oldest;
            while r.ahead.remove(&r.next) {
                r.next += 1;
            }
        }
        if msg.seq < r.next || !r.ahead.insert(msg.seq) {
            self.repeated += 1;
            return false;
        }
        while r.ahead.remove(&r.next) {
            r.next += 1;
        }
        true
    }

    /// Trajectories known to be missing (a later one arrived, they did not yet).
    pub fn missing(&self) -> u64 {
        self.actors
            .values()
            .map(|r| r.ahead.last().map_or(0, |last| last + 1 - r.next) - r.ahead.len() as u64)
            .sum()
    }

    /// The acknowledgements to send with the next weights.
    pub fn acks(&self) -> Vec<Ack> {
        self.actors
            .iter()
            .map(|(&actor, r)| Ack {
                actor,
                incarnation: r.incarnation,
                next_seq: r.next,
            })
            .collect()
    }
}

/// A publisher of whole messages with `Block` at `priority` (evaluation requests and
/// results, the stop).
pub struct MessagePublisher {
    run: String,
    publisher: Publisher<'static>,
}

impl MessagePublisher {
    pub async fn new(
        session: &Session,
        keys: &Keys,
        key: String,
        priority: Priority,
    ) -> Result<Self> {
        let publisher = session
            .declare_publisher(key)
            .congestion_control(CongestionControl::Block)
            .priority(priority)
            .await
            .map_err(zerr("declaring a publisher"))?;
        Ok(Self {
            run: keys.run().to_string(),
            publisher,
        })
    }

    pub async fn send(&self, body: &Body) -> Result<()> {
        self.publisher
            .put(wire::encode(&self.run, body))
            .await
            .map_err(|e| anyhow!("publishing on {}: {e}", self.publisher.key_expr()))
    }

    /// Send a message encoded already (by [`wire::encode`], for this publisher's run).
    pub async fn send_encoded(&self, message: &[u8]) -> Result<()> {
        self.publisher
            .put(message.to_vec())
            .await
            .map_err(|e| anyhow!("publishing on {}: {e}", self.publisher.key_expr()))
    }

    /// Whether a matching subscription is known yet.
    pub async fn has_subscribers(&self) -> Result<bool> {
        has_subscribers(&self.publisher).await
    }
}

/// Put one message on `key` with `Block` at `priority` (for keys without a long-lived
/// publisher, such as each actor's evaluation requests).
pub async fn put_message(
    session: &Session,
    keys: &Keys,
    key: String,
    body: &Body,
    priority: Priority,
) -> Result<()> {
    session
        .put(&key, wire::encode(keys.run(), body))
        .congestion_control(CongestionControl::Block)
        .priority(priority)
        .await
        .map_err(|e| anyhow!("publishing on {key}: {e}"))
}

async fn has_subscribers(publisher: &Publisher<'static>) -> Result<bool> {
    let status = publisher.matching_status().await.map_err(|e| {
        anyhow!(
            "reading the matching status of publisher {}: {e}",
            publisher.key_expr()
        )
    })?;
    Ok(status.matching())
}

/// Wait until `ready` says yes, polling every few milliseconds, for at most `limit`.
/// (Zenoh declarations reach the other side asynchronously; this waits for the condition,
/// not for a guessed time.)
pub async fn wait_until<F, Fut>(limit: Duration, mut ready: F) -> Result<()>
where
    F: FnMut() -> Fut,
    Fut: std::future::Future<Output = Result<bool>>,
{
    let start = tokio::time::Instant::now();
    while !ready().await? {
        if start.elapsed() > limit {
            anyhow::bail!("gave up after {limit:?} waiting for Zenoh peers to see each other");
        }
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
    Ok(())
}

/// Who is labelling a run now, from the teachers' liveliness tokens (one per person with a
/// page open; Zenoh removes a token when its teacher's session goes, so a teacher that
/// dies takes its people with it).
pub struct Labellers {
    alive: Arc<Mutex<BTreeSet<String>>>,
    _subscriber: Subscriber<()>,
}

impl Labellers {
    pub async fn watch(session: &Session, keys: &Keys) -> Result<Self> {
        let alive: Arc<Mutex<BTreeSet<String>>> = Arc::default();
        let set = alive.clone();
        let subscriber = session
            .liveliness()
            .declare_subscriber(keys.all_labellers())
            .history(true)
            .callback(move |s: Sample| {
                let key = s.key_expr().to_string();
                let mut set = set.lock().unwrap_or_else(|e| e.into_inner());
                match s.kind() {
                    zenoh::sample::SampleKind::Put => set.insert(key),
                    zenoh::sample::SampleKind::Delete => set.remove(&key),
                };
            })
            .await
            .map_err(|e| anyhow!("watching the labellers of {keys}: {e}"))?;
        Ok(Self {
            alive,
            _subscriber: subscriber,
        })
    }

    /// People labelling now.
    pub fn count(&self) -> usize {
        self.alive.lock().unwrap_or_else(|e| e.into_inner()).len()
    }
}

/// The liveliness tokens of the people labelling at teacher `teacher` (what [`Labellers`]
/// watches): one per person present, declared when they come and undeclared when they go.
pub struct LabellerTokens {
    session: Session,
    keys: Keys,
    teacher: String,
    tokens: BTreeMap<String, zenoh::liveliness::LivelinessToken>,
}

impl LabellerTokens {
    pub fn new(session: &Session, keys: &Keys, teacher: &str) -> Self {
        Self {
            session: session.clone(),
            keys: keys.clone(),
            teacher: teacher.to_string(),
            tokens: BTreeMap::new(),
        }
    }

    /// Hold a token for each of `present`, and none for anyone else.
    pub async fn hold(&mut self, present: &[String]) -> Result<()> {
        self.tokens.retain(|name, _| present.contains(name));
        for name in present {
            if self.tokens.contains_key(name) {
                continue;
            }
            let key = self.keys.labeller(&self.teacher, name);
            let token = self
                .session
                .liveliness()
                .declare_token(key)
                .await
                .map_err(|e| anyhow!("declaring labeller {name:?}'s liveliness: {e}"))?;
            self.tokens.insert(name.clone(), token);
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::trajectory::TRAJECTORY_FORMAT;

    fn msg(actor: u32, incarnation: u64, seq: u64) -> TrajectoryMsg {
        TrajectoryMsg {
            actor,
            incarnation,
            seq,
            oldest: 0,
            trajectory: Trajectory {
                format: TRAJECTORY_FORMAT,
                seed: seq,
                policy_version: 1,
                obs_dim: 1,
                act_dim: 1,
                obs: vec![0.0],
                actions: vec![],
                rewards: vec![],
                outcome: Default::default(),
                replay: None,
            },
        }
    }

    #[test]
    fn receipts_take_each_trajectory_once_and_count_the_missing() {
        let mut r = Receipts::default();
        assert!(r.take(&msg(0, 7, 0)));
        assert!(r.take(&msg(0, 7, 1)));
        // 2 and 3 are lost on the way; 4 arrives.
        assert!(r.take(&msg(0, 7, 4)));
        assert!(r.take(&msg(1, 9, 0)));
        assert_eq!(r.missing(), 2);
        let ack = |r: &Receipts, actor| r.acks().into_iter().find(|a| a.actor == actor).unwrap();
        assert_eq!(ack(&r, 0).next_seq, 2);
        // The actor sends its unacknowledged ones again: 2 and 3 are new, 4 is not.
        assert!(r.take(&msg(0, 7, 2)));
        assert!(r.take(&msg(0, 7, 3)));
        assert!(!r.take(&msg(0, 7, 4)));
        assert!(!r.take(&msg(0, 7, 0)));
        assert_eq!(r.repeated, 2);
        assert_eq!(r.missing(), 0);
        assert_eq!(ack(&r, 0).next_seq, 5);
        // A restarted actor numbers from 0 again.
        assert!(r.take(&msg(0, 8, 0)));
        assert_eq!(ack(&r, 0).incarnation, 8);
        assert_eq!(ack(&r, 0).next_seq, 1);
        // A learner restarted from a checkpoint knows less than the actor: the actor holds
        // only 6 and up (1-5 were acknowledged since), so nothing below 6 is missing.
        let restored = r.clone();
        let mut r = restored;
        assert!(r.take(&TrajectoryMsg {
            oldest: 6,
            ..msg(0, 8, 7)
        }));
        assert_eq!(r.missing(), 1, "6 is still to come");
        assert!(r.take(&TrajectoryMsg {
            oldest: 6,
            ..msg(0, 8, 6)
        }));
        assert_eq!(r.missing(), 0);
        assert_eq!(ack(&r, 0).next_seq, 8);
    }
}
