//! A foreign Zenoh client puts malformed messages on every key of a run while it trains:
//! every bad message is dropped and counted, no actor stops on a bad stop, and training
//! goes on to its end.

mod support;

use std::time::Duration;

use pbrl_actor::runner::{self, ActorConfig, Task};
use pbrl_actor::WorldConfig;
use pbrl_common::bus::WeightsClient;
use pbrl_common::connect::{free_local_port, ConnectArgs};
use pbrl_common::trajectory::TRAJECTORY_FORMAT;
use pbrl_common::wire::{Body, EvalRequest, EvalResult, Stop, Tensor, TrajectoryMsg, Weights};
use pbrl_common::{Keys, Outcome, StepRewards, Trajectory};
use pbrl_learner::run::service::{self, LearnerConfig};
use support::{bad_payloads, put_all};

fn trajectory(nan: bool, short: bool) -> Body {
    let mut t = Trajectory {
        format: TRAJECTORY_FORMAT,
        seed: 1,
        policy_version: 1,
        obs_dim: 4,
        act_dim: 2,
        obs: vec![0.5; 4 * 31],
        actions: vec![0.1; 2 * 30],
        rewards: vec![StepRewards::default(); 30],
        outcome: Default::default(),
        replay: None,
    };
    if nan {
        t.obs[5] = f32::NAN;
    }
    if short {
        t.actions.pop();
    }
    Body::Trajectory(Box::new(TrajectoryMsg {
        actor: 0,
        incarnation: 77,
        seq: 0,
        oldest: 0,
        trajectory: t,
    }))
}

fn weights(nan: bool, short: bool) -> Weights {
    Weights {
        version: 1_000_000,
        env_steps: 0,
        obs_dim: 4,
        act_dim: 2,
        tensors: vec![Tensor {
            name: "l0.weight".into(),
            shape: vec![2, 4],
            data: vec![if nan { f32::NAN } else { 0.0 }; if short { 7 } else { 8 }],
        }],
        obs_mean: vec![0.0; 4],
        obs_var: vec![1.0; 4],
        obs_clip: 10.0,
        random_actions: false,
        episodes_per_actor: 0,
        acks: Vec::new(),
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn malformed_messages_on_every_key_while_a_run_trains_are_dropped_and_it_goes_on() {
    // The learner's session is the router, as `deploy/local.sh` runs it.
    let endpoint = format!("tcp/127.0.0.1:{}", free_local_port().unwrap());
    let session = ConnectArgs::router_on(&endpoint).open().await.unwrap();
    let run = "foreign-test";
    let keys = Keys::new(run).unwrap();
    let cfg = LearnerConfig {
        publish_every: 10,
        ..support::bus_learner(run, 100_000, 300, 10)
    };
    let learner = tokio::spawn(service::run(cfg, session.clone(), std::future::pending()));
    let mut actors = Vec::new();
    for id in 0..2 {
        let s = ConnectArgs::connecting_to(&endpoint).open().await.unwrap();
        let acfg = ActorConfig {
            id,
            run: run.into(),
            task: Task::Point,
            world: WorldConfig::default(),
            seed: 5,
        };
        actors.push(tokio::spawn(runner::run(acfg, s, std::future::pending())));
    }

    // The foreign client waits until training is under way.
    let foreign = ConnectArgs::connecting_to(&endpoint).open().await.unwrap();
    let mut watch = WeightsClient::new(&foreign, &keys).await.unwrap();
    loop {
        let w = tokio::time::timeout(Duration::from_secs(60), watch.next())
            .await
            .unwrap()
            .unwrap();
        if w.version >= 5 {
            break;
        }
    }

    let stop = || {
        Body::Stop(Stop {
            env_steps: 1,
            version: 1,
        })
    };
    let request = |w: Weights| {
        Body::EvalRequest(Box::new(EvalRequest {
            id: 1,
            actor: 0,
            weights: w,
            seeds: vec![1],
            sampled: false,
            steps: false,
        }))
    };
    let result = |x: f32| {
        Body::EvalResult(EvalResult {
            id: 1,
            actor: 0,
            version: 1,
            episodes: vec![Outcome {
                return_truth: x,
                ..Default::default()
            }],
            sampled: Vec::new(),
            steps: Vec::new(),
        })
    };
    // (key, bad payloads, whether the learner receives it)
    let sprays = [
        (
            keys.trajectory(0),
            bad_payloads(
                run,
                &trajectory(false, false),
                Some(trajectory(false, true)),
                Some(trajectory(true, false)),
                stop(),
            ),
            true,
        ),
        (
            keys.eval_result(1),
            bad_payloads(run, &result(1.0), None, Some(result(f32::NAN)), stop()),
            true,
        ),
        (
            keys.weights(),
            bad_payloads(
                run,
                &Body::Weights(weights(false, false)),
                Some(Body::Weights(weights(false, true))),
                Some(Body::Weights(weights(true, false))),
                stop(),
            ),
            false,
        ),
        (
            keys.eval_request(0),
            bad_payloads(
                run,
                &request(weights(false, false)),
                Some(request(weights(false, true))),
                Some(request(weights(true, false))),
                stop(),
            ),
            false,
        ),
        (
            keys.stop(),
            bad_payloads(
                run,
                &stop(),
                None,
                None,
                Body::Weights(weights(false, false)),
            ),
            false,
        ),
    ];
    let mut to_learner = 0;
    for (key, bad, learner_gets) in &sprays {
        let payloads: Vec<Vec<u8>> = bad.iter().map(|(_, bytes)| bytes.clone()).collect();
        put_all(&foreign, key, &payloads).await;
        if *learner_gets {
            to_learner += bad.len() as u64;
        }
    }
    assert!(
        !learner.is_finished(),
        "the run was still training during the spray"
    );
    let after_spray = watch.newest().map_or(0, |w| w.version);

    let summary = support::run_ends(learner, actors, 300).await;
    assert!(summary.env_steps >= 100_000);
    assert_eq!(
        summary.dropped_messages, to_learner,
        "each bad message to the learner dropped and counted once"
    );
    for actor in 0..2 {
        let last = summary.last_version_by_actor[&actor];
        assert!(
            last > after_spray,
            "actor {actor} trained on after the spray (its last version {last}, {after_spray} then)"
        );
    }
    for row in &summary.rows {
        assert_eq!(row.eval_episodes, 4, "every row evaluated: {row:?}");
    }
}
