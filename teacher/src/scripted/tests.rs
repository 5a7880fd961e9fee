use super::*;
use clap::ValueEnum;
use Preference::{Equal, First, Second, Skip};

fn teacher(cfg: ScriptedConfig) -> Scripted {
    Scripted::new(cfg).unwrap() // the configs here are valid
}

fn table(kind: TeacherKind) -> Scripted {
    teacher(ScriptedConfig::of(kind, 7))
}

/// Fraction of `n` answers to the same pair that are `Second`.
fn second_rate(t: &mut Scripted, first: &[f32], second: &[f32], n: usize) -> f64 {
    let k = (0..n).filter(|_| t.answer(first, second) == Second).count();
    k as f64 / n as f64
}

#[test]
fn table_one_values_and_names() {
    // (kind, beta, gamma, eps, delta_skip, delta_equal) from method.md section 4.
    let rows = [
        (TeacherKind::Oracle, None, 1.0, 0.0, 0.0, 0.0),
        (TeacherKind::Noisy, Some(1.0), 1.0, 0.0, 0.0, 0.0),
        (TeacherKind::Mistake, None, 1.0, 0.1, 0.0, 0.0),
        (TeacherKind::Skip, None, 1.0, 0.0, 0.1, 0.0),
        (TeacherKind::Equal, None, 1.0, 0.0, 0.0, 0.1),
        (TeacherKind::Myopic, None, 0.99, 0.0, 0.0, 0.0),
    ];
    for (kind, beta, gamma, eps, delta_skip, delta_equal) in rows {
        let c = ScriptedConfig::of(kind, 3);
        let want = ScriptedConfig {
            kind,
            beta,
            gamma,
            eps,
            delta_skip,
            delta_equal,
            r_min: -350.0,
            avg_window: 100,
            seed: 3,
            weber: 0.0,
        };
        assert_eq!(c, want);
        c.validate().unwrap();
        // One name for the config file, the command line and answers.
        let serde_name = serde_json::to_string(&kind).unwrap();
        assert_eq!(serde_name, format!("\"{}\"", kind.name()));
        let clap_name = kind.to_possible_value().unwrap();
        assert_eq!(clap_name.get_name(), kind.name());
        let back: ScriptedConfig =
            serde_json::from_str(&serde_json::to_string(&c).unwrap()).unwrap();
        assert_eq!(back, c);
    }
    assert_eq!(TeacherKind::ALL.len(), rows.len());
}

#[test]
fn oracle_prefers_the_larger_sum_and_a_tie_is_first() {
    let mut t = table(TeacherKind::Oracle);
    // sums: 3 vs 4 -> Second; 4 vs 3 -> First
    assert_eq!(t.answer(&[1.0, 2.0], &[0.0, 4.0]), Second);
    assert_eq!(t.answer(&[0.0, 4.0], &[1.0, 2.0]), First);
    // Different lengths: 1 + 1 + 1 = 3 > 2.
    assert_eq!(t.answer(&[1.0, 1.0, 1.0], &[2.0]), First);
    // A tie is First (B-Pref: label = 1 * (sum1 < sum2) = 0).
    assert_eq!(t.answer(&[1.0, 2.0], &[3.0]), First);
    // Feeding-like negative returns: -120 vs -80.
    assert_eq!(t.answer(&[-60.0, -60.0], &[-40.0, -40.0]), Second);
}

#[test]
fn mistake_flips_at_rate_eps_and_is_deterministic_per_seed() {
    // Oracle answer First (5 > 1); a mistake teacher answers Second with rate 0.1.
    let (a, b) = ([5.0f32], [1.0f32]);
    let n = 4000;
    let rate = second_rate(&mut table(TeacherKind::Mistake), &a, &b, n);
    // std of the rate: sqrt(0.1 * 0.9 / 4000) = 0.0047; allow about 4 std.
    assert!((rate - 0.1).abs() < 0.02, "flip rate {rate}");
    let answers = |seed| {
        let mut t = teacher(ScriptedConfig::of(TeacherKind::Mistake, seed));
        (0..200).map(|_| t.answer(&a, &b)).collect::<Vec<_>>()
    };
    assert_eq!(answers(11), answers(11));
    assert_ne!(answers(11), answers(12));
}

