//! Weights and trajectories over Zenoh, through an in-process router on loopback.

mod support;

use support::{bad_payloads, put_all, trajectory};

use std::time::Duration;

use pbrl_common::bus::{wait_until, Inbox, TrajectoryPublisher, WeightsClient, WeightsServer};
use pbrl_common::connect::{free_local_port, ConnectArgs};
use pbrl_common::wire::{self, Body, Tensor, Weights};
use pbrl_common::{Keys, Trajectory};

const LIMIT: Duration = Duration::from_secs(20);

fn weights(version: u64) -> Weights {
    Weights {
        version,
        env_steps: 10 * version,
        obs_dim: 2,
        act_dim: 1,
        // A large tensor, so that the message is fragmented (about 4 MB).
        tensors: vec![Tensor {
            name: "pi.l0.weight".into(),
            shape: vec![1000, 1000],
            data: vec![version as f32; 1_000_000],
        }],
        obs_mean: vec![0.0, 0.0],
        obs_var: vec![1.0, 1.0],
        obs_clip: 10.0,
        random_actions: false,
        episodes_per_actor: 0,
        acks: Vec::new(),
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn learner_and_actors_exchange_weights_and_trajectories_through_a_router() {
    let endpoint = format!("tcp/127.0.0.1:{}", free_local_port().unwrap());
    let _router = ConnectArgs::router_on(&endpoint).open().await.unwrap();
    let keys = Keys::new("bus-test").unwrap();
    let learner = ConnectArgs::connecting_to(&endpoint).open().await.unwrap();
    let actor_a = ConnectArgs::connecting_to(&endpoint).open().await.unwrap();

    let server = WeightsServer::new(&learner, &keys).await.unwrap();
    let mut trajectories = Inbox::trajectories(&learner, &keys).await.unwrap();
    let mut client_a = WeightsClient::new(&actor_a, &keys).await.unwrap();
    // Nobody has published yet: a query finds nothing.
    assert!(client_a
        .fetch(&actor_a, Duration::from_millis(500))
        .await
        .unwrap()
        .is_none());

    wait_until(LIMIT, || server.has_subscribers())
        .await
        .unwrap();
    server.publish(&weights(1)).await.unwrap();
    let got = client_a.next().await.unwrap();
    assert_eq!(got.version, 1);
    assert_eq!(
        got.tensors[0].data.len(),
        1_000_000,
        "a 4 MB message arrives whole"
    );

    // An actor that joins late gets the current version at once, by query.
    server.publish(&weights(2)).await.unwrap();
    assert_eq!(client_a.next().await.unwrap().version, 2);
    let actor_b = ConnectArgs::connecting_to(&endpoint).open().await.unwrap();
    let client_b = WeightsClient::new(&actor_b, &keys).await.unwrap();
    let late = client_b
        .fetch(&actor_b, LIMIT)
        .await
        .unwrap()
        .expect("the learner answers");
    assert_eq!(late.version, 2);

    // Trajectories from both actors reach the learner, tagged with their actor.
    let mut pub_a = TrajectoryPublisher::new(&actor_a, &keys, 0).await.unwrap();
    let mut pub_b = TrajectoryPublisher::new(&actor_b, &keys, 1).await.unwrap();
    wait_until(LIMIT, || pub_a.has_subscribers()).await.unwrap();
    wait_until(LIMIT, || pub_b.has_subscribers()).await.unwrap();
    for s in 0..5 {
        pub_a.publish(trajectory(s)).await.unwrap();
        pub_b.publish(trajectory(100 + s)).await.unwrap();
    }
    let mut seen = Vec::new();
    for _ in 0..10 {
        let t = trajectories.next().await.unwrap();
        assert_eq!(t.trajectory.seed >= 100, t.actor == 1);
        assert_eq!(t.seq, t.trajectory.seed % 100, "numbered per actor from 0");
        seen.push(t.trajectory.seed);
    }
    seen.sort();
    assert_eq!(seen, vec![0, 1, 2, 3, 4, 100, 101, 102, 103, 104]);
    assert_eq!(trajectories.dropped.get(), 0);
}

/// Put every payload on `key` from a foreign session, then `good`.
async fn spray(foreign: &zenoh::Session, key: &str, bad: &[(&str, Vec<u8>)], good: Vec<u8>) {
    let mut payloads: Vec<Vec<u8>> = bad.iter().map(|(_, bytes)| bytes.clone()).collect();
    payloads.push(good);
    put_all(foreign, key, &payloads).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_messages_on_every_key_are_dropped_counted_and_the_receivers_keep_going() {
    use pbrl_common::wire::{EvalRequest, EvalResult, Stop, TrajectoryMsg};
    let endpoint = format!("tcp/127.0.0.1:{}", free_local_port().unwrap());
    let _router = ConnectArgs::router_on(&endpoint).open().await.unwrap();
    let run = "bad-input";
    let keys = Keys::new(run).unwrap();
    let learner = ConnectArgs::connecting_to(&endpoint).open().await.unwrap();
    let actor = ConnectArgs::connecting_to(&endpoint).open().await.unwrap();
    let foreign = ConnectArgs::connecting_to(&endpoint).open().await.unwrap();
    let mut trajectories = Inbox::trajectories(&learner, &keys).await.unwrap();
    let mut results = Inbox::eval_results(&learner, &keys).await.unwrap();
    let mut requests = Inbox::eval_requests(&actor, &keys, 0).await.unwrap();
    let mut stops = Inbox::stops(&actor, &keys).await.unwrap();
    let mut weights_in = WeightsClient::new(&actor, &keys).await.unwrap();
    let stop = || {
        Body::Stop(Stop {
            env_steps: 1,
            version: 1,
        })
    };

    // Trajectories.
    let msg = |t: Trajectory| {
        Body::Trajectory(Box::new(TrajectoryMsg {
            actor: 7,
            incarnation: 1,
            seq: 0,
            oldest: 0,
            trajectory: t,
        }))
    };
    let mut nan = trajectory(1);
    nan.obs[3] = f32::NAN;
    let mut short = trajectory(2);
    short.actions.pop();
    let bad = bad_payloads(
        run,
        &msg(trajectory(3)),
        Some(msg(short)),
        Some(msg(nan)),
        stop(),
    );
    spray(
        &foreign,
        &keys.trajectory(7),
        &bad,
        wire::encode(run, &msg(trajectory(3))),
    )
    .await;
    let t = trajectories.next().await.unwrap();
    assert_eq!(
        t.trajectory.seed, 3,
        "the good message after the bad ones arrives"
    );
    assert_eq!(trajectories.dropped.get(), bad.len() as u64);

    // Weights.
    let mut short = weights(5);
    short.obs_mean.pop();
    let mut nan = weights(5);
    nan.tensors[0].data[17] = f32::NAN;
    let bad = bad_payloads(
        run,
        &Body::Weights(weights(5)),
        Some(Body::Weights(short)),
        Some(Body::Weights(nan)),
        stop(),
    );
    spray(
        &foreign,
        &keys.weights(),
        &bad,
        wire::encode(run, &Body::Weights(weights(5))),
    )
    .await;
    assert_eq!(weights_in.next().await.unwrap().version, 5);
    assert_eq!(weights_in.dropped.get(), bad.len() as u64);

    // Evaluation requests.
    let request = |w: Weights| {
        Body::EvalRequest(Box::new(EvalRequest {
            id: 9,
            actor: 0,
            weights: w,
            seeds: vec![1, 2],
            sampled: true,
            steps: false,
        }))
    };
    let mut short = weights(6);
    short.tensors[0].shape = vec![3, 3];
    let mut nan = weights(6);
    nan.obs_var[0] = f32::INFINITY;
    let bad = bad_payloads(
        run,
        &request(weights(6)),
        Some(request(short)),
        Some(request(nan)),
        stop(),
    );
    spray(
        &foreign,
        &keys.eval_request(0),
        &bad,
        wire::encode(run, &request(weights(6))),
    )
    .await;
    assert_eq!(requests.next().await.unwrap().id, 9);
    assert_eq!(requests.dropped.get(), bad.len() as u64);

    // Evaluation results.
    let result = |x: f32| {
        Body::EvalResult(EvalResult {
            id: 9,
            actor: 0,
            version: 6,
            episodes: vec![pbrl_common::Outcome {
                return_truth: x,
                ..Default::default()
            }],
            sampled: Vec::new(),
            steps: Vec::new(),
        })
    };
    let bad = bad_payloads(run, &result(1.0), None, Some(result(f32::NAN)), stop());
    spray(
        &foreign,
        &keys.eval_result(0),
        &bad,
        wire::encode(run, &result(1.0)),
    )
    .await;
    assert_eq!(results.next().await.unwrap().episodes[0].return_truth, 1.0);
    assert_eq!(results.dropped.get(), bad.len() as u64);

    // The stop: only a decoded stop of this run and format stops an actor.
    let bad = bad_payloads(run, &stop(), None, None, Body::Weights(weights(1)));
    spray(
        &foreign,
        &keys.stop(),
        &bad,
        wire::encode(
            run,
            &Body::Stop(Stop {
                env_steps: 42,
                version: 3,
            }),
        ),
    )
    .await;
    assert_eq!(stops.next().await.unwrap().env_steps, 42);
    assert!(
        stops.try_next().is_none(),
        "nothing bad got through as a stop"
    );
    assert_eq!(stops.dropped.get(), bad.len() as u64);
}
