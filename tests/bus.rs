//! Weights and trajectories over Zenoh, through an in-process router on loopback.

use std::time::Duration;

use pbrl_common::bus::{
    wait_until, TrajectoryPublisher, TrajectorySubscriber, WeightsClient, WeightsServer,
};
use pbrl_common::connect::{free_local_port, ConnectArgs};
use pbrl_common::trajectory::TRAJECTORY_FORMAT;
use pbrl_common::wire::{self, Body, Tensor, Weights};
use pbrl_common::{Keys, StepRewards, Trajectory};

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
    }
}

fn trajectory(seed: u64) -> Trajectory {
    Trajectory {
        format: TRAJECTORY_FORMAT,
        seed,
        policy_version: 3,
        obs_dim: 2,
        act_dim: 1,
        obs: vec![0.5; 2 * 201],
        actions: vec![0.1; 200],
        rewards: vec![StepRewards::default(); 200],
        outcome: Default::default(),
        replay: None,
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
    let trajectories = TrajectorySubscriber::new(&learner, &keys).await.unwrap();
    let client_a = WeightsClient::new(&actor_a, &keys).await.unwrap();
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
    let pub_a = TrajectoryPublisher::new(&actor_a, &keys, 0).await.unwrap();
    let pub_b = TrajectoryPublisher::new(&actor_b, &keys, 1).await.unwrap();
    wait_until(LIMIT, || pub_a.has_subscribers()).await.unwrap();
    wait_until(LIMIT, || pub_b.has_subscribers()).await.unwrap();
    for s in 0..5 {
        pub_a.publish(trajectory(s), false).await.unwrap();
        pub_b.publish(trajectory(100 + s), false).await.unwrap();
    }
    let mut seen = Vec::new();
    for _ in 0..10 {
        let t = trajectories.next().await.unwrap();
        assert_eq!(t.trajectory.seed >= 100, t.actor == 1);
        seen.push(t.trajectory.seed);
    }
    seen.sort();
    assert_eq!(seen, vec![0, 1, 2, 3, 4, 100, 101, 102, 103, 104]);
    assert_eq!(trajectories.dropped.get(), 0);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_messages_are_dropped_counted_and_the_receiver_keeps_going() {
    let endpoint = format!("tcp/127.0.0.1:{}", free_local_port().unwrap());
    let _router = ConnectArgs::router_on(&endpoint).open().await.unwrap();
    let keys = Keys::new("bad-input").unwrap();
    let learner = ConnectArgs::connecting_to(&endpoint).open().await.unwrap();
    let actor = ConnectArgs::connecting_to(&endpoint).open().await.unwrap();
    let trajectories = TrajectorySubscriber::new(&learner, &keys).await.unwrap();
    let raw = actor
        .declare_publisher(keys.trajectory(7))
        .congestion_control(zenoh::qos::CongestionControl::Block)
        .await
        .unwrap();
    wait_until(LIMIT, || async {
        Ok(raw.matching_status().await.unwrap().matching())
    })
    .await
    .unwrap();
    let mut nan = trajectory(1);
    nan.obs[3] = f32::NAN;
    let mut short = trajectory(2);
    short.actions.pop();
    let good = trajectory(3);
    let msg = |t: Trajectory| {
        wire::encode(
            "bad-input",
            &Body::Trajectory(Box::new(wire::TrajectoryMsg {
                actor: 7,
                eval: false,
                trajectory: t,
            })),
        )
    };
    raw.put(vec![1u8, 2, 3]).await.unwrap(); // does not decode
    raw.put(msg(nan)).await.unwrap(); // holds NaN
    raw.put(msg(short)).await.unwrap(); // wrong dimensions
    raw.put(wire::encode("another-run", &Body::Stop))
        .await
        .unwrap(); // another run
    raw.put(msg(good)).await.unwrap();
    let t = trajectories.next().await.unwrap();
    assert_eq!(
        t.trajectory.seed, 3,
        "the good message after the bad ones arrives"
    );
    assert_eq!(trajectories.dropped.get(), 4);
}