#[test]
fn skip_happens_below_the_threshold_and_not_above() {
    // Both teachers first see two pairs of return -50, then one pair whose returns sum
    // to -670, so the window holds the same six returns:
    //   R_avg = (4 * -50 + -670) / 6 = -145.0
    //   threshold = (R_avg - r_min) * delta_skip = (-145 + 350) * 0.1 = 20.5
    // Pair (-330, -340): max - r_min = -330 + 350 = 20 < 20.5 -> Skip.
    // Pair (-329, -341): max - r_min = -329 + 350 = 21 > 20.5 -> judged, First.
    let warm = |t: &mut Scripted| {
        for _ in 0..2 {
            // max - r_min = 300 > (-50 + 350) * 0.1 = 30: judged (a tie, First)
            assert_eq!(t.answer(&[-25.0, -25.0], &[-50.0]), First);
        }
    };
    let mut below = table(TeacherKind::Skip);
    warm(&mut below);
    assert_eq!(below.answer(&[-165.0, -165.0], &[-340.0]), Skip);
    assert_eq!(below.r_avg(), Some(-145.0));

    let mut above = table(TeacherKind::Skip);
    warm(&mut above);
    assert_eq!(above.answer(&[-329.0], &[-341.0]), First);
    assert_eq!(above.r_avg(), Some(-145.0));

    // The oracle never skips the same pair.
    let mut oracle = table(TeacherKind::Oracle);
    warm(&mut oracle);
    assert_eq!(oracle.answer(&[-165.0, -165.0], &[-340.0]), First);
}

#[test]
fn equal_answers_close_pairs_and_overrides_a_mistake() {
    // First pair: window [-100, -101], R_avg = -100.5,
    //   threshold = (-100.5 + 350) * 0.1 = 24.95; |(-100) - (-101)| = 1 < 24.95 -> Equal.
    // Second pair: window [-100, -101, -50, -250], R_avg = -125.25,
    //   threshold = (-125.25 + 350) * 0.1 = 22.475; |-50 - -250| = 200 -> not equal,
    //   the oracle says First.
    let near = ([-50.0f32, -50.0], [-101.0f32]);
    let far = ([-50.0f32], [-125.0f32, -125.0]);

    let mut equal = table(TeacherKind::Equal);
    assert_eq!(equal.answer(&near.0, &near.1), Equal);
    assert_eq!(equal.answer(&far.0, &far.1), First);

    // With eps = 1 every answer is flipped, except Equal, which overrides the mistake.
    let mut erring = teacher(ScriptedConfig {
        eps: 1.0,
        ..ScriptedConfig::of(TeacherKind::Equal, 7)
    });
    assert_eq!(erring.answer(&near.0, &near.1), Equal);
    assert_eq!(erring.answer(&far.0, &far.1), Second);
    assert_eq!(erring.r_avg(), Some(-125.25));
}

#[test]
fn equal_is_judged_on_undiscounted_sums() {
    // gamma = 0.5: first [-100, -100]: R = -200, R' = 0.5 * -100 + -100 = -150
    //              second [-200, 0]:   R = -200, R' = 0.5 * -200 + 0    = -100
    // Undiscounted the two are equal (|R0 - R1| = 0 < threshold) -> Equal, although
    // the myopic sums alone would pick Second.
    let cfg = ScriptedConfig {
        gamma: 0.5,
        ..ScriptedConfig::of(TeacherKind::Equal, 7)
    };
    assert_eq!(
        teacher(cfg).answer(&[-100.0, -100.0], &[-200.0, 0.0]),
        Equal
    );
    let cfg = ScriptedConfig {
        gamma: 0.5,
        ..ScriptedConfig::of(TeacherKind::Oracle, 7)
    };
    assert_eq!(
        teacher(cfg).answer(&[-100.0, -100.0], &[-200.0, 0.0]),
        Second
    );
}

