use super::*;

fn weights() -> Weights {
    Weights {
        version: 4,
        env_steps: 100,
        obs_dim: 2,
        act_dim: 1,
        tensors: vec![Tensor {
            name: "l0.weight".into(),
            shape: vec![1, 2],
            data: vec![0.5, -0.5],
        }],
        obs_mean: vec![0.0, 1.0],
        obs_var: vec![1.0, 2.0],
        obs_clip: 10.0,
        random_actions: false,
        episodes_per_actor: 0,
        acks: Vec::new(),
    }
}

#[test]
fn round_trip_and_refusals() {
    let b = Body::Weights(weights());
    assert_eq!(decode("r", &encode("r", &b)).unwrap(), b);
    assert!(matches!(
        decode("other", &encode("r", &b)),
        Err(WireError::Run { .. })
    ));
    assert!(matches!(decode("r", &[0, 1, 2]), Err(WireError::Decode(_))));
    let mut w = weights();
    w.tensors[0].data.push(1.0);
    let e = decode("r", &encode("r", &Body::Weights(w))).unwrap_err();
    assert!(e.to_string().contains("l0.weight"), "{e}");
    let mut w = weights();
    w.obs_var[1] = f32::NAN;
    assert!(matches!(
        decode("r", &encode("r", &Body::Weights(w))),
        Err(WireError::NonFinite { .. })
    ));
    let mut w = weights();
    w.obs_mean.pop();
    assert!(matches!(
        decode("r", &encode("r", &Body::Weights(w))),
        Err(WireError::Shape { .. })
    ));
    // Another format version is refused.
    let env = Envelope {
        format: WIRE_FORMAT + 1,
        run: "r".into(),
        body: Body::Stop(Stop {
            env_steps: 1,
            version: 1,
        }),
    };
    let bytes = bincode::serde::encode_to_vec(&env, bincode::config::standard()).unwrap();
    assert!(matches!(
        decode("r", &bytes),
        Err(WireError::Format { found, .. }) if found == WIRE_FORMAT + 1
    ));
    // Too large to be a pbrl message: refused unread.
    assert!(matches!(
        decode("r", &vec![0u8; MAX_MESSAGE_BYTES + 1]),
        Err(WireError::TooLarge { .. })
    ));
}

#[test]
fn evaluation_steps_round_trip_and_bad_ones_are_refused() {
    // Two episodes of 3 steps, observation 2, action 1.
    let steps = |obs: usize, act: usize, truth: usize| EvalSteps {
        obs: vec![0.5; obs],
        actions: vec![0.1; act],
        truth: vec![-1.0; truth],
        human: vec![-0.5; truth],
        task: vec![-0.5; truth],
        features: vec![0.25; truth * crate::trajectory::FEATURES],
    };
    let result = |s: Vec<EvalSteps>| {
        Body::EvalResult(EvalResult {
            id: 1,
            actor: 0,
            version: 3,
            episodes: vec![Outcome::default(); 2],
            sampled: Vec::new(),
            steps: s,
        })
    };
    let good = result(vec![steps(6, 3, 3), steps(6, 3, 3)]);
    assert_eq!(decode("r", &encode("r", &good)).unwrap(), good);
    let none = result(Vec::new());
    assert_eq!(decode("r", &encode("r", &none)).unwrap(), none);
    let refused = |s: Vec<EvalSteps>| decode("r", &encode("r", &result(s))).unwrap_err();
    // One episode's steps for two episodes.
    let e = refused(vec![steps(6, 3, 3)]);
    assert!(e.to_string().contains("steps"), "{e}");
    // Observations that are not whole steps; actions with no steps.
    let e = refused(vec![steps(6, 3, 3), steps(7, 3, 3)]);
    assert!(e.to_string().contains("steps[1].obs"), "{e}");
    let e = refused(vec![steps(6, 3, 3), steps(0, 3, 0)]);
    assert!(e.to_string().contains("steps[1].actions"), "{e}");
    // Features that are not whole steps; none at all is fine.
    let mut short = steps(6, 3, 3);
    short.features.pop();
    let e = refused(vec![steps(6, 3, 3), short]);
    assert!(e.to_string().contains("steps[1].features"), "{e}");
    let mut bare = steps(6, 3, 3);
    bare.features.clear();
    let ok = result(vec![steps(6, 3, 3), bare]);
    assert_eq!(decode("r", &encode("r", &ok)).unwrap(), ok);
    let mut nan = steps(6, 3, 3);
    nan.truth[2] = f32::NAN;
    assert!(matches!(
        decode("r", &encode("r", &result(vec![steps(6, 3, 3), nan]))),
        Err(WireError::NonFinite { .. })
    ));
}

