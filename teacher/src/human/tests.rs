use super::store::stored_query;
use super::*;
use crate::file::code;
use crate::teacher::Served;
use pbrl_common::wire::Shown as Side;
use std::path::Path;

/// A query whose sides' truths are `first` and `second` at every step.
pub(crate) fn query(id: u64, first: f32, second: f32) -> Query {
    let side = |k: u64, r: f32| Side {
        id: 2 * id + k,
        seed: id,
        policy_version: 1,
        act_dim: 1,
        actions: vec![0.0; 2],
        truth: vec![r, r],
        replay: None,
        start: 0,
        len: 2,
    };
    Query {
        id,
        session: 1,
        asked_at_ms: 1,
        expires_at_ms: 0,
        first: side(0, first),
        second: side(1, second),
        r_avg: None,
        withdraw_at_steps: 0,
        more: Vec::new(),
    }
}

/// The desk served as the teacher loop serves it: with its outbox, in the same file.
fn desk(path: &Path, f: impl FnOnce(&mut HumanConfig)) -> Served<Desk> {
    let mut cfg = HumanConfig {
        repeat_share: 0.0,
        ..HumanConfig::default()
    };
    f(&mut cfg);
    let file = TeacherFile::open(path).unwrap();
    let desk = Desk::open(cfg, &file, "run", "human-0").unwrap();
    Served::new(desk, Outbox::open(&file, "human-0").unwrap())
}

// NOTE: the tests reach the desk's own state through the loop's wrapper.
impl std::ops::Deref for Served<Desk> {
    type Target = Desk;
    fn deref(&self) -> &Desk {
        &self.teacher
    }
}

impl std::ops::DerefMut for Served<Desk> {
    fn deref_mut(&mut self) -> &mut Desk {
        &mut self.teacher
    }
}

fn ms(ms: u64) -> std::time::Duration {
    std::time::Duration::from_millis(ms)
}

fn ack(queries: &[u64]) -> pbrl_common::wire::AnswerAck {
    pbrl_common::wire::AnswerAck {
        teacher_id: "human-0".into(),
        queries: queries.to_vec(),
        repeats: Vec::new(),
    }
}

/// The choice that means `p` on the pair as shown.
fn choose(s: &Showing, p: Preference) -> Choice {
    match (p, s.swapped) {
        (Preference::First, false) | (Preference::Second, true) => Choice::Left,
        (Preference::Second, false) | (Preference::First, true) => Choice::Right,
        (Preference::Equal, _) => Choice::Equal,
        (Preference::Skip, _) => Choice::Skip,
    }
}

#[test]
fn a_person_whose_page_is_open_is_present_answering_or_not() {
    let dir = tempfile::tempdir().unwrap();
    let mut d = desk(&dir.path().join("h.sqlite"), |_| {});
    assert!(d.present().is_empty());
    // Only the status poll of an idle page: no pair asked, no answer given.
    d.seen("ada");
    d.seen("not/a name");
    assert_eq!(d.present(), vec!["ada".to_string()]);
}

