//! Weights and trajectories over Zenoh, with the quality of service each needs.
//!
//! - Weights: `CongestionControl::Block` at `Priority::DataHigh`, never dropped; the learner
//!   also answers queries with the newest weights, so an actor that joins late starts
//!   from the current version at once.
//! - Trajectories: `Block` at `Priority::Data` (whole episodes, 60-70 KB each; a plain put
//!   uses `Drop`, and large messages sent that way are known to be lost).
//!
//! Receivers decode with [`crate::wire::decode`]; a message that does not decode, comes
//! from another run or format, or holds bad numbers is dropped with a warning and counted.

use std::sync::{Arc, Mutex};
use std::time::Duration;

use anyhow::{anyhow, Result};
use zenoh::handlers::FifoChannelHandler;
use zenoh::pubsub::{Publisher, Subscriber};
use zenoh::qos::{CongestionControl, Priority};
use zenoh::sample::Sample;
use zenoh::Session;

use crate::keys::Keys;
use crate::trajectory::Trajectory;
use crate::wire::{self, Body, TrajectoryMsg, Weights};

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
        let queryable = session
            .declare_queryable(keys.weights())
            .await
            .map_err(zerr("declaring the weights queryable"))?;
        let latest: Arc<Mutex<Option<Vec<u8>>>> = Arc::default();
        let shared = latest.clone();
        let task = tokio::spawn(async move {
            while let Ok(query) = queryable.recv_async().await {
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

/// The actor's side of the weights.
pub struct WeightsClient {
    run: String,
    key: String,
    subscriber: Subscriber<FifoChannelHandler<Sample>>,
    pub dropped: Dropped,
}

impl WeightsClient {
    pub async fn new(session: &Session, keys: &Keys) -> Result<Self> {
        let subscriber = session
            .declare_subscriber(keys.weights())
            .await
            .map_err(zerr("declaring the weights subscriber"))?;
        Ok(Self {
            run: keys.run().to_string(),
            key: keys.weights(),
            subscriber,
            dropped: Dropped::default(),
        })
    }

    /// Ask the learner for its newest weights (an actor that joins late); `None` when no
    /// learner answered within `timeout`.
    pub async fn fetch(&self, session: &Session, timeout: Duration) -> Result<Option<Weights>> {
        let replies = session
            .get(self.key.as_str())
            .timeout(timeout)
            .await
            .map_err(zerr("querying the newest weights"))?;
        let mut best: Option<Weights> = None;
        while let Ok(reply) = replies.recv_async().await {
            if let Some(w) = reply.result().ok().and_then(|sample| self.take(sample)) {
                keep_newest(&mut best, w);
            }
        }
        Ok(best)
    }

    /// The newest weights that arrived since the last call, without waiting.
    pub fn newest(&self) -> Option<Weights> {
        let mut best: Option<Weights> = None;
        while let Ok(Some(sample)) = self.subscriber.try_recv() {
            if let Some(w) = self.take(&sample) {
                keep_newest(&mut best, w);
            }
        }
        best
    }

    /// Wait for the next weights message.
    pub async fn next(&self) -> Result<Weights> {
        loop {
            let sample = self
                .subscriber
                .recv_async()
                .await
                .map_err(zerr("receiving weights"))?;
            if let Some(w) = self.take(&sample) {
                return Ok(w);
            }
        }
    }

    fn take(&self, sample: &Sample) -> Option<Weights> {
        accept(&self.run, sample, &self.dropped, |b| match b {
            Body::Weights(w) => Some(w),
            _ => None,
        })
    }
}

/// Keep `w` in `best` if it is a newer version.
fn keep_newest(best: &mut Option<Weights>, w: Weights) {
    if best.as_ref().is_none_or(|b| w.version > b.version) {
        *best = Some(w);
    }
}

/// An actor's trajectory publisher.
pub struct TrajectoryPublisher {
    run: String,
    actor: u32,
    publisher: Publisher<'static>,
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
            publisher,
        })
    }

    pub async fn publish(&self, trajectory: Trajectory, eval: bool) -> Result<()> {
        let msg = TrajectoryMsg {
            actor: self.actor,
            eval,
            trajectory,
        };
        let bytes = wire::encode(&self.run, &Body::Trajectory(Box::new(msg)));
        self.publisher
            .put(bytes)
            .await
            .map_err(zerr("publishing a trajectory"))
    }

    /// Whether the learner's subscription is known yet.
    pub async fn has_subscribers(&self) -> Result<bool> {
        has_subscribers(&self.publisher).await
    }
}

/// A publisher of whole messages with `Block` at `priority` (evaluation requests and
/// results).
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

/// A subscription that decodes every message and keeps the kind `pick` accepts; anything
/// else is dropped with a warning and counted.
pub struct MessageSubscriber {
    run: String,
    subscriber: Subscriber<FifoChannelHandler<Sample>>,
    pub dropped: Dropped,
}

impl MessageSubscriber {
    pub async fn new(session: &Session, keys: &Keys, key: String) -> Result<Self> {
        let subscriber = session
            .declare_subscriber(key)
            .await
            .map_err(zerr("declaring a subscriber"))?;
        Ok(Self {
            run: keys.run().to_string(),
            subscriber,
            dropped: Dropped::default(),
        })
    }

    /// The next valid message of the kind `pick` accepts.
    pub async fn next<T>(&self, pick: impl Fn(Body) -> Option<T>) -> Result<T> {
        loop {
            let sample = self
                .subscriber
                .recv_async()
                .await
                .map_err(|e| anyhow!("receiving on {}: {e}", self.subscriber.key_expr()))?;
            if let Some(t) = accept(&self.run, &sample, &self.dropped, &pick) {
                return Ok(t);
            }
        }
    }

    /// A valid message already received, if any.
    pub fn try_next<T>(&self, pick: impl Fn(Body) -> Option<T>) -> Result<Option<T>> {
        while let Some(sample) = self
            .subscriber
            .try_recv()
            .map_err(|e| anyhow!("receiving on {}: {e}", self.subscriber.key_expr()))?
        {
            if let Some(t) = accept(&self.run, &sample, &self.dropped, &pick) {
                return Ok(Some(t));
            }
        }
        Ok(None)
    }
}

/// The learner's subscription to every actor's trajectories.
pub struct TrajectorySubscriber {
    inner: MessageSubscriber,
    pub dropped: Dropped,
}

impl TrajectorySubscriber {
    pub async fn new(session: &Session, keys: &Keys) -> Result<Self> {
        let inner = MessageSubscriber::new(session, keys, keys.all_trajectories()).await?;
        Ok(Self {
            dropped: inner.dropped.clone(),
            inner,
        })
    }

    /// The next valid trajectory (invalid ones are dropped and counted).
    pub async fn next(&self) -> Result<TrajectoryMsg> {
        self.inner
            .next(|b| match b {
                Body::Trajectory(t) => Some(*t),
                _ => None,
            })
            .await
    }
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
