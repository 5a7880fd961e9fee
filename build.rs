//! `PBRL_SKIP_BROWSER=1` at build time marks the tests that need a browser as ignored, so a
//! machine without Chromium reports them as skipped (cargo test's "ignored"), never as
//! passed.
fn main() {
    println!("cargo:rustc-check-cfg=cfg(skip_browser)");
    println!("cargo:rerun-if-env-changed=PBRL_SKIP_BROWSER");
    if std::env::var("PBRL_SKIP_BROWSER").as_deref() == Ok("1") {
        println!("cargo:rustc-cfg=skip_browser");
    }
}
