use super::*;

/// A trajectory's numbers: odd values (negative zero, subnormals, ...) to check that
/// every bit comes back.
struct Traj {
    actor: u32,
    incarnation: u64,
    seq: u64,
    obs: Vec<f32>,
    actions: Vec<f32>,
}

const OBS_DIM: usize = 3;
const ACT_DIM: usize = 2;

fn traj(actor: u32, seq: u64, steps: usize) -> Traj {
    let odd = [-0.0, f32::MIN_POSITIVE / 3.0, 1.0 / 3.0, f32::MAX, -1.5e-30];
    Traj {
        actor,
        // Above 2^63, as random incarnations are half the time.
        incarnation: u64::MAX - 7,
        seq,
        obs: (0..steps * OBS_DIM)
            .map(|i| odd[(i + seq as usize) % odd.len()])
            .collect(),
        actions: (0..steps * ACT_DIM)
            .map(|i| odd[(i + 2 + actor as usize) % odd.len()])
            .collect(),
    }
}

fn stored(t: &Traj) -> StoredTrajectory<'_> {
    StoredTrajectory {
        actor: t.actor,
        incarnation: t.incarnation,
        seq: t.seq,
        seed: (1 << 63) + t.seq,
        policy_version: 4 + t.seq,
        obs_dim: OBS_DIM,
        act_dim: ACT_DIM,
        obs: &t.obs,
        actions: &t.actions,
        features: &[],
        segment: (0, t.actions.len() / ACT_DIM),
    }
}

fn message(q: u64, a: u64, b: u64) -> Vec<u8> {
    format!("query {q} of {a} and {b}").into_bytes()
}

fn ask(store: &mut LabelStore, a: &Traj, b: &Traj) -> Asked {
    store
        .ask(
            1,
            "disagreement",
            5_000,
            1_000,
            &stored(a),
            &stored(b),
            message,
        )
        .unwrap()
}

/// What a run leaves in the store at `path`: one query of two trajectories, answered
/// `p` if given, and the store closed.
fn left_behind(path: &Path, p: Option<Preference>) -> Asked {
    let mut store = LabelStore::open(path, "run").unwrap();
    let q = ask(&mut store, &traj(0, 1, 3), &traj(1, 1, 3));
    if let Some(p) = p {
        answer(&mut store, q.query, p);
    }
    q
}

fn answer(store: &mut LabelStore, query: u64, p: Preference) -> Stored {
    store
        .answer(
            &Answer::scripted(query, p, "oracle", "oracle-0", 1_500),
            2_000 + query,
        )
        .unwrap()
}

fn bits(xs: &[f32]) -> Vec<u32> {
    xs.iter().map(|x| x.to_bits()).collect()
}

#[test]
fn a_label_round_trips_through_the_file() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("labels.sqlite");
    let (a, b, c) = (traj(0, 1, 4), traj(1, 2, 5), traj(0, 3, 2));
    let (q1, q2) = {
        let mut store = LabelStore::open(&path, "run").unwrap();
        let q1 = ask(&mut store, &a, &b);
        let q2 = ask(&mut store, &c, &b);
        assert_eq!(
            answer(&mut store, q1.query, Preference::Second),
            Stored::New
        );
        assert_eq!(answer(&mut store, q2.query, Preference::Skip), Stored::New);
        (q1, q2)
    };
    assert!(q2.query > q1.query);
    let store = LabelStore::open(&path, "run").unwrap();
    assert_eq!(
        store.counts().unwrap(),
        Counts {
            asked: 2,
            answered: 2,
            second: 1,
            skipped: 1,
            ..Counts::default()
        }
    );
    // A skip counts against the budget, but is no label.
    assert_eq!(
        store.labels_since(0).unwrap(),
        vec![LabelRow {
            answer_no: 1,
            query: q1.query,
            session: 1,
            first: q1.first,
            second: q1.second,
            first_segment: (0, a.actions.len() / ACT_DIM),
            second_segment: (0, b.actions.len() / ACT_DIM),
            preference: Preference::Second,
            answered_at_ms: 2_000 + q1.query,
            more: Vec::new(),
            ranks: Vec::new(),
        }]
    );
    assert!(store.labels_since(1).unwrap().is_empty());
    for (id, t) in [(q1.first, &a), (q1.second, &b), (q2.first, &c)] {
        let s = store.steps(id).unwrap();
        assert_eq!(
            (s.steps, s.obs_dim, s.act_dim),
            (t.actions.len() / ACT_DIM, OBS_DIM, ACT_DIM)
        );
        assert_eq!(bits(&s.obs), bits(&t.obs));
        assert_eq!(bits(&s.actions), bits(&t.actions));
    }
    let e = store.steps(99).unwrap_err().to_string();
    assert!(e.contains("99") && e.contains("labels.sqlite"), "{e}");
    // The view for people: both trajectories' versions and seeds, u64 seeds by bits.
    let (seed, version): (i64, i64) = store
        .conn
        .query_row(
            "SELECT second_seed, second_policy_version FROM labels WHERE query = ?1",
            [q1.query as i64],
            |r| Ok((r.get(0)?, r.get(1)?)),
        )
        .unwrap();
    assert_eq!((seed as u64, version), ((1 << 63) + 2, 6));
    // Durable settings, as read back.
    let sync: i64 = store
        .conn
        .pragma_query_value(None, "synchronous", |r| r.get(0))
        .unwrap();
    let mode: String = store
        .conn
        .pragma_query_value(None, "journal_mode", |r| r.get(0))
        .unwrap();
    assert_eq!((sync, mode.as_str()), (2, "wal"));
}