#[test]
fn a_stale_query_is_offered_to_nobody_new_and_who_holds_it_may_answer() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("h.sqlite");
    let mut d = desk(&path, |_| {});
    let status = |env_steps| LearnerStatus {
        env_steps,
        ..LearnerStatus::default()
    };
    let stale_at = |id, steps| {
        let mut q = query(id, 1.0, 0.0);
        q.withdraw_at_steps = steps;
        q
    };
    d.learner_status(status(500));
    d.receive(stale_at(1, 1_000)).unwrap();
    d.receive(stale_at(2, 0)).unwrap();
    let held = d.next("ada", None).unwrap().unwrap();
    assert_eq!(held.query.id, 1);
    // The learner has gone past query 1's withdrawal: bob is not offered it (nor would
    // he be once ada's lease ends), a query already stale on arrival is not queued,
    // and ada, who holds it, sees it again and answers it.
    d.learner_status(status(1_500));
    d.receive(stale_at(3, 1_200)).unwrap();
    assert_eq!(d.next("bob", None).unwrap().unwrap().query.id, 2);
    assert!(d.next("cyd", None).unwrap().is_none());
    assert_eq!(d.next("ada", None).unwrap().unwrap().query.id, 1);
    d.expire().unwrap();
    assert!(d.queries.contains_key(&1), "ada still holds it");
    d.answer("ada", 1, Choice::Left, 800, [1, 1]).unwrap();
    // Each first showing is kept with where the learner stood.
    let shown: Vec<(i64, String, i64)> = d
        .store
        .rows("SELECT query, labeller, env_steps FROM shown ORDER BY query, labeller")
        .unwrap();
    assert_eq!(
        shown,
        [(1, "ada".to_string(), 500), (2, "bob".to_string(), 1_500)]
    );
    // A stale query nobody holds leaves the queue.
    d.receive(stale_at(4, 2_000)).unwrap();
    d.learner_status(status(2_000));
    d.expire().unwrap();
    assert!(!d.queries.contains_key(&4) && !d.queries.contains_key(&3));
    // A query an older build kept (no withdrawal step) reads back, never withdrawn.
    let old = pbrl_common::wire::v8::Query {
        id: 9,
        session: 1,
        asked_at_ms: 1,
        expires_at_ms: 0,
        first: query(9, 1.0, 0.0).first,
        second: query(9, 1.0, 0.0).second,
        r_avg: None,
    };
    let bytes = bincode::serde::encode_to_vec(&old, code()).unwrap();
    let read = stored_query(&bytes).unwrap();
    assert_eq!((read.id, read.withdraw_at_steps), (9, 0));
    let now = stale_at(10, 7);
    let bytes = bincode::serde::encode_to_vec(&now, code()).unwrap();
    assert_eq!(stored_query(&bytes).unwrap(), now);
}

#[test]
fn sides_undo_leases_and_the_oracle_shadow() {
    let dir = tempfile::tempdir().unwrap();
    let mut d = desk(&dir.path().join("t.sqlite"), |c| {
        c.shadow = Some(Shadow::Oracle);
        c.undo_s = 3600;
    });
    for id in 1..=40 {
        d.receive(query(id, id as f32, 0.0)).unwrap();
    }
    // Sides are shuffled: over 40 queries both ways occur, and a choice maps back.
    let shown: Vec<Showing> = (0..40)
        .map(|_| {
            let s = d.next("ann", None).unwrap().unwrap();
            d.leases.remove(&s.query.id);
            d.answered.insert(s.query.id);
            s
        })
        .collect();
    assert!(shown.iter().any(|s| s.swapped) && shown.iter().any(|s| !s.swapped));
    // A repeat's sides are drawn afresh: over 40 queries, some differ from the first time.
    assert!((1..=40).any(|q| d.swapped(q, "ann", false) != d.swapped(q, "ann", true)));
    assert!((1..=40).any(|q| d.swapped(q, "ann", false) == d.swapped(q, "ann", true)));
    d.answered.clear();
    // Leases: bob is not shown what ann holds.
    let a = d.next("ann", None).unwrap().unwrap();
    let b = d.next("bob", None).unwrap().unwrap();
    assert_ne!(a.query.id, b.query.id);
    // ann prefers the second trajectory; the store's answer says so whatever the sides.
    d.answer(
        "ann",
        a.query.id,
        choose(&a, Preference::Second),
        900,
        [2, 1],
    )
    .unwrap();
    let g = &d.given[&(a.query.id, "ann".to_string(), false)];
    assert_eq!(g.answer.preference, Preference::Second);
    assert_eq!(g.answer.labeller, "ann");
    // The truth prefers the first (return id against 0): the shadow says first.
    assert_eq!(g.answer.shadow, Some(Preference::First));
    assert_eq!(
        d.answer("bob", a.query.id, Choice::Left, 1, [0, 0]),
        Err(Refused::AnsweredByOther(a.query.id))
    );
    assert_eq!(
        d.answer("ann", a.query.id, Choice::Left, 1, [0, 0]),
        Err(Refused::Answered(a.query.id))
    );
    assert_eq!(
        d.answer("ann", 999, Choice::Left, 1, [0, 0]),
        Err(Refused::Unknown(999))
    );
    // Undo gives the pair back to ann first; nothing is sent meanwhile.
    assert_eq!(d.undo("ann"), Ok(a.query.id));
    assert_eq!(d.undo("ann"), Err(Refused::NothingToUndo));
    assert_eq!(d.next("ann", None).unwrap().unwrap().query.id, a.query.id);
    assert!(d.due(ms(1000)).unwrap().is_empty());
    assert!(matches!(d.next("a/b", None), Err(Refused::Invalid(_))));
}

