//! The bus table of `docs/bus.md` against `common::keys`, so the two cannot drift apart:
//! every key [`Keys`] makes is a row of the table, every row is a key [`Keys`] makes, the
//! README's picture names each key, and no page names a key that does not exist.
//!
//! A key is compared in the table's form: the run is `<run>`, an actor's number or a
//! teacher's id `<id>`, a labeller's name `<name>`; a subscription's `*` stands for one
//! of them.

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};

use pbrl_common::keys::Keys;

// NOTE: values that no fixed part of a key holds (the learner's id is 0), so each stands
// for its placeholder alone.
const RUN: &str = "the-run";
const ACTOR: u32 = 7;
const TEACHER: &str = "the-teacher";
const NAME: &str = "the-name";

/// Every key `Keys` makes, by the method that makes it.
fn made(k: &Keys) -> Vec<(&'static str, String)> {
    vec![
        ("weights", k.weights()),
        ("trajectory", k.trajectory(ACTOR)),
        ("all_trajectories", k.all_trajectories()),
        ("eval_request", k.eval_request(ACTOR)),
        ("eval_result", k.eval_result(ACTOR)),
        ("all_eval_results", k.all_eval_results()),
        ("queries", k.queries()),
        ("answer", k.answer(TEACHER)),
        ("all_answers", k.all_answers()),
        ("answer_ack", k.answer_ack(TEACHER)),
        ("status", k.status()),
        ("labeller", k.labeller(TEACHER, NAME)),
        ("all_labellers", k.all_labellers()),
        ("stop", k.stop()),
    ]
}

fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

fn read(path: &Path) -> String {
    std::fs::read_to_string(path).unwrap_or_else(|e| panic!("reading {}: {e}", path.display()))
}

/// A key made with the values above, in the table's form.
fn placeholders(key: &str) -> String {
    let actor = ACTOR.to_string();
    key.split('/')
        .map(|s| match s {
            _ if s == RUN => "<run>",
            _ if s == actor || s == TEACHER => "<id>",
            _ if s == NAME => "<name>",
            s => s,
        })
        .collect::<Vec<_>>()
        .join("/")
}

/// Whether a table key covers `key`, where `key` may hold `*` for a placeholder.
fn covers(row: &str, key: &str) -> bool {
    let (r, k): (Vec<_>, Vec<_>) = (row.split('/').collect(), key.split('/').collect());
    r.len() == k.len()
        && r.iter()
            .zip(&k)
            .all(|(r, k)| r == k || (*k == "*" && r.starts_with('<') && r.ends_with('>')))
}

/// The keys of the table's rows (`| `pbrl/...` | publisher | readers | priority | what |`).
fn table_keys(bus_md: &str) -> Vec<String> {
    bus_md
        .lines()
        .filter(|l| l.starts_with("| `pbrl/"))
        .map(|l| {
            let cells: Vec<&str> = l.trim_matches('|').split(" | ").map(str::trim).collect();
            assert!(
                cells.len() == 5 && cells.iter().all(|c| !c.is_empty()),
                "docs/bus.md: a row needs its key, who publishes it, who reads it, its \
                 priority and what it carries, in 5 cells: {l}"
            );
            cells[0].trim_matches('`').to_string()
        })
        .collect()
}

/// The names of `Keys`' methods that make a key (`pub fn name(&self, ...) -> String`).
fn key_methods(keys_rs: &str) -> BTreeSet<String> {
    keys_rs
        .split("pub fn ")
        .skip(1)
        .filter_map(|rest| {
            let signature = &rest[..rest.find('{')?];
            let name = &signature[..signature.find(['(', '<'])?];
            (signature.contains("&self") && signature.contains("-> String"))
                .then(|| name.to_string())
        })
        .collect()
}

/// Every `pbrl/<run>/...` named in `text`.
fn keys_named(text: &str) -> Vec<String> {
    let prefix = "pbrl/<run>/";
    text.match_indices(prefix)
        .map(|(at, _)| {
            let rest = &text[at + prefix.len()..];
            let end = rest
                .find(|c: char| !(c.is_ascii_alphanumeric() || "<>*/_-".contains(c)))
                .unwrap_or(rest.len());
            format!("{prefix}{}", rest[..end].trim_end_matches('/'))
        })
        .filter(|k| k.len() > prefix.len())
        .collect()
}