#[test]
fn myopic_weighs_late_steps_and_can_reverse_the_oracle() {
    // Reference (Python):
    //   first = [10] + [0] * 99;  second = [0] * 99 + [9]
    //   sum(first), sum(second)                                   # 10, 9: oracle First
    //   sum(r * 0.99 ** (99 - t) for t, r in enumerate(first))   # 3.697296376497264
    //   sum(r * 0.99 ** (99 - t) for t, r in enumerate(second))  # 9.0: myopic Second
    let mut first = vec![0.0f32; 100];
    first[0] = 10.0;
    let mut second = vec![0.0f32; 100];
    second[99] = 9.0;
    assert!((discounted(&first, 0.99) - 3.697296376497264).abs() < 1e-12);
    assert_eq!(discounted(&second, 0.99), 9.0);
    assert_eq!(table(TeacherKind::Oracle).answer(&first, &second), First);
    assert_eq!(table(TeacherKind::Myopic).answer(&first, &second), Second);

    // Each trajectory is weighted from its own last step:
    //   [1, 2, 3] at 0.5: 1 * 0.25 + 2 * 0.5 + 3 = 4.25;  [4.5]: 4.5
    assert_eq!(discounted(&[1.0, 2.0, 3.0], 0.5), 4.25);
    assert_eq!(discounted(&[], 0.5), 0.0);
    let mut t = teacher(ScriptedConfig {
        gamma: 0.5,
        ..ScriptedConfig::of(TeacherKind::Myopic, 7)
    });
    assert_eq!(t.answer(&[1.0, 2.0, 3.0], &[4.5]), Second); // undiscounted: 6 > 4.5
}

#[test]
fn noisy_matches_the_sigmoid_and_is_deterministic_per_seed() {
    // Reference (Python): 1 / (1 + math.exp(-0.5)) = 0.6224593312018546
    assert!((sigmoid(0.5) - 0.6224593312018546).abs() < 1e-15);
    assert_eq!(sigmoid(0.0), 0.5);
    // Stable at the extremes: no NaN, no overflow.
    assert_eq!(sigmoid(1000.0), 1.0);
    assert_eq!(sigmoid(-1000.0), 0.0);
    assert!((sigmoid(-0.5) - (1.0 - 0.6224593312018546)).abs() < 1e-15);

    // R0 = 1, R1 = 1.5: P[Second] = sigmoid(1 * 0.5) = 0.6225.
    let (a, b) = ([0.5f32, 0.5], [1.5f32]);
    let n = 4000;
    let rate = second_rate(&mut table(TeacherKind::Noisy), &a, &b, n);
    // std of the rate: sqrt(0.6225 * 0.3775 / 4000) = 0.0077; allow about 4 std.
    assert!((rate - 0.6224593312018546).abs() < 0.03, "rate {rate}");
    // Swapped, P[Second] = sigmoid(-0.5) = 0.3775.
    let rate = second_rate(&mut table(TeacherKind::Noisy), &b, &a, n);
    assert!(
        (rate - 0.3775406687981454).abs() < 0.03,
        "swapped rate {rate}"
    );
    // Far apart the choice is certain.
    let mut t = table(TeacherKind::Noisy);
    assert_eq!(second_rate(&mut t, &[-1000.0], &[0.0], 100), 1.0);
    assert_eq!(second_rate(&mut t, &[0.0], &[-1000.0], 100), 0.0);

    let answers = |seed| {
        let mut t = teacher(ScriptedConfig::of(TeacherKind::Noisy, seed));
        (0..200).map(|_| t.answer(&a, &b)).collect::<Vec<_>>()
    };
    assert_eq!(answers(5), answers(5));
    assert_ne!(answers(5), answers(6));
}