#[test]
fn a_repeated_answer_leaves_the_first_and_an_unknown_query_is_unknown() {
    let dir = tempfile::tempdir().unwrap();
    let mut store = LabelStore::open(&dir.path().join("labels.sqlite"), "run").unwrap();
    let q = ask(&mut store, &traj(0, 1, 3), &traj(0, 2, 3));
    assert_eq!(answer(&mut store, q.query, Preference::First), Stored::New);
    assert_eq!(
        store
            .answer(
                &Answer::scripted(q.query, Preference::Second, "human", "ann", 9),
                9
            )
            .unwrap(),
        Stored::Repeated
    );
    let labels = store.labels_since(0).unwrap();
    assert_eq!(labels.len(), 1);
    assert_eq!(labels[0].preference, Preference::First);
    assert_eq!(labels[0].answered_at_ms, 2_000 + q.query);
    let teacher: String = store
        .conn
        .query_row("SELECT teacher_id FROM queries", [], |r| r.get(0))
        .unwrap();
    assert_eq!(teacher, "oracle-0");
    assert_eq!(
        answer(&mut store, q.query + 1, Preference::First),
        Stored::Unknown
    );
    assert_eq!(store.counts().unwrap().asked, 1);
}

#[test]
fn an_answer_after_a_restart_is_stored_once() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("labels.sqlite");
    let q = left_behind(&path, None);
    // The learner restarts; the teacher, unacknowledged, sends its answer twice.
    let mut store = LabelStore::open(&path, "run").unwrap();
    assert_eq!(store.open_queries().unwrap().len(), 1);
    assert_eq!(answer(&mut store, q.query, Preference::Equal), Stored::New);
    drop(store);
    let mut store = LabelStore::open(&path, "run").unwrap();
    assert_eq!(
        answer(&mut store, q.query, Preference::Equal),
        Stored::Repeated
    );
    let c = store.counts().unwrap();
    assert_eq!((c.asked, c.answered, c.equal, c.open), (1, 1, 1, 0));
    // Ids are never reused: the next query's id is above every earlier one.
    let next = ask(&mut store, &traj(0, 5, 3), &traj(1, 5, 3));
    assert!(next.query > q.query && next.first > q.second);
}