#[test]
fn the_bus_table_lists_every_key_that_common_keys_makes_and_no_other() {
    let keys = Keys::new(RUN).expect("a valid run id");
    let made = made(&keys);
    let rows = table_keys(&read(&root().join("docs/bus.md")));
    assert!(!rows.is_empty(), "docs/bus.md has no table rows");

    // A method added to `Keys` must come into `made` (and so into the table).
    let listed: BTreeSet<String> = made.iter().map(|(m, _)| m.to_string()).collect();
    let in_source = key_methods(&read(&root().join("common/src/keys.rs")));
    if let Some(m) = in_source.difference(&listed).next() {
        panic!(
            "Keys::{m} makes a key this test does not know: add it to `made` here and its \
             row to docs/bus.md"
        );
    }
    if let Some(m) = listed.difference(&in_source).next() {
        panic!("Keys::{m} is gone from common/src/keys.rs: take it out of `made` here");
    }

    let mut seen = BTreeSet::new();
    for row in &rows {
        assert!(seen.insert(row), "docs/bus.md lists {row} twice");
    }
    let concrete: BTreeSet<String> = made
        .iter()
        .filter(|(_, k)| !k.contains('*'))
        .map(|(_, k)| placeholders(k))
        .collect();
    for (method, key) in &made {
        let key = placeholders(key);
        let found = if key.contains('*') {
            rows.iter().any(|r| covers(r, &key))
        } else {
            rows.contains(&key)
        };
        assert!(
            found,
            "Keys::{method} makes {key}, which docs/bus.md's table does not list"
        );
    }
    for row in &rows {
        assert!(
            concrete.contains(row),
            "docs/bus.md lists {row}, which common::keys does not make"
        );
    }
}

#[test]
fn the_readme_picture_names_every_key_and_no_page_names_another() {
    let rows = table_keys(&read(&root().join("docs/bus.md")));
    let readme = read(&root().join("README.md"));
    let picture = readme
        .split("```text\n")
        .nth(1)
        .and_then(|rest| rest.split("```").next())
        .expect("README.md has a picture of the processes in a ```text block");
    for row in &rows {
        let suffix = row.trim_start_matches("pbrl/<run>/");
        assert!(
            picture.contains(suffix),
            "README.md's picture does not name {suffix} (a key of docs/bus.md)"
        );
    }

    let mut pages = vec![root().join("README.md")];
    for dir in ["docs", "results"] {
        for entry in std::fs::read_dir(root().join(dir)).expect("reading a folder of pages") {
            let path = entry.expect("reading a folder entry").path();
            let readme = path.join("README.md");
            if path.extension().is_some_and(|e| e == "md") {
                pages.push(path);
            } else if readme.is_file() {
                pages.push(readme);
            }
        }
    }
    for page in &pages {
        for key in keys_named(&read(page)) {
            assert!(
                rows.iter().any(|r| covers(r, &key)),
                "{} names {key}, which docs/bus.md's table does not list",
                page.strip_prefix(root()).unwrap_or(page).display()
            );
        }
    }
}

#[test]
fn the_table_form_of_a_key() {
    assert_eq!(
        placeholders("pbrl/the-run/teacher/the-teacher/labeller/the-name"),
        "pbrl/<run>/teacher/<id>/labeller/<name>"
    );
    assert_eq!(
        placeholders("pbrl/the-run/learner/0/eval/7"),
        "pbrl/<run>/learner/0/eval/<id>"
    );
    assert!(covers(
        "pbrl/<run>/actor/<id>/trajectory",
        "pbrl/<run>/actor/*/trajectory"
    ));
    assert!(!covers(
        "pbrl/<run>/actor/<id>/trajectory",
        "pbrl/<run>/actor/*/eval"
    ));
    // A signature rustfmt wrapped over lines still counts; `new` and `run` make no key.
    let source = concat!(
        "pub fn new(run: &str) -> Result<Self, E> {}\n",
        "pub fn run(&self) -> &str {}\n",
        "pub fn stop(\n        &self,\n    ) -> String {}",
    );
    assert_eq!(key_methods(source), BTreeSet::from(["stop".to_string()]));
}