#[test]
fn draws_happen_only_where_documented() {
    // One f64 draw takes one u64, two 32-bit words of the ChaCha stream.
    let words = |t: &Scripted| t.rng.get_word_pos();
    for kind in [
        TeacherKind::Oracle,
        TeacherKind::Skip,
        TeacherKind::Equal,
        TeacherKind::Myopic,
    ] {
        let mut t = table(kind);
        for _ in 0..10 {
            t.answer(&[1.0, 2.0], &[3.0, -1.0]);
        }
        assert_eq!(words(&t), 0, "{kind:?} drew");
    }
    // Noisy: one draw per judged query; mistake: one per query.
    let mut t = table(TeacherKind::Noisy);
    t.answer(&[1.0], &[2.0]);
    assert_eq!(words(&t), 2);
    let mut t = table(TeacherKind::Mistake);
    t.answer(&[1.0], &[2.0]);
    assert_eq!(words(&t), 2);
    // Both: two draws. Skip and Equal answers draw nothing.
    let mut t = teacher(ScriptedConfig {
        eps: 0.1,
        delta_equal: 0.1,
        ..ScriptedConfig::of(TeacherKind::Noisy, 7)
    });
    t.answer(&[-10.0], &[-200.0]);
    assert_eq!(words(&t), 4);
    assert_eq!(t.answer(&[-10.0], &[-10.5]), Equal);
    assert_eq!(words(&t), 4);
}

#[test]
fn in_a_session_the_thresholds_scale_the_sessions_r_avg_to_the_segment() {
    // The authors' thresholds: R_avg of the session (the newest training episodes,
    // -100 a whole episode), scaled by the segment's share of an episode (50 of 200);
    // with r_min -350: floor -87.5, scale 62.5, so skip below -87.5 + 6.25 = -81.25
    // and equal within 6.25.
    let mut skip = table(TeacherKind::Skip);
    assert_eq!(
        skip.answer_in_session(&[-82.0], &[-85.0], -100.0, 0.25, None),
        Preference::Skip
    );
    assert_eq!(
        skip.answer_in_session(&[-81.0], &[-85.0], -100.0, 0.25, None),
        Preference::First
    );
    let mut equal = table(TeacherKind::Equal);
    assert_eq!(
        equal.answer_in_session(&[-50.0], &[-56.2], -100.0, 0.25, None),
        Preference::Equal
    );
    assert_eq!(
        equal.answer_in_session(&[-50.0], &[-56.3], -100.0, 0.25, None),
        Preference::First
    );
    // Whole trajectories (fraction 1): the window's rule with R_avg fixed. The window
    // is not touched by a session's answers.
    assert_eq!(
        equal.answer_in_session(&[-100.0], &[-124.0], -100.0, 1.0, None),
        Preference::Equal
    );
    assert_eq!(equal.r_avg(), None);
    // Nothing to judge by: skipped.
    assert_eq!(
        equal.answer_in_session(&[-1.0], &[-2.0], f64::NAN, 1.0, None),
        Preference::Skip
    );
    assert_eq!(
        equal.answer_in_session(&[-1.0], &[-2.0], -100.0, 0.0, None),
        Preference::Skip
    );
}

#[test]
fn r_avg_is_the_mean_of_the_last_window_returns_shown() {
    let mut t = teacher(ScriptedConfig {
        avg_window: 3,
        ..ScriptedConfig::of(TeacherKind::Oracle, 7)
    });
    assert_eq!(t.r_avg(), None);
    t.answer(&[1.0], &[2.0]); // window [1, 2]
    assert_eq!(t.r_avg(), Some(1.5));
    t.answer(&[1.0, 2.0], &[4.0]); // window [2, 3, 4]
    assert_eq!(t.r_avg(), Some(3.0));
    t.answer(&[10.0], &[15.0, 5.0]); // window [4, 10, 20]
    assert_eq!(t.r_avg(), Some(34.0 / 3.0));
}