#[test]
fn a_trajectory_in_two_queries_is_stored_once() {
    let dir = tempfile::tempdir().unwrap();
    let mut store = LabelStore::open(&dir.path().join("labels.sqlite"), "run").unwrap();
    let (a, b, c) = (traj(0, 1, 3), traj(0, 2, 3), traj(2, 1, 3));
    let q1 = ask(&mut store, &a, &b);
    let q2 = ask(&mut store, &c, &a);
    assert_eq!(q2.second, q1.first);
    let n: i64 = store
        .conn
        .query_row("SELECT count(*) FROM trajectories", [], |r| r.get(0))
        .unwrap();
    assert_eq!(n, 3);
    // The same numbering with another episode is a bug upstream: refused, named.
    let mut other = stored(&a);
    other.seed += 1;
    let e = store
        .ask(1, "uniform", 0, 0, &other, &stored(&b), message)
        .unwrap_err();
    assert!(format!("{e:#}").contains("(actor 0, incarnation"), "{e:#}");
    // A trajectory against itself, or of the wrong shape, is refused before storing.
    assert!(store
        .ask(1, "uniform", 0, 0, &stored(&a), &stored(&a), message)
        .is_err());
    let mut short = stored(&c);
    short.obs = &c.obs[1..];
    let e = store
        .ask(1, "uniform", 0, 0, &stored(&a), &short, message)
        .unwrap_err();
    assert!(e.to_string().contains("second trajectory"), "{e}");
    assert_eq!(store.counts().unwrap().asked, 2);
}

#[test]
fn a_schema_1_store_is_upgraded_in_place_and_keeps_its_labels() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("labels.sqlite");
    let q = left_behind(&path, Some(Preference::First));
    // Back to the layout of schema 1, as an older build wrote it.
    let conn = Connection::open(&path).unwrap();
    conn.execute_batch(
        "DROP VIEW labels; DROP TABLE repeats;
         ALTER TABLE queries DROP COLUMN labeller;
         ALTER TABLE queries DROP COLUMN replays_first;
         ALTER TABLE queries DROP COLUMN replays_second;
         ALTER TABLE queries DROP COLUMN shadow;
         ALTER TABLE queries DROP COLUMN first_start;
         ALTER TABLE queries DROP COLUMN first_len;
         ALTER TABLE queries DROP COLUMN second_start;
         ALTER TABLE queries DROP COLUMN second_len;
         ALTER TABLE trajectories DROP COLUMN features;
         ALTER TABLE queries DROP COLUMN withdrawn_at_steps;
         DROP TABLE query_attempts; ALTER TABLE queries DROP COLUMN ranks;
         CREATE VIEW labels AS SELECT id AS query FROM queries;
         UPDATE meta SET value = '1' WHERE key = 'schema';",
    )
    .unwrap();
    drop(conn);
    let mut store = LabelStore::open(&path, "run").unwrap();
    assert_eq!(store.counts().unwrap().first, 1);
    let a = Answer {
        labeller: "ann".into(),
        repeat: true,
        ..Answer::scripted(q.query, Preference::Second, "human", "human-0", 5)
    };
    assert_eq!(store.repeat(&a, 9).unwrap(), Stored::New);
    assert_eq!(store.repeat(&a, 9).unwrap(), Stored::Repeated);
    let schema: String = store
        .conn
        .query_row("SELECT value FROM meta WHERE key = 'schema'", [], |r| {
            r.get(0)
        })
        .unwrap();
    assert_eq!(schema, SCHEMA.to_string());
    let rows = store.labels_since(0).unwrap();
    assert_eq!(
        (rows[0].first_segment, rows[0].second_segment),
        ((0, 3), (0, 3))
    );
}

