//! The cause of the closed transports, reproduced: a subscriber whose handler waits on the
//! service (zenoh's default bounded FIFO, not drained) blocks the thread that reads its
//! link; the router's queue towards it fills, the router's push waits, and after
//! `wait_before_close` zenoh closes the transport and drops what was queued. The same
//! load on pbrl's `Inbox` (a callback that never waits) closes nothing and loses nothing.
//! (Each test file is its own process: the blocked reader below never frees its thread.)

mod support;

use std::time::Duration;

use pbrl_common::bus::{wait_until, Inbox};
use pbrl_common::connect::{free_local_port, ConnectArgs};
use pbrl_common::wire::{self, Body, TrajectoryMsg};
use pbrl_common::Keys;

/// A 200-step trajectory message (about 20 KB).
fn message(run: &str, seq: u64) -> Vec<u8> {
    wire::encode(
        run,
        &Body::Trajectory(Box::new(TrajectoryMsg {
            actor: 0,
            incarnation: 1,
            seq,
            oldest: 0,
            trajectory: support::trajectory(seq),
        })),
    )
}

/// Messages sent while nobody drains: more than the FIFO's 256, the socket buffers and
/// the router's queue hold.
const SENT: u64 = 3000;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_receive_path_that_waits_on_the_service_closes_the_transport_and_an_inbox_does_not() {
    assert_eq!(support::closed_transports(), 0);
    let dir = tempfile::tempdir().unwrap();
    let config = Some(support::short_wait_config(dir.path(), 300));
    let endpoint = format!("tcp/127.0.0.1:{}", free_local_port().unwrap());
    let _router = ConnectArgs {
        config: config.clone(),
        ..ConnectArgs::router_on(&endpoint)
    }
    .open()
    .await
    .unwrap();
    let session = || async {
        ConnectArgs {
            config: config.clone(),
            ..ConnectArgs::connecting_to(&endpoint)
        }
        .open()
        .await
        .unwrap()
    };
    let (learner, actor) = (session().await, session().await);
    let keys = Keys::new("stall").unwrap();
    let publisher = actor
        .declare_publisher(keys.trajectory(0))
        .congestion_control(zenoh::qos::CongestionControl::Block)
        .await
        .unwrap();

    // pbrl's inbox, never drained while the messages come: every one arrives.
    let mut inbox = Inbox::trajectories(&learner, &keys).await.unwrap();
    wait_until(Duration::from_secs(20), || async {
        Ok(publisher.matching_status().await.unwrap().matching())
    })
    .await
    .unwrap();
    for seq in 0..SENT {
        publisher.put(message("stall", seq)).await.unwrap();
    }
    wait_until(Duration::from_secs(60), || async {
        Ok(inbox.held() as u64 == SENT)
    })
    .await
    .expect("every message reaches the inbox while nobody drains it");
    for seq in 0..SENT {
        assert_eq!(inbox.next().await.unwrap().seq, seq, "in order, each once");
    }
    assert_eq!(support::closed_transports(), 0, "no transport closed");
    drop(inbox);

    // Today's receive path before this fix: zenoh's default handler (a FIFO of 256), drained
    // only when the service gets to it. The service is busy; the transport is closed.
    let fifo = learner
        .declare_subscriber(keys.trajectory(0))
        .await
        .unwrap();
    for seq in 0..SENT {
        // NOTE: after the close the router drops what it cannot route; puts go on.
        publisher.put(message("stall", seq)).await.unwrap();
        if support::closed_transports() > 0 {
            break;
        }
    }
    wait_until(Duration::from_secs(60), || async {
        Ok(support::closed_transports() > 0)
    })
    .await
    .expect("zenoh closes the transport to the session whose reader is blocked");
    let mut received = 0;
    while let Ok(Some(_)) = fifo.try_recv() {
        received += 1;
    }
    assert!(
        received < SENT,
        "messages were lost with the transport ({received} of {SENT} arrived)"
    );
}