#[test]
fn empty_or_non_finite_trajectories_are_skipped_and_not_remembered() {
    let mut t = table(TeacherKind::Noisy);
    assert_eq!(t.answer(&[], &[1.0]), Skip);
    assert_eq!(t.answer(&[1.0], &[]), Skip);
    assert_eq!(t.answer(&[], &[]), Skip);
    assert_eq!(t.answer(&[f32::NAN], &[1.0]), Skip);
    assert_eq!(t.answer(&[1.0], &[2.0, f32::INFINITY]), Skip);
    assert_eq!(t.r_avg(), None);
    assert_eq!(t.rng.get_word_pos(), 0);
}

#[test]
fn validate_names_the_field_and_its_value() {
    let base = || ScriptedConfig::of(TeacherKind::Oracle, 7);
    let cases = [
        (
            ScriptedConfig {
                beta: Some(0.0),
                ..base()
            },
            "beta = 0",
        ),
        (
            ScriptedConfig {
                beta: Some(f64::INFINITY),
                ..base()
            },
            "beta = inf",
        ),
        (
            ScriptedConfig {
                gamma: 0.0,
                ..base()
            },
            "gamma = 0",
        ),
        (
            ScriptedConfig {
                gamma: 1.5,
                ..base()
            },
            "gamma = 1.5",
        ),
        (
            ScriptedConfig {
                eps: -0.1,
                ..base()
            },
            "eps = -0.1",
        ),
        (ScriptedConfig { eps: 1.1, ..base() }, "eps = 1.1"),
        (
            ScriptedConfig {
                eps: f64::NAN,
                ..base()
            },
            "eps = NaN",
        ),
        (
            ScriptedConfig {
                delta_skip: -1.0,
                ..base()
            },
            "delta_skip = -1",
        ),
        (
            ScriptedConfig {
                delta_equal: f64::NAN,
                ..base()
            },
            "delta_equal = NaN",
        ),
        (
            ScriptedConfig {
                r_min: f64::NEG_INFINITY,
                ..base()
            },
            "r_min = -inf",
        ),
        (
            ScriptedConfig {
                avg_window: 0,
                ..base()
            },
            "avg_window = 0",
        ),
    ];
    for (cfg, want) in cases {
        let err = cfg.validate().unwrap_err().to_string();
        assert!(err.contains(want), "{err:?} should contain {want:?}");
        let err = Scripted::new(cfg).unwrap_err().to_string();
        assert!(err.contains(want), "{err:?} should contain {want:?}");
    }
    ScriptedConfig {
        eps: 1.0,
        gamma: 1e-3,
        beta: Some(1e-3),
        ..base()
    }
    .validate()
    .unwrap();
}

#[test]
fn hurried_takes_the_livelier_of_two_close_attempts_and_the_better_of_two_far_ones() {
    let c = ScriptedConfig::of(TeacherKind::Hurried, 1);
    assert_eq!(c.weber, 0.2);
    assert_eq!(
        ScriptedConfig {
            weber: 0.0,
            ..c.clone()
        },
        ScriptedConfig {
            kind: TeacherKind::Hurried,
            ..ScriptedConfig::of(TeacherKind::Oracle, 1)
        }
    );
    assert_eq!(TeacherKind::Hurried.name(), "hurried");
    let mut t = teacher(c);
    // -30 against -34: 4 < 0.2 * 34, too close. The second moves more: Second, though
    // the first is better.
    let (a, b) = ([-15.0f32, -15.0], [-17.0f32, -17.0]);
    let lively = Some([0.1, 0.5]);
    assert_eq!(t.answer_in_session(&a, &b, -100.0, 0.25, lively), Second);
    assert_eq!(
        t.answer_in_session(&a, &b, -100.0, 0.25, Some([0.5, 0.1])),
        First
    );
    // Without the actions it cannot tell: Equal.
    assert_eq!(t.answer_in_session(&a, &b, -100.0, 0.25, None), Equal);
    // -30 against -50: far enough, the better one whatever moves more.
    let far = [-25.0f32, -25.0];
    assert_eq!(
        t.answer_in_session(&a, &far, -100.0, 0.25, Some([0.1, 0.9])),
        First
    );
    // The oracle is never drawn to the livelier one.
    let mut oracle = table(TeacherKind::Oracle);
    assert_eq!(
        oracle.answer_in_session(&a, &b, -100.0, 0.25, lively),
        First
    );
    // Out of range: refused by name.
    let bad = ScriptedConfig {
        weber: 1.5,
        ..ScriptedConfig::of(TeacherKind::Hurried, 1)
    };
    assert!(Scripted::new(bad)
        .unwrap_err()
        .to_string()
        .contains("weber = 1.5"));
}