#[test]
fn a_schema_2_store_reads_its_queries_as_whole_trajectories_and_stores_segments() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("labels.sqlite");
    let q = left_behind(&path, Some(Preference::Second));
    // Back to the layout of schema 2, as the build before segments wrote it.
    let conn = Connection::open(&path).unwrap();
    conn.execute_batch(
        "DROP VIEW labels;
         ALTER TABLE queries DROP COLUMN first_start;
         ALTER TABLE queries DROP COLUMN first_len;
         ALTER TABLE queries DROP COLUMN second_start;
         ALTER TABLE queries DROP COLUMN second_len;
         ALTER TABLE trajectories DROP COLUMN features;
         ALTER TABLE queries DROP COLUMN withdrawn_at_steps;
         DROP TABLE query_attempts; ALTER TABLE queries DROP COLUMN ranks;
         CREATE VIEW labels AS SELECT id AS query FROM queries;
         UPDATE meta SET value = '2' WHERE key = 'schema';",
    )
    .unwrap();
    drop(conn);
    let mut store = LabelStore::open(&path, "run").unwrap();
    let rows = store.labels_since(0).unwrap();
    assert_eq!(rows.len(), 1);
    assert_eq!(rows[0].query, q.query);
    assert_eq!(rows[0].preference, Preference::Second);
    assert_eq!(
        (rows[0].first_segment, rows[0].second_segment),
        ((0, 3), (0, 3))
    );
    // A new query compares segments; they come back with its label and in the view.
    let (a, b) = (traj(0, 7, 5), traj(1, 7, 5));
    let (mut sa, mut sb) = (stored(&a), stored(&b));
    (sa.segment, sb.segment) = ((1, 3), (2, 3));
    // Schema 4: a trajectory keeps its comfort features (the older ones none).
    let features: Vec<f32> = (0..5 * 6).map(|i| i as f32 * 0.5).collect();
    sa.features = &features;
    let asked = store.ask(2, "uniform", 10, 5, &sa, &sb, message).unwrap();
    answer(&mut store, asked.query, Preference::First);
    assert!(store.steps(rows[0].first).unwrap().features.is_empty());
    // Asked again with its features, an older trajectory gains them.
    let old = traj(0, 1, 3);
    let mut again = stored(&old);
    let old_features = vec![1.5; 3 * 6];
    again.features = &old_features;
    let re = store
        .ask(2, "uniform", 10, 5, &again, &sb, message)
        .unwrap();
    assert_eq!(re.first, rows[0].first, "the same trajectory");
    assert_eq!(store.steps(re.first).unwrap().features, old_features);
    assert_eq!(store.steps(asked.first).unwrap().features, features);
    assert!(store.steps(asked.second).unwrap().features.is_empty());
    let mut ragged = stored(&a);
    ragged.features = &features[..7];
    let e = store
        .ask(2, "uniform", 10, 5, &ragged, &sb, message)
        .unwrap_err();
    assert!(format!("{e:#}").contains("comfort feature"), "{e:#}");
    let rows = store.labels_since(rows[0].answer_no).unwrap();
    assert_eq!(
        (rows[0].first_segment, rows[0].second_segment),
        ((1, 3), (2, 3))
    );
    let view: Vec<(i64, i64, i64, i64)> = store
        .conn
        .prepare("SELECT first_start, first_len, second_start, second_len FROM labels")
        .unwrap()
        .query_map([], |r| Ok((r.get(0)?, r.get(1)?, r.get(2)?, r.get(3)?)))
        .unwrap()
        .collect::<rusqlite::Result<_>>()
        .unwrap();
    assert_eq!(view, vec![(0, 3, 0, 3), (1, 3, 2, 3)]);
    // A segment outside its trajectory is refused, named.
    sa.segment = (3, 3);
    let e = store
        .ask(2, "uniform", 10, 5, &sa, &sb, message)
        .unwrap_err();
    assert!(
        format!("{e:#}").contains("segment start 3, length 3"),
        "{e:#}"
    );
}

#[test]
fn open_queries_keep_their_message_until_answered_or_expired() {
    let dir = tempfile::tempdir().unwrap();
    let mut store = LabelStore::open(&dir.path().join("labels.sqlite"), "run").unwrap();
    let q1 = ask(&mut store, &traj(0, 1, 3), &traj(0, 2, 3));
    let q2 = ask(&mut store, &traj(0, 3, 3), &traj(0, 4, 3));
    let q3 = ask(&mut store, &traj(0, 5, 3), &traj(0, 6, 3));
    let open = store.open_queries().unwrap();
    assert_eq!(
        open,
        [&q1, &q2, &q3]
            .map(|q| (q.query, 1_000, message(q.query, q.first, q.second)))
            .to_vec()
    );
    assert_eq!(answer(&mut store, q2.query, Preference::First), Stored::New);
    assert!(store.expire(q1.query, 3_000).unwrap());
    assert!(!store.expire(q1.query, 3_001).unwrap());
    assert!(!store.expire(q2.query, 3_001).unwrap());
    assert_eq!(
        store.open_queries().unwrap(),
        vec![(q3.query, 1_000, message(q3.query, q3.first, q3.second))]
    );
    let c = store.counts().unwrap();
    assert_eq!((c.asked, c.answered, c.expired, c.open), (3, 1, 1, 1));
    // A late answer is a person's judgement too: stored, and counted as late.
    assert_eq!(
        answer(&mut store, q1.query, Preference::Second),
        Stored::Late
    );
    let c = store.counts().unwrap();
    assert_eq!((c.answered, c.expired, c.late, c.labels()), (2, 0, 1, 2));
    // Answered out of query order: the cursor is the answer's number.
    let labels = store.labels_since(0).unwrap();
    assert_eq!(
        labels.iter().map(|l| l.query).collect::<Vec<_>>(),
        vec![q2.query, q1.query]
    );
    let after = store.labels_since(labels[0].answer_no).unwrap();
    assert_eq!(after.len(), 1);
    assert_eq!(after[0].query, q1.query);
}