fn shown(id: u64, steps: usize) -> Shown {
    Shown {
        id,
        seed: 7,
        policy_version: 2,
        act_dim: 2,
        actions: vec![0.5; 2 * steps],
        truth: vec![-1.0; steps],
        replay: None,
        start: 0,
        len: steps as u32,
    }
}

#[test]
fn a_segment_outside_its_trajectory_is_refused() {
    let query = |first: Shown| {
        Body::Query(Box::new(Query {
            id: 3,
            session: 1,
            asked_at_ms: 1,
            expires_at_ms: 0,
            first,
            second: shown(2, 4),
            r_avg: Some(-80.0),
            withdraw_at_steps: 0,
            more: Vec::new(),
        }))
    };
    let mut s = shown(1, 4);
    (s.start, s.len) = (1, 2);
    assert_eq!(s.segment(), 1..3);
    assert_eq!(s.segment_truth().len(), 2);
    let ok = query(s.clone());
    assert_eq!(decode("r", &encode("r", &ok)).unwrap(), ok);
    for (start, len) in [(3, 2), (0, 0), (4, 1)] {
        (s.start, s.len) = (start, len);
        let e = decode("r", &encode("r", &query(s.clone()))).unwrap_err();
        assert!(e.to_string().contains("first.start"), "{start}, {len}: {e}");
    }
}

#[test]
fn a_format_6_query_reads_as_whole_trajectories() {
    // Format 6's layout, written field by field as bincode writes serde's structs.
    #[derive(Serialize)]
    struct Shown6 {
        id: u64,
        seed: u64,
        policy_version: u64,
        act_dim: u32,
        actions: Vec<f32>,
        truth: Vec<f32>,
        replay: Option<Replay>,
    }
    #[derive(Serialize)]
    struct Query6 {
        id: u64,
        session: u64,
        asked_at_ms: u64,
        expires_at_ms: u64,
        first: Shown6,
        second: Shown6,
    }
    let side = |id: u64| Shown6 {
        id,
        seed: 7,
        policy_version: 2,
        act_dim: 2,
        actions: vec![0.5; 8],
        truth: vec![-1.0; 4],
        replay: None,
    };
    let q6 = Query6 {
        id: 3,
        session: 1,
        asked_at_ms: 1,
        expires_at_ms: 0,
        first: side(1),
        second: side(2),
    };
    let bytes =
        bincode::serde::encode_to_vec((6u16, "r", 5u32, &q6), bincode::config::standard()).unwrap();
    assert!(
        decode("r", &bytes).is_err(),
        "this build does not speak format 6"
    );
    let q = decode_stored_query("r", &bytes).unwrap();
    assert_eq!(
        q,
        Query {
            id: 3,
            session: 1,
            asked_at_ms: 1,
            expires_at_ms: 0,
            first: shown(1, 4),
            second: shown(2, 4),
            r_avg: None,
            withdraw_at_steps: 0,
            more: Vec::new(),
        }
    );
    assert!(matches!(
        decode_stored_query("other", &bytes),
        Err(WireError::Run { .. })
    ));
    // Formats 7's and 8's query is this build's without the withdrawal step: never
    // withdrawn.
    let old = v8::Query {
        id: q.id,
        session: q.session,
        asked_at_ms: q.asked_at_ms,
        expires_at_ms: q.expires_at_ms,
        first: q.first.clone(),
        second: q.second.clone(),
        r_avg: Some(-3.5),
    };
    for format in [7u16, 8] {
        let bytes =
            bincode::serde::encode_to_vec((format, "r", 5u32, &old), bincode::config::standard())
                .unwrap();
        assert!(
            decode("r", &bytes).is_err(),
            "a receiver speaks format {WIRE_FORMAT} only"
        );
        let read = decode_stored_query("r", &bytes).unwrap();
        assert_eq!(read.r_avg, Some(-3.5), "format {format}");
        assert_eq!(read.withdraw_at_steps, 0, "format {format}");
        assert!(!read.stale_at(u64::MAX), "format {format}");
        assert_eq!(
            (read.first, read.second),
            (q.first.clone(), q.second.clone())
        );
    }
    // This build's stored query says when it is withdrawn.
    let mut now = q.clone();
    now.withdraw_at_steps = 5_000;
    let bytes = encode("r", &Body::Query(Box::new(now.clone())));
    assert_eq!(decode_stored_query("r", &bytes).unwrap(), now);
    assert!(!now.stale_at(4_999) && now.stale_at(5_000) && now.stale_at(9_000));
    // Format 9's query is laid out as this build's (10 changed only the learner's status):
    // a store of that build still asks its open queries; a receiver refuses the format.
    let nine = bincode::serde::encode_to_vec((9u16, "r", 5u32, &now), bincode::config::standard())
        .unwrap();
    assert!(decode("r", &nine).is_err());
    assert_eq!(decode_stored_query("r", &nine).unwrap(), now);
    // Format 6's answer (body 6) is not a query.
    let answer =
        bincode::serde::encode_to_vec((6u16, "r", 6u32, &q6), bincode::config::standard()).unwrap();
    assert!(decode_stored_query("r", &answer).is_err());
}