#[test]
fn answers_survive_a_restart_until_acknowledged_and_go_once_past_undo() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("t.sqlite");
    let (q1, q2) = {
        let mut d = desk(&path, |c| c.undo_s = 0);
        for id in [7, 8, 9] {
            d.receive(query(id, 1.0, 0.0)).unwrap();
        }
        let s1 = d.next("ann", None).unwrap().unwrap();
        d.answer("ann", s1.query.id, Choice::Left, 10, [1, 1])
            .unwrap();
        let s2 = d.next("ann", None).unwrap().unwrap();
        d.answer("ann", s2.query.id, Choice::Equal, 10, [1, 1])
            .unwrap();
        // bob's page shows the last open pair.
        assert!(d.next("bob", None).unwrap().is_some());
        // NOTE: dropped without sending: a teacher killed before the learner heard.
        (s1.query.id, s2.query.id)
    };
    let mut d = desk(&path, |c| c.undo_s = 0);
    assert_eq!(d.open_queries(), 1);
    // The pair on bob's page stays his across the restart.
    assert!(d.next("ann", None).unwrap().is_none());
    assert!(d.next("bob", None).unwrap().is_some());
    let sent = d.due(ms(60_000)).unwrap();
    let mut ids: Vec<u64> = sent.iter().map(|a| a.query).collect();
    ids.sort();
    assert_eq!(ids, vec![q1, q2]);
    // Sent once; again only after the resend interval.
    assert!(d.due(ms(60_000)).unwrap().is_empty());
    // The learner asks q1 again (it did not hear): the same answer, not a new judgement.
    let again = d.receive(query(q1, 1.0, 0.0)).unwrap().unwrap();
    assert_eq!(again.query, q1);
    assert_eq!(d.acknowledged(&ack(&[q1, q2])).unwrap(), 2);
    assert_eq!(d.unacknowledged(), 0);
    drop(d);
    let mut d = desk(&path, |c| c.undo_s = 0);
    assert!(d.due(ms(0)).unwrap().is_empty());
    assert_eq!(d.open_queries(), 1);
}

