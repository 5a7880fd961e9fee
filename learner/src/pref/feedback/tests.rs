use super::train::{lower_priority, pseudo_labels};
use super::*;
use crate::pref::config::SegmentStart;
use pbrl_common::wire::{Answer, Preference};
use pbrl_common::{StepRewards, Trajectory};
use std::path::Path;

/// This thread's nice value.
#[cfg(target_os = "linux")]
fn thread_nice() -> i32 {
    // SAFETY: getpriority only reads this thread's priority.
    unsafe { libc::getpriority(libc::PRIO_PROCESS, 0) }
}

#[cfg(target_os = "linux")]
#[test]
fn the_feedback_job_runs_ten_nice_levels_below_its_caller_and_never_above_it() {
    std::thread::spawn(|| {
        let before = thread_nice();
        lower_priority();
        assert_eq!(thread_nice(), (before + 10).min(19));
    })
    .join()
    .unwrap();
    // A learner run under `nice -n 15` (as `pbrl exp` grids often are): the job must
    // not come out at nice 10, above the learner.
    std::thread::spawn(|| {
        let niced = thread_nice().max(15);
        // SAFETY: setpriority only sets this thread's priority (raising a nice value
        // needs no privilege).
        assert_eq!(
            unsafe { libc::setpriority(libc::PRIO_PROCESS, 0, niced) },
            0
        );
        lower_priority();
        assert_eq!(thread_nice(), 19);
    })
    .join()
    .unwrap();
}

fn msg(seq: u64) -> TrajectoryMsg {
    let steps = 3;
    TrajectoryMsg {
        actor: 0,
        incarnation: 1,
        seq,
        oldest: 0,
        trajectory: Trajectory {
            format: pbrl_common::trajectory::TRAJECTORY_FORMAT,
            seed: seq,
            policy_version: 1,
            obs_dim: 2,
            act_dim: 1,
            obs: vec![seq as f32; (steps + 1) * 2],
            actions: vec![0.5; steps],
            rewards: vec![StepRewards::default(); steps],
            ..Trajectory::default()
        },
    }
}

#[test]
fn open_queries_are_bounded_and_a_due_session_waits_for_answers() {
    let cfg = PrefConfig {
        unsup_steps: 0,
        queries_per_session: 30,
        feedback_interval: 100,
        max_open_queries: 50,
        ..PrefConfig::plain()
    };
    let mut f = Feedback::new(&cfg, "run", 2, 1, 0, Path::new(":memory:")).unwrap();
    for seq in 0..40 {
        f.observe(&msg(seq));
    }
    let mut asked = Vec::new();
    for env_steps in [0, 100, 200, 300] {
        if let Some(done) = f.start(env_steps, true).unwrap() {
            asked.extend(f.finish(done, env_steps).unwrap().0);
        }
        assert!(f.open() <= 50, "{} open at {env_steps}", f.open());
    }
    // 30, then the 20 the bound leaves; then the sessions wait: nobody answered.
    assert_eq!(asked.len(), 50);
    assert_eq!(f.open(), 50);
    assert!(f.waiting(400).unwrap());
    assert!(f.start(400, true).unwrap().is_none());
    // One answer makes room for one query.
    let a = Answer::scripted(asked[0].id, Preference::First, "oracle", "o-0", 1);
    assert!(matches!(f.answer(&a).unwrap(), Answered::Ack(_)));
    assert!(!f.waiting(400).unwrap());
    let mut more = Vec::new();
    for _ in 0..2 {
        // NOTE: the first job may be the training on the new label.
        if let Some(done) = f.start(400, true).unwrap() {
            more.extend(f.finish(done, 400).unwrap().0);
        }
    }
    assert_eq!(more.len(), 1);
    assert!(f.waiting(500).unwrap());
}

