//! A person's short sitting, as the labelling page shows it in a real browser: the robot
//! that keeps time with the person stops and says so until their answers are in, and the
//! time the rest of the sitting needs at their pace; three attempts ranked with keys, ties
//! and taking back, stored as one answer with each attempt's place. (`tests/labelling.rs`
//! has the page's pairs; both need a browser, `support::web`.)

use std::path::Path;

use serde_json::json;

mod support;

use support::page::{human_train, one_at_a_time, ARROW_RIGHT, BACKSPACE, ENTER};
use support::poll::poll;
use support::store::{sql, wait_for_answers};
use support::web::{browser_wanted, Api, Browser};

#[test]
#[cfg_attr(skip_browser, ignore = "PBRL_SKIP_BROWSER=1: needs a browser")]
fn a_person_the_robot_keeps_time_with_sees_it_stopped_until_they_answer() {
    let _one = one_at_a_time();
    assert!(browser_wanted("the keeping-time browser test"));
    let dir = tempfile::tempdir().unwrap();
    // NOTE: 2 answers, both asked at the first session (a session asks what the episodes
    // so far allow, one query a trajectory; the robot then stands still, so no more come).
    let budget = 2;
    let max = format!("--max-feedback={budget}");
    let (addr, out, train) = human_train(
        dir.path(),
        "held",
        &[
            "--undo-s=1",
            "--repeat-share=0",
            "--feedback-span=0",
            "--label-slack-steps=0",
            &max,
        ],
    );
    let api = Api {
        addr: addr.clone(),
        token: None,
        log: train.log.clone(),
    };
    let browser = Browser::open(dir.path());
    browser.label(&addr, "Wen");
    browser.playing(120, "a pair playing", &train.log);
    let chip = || {
        browser
            .exec(
                "return document.getElementById('p-training-text').textContent;",
                json!([]),
            )
            .as_str()
            .unwrap_or("")
            .to_string()
    };
    let held_text = poll(
        60,
        || {
            browser.page(
                &format!("the page saying the robot stopped (chip: {:?})", chip()),
                &train.log,
            )
        },
        || {
            let t = chip();
            t.contains("stopped").then_some(t)
        },
    );
    assert_eq!(
        held_text,
        "the robot has stopped: it waits for your answers"
    );
    let status = api.call("GET", "/api/v1/status", None).json();
    assert_eq!(status["held"], true, "{status}");
    let held_at = api.env_steps(30);
    let shots = Path::new(env!("CARGO_TARGET_TMPDIR")).join("screenshots/labelling");
    std::fs::create_dir_all(&shots).unwrap();
    std::fs::write(shots.join("held.png"), browser.screenshot()).unwrap();

    // The person answers: every answer but the last shows the next pair.
    for k in 0..budget - 1 {
        browser.press(ARROW_RIGHT, &format!("answer {k}"), &train.log);
    }
    // The page knows their pace now: the time the rest of the sitting needs at it.
    let left = poll(
        30,
        || browser.page("the time left at the person's pace", &train.log),
        || {
            browser
                .exec(
                    "const c = document.getElementById('p-left'); \
                     return c.hidden ? null : c.textContent;",
                    json!([]),
                )
                .as_str()
                .map(str::to_string)
        },
    );
    assert!(
        left.starts_with("about ") && left.ends_with(" left at your pace"),
        "{left}"
    );
    std::fs::write(shots.join("pace.png"), browser.screenshot()).unwrap();
    assert_eq!(
        api.env_steps(30),
        held_at,
        "the learner ran on while it waited for the person"
    );
    browser.key(ARROW_RIGHT);
    let db = out.join("labels.sqlite");
    wait_for_answers(&db, budget, 60, 0, &train.log);
    // Answered and trained on: the robot goes on, and the page says so.
    poll(
        120,
        || format!("the learner going on after the answers{}", train.tail()),
        || (api.env_steps(30) > held_at).then_some(()),
    );
    poll(
        60,
        || {
            browser.page(
                &format!("the page no longer saying stopped (chip: {:?})", chip()),
                &train.log,
            )
        },
        || (!chip().contains("stopped")).then_some(()),
    );
}

#[test]
#[cfg_attr(skip_browser, ignore = "PBRL_SKIP_BROWSER=1: needs a browser")]
fn a_person_ranks_three_attempts_with_keys_and_the_store_keeps_each_place() {
    let _one = one_at_a_time();
    assert!(browser_wanted("the ranking browser test"));
    let dir = tempfile::tempdir().unwrap();
    let (addr, out, train) = human_train(
        dir.path(),
        "rank",
        &[
            "--undo-s=1",
            "--repeat-share=0",
            "--query-attempts=3",
            "--max-feedback=2",
            "--feedback-span=0",
        ],
    );
    let browser = Browser::open(dir.path());
    browser.label(&addr, "Ria");
    let query = browser.playing(120, "a ranking playing", &train.log);
    let shown = browser.exec(
        "return [...document.querySelectorAll('main > section.attempt')] \
         .filter((s) => !s.hidden).map((s) => s.id);",
        json!([]),
    );
    assert_eq!(shown, json!(["att-r0", "att-r1", "att-r2"]));
    assert_eq!(browser.body("kind"), "rank");
    let places = || {
        browser.exec(
            "return ['r0', 'r1', 'r2'].map((s) => document.getElementById('place-' + s).textContent);",
            json!([]),
        )
    };
    // The second shown is best, the third ties with it; the first places itself last.
    browser.key("2");
    browser.key("=");
    browser.key("3");
    assert_eq!(places(), json!(["3rd", "tied 1st", "tied 1st"]));
    // Taken back and placed again the same way.
    browser.key(BACKSPACE);
    assert_eq!(places(), json!(["", "1st", ""]));
    browser.key("=");
    browser.key("3");
    assert_eq!(places(), json!(["3rd", "tied 1st", "tied 1st"]));
    let shots = Path::new(env!("CARGO_TARGET_TMPDIR")).join("screenshots/labelling");
    std::fs::create_dir_all(&shots).unwrap();
    std::fs::write(shots.join("rank.png"), browser.screenshot()).unwrap();
    browser.key(ENTER);
    let db = out.join("labels.sqlite");
    let rows = poll(
        60,
        || format!("the ranking of query {query} stored{}", train.tail()),
        || {
            let rows = sql(
                &db,
                &format!("SELECT ranks, labeller FROM queries WHERE id = {query}"),
            )
            .ok()?;
            rows.first().filter(|r| r["ranks"].is_string()).cloned()
        },
    );
    let mut ranks: Vec<u8> = rows["ranks"]
        .as_str()
        .unwrap()
        .split(',')
        .map(|p| p.parse().unwrap())
        .collect();
    assert_eq!(rows["labeller"], "Ria");
    ranks.sort();
    assert_eq!(
        ranks,
        [0, 0, 2],
        "two tied best and one last, in the query's order"
    );
    let attempts = sql(
        &db,
        &format!("SELECT k FROM query_attempts WHERE query = {query}"),
    )
    .unwrap();
    assert_eq!(attempts, [json!({"k": 2})]);
}