#[test]
fn a_withdrawn_query_spends_no_budget_and_its_late_answer_is_stored_once() {
    let dir = tempfile::tempdir().unwrap();
    let mut store = LabelStore::open(&dir.path().join("labels.sqlite"), "run").unwrap();
    let q1 = ask(&mut store, &traj(0, 1, 3), &traj(1, 1, 3));
    // A second query stays open throughout.
    ask(&mut store, &traj(0, 2, 3), &traj(1, 2, 3));
    assert!(store.withdraw(q1.query, 2_000, 7_000).unwrap());
    assert!(
        !store.withdraw(q1.query, 2_001, 7_100).unwrap(),
        "withdrawn once"
    );
    let c = store.counts().unwrap();
    assert_eq!((c.asked, c.expired, c.withdrawn, c.open), (2, 1, 1, 1));
    assert_eq!(c.spent(), 1, "a withdrawn query spent no one's time");
    assert_eq!(store.open_queries().unwrap().len(), 1);
    // The person who held it answers after all: stored once, as late, and it counts.
    assert_eq!(
        answer(&mut store, q1.query, Preference::First),
        Stored::Late
    );
    assert_eq!(
        answer(&mut store, q1.query, Preference::First),
        Stored::Repeated
    );
    let c = store.counts().unwrap();
    assert_eq!((c.withdrawn, c.late, c.labels(), c.spent()), (0, 1, 1, 2));
    let at: i64 = store
        .conn
        .query_row(
            "SELECT withdrawn_at_steps FROM queries WHERE id = ?1",
            [int(q1.query)],
            |r| r.get(0),
        )
        .unwrap();
    assert_eq!(at, 7_000, "where it was withdrawn is kept");
    assert_eq!(store.labels_since(0).unwrap().len(), 1);
}

#[test]
fn another_runs_store_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("labels.sqlite");
    drop(LabelStore::open(&path, "feeding-a").unwrap());
    let e = LabelStore::open(&path, "feeding-b")
        .err()
        .unwrap()
        .to_string();
    assert!(
        e.contains("\"feeding-a\"") && e.contains("\"feeding-b\"") && e.contains("labels.sqlite"),
        "{e}"
    );
    // Nor is a file that is not a store taken for one.
    let junk = dir.path().join("junk.sqlite");
    std::fs::write(&junk, vec![0x5a; 4096]).unwrap();
    let e = format!("{:#}", LabelStore::open(&junk, "feeding-a").err().unwrap());
    assert!(e.contains("junk.sqlite"), "{e}");
}

#[test]
fn a_second_connection_reads_while_the_first_writes() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("labels.sqlite");
    let mut writer = LabelStore::open(&path, "run").unwrap();
    let reader = LabelStore::open(&path, "run").unwrap();
    let q = ask(&mut writer, &traj(0, 1, 3), &traj(0, 2, 3));
    answer(&mut writer, q.query, Preference::Equal);
    assert_eq!(reader.labels_since(0).unwrap().len(), 1);
    assert_eq!(reader.steps(q.first).unwrap().steps, 3);
}