#[test]
fn keeping_time_holds_from_the_slack_past_an_ask_until_its_answers_are_trained_on() {
    let cfg = PrefConfig {
        unsup_steps: 0,
        queries_per_session: 2,
        feedback_interval: 1_000,
        label_slack_steps: Some(300),
        label_slack_s: Some(60.0),
        ..PrefConfig::plain()
    };
    let mut f = Feedback::new(&cfg, "run", 2, 1, 0, Path::new(":memory:")).unwrap();
    for seq in 0..10 {
        f.observe(&msg(seq));
    }
    let t0 = Instant::now();
    assert!(!f.holds(5_000, t0), "nothing asked: nothing to wait for");
    let done = f.start(100, true).unwrap().unwrap();
    let asked = f.finish(done, 100).unwrap().0;
    assert_eq!(asked.len(), 2);
    // Asked at 100: the learner may run to 400, or for 60 s.
    assert!(!f.holds(399, t0));
    assert!(f.holds(400, t0));
    assert!(f.holds(100, t0 + Duration::from_secs(61)));
    // One answer in: the other is still open.
    for (k, q) in asked.iter().enumerate() {
        let a = Answer::scripted(q.id, Preference::First, "oracle", "o-0", 1);
        assert!(matches!(f.answer(&a).unwrap(), Answered::Ack(_)));
        // Answered but not trained on: still held.
        assert!(f.holds(400, t0), "after answer {k}");
    }
    let done = f.start(400, true).unwrap().unwrap();
    assert!(matches!(done, JobDone::Trained { .. }));
    f.finish(done, 400).unwrap();
    assert!(!f.holds(400, t0 + Duration::from_secs(61)));
    // Unset, the learner never waits.
    let never = PrefConfig {
        label_slack_steps: None,
        label_slack_s: None,
        ..cfg
    };
    let mut g = Feedback::new(&never, "run", 2, 1, 0, Path::new(":memory:")).unwrap();
    for seq in 0..10 {
        g.observe(&msg(seq));
    }
    let done = g.start(100, true).unwrap().unwrap();
    assert_eq!(g.finish(done, 100).unwrap().0.len(), 2);
    assert!(!g.holds(u64::MAX, t0 + Duration::from_secs(1_000_000)));
}

#[test]
fn with_people_queries_are_asked_just_in_time_and_a_stale_one_is_withdrawn() {
    let cfg = PrefConfig {
        unsup_steps: 0,
        queries_per_session: 10,
        feedback_interval: 10_000,
        open_per_labeller: 2,
        query_stale_steps: 500,
        queries_per_trajectory: 1,
        ..PrefConfig::plain()
    };
    let mut f = Feedback::new(&cfg, "run", 2, 1, 0, Path::new(":memory:")).unwrap();
    for seq in 0..40 {
        f.observe(&msg(seq));
    }
    let run = |f: &mut Feedback, env_steps| {
        let mut out = Vec::new();
        for _ in 0..3 {
            if let Some(done) = f.start(env_steps, true).unwrap() {
                out.extend(f.finish(done, env_steps).unwrap().0);
            }
        }
        out
    };
    // Nobody at a page yet: room for one person's 2; the session's other 8 are owed.
    let first = run(&mut f, 0);
    assert_eq!(first.len(), 2);
    assert!(f.waiting(0).unwrap());
    assert!(first.iter().all(|q| q.withdraw_at_steps == 500));
    // Two people: room for 4, asked at once from what is owed.
    f.set_labellers(2);
    let more = run(&mut f, 100);
    assert_eq!(more.len(), 2);
    assert_eq!(f.open(), 4);
    // No trajectory is in two open queries.
    let mut sides: Vec<u64> = first
        .iter()
        .chain(&more)
        .flat_map(|q| [q.first.seed, q.second.seed])
        .collect();
    sides.sort();
    sides.dedup();
    assert_eq!(sides.len(), 8, "a trajectory in two open queries");
    // Past 500 env steps the first two are stale: withdrawn, and fresh ones asked.
    f.retry(550).unwrap();
    assert_eq!(f.open(), 2);
    let c = f.counts().unwrap();
    assert_eq!((c.withdrawn, c.spent()), (2, 2));
    let fresh = run(&mut f, 550);
    assert_eq!(fresh.len(), 2);
    assert!(fresh.iter().all(|q| q.withdraw_at_steps == 1_050));
    // A withdrawn query's late answer is stored, once, and joins D.
    let a = Answer::scripted(first[0].id, Preference::First, "human", "h-0", 1);
    assert!(matches!(f.answer(&a).unwrap(), Answered::Ack(_)));
    assert!(matches!(f.answer(&a).unwrap(), Answered::Ack(_)));
    let c = f.counts().unwrap();
    assert_eq!((c.late, c.labels(), c.withdrawn), (1, 1, 1));
    assert_eq!(f.data.len(), 1);
}