#[test]
fn queries_and_answers_round_trip_and_bad_ones_are_refused() {
    let q = Body::Query(Box::new(Query {
        id: 3,
        session: 1,
        asked_at_ms: 1,
        expires_at_ms: 0,
        first: shown(1, 4),
        second: shown(2, 4),
        r_avg: None,
        withdraw_at_steps: 0,
        more: Vec::new(),
    }));
    assert_eq!(decode("r", &encode("r", &q)).unwrap(), q);
    let mut bad = shown(1, 4);
    bad.actions.pop();
    let e = decode(
        "r",
        &encode(
            "r",
            &Body::Query(Box::new(Query {
                id: 3,
                session: 1,
                asked_at_ms: 1,
                expires_at_ms: 0,
                first: shown(1, 4),
                second: bad,
                r_avg: None,
                withdraw_at_steps: 0,
                more: Vec::new(),
            })),
        ),
    )
    .unwrap_err();
    assert!(e.to_string().contains("second.actions"), "{e}");
    let answer = |teacher_id: &str| Answer::scripted(3, Preference::Equal, "oracle", teacher_id, 2);
    let a = Body::Answer(answer("oracle-0"));
    assert_eq!(decode("r", &encode("r", &a)).unwrap(), a);
    let e = decode("r", &encode("r", &Body::Answer(answer("a/b")))).unwrap_err();
    assert!(e.to_string().contains("teacher_id"), "{e}");
    for p in [
        Preference::First,
        Preference::Second,
        Preference::Equal,
        Preference::Skip,
    ] {
        assert_eq!(Preference::parse(p.name()), Some(p));
    }
}

#[test]
fn a_ranking_round_trips_and_bad_places_name_their_field() {
    let mut q = Query {
        id: 4,
        session: 2,
        asked_at_ms: 1,
        expires_at_ms: 0,
        first: shown(1, 4),
        second: shown(2, 4),
        r_avg: Some(-10.0),
        withdraw_at_steps: 0,
        more: vec![shown(3, 4), shown(4, 4)],
    };
    assert_eq!(q.len(), 4);
    assert_eq!(q.attempts().map(|s| s.id).collect::<Vec<_>>(), [1, 2, 3, 4]);
    let body = Body::Query(Box::new(q.clone()));
    assert_eq!(decode("r", &encode("r", &body)).unwrap(), body);
    let mut bad = shown(5, 4);
    bad.len = 9;
    q.more[1] = bad;
    let e = decode("r", &encode("r", &Body::Query(Box::new(q.clone())))).unwrap_err();
    assert!(e.to_string().contains("more[1].start"), "{e}");
    q.more = vec![shown(3, 4); 3];
    let e = decode("r", &encode("r", &Body::Query(Box::new(q)))).unwrap_err();
    assert!(e.to_string().contains("more is \"5 attempts\""), "{e}");

    // Places, ties allowed; the preference is the first two's order.
    let a = Answer::ranked(4, vec![1, 0, 1, 2], "oracle", "oracle-0", 3);
    assert_eq!(a.preference, Preference::Second);
    let body = Body::Answer(a.clone());
    assert_eq!(decode("r", &encode("r", &body)).unwrap(), body);
    for (ranks, preference, why) in [
        (vec![0, 1], Preference::First, "3 or 4"),
        (vec![0, 1, 3], Preference::First, "below the number"),
        (vec![0, 1, 2], Preference::Second, "order of the first two"),
    ] {
        let bad = Answer {
            ranks,
            preference,
            ..a.clone()
        };
        let e = decode("r", &encode("r", &Body::Answer(bad))).unwrap_err();
        assert!(
            e.to_string().contains("ranks") && e.to_string().contains(why),
            "{e}"
        );
    }
}