#[test]
fn a_committed_answer_survives_a_crash() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("labels.sqlite");
    let wal = dir.path().join("labels.sqlite-wal");
    let mut store = LabelStore::open(&path, "run").unwrap();
    let q = ask(&mut store, &traj(0, 1, 3), &traj(0, 2, 3));
    let open = ask(&mut store, &traj(0, 3, 3), &traj(0, 2, 3));
    assert_eq!(answer(&mut store, q.query, Preference::First), Stored::New);
    // NOTE: the crash: copy the files as they are while the store is still open (no
    // close, no checkpoint; the WAL still holds the commits), and open the copy.
    assert!(std::fs::metadata(&wal).unwrap().len() > 0);
    let crashed = tempfile::tempdir().unwrap();
    let copy = crashed.path().join("labels.sqlite");
    std::fs::copy(&path, &copy).unwrap();
    std::fs::copy(&wal, crashed.path().join("labels.sqlite-wal")).unwrap();
    let recovered = LabelStore::open(&copy, "run").unwrap();
    let labels = recovered.labels_since(0).unwrap();
    assert_eq!(labels.len(), 1);
    assert_eq!(
        (labels[0].query, labels[0].preference),
        (q.query, Preference::First)
    );
    assert_eq!(recovered.steps(q.second).unwrap().steps, 3);
    // The open query can be asked again, as it was sent.
    assert_eq!(
        recovered.open_queries().unwrap(),
        vec![(
            open.query,
            1_000,
            message(open.query, open.first, open.second)
        )]
    );
    // (Open until here, so that nothing closed it cleanly before the copy.)
    drop(store);
}

#[test]
fn a_ranking_is_one_answer_with_every_attempt_and_a_misfit_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("labels.sqlite");
    let mut store = LabelStore::open(&path, "run").unwrap();
    let ts: Vec<Traj> = (0..4).map(|k| traj(1, k, 4 + k as usize)).collect();
    let mut sides: Vec<StoredTrajectory<'_>> = ts.iter().map(stored).collect();
    sides[3].segment = (1, 2);
    let refs: Vec<&StoredTrajectory<'_>> = sides.iter().collect();
    let asked = store
        .ask_attempts(3, "disagreement", 7_000, 2_000, &refs, |q, ids| {
            format!("query {q} of {ids:?}").into_bytes()
        })
        .unwrap();
    assert_eq!(asked.more.len(), 2);
    // A pair's answer to a ranking, and places for three of four attempts, do not fit.
    let pair = Answer::scripted(asked.query, Preference::First, "oracle", "o-0", 1);
    assert_eq!(store.answer(&pair, 10).unwrap(), Stored::Misfit);
    let three = Answer::ranked(asked.query, vec![0, 1, 2], "oracle", "o-0", 1);
    assert_eq!(store.answer(&three, 10).unwrap(), Stored::Misfit);
    assert_eq!(store.counts().unwrap().open, 1, "still open");
    let ranked = Answer::ranked(asked.query, vec![2, 0, 2, 1], "oracle", "o-0", 1);
    assert_eq!(store.answer(&ranked, 11).unwrap(), Stored::New);
    assert_eq!(store.answer(&ranked, 12).unwrap(), Stored::Repeated);
    let counts = store.counts().unwrap();
    assert_eq!((counts.asked, counts.answered, counts.open), (1, 1, 0));
    // Read back after a reopen: one label, every attempt with its segment, the places.
    drop(store);
    let store = LabelStore::open(&path, "run").unwrap();
    let rows = store.labels_since(0).unwrap();
    assert_eq!(rows.len(), 1);
    let r = &rows[0];
    assert_eq!(r.ranks, [2, 0, 2, 1]);
    assert_eq!(r.preference, Preference::Second);
    let ids = [asked.first, asked.second, asked.more[0], asked.more[1]];
    let segs = [(0, 4), (0, 5), (0, 6), (1, 2)];
    assert_eq!(r.attempts(), ids.into_iter().zip(segs).collect::<Vec<_>>());
    for (id, t) in ids.iter().zip(&ts) {
        assert_eq!(store.steps(*id).unwrap().actions, t.actions);
    }
    // A pair's row has no places and two attempts.
    let mut store = store;
    let q = ask(&mut store, &ts[0], &ts[1]);
    store
        .answer(
            &Answer::scripted(q.query, Preference::Equal, "oracle", "o-0", 1),
            20,
        )
        .unwrap();
    let rows = store.labels_since(r.answer_no).unwrap();
    assert_eq!((rows[0].ranks.len(), rows[0].attempts().len()), (0, 2));
}