/// A 200-step trajectory numbered `seq`: observation (seq, step), truth `seq` a step.
fn long(seq: u64) -> TrajectoryMsg {
    let steps = 200;
    let mut m = msg(seq);
    let t = &mut m.trajectory;
    t.obs = (0..=steps).flat_map(|k| [seq as f32, k as f32]).collect();
    t.actions = vec![0.5; steps];
    t.rewards = vec![
        StepRewards {
            truth: seq as f32,
            ..StepRewards::default()
        };
        steps
    ];
    m
}

#[test]
fn queries_compare_segments_of_the_newest_trajectories_with_the_sessions_r_avg() {
    let cfg = PrefConfig {
        unsup_steps: 0,
        queries_per_session: 20,
        feedback_interval: 100,
        segment_len: 50,
        query_recent: 10,
        ..PrefConfig::plain()
    };
    let mut f = Feedback::new(&cfg, "run", 2, 1, 3, Path::new(":memory:")).unwrap();
    for seq in 0..150 {
        f.observe(&long(seq));
    }
    let done = f.start(0, true).unwrap().unwrap();
    let queries = f.finish(done, 0).unwrap().0;
    assert_eq!(queries.len(), 20);
    let mut starts = std::collections::BTreeSet::new();
    for q in &queries {
        // R_avg: the mean return of the newest 100 (seq 50..150, 200 steps each).
        assert_eq!(q.r_avg, Some(99.5 * 200.0));
        for s in [&q.first, &q.second] {
            assert_eq!(s.len, 50);
            assert!(s.start as usize + 50 <= 200);
            starts.insert(s.start);
            // Policy-aligned: only the newest 10 (seq 140..150, seeds = seq).
            assert!(s.seed >= 140, "seed {}", s.seed);
            assert_eq!(
                s.steps(),
                200,
                "the whole trajectory travels for the replay"
            );
        }
    }
    assert!(starts.len() > 20, "starts are drawn: {starts:?}");
    // The label trains on the segments: their observations carry the step numbers.
    let q = &queries[0];
    let a = Answer::scripted(q.id, Preference::Second, "oracle", "o-0", 1);
    assert!(matches!(f.answer(&a).unwrap(), Answered::Ack(_)));
    let l = f.data.last().unwrap().clone();
    assert_eq!(l.first.obs.len(), 50 * 2);
    assert_eq!(l.first.obs[1], q.first.start as f32);
    assert_eq!(l.second.obs[99], (q.second.start + 49) as f32);
    // The whole trajectories stay in memory only while a query in flight compares
    // them: once every query is answered, D holds only its segments.
    let open = |f: &Feedback, id: u64| {
        f.in_flight
            .values()
            .any(|o| o.query.first.id == id || o.query.second.id == id)
    };
    for id in [q.first.id, q.second.id] {
        assert_eq!(
            f.segments.contains_key(&id),
            open(&f, id),
            "trajectory {id}"
        );
    }
    for q in &queries[1..] {
        let a = Answer::scripted(q.id, Preference::First, "oracle", "o-0", 1);
        assert!(matches!(f.answer(&a).unwrap(), Answered::Ack(_)));
    }
    assert!(f.in_flight.is_empty());
    assert!(
        f.segments.is_empty(),
        "{} whole trajectories kept",
        f.segments.len()
    );
    // The same after a restart: D is read back from the store with its segments.
    let d = |f: &Feedback| {
        let mut d: Vec<_> = f
            .data
            .iter()
            .map(|l| (l.first.obs.clone(), l.second.obs.clone()))
            .collect();
        d.sort_by(|a, b| a.partial_cmp(b).unwrap());
        d
    };
    let before = d(&f);
    f.reload().unwrap();
    assert_eq!(f.data.len(), 20);
    assert_eq!(d(&f), before);
    assert!(f.segments.is_empty(), "a reload keeps whole trajectories");
}

