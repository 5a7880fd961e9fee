//! The labelling page across machines is HTTPS: `pbrl teacher --teacher human` refuses to listen
//! beyond loopback without a certificate, and with one (from `deploy/certs.sh page:...`)
//! serves the page and its API over TLS: a client that trusts the CA gets them, one that
//! does not, or that speaks plain HTTP to the port, gets nothing.

use std::process::{Command, Output};

use pbrl_common::connect::{free_local_port, ConnectArgs};

mod support;

use support::deploy::certs;
use support::poll::poll_async;
use support::proc::pbrl;

fn curl(args: &[&str]) -> Output {
    Command::new("curl")
        .args(["--silent", "--show-error", "--max-time", "20"])
        .args(args)
        .output()
        .expect("curl runs")
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_page_beyond_loopback_is_https_only_and_a_client_without_the_ca_sees_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let endpoint = format!("tcp/127.0.0.1:{}", free_local_port().unwrap());
    let _router = ConnectArgs::router_on(&endpoint).open().await.unwrap();
    let c = d.join("certs");
    certs(
        &c,
        "ward",
        None,
        &["router:hub@127.0.0.1", "page:ward@127.0.0.1"],
    );
    let teacher = |http: &str, extra: &[String]| -> Vec<String> {
        let mut a: Vec<String> = [
            "teacher",
            "--teacher=human",
            "--run=ward",
            "--repeat-share=0",
            "--token=s3cret",
        ]
        .iter()
        .map(|s| s.to_string())
        .collect();
        a.extend([
            format!("--connect={endpoint}"),
            format!("--http={http}"),
            format!("--teacher-state={}", d.join("teacher.sqlite").display()),
        ]);
        a.extend_from_slice(extra);
        a
    };

    // Beyond loopback without a certificate: refused at start, naming the flags.
    let out = pbrl(teacher("0.0.0.0:0", &[])).rust_log("warn").output();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success(),
        "plain HTTP beyond loopback was served"
    );
    assert!(
        err.contains("--https-cert"),
        "the refusal names the flags: {err}"
    );

    // With the page's certificate: HTTPS.
    let port = free_local_port().unwrap();
    let addr = format!("127.0.0.1:{port}");
    let tls = [
        format!("--https-cert={}", c.join("page-ward.pem").display()),
        format!("--https-key={}", c.join("page-ward.key").display()),
    ];
    let page = pbrl(teacher(&addr, &tls))
        .dir(d)
        .log("teacher")
        .rust_log("warn,pbrl=info,pbrl_teacher=info")
        .spawn();
    poll_async(
        60,
        || format!("the page to listen{}", page.tail()),
        || std::net::TcpStream::connect(&addr).ok(),
    )
    .await;
    let ca = c.join("ca.pem").display().to_string();
    let url = format!("https://{addr}");
    let got = curl(&["--cacert", &ca, &format!("{url}/")]);
    assert!(
        got.status.success(),
        "{}",
        String::from_utf8_lossy(&got.stderr)
    );
    let html = String::from_utf8_lossy(&got.stdout);
    assert!(html.contains("<html"), "the page: {html}");
    let got = curl(&[
        "--cacert",
        &ca,
        "-H",
        "Authorization: Bearer s3cret",
        &format!("{url}/api/v1/status?labeller=ana"),
    ]);
    assert!(
        got.status.success(),
        "{}",
        String::from_utf8_lossy(&got.stderr)
    );
    let status: serde_json::Value = serde_json::from_slice(&got.stdout).unwrap();
    assert!(status.is_object(), "{status}");
    assert!(
        page.log()
            .contains(&format!("labelling page on https://{addr}/")),
        "{}",
        page.log()
    );

    // Without the CA the certificate is not trusted; plain HTTP to the port gets no page.
    let got = curl(&[&format!("{url}/")]);
    assert!(
        !got.status.success(),
        "a client that does not trust the CA got the page"
    );
    let got = curl(&[&format!("http://{addr}/")]);
    assert!(
        !got.status.success() || !String::from_utf8_lossy(&got.stdout).contains("<html"),
        "plain HTTP got the page"
    );
    // The page still serves after the failed handshakes.
    let got = curl(&["--cacert", &ca, &format!("{url}/")]);
    assert!(
        got.status.success(),
        "{}",
        String::from_utf8_lossy(&got.stderr)
    );
}