#[test]
fn a_share_of_answers_is_asked_again_of_the_same_person_and_of_another() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("t.sqlite");
    let mut d = desk(&path, |c| {
        c.repeat_share = 1.0;
        c.undo_s = 0;
    });
    for id in 1..=10 {
        d.receive(query(id, 1.0, 0.0)).unwrap();
    }
    // bob is present (asked for a pair); ann answers query 1.
    let held = d.next("bob", None).unwrap().unwrap();
    let s = d.next("ann", None).unwrap().unwrap();
    let first = s.query.id;
    d.answer("ann", first, Choice::Left, 10, [1, 1]).unwrap();
    // bob gets it at his next pair (his lease stays his own otherwise).
    let r = d.next("bob", Some(held.query.id)).unwrap().unwrap();
    assert!(r.repeat && r.query.id == first);
    d.answer("bob", first, Choice::Right, 10, [1, 1]).unwrap();
    // ann gets it again after three more answers, not before.
    for _ in 0..3 {
        let s = d.next("ann", None).unwrap().unwrap();
        assert!(!s.repeat);
        d.answer("ann", s.query.id, Choice::Skip, 10, [1, 1])
            .unwrap();
    }
    // The first answer reaches the learner; a restart keeps the query answered (not
    // open again) while its repeat waits.
    assert!(d
        .due(ms(60_000))
        .unwrap()
        .iter()
        .any(|a| a.query == first && !a.repeat));
    assert_eq!(d.acknowledged(&ack(&[first])).unwrap(), 1);
    drop(d);
    let mut d = desk(&path, |c| {
        c.repeat_share = 1.0;
        c.undo_s = 0;
    });
    assert!(d.answered.contains(&first));
    let r = d.next("ann", None).unwrap().unwrap();
    assert!(r.repeat && r.query.id == first);
    // A repeat shows under another number than its first showing (ann's was
    // `s.display`), and the same one on a reload.
    assert_ne!(r.display, s.display);
    assert!((1000..10_000).contains(&r.display));
    assert_eq!(d.next("ann", None).unwrap().unwrap().display, r.display);
    d.answer("ann", first, Choice::Equal, 10, [1, 1]).unwrap();
    let repeats: Vec<(String, bool)> = d
        .due(ms(60_000))
        .unwrap()
        .into_iter()
        .filter(|a| a.query == first)
        .map(|a| (a.labeller, a.repeat))
        .collect();
    // The first answer went before the restart; bob's repeat (given before it) and
    // ann's go now.
    assert_eq!(repeats.len(), 2, "{repeats:?}");
    assert!(repeats.contains(&("bob".into(), true)));
    assert!(repeats.contains(&("ann".into(), true)));
}

#[test]
fn a_ranking_is_shown_in_a_persons_order_and_its_places_are_put_back() {
    let dir = tempfile::tempdir().unwrap();
    let mut d = desk(&dir.path().join("t.sqlite"), |c| c.undo_s = 0);
    let mut q = query(1, 3.0, 1.0);
    let mut third = q.first.clone();
    third.id = 9;
    q.more = vec![third];
    d.receive(q).unwrap();
    d.receive(query(2, 1.0, 2.0)).unwrap();
    let shown = d.next("ada", None).unwrap().unwrap();
    assert_eq!(shown.query.id, 1);
    let order = shown.order.clone();
    let mut sorted = order.clone();
    sorted.sort();
    assert_eq!(sorted, [0, 1, 2], "every attempt shown once");
    assert_eq!(
        d.next("ada", None).unwrap().unwrap().order,
        order,
        "the same on a reload"
    );
    // A pair's choice on a ranking, or places for two of its three, are refused.
    for (v, why) in [
        (Verdict::Choice(Choice::Left), "asks to rank 3"),
        (Verdict::Places(vec![0, 1]), "shows 3 attempts"),
        (Verdict::Places(vec![0, 1, 3]), "shows 3 attempts"),
    ] {
        match d.give("ada", 1, v, 10, [0, 0]) {
            Err(Refused::Invalid(e)) => assert!(e.contains(why), "{e}"),
            other => panic!("{other:?}"),
        }
    }
    match d.give("ada", 2, Verdict::Places(vec![0, 1]), 10, [0, 0]) {
        Err(Refused::Invalid(e)) => assert!(e.contains("a pair"), "{e}"),
        other => panic!("{other:?}"),
    }
    // Places as shown: the attempt shown first is the best, then the second, the third.
    d.give("ada", 1, Verdict::Places(vec![0, 1, 2]), 10, [0, 0])
        .unwrap();
    let sent = d.due(ms(60_000)).unwrap();
    let a = sent.iter().find(|a| a.query == 1).unwrap();
    let mut want = vec![0u8; 3];
    for (k, &attempt) in order.iter().enumerate() {
        want[attempt] = k as u8;
    }
    assert_eq!(a.ranks, want);
    assert_eq!(a.preference, Preference::of_places(want[0], want[1]));
}