#[test]
fn segment_starts_are_golden_for_a_seed() {
    // The draw of segments is part of a run's determinism: the same seed, the same
    // starts (a change here changes every `--sync` curve).
    let cfg = PrefConfig {
        unsup_steps: 0,
        queries_per_session: 4,
        sampler: Sampler::Uniform,
        segment_len: 50,
        ..PrefConfig::plain()
    };
    let mut f = Feedback::new(&cfg, "run", 2, 1, 3, Path::new(":memory:")).unwrap();
    for seq in 0..20 {
        f.observe(&long(seq));
    }
    let done = f.start(0, true).unwrap().unwrap();
    let q = f.finish(done, 0).unwrap().0;
    let got: Vec<(u64, u32, u64, u32)> = q
        .iter()
        .map(|q| (q.first.seed, q.first.start, q.second.seed, q.second.start))
        .collect();
    assert_eq!(got, GOLDEN_STARTS.to_vec());
    // The end of the trajectory, on request.
    let cfg = PrefConfig {
        segment_start: SegmentStart::End,
        ..cfg
    };
    let mut f = Feedback::new(&cfg, "run", 2, 1, 3, Path::new(":memory:")).unwrap();
    for seq in 0..20 {
        f.observe(&long(seq));
    }
    let done = f.start(0, true).unwrap().unwrap();
    let q = f.finish(done, 0).unwrap().0;
    assert!(q
        .iter()
        .all(|q| q.first.start == 150 && q.second.start == 150));
}

#[test]
fn pseudo_labels_are_the_ensembles_sure_answers_and_nothing_else() {
    // A reward that learnt "more obs[0] is better" (segments of constant obs).
    let seg = |v: f32, steps: usize| Segment {
        obs: vec![v; steps],
        actions: vec![0.0; steps],
        features: Vec::new(),
    };
    let cfg = crate::pref::reward_model::RewardModelConfig {
        hidden: vec![16],
        lr: 3e-3,
        seed: 1,
        ..crate::pref::reward_model::RewardModelConfig::plain()
    };
    let mut model = RewardModel::new(cfg, 1, 1).unwrap();
    let labels: Vec<Labelled> = (0..64)
        .map(|k| {
            let (a, b) = ((k % 8) as f32 / 4.0 - 1.0, ((k / 8) % 8) as f32 / 4.0 - 1.0);
            Labelled {
                first: Arc::new(seg(a, 5)),
                second: Arc::new(seg(b, 5)),
                target: if b > a {
                    1.0
                } else if a > b {
                    0.0
                } else {
                    0.5
                },
            }
        })
        .collect();
    model.train(&labels).unwrap();
    let side = |v: f32| Side {
        trajectory: Arc::new(Candidate {
            key: crate::pref::query::TrajKey {
                actor: 0,
                incarnation: 0,
                seq: (100.0 * v) as u64,
            },
            seed: 0,
            policy_version: 0,
            obs_dim: 1,
            act_dim: 1,
            obs: vec![v; 5],
            actions: vec![0.0; 5],
            truth: vec![0.0; 5],
            features: Vec::new(),
        }),
        start: 0,
        len: 5,
    };
    // Sure: the far ends, either way round; unsure: two alike.
    let pairs = vec![
        (side(-1.0), side(1.0)),
        (side(1.0), side(-1.0)),
        (side(0.5), side(0.5)),
    ];
    let got = pseudo_labels(&model, &pairs, 0.6).unwrap();
    let targets: Vec<f32> = got.iter().map(|l| l.target).collect();
    assert_eq!(targets, vec![1.0, 0.0], "the alike pair is left out");
    assert_eq!(got[0].first.obs, vec![-1.0; 5]);
    // Nothing is sure enough at tau 1.
    assert!(pseudo_labels(&model, &pairs, 1.0).unwrap().is_empty());
}

const GOLDEN_STARTS: [(u64, u32, u64, u32); 4] = [
    (6, 122, 2, 122),
    (7, 80, 12, 28),
    (3, 108, 1, 58),
    (16, 30, 13, 42),
];

