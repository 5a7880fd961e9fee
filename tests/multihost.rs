//! pbrl across three hosts through the stock `zenohd` router over TLS with access control
//! by role: the hosts are network namespaces with their own addresses on a virtual link
//! (made here; root and iproute2 are needed, and without them the test fails, saying so).
//! The learner is on one host, the router on a second, two actors and a scripted teacher
//! on a third, each with its own certificate from `deploy/certs.sh`; a Decoupled PEBBLE run
//! on the point task, with the default label-efficient settings, finishes and every answer
//! the teacher gave is in the label store once.

mod support;

use support::deploy::Deployment;

#[test]
fn decoupled_pebble_across_three_hosts_over_tls_stores_every_label_once() {
    let mut d = Deployment::new("three-hosts", 4_000, true);
    d.start_all();
    d.finish(600);
}