#[test]
fn a_ranking_orders_by_return_ties_the_close_and_errs_as_each_teacher_does() {
    let (a, b, c, d) = ([1.0f32, 1.0], [3.0f32, 3.0], [2.0f32, 2.0], [2.05f32, 2.0]);
    let four: [&[f32]; 4] = [&a, &b, &c, &d];
    let mut oracle = table(TeacherKind::Oracle);
    assert_eq!(
        oracle.rank_returns(&four, Some(0.0), 1.0, None),
        Some(vec![3, 0, 2, 1])
    );
    // Equal: returns 4.0 and 4.05 are within 0.1 of (R_avg - r_min) = 10.
    let mut equal = teacher(ScriptedConfig {
        r_min: -10.0,
        ..ScriptedConfig::of(TeacherKind::Equal, 1)
    });
    assert_eq!(
        equal.rank_returns(&four, Some(0.0), 1.0, None),
        Some(vec![3, 0, 1, 1])
    );
    // Skip: even the best is poor.
    let mut skip = teacher(ScriptedConfig {
        r_min: -10.0,
        delta_skip: 2.0,
        ..ScriptedConfig::of(TeacherKind::Skip, 1)
    });
    assert_eq!(skip.rank_returns(&four, Some(0.0), 1.0, None), None);
    // Noisy: Plackett-Luce; a wide gap is ranked as the oracle does nearly always, a
    // narrow one about half the time.
    let mut noisy = table(TeacherKind::Noisy);
    let (lo, hi) = ([0.0f32], [10.0f32]);
    let (x, y) = ([5.0f32], [5.1f32]);
    let wide: [&[f32]; 3] = [&lo, &hi, &x];
    let n = 2000;
    let best_first = (0..n)
        .filter(|_| noisy.rank_returns(&wide, Some(0.0), 1.0, None).unwrap()[1] == 0)
        .count() as f64
        / n as f64;
    assert!(best_first > 0.98, "{best_first}");
    let narrow: [&[f32]; 3] = [&x, &y, &lo];
    let first_ahead = (0..n)
        .filter(|_| {
            let p = noisy.rank_returns(&narrow, Some(0.0), 1.0, None).unwrap();
            p[0] < p[1]
        })
        .count() as f64
        / n as f64;
    assert!((first_ahead - sigmoid(-0.1)).abs() < 0.05, "{first_ahead}");
    // Mistake: one adjacent pair swapped in about eps of the rankings.
    let mut mistake = table(TeacherKind::Mistake);
    let wrong = (0..n)
        .filter(|_| mistake.rank_returns(&four, Some(0.0), 1.0, None).unwrap() != [3, 0, 2, 1])
        .count() as f64
        / n as f64;
    assert!((wrong - 0.1).abs() < 0.03, "{wrong}");
    // Hurried: of two too close to tell apart, the livelier goes first.
    let mut hurried = table(TeacherKind::Hurried);
    let moves = [0.1, 0.1, 0.9, 0.1];
    assert_eq!(
        hurried.rank_returns(&four, Some(0.0), 1.0, Some(&moves)),
        Some(vec![3, 0, 1, 2])
    );
}