#[test]
fn rankings_of_a_known_order_are_asked_stored_as_all_their_pairs_and_learnt() {
    let cfg = PrefConfig {
        unsup_steps: 0,
        queries_per_session: 12,
        feedback_interval: 100,
        query_attempts: 4,
        query_recent: 0,
        max_feedback: 12,
        ..PrefConfig::plain()
    };
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("labels.sqlite");
    let mut f = Feedback::new(&cfg, "run", 2, 1, 0, &path).unwrap();
    for seq in 0..40 {
        f.observe(&msg(seq));
    }
    let done = f.start(0, true).unwrap().unwrap();
    let asked = f.finish(done, 0).unwrap().0;
    assert_eq!(asked.len(), 12);
    // The teacher's order: the larger observation is better (msg's obs are its seq).
    let value = |s: &pbrl_common::wire::Shown| s.id;
    let mut seqs = Vec::new();
    for q in &asked {
        assert_eq!(q.len(), 4, "a ranking of four");
        let obs: Vec<f32> = q
            .attempts()
            .map(|s| f.segment(value(s)).unwrap().obs[0])
            .collect();
        seqs.extend(obs.iter().copied());
        let places: Vec<u8> = obs
            .iter()
            .map(|o| obs.iter().filter(|x| *x > o).count() as u8)
            .collect();
        let a = Answer::ranked(q.id, places, "oracle", "o-0", 1);
        assert!(matches!(f.answer(&a).unwrap(), Answered::Ack(_)));
    }
    assert_eq!(
        f.data.len(),
        12 * 6,
        "each ranking of four is six pairs of D"
    );
    assert_eq!(f.counts().unwrap().answered, 12, "and one answer each");
    let done = f.start(0, true).unwrap().unwrap();
    assert!(matches!(done, JobDone::Trained { .. }));
    f.finish(done, 0).unwrap();
    assert!(
        f.counters.accuracy >= 0.95,
        "accuracy {}",
        f.counters.accuracy
    );
    // D read back from the store after a restart is the same 72 pairs.
    let mut g = Feedback::new(&cfg, "run", 2, 1, 0, &path).unwrap();
    g.reload().unwrap();
    assert_eq!(g.data.len(), 72);
    let targets = |d: &[Labelled]| d.iter().map(|l| l.target).collect::<Vec<_>>();
    assert_eq!(targets(&g.data), targets(&f.data));
    assert!(seqs.iter().any(|&s| s != seqs[0]));
}

#[test]
fn the_agreement_is_counted_on_answers_the_trained_ensemble_had_not_seen() {
    let cfg = PrefConfig {
        unsup_steps: 0,
        queries_per_session: 8,
        feedback_interval: 100,
        query_recent: 0,
        ..PrefConfig::plain()
    };
    let mut f = Feedback::new(&cfg, "run", 2, 1, 0, Path::new(":memory:")).unwrap();
    for seq in 0..40 {
        f.observe(&msg(seq));
    }
    // The larger observation is better; answers before any training count nothing.
    let answer_all = |f: &mut Feedback, asked: &[Outgoing]| {
        for q in asked {
            let (a, b) = (
                f.segment(q.first.id).unwrap().obs[0],
                f.segment(q.second.id).unwrap().obs[0],
            );
            let p = if a > b {
                Preference::First
            } else {
                Preference::Second
            };
            f.answer(&Answer::scripted(q.id, p, "oracle", "o-0", 1))
                .unwrap();
        }
    };
    let done = f.start(0, true).unwrap().unwrap();
    let asked = f.finish(done, 0).unwrap().0;
    answer_all(&mut f, &asked);
    assert_eq!(f.agreement(), None, "nothing trained yet");
    for session in 1..=6 {
        // Train on what is answered, then a session more, answered.
        let env_steps = 100 * session;
        while let Some(done) = f.start(env_steps, true).unwrap() {
            let asked = f.finish(done, env_steps).unwrap().0;
            answer_all(&mut f, &asked);
        }
    }
    let (share, n) = f.agreement().unwrap();
    assert_eq!(n, AGREEMENT_WINDOW);
    assert!(
        share > 0.7,
        "a trained ensemble agrees with a plain order: {share}"
    );
}
