//! The ensemble's golden values, gradients against autodiff, and learning tests.
use super::*;
use crate::testutil::assert_same_gradients;
use rand::Rng;

/// Draw `n` random segments of `steps` steps (test helper and bench).
fn random_segments(
    rng: &mut impl Rng,
    n: usize,
    steps: usize,
    o: usize,
    a: usize,
) -> Vec<Arc<Segment>> {
    (0..n)
        .map(|_| {
            Arc::new(Segment {
                obs: (0..steps * o)
                    .map(|_| rng.random_range(-1.0..1.0))
                    .collect(),
                actions: (0..steps * a)
                    .map(|_| rng.random_range(-1.2..1.2))
                    .collect(),
                features: Vec::new(),
            })
        })
        .collect()
}

fn col(v: &[f32]) -> Tensor {
    Tensor::from_slice(v, v.len(), &Device::Cpu).unwrap()
}

fn small(seed: u64, hidden: &[usize]) -> RewardModelConfig {
    RewardModelConfig {
        hidden: hidden.to_vec(),
        seed,
        ..RewardModelConfig::plain()
    }
}

/// The members' sums and the mean reward computed with candle's ops from scratch.
fn reference_rewards(model: &RewardModel, obs: &[f32], act: &[f32]) -> Vec<Vec<f32>> {
    let mut x = Vec::new();
    let (o, a) = (model.obs_dim, model.act_dim);
    for (orow, arow) in obs.chunks_exact(o).zip(act.chunks_exact(a)) {
        for ((v, m), s) in orow.iter().zip(&model.norm.mean).zip(&model.norm.std) {
            x.push(((v - m) / s).clamp(-10.0, 10.0));
        }
        x.extend(arow.iter().map(|v| v.clamp(-1.0, 1.0)));
    }
    let x = Tensor::from_vec(x, (obs.len() / o, o + a), &Device::Cpu).unwrap();
    model
        .nets
        .iter()
        .map(|n| {
            n.net
                .forward(&x)
                .unwrap()
                .flatten_all()
                .unwrap()
                .to_vec1()
                .unwrap()
        })
        .collect()
}

#[test]
fn bradley_terry_loss_matches_the_reference() {
    // Reference (Python, math module only):
    //   import math
    //   def ce(s0, s1, p):   # -[(1-p) log softmax(s)[0] + p log softmax(s)[1]]
    //       l0 = s0 - math.log(math.exp(s0) + math.exp(s1))
    //       l1 = s1 - math.log(math.exp(s0) + math.exp(s1))
    //       return -((1 - p) * l0 + p * l1)
    //   s0, s1, p = [1.0, 2.0, -0.5, 30.0], [3.0, -1.0, 0.5, -30.0], [1.0, 0.0, 0.5, 1.0]
    //   [ce(*x) for x in zip(s0, s1, p)]
    //   # [0.12692801104297263, 0.04858735157374206, 0.8132616875182228, 60.0]
    //   sum(_) / 4   # 15.247194262533735
    let want = [0.126_928_01f64, 0.048_587_35, 0.813_261_7, 60.0];
    for (i, w) in want.iter().enumerate() {
        let (s0, s1, p) = (
            [1.0f32, 2.0, -0.5, 30.0][i],
            [3.0f32, -1.0, 0.5, -30.0][i],
            [1.0f32, 0.0, 0.5, 1.0][i],
        );
        let got = bradley_terry_loss(&col(&[s0]), &col(&[s1]), &col(&[p]))
            .unwrap()
            .to_scalar::<f32>()
            .unwrap() as f64;
        assert!(
            (got - w).abs() < 1e-5 * w.max(1.0),
            "pair {i}: {got} vs {w}"
        );
    }
    let all = bradley_terry_loss(
        &col(&[1.0, 2.0, -0.5, 30.0]),
        &col(&[3.0, -1.0, 0.5, -30.0]),
        &col(&[1.0, 0.0, 0.5, 1.0]),
    )
    .unwrap()
    .to_scalar::<f32>()
    .unwrap();
    assert!((all - 15.247_194).abs() < 1e-4, "{all}");
    // The equal label's gradient: d/d s1 = P - p = sigmoid(1) - 0.5 = 0.2310585786300049,
    // so a soft target pulls P toward 0.5 from either side.
    let s1 = candle_core::Var::from_slice(&[0.5f32], 1, &Device::Cpu).unwrap();
    let l = bradley_terry_loss(&col(&[-0.5]), s1.as_tensor(), &col(&[0.5])).unwrap();
    let g = l
        .backward()
        .unwrap()
        .get(&s1)
        .unwrap()
        .to_vec1::<f32>()
        .unwrap()[0];
    assert!((g - 0.231_058_58).abs() < 1e-6, "{g}");
}

#[test]
fn hand_gradients_are_candle_autodiffs() {
    let mut model = RewardModel::new(small(3, &[16, 12]), 3, 2).unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(4);
    // Uneven lengths, one equal label, a target that is neither.
    let segs: Vec<Arc<Segment>> = [7, 9, 5, 11, 8, 6]
        .iter()
        .flat_map(|&s| random_segments(&mut rng, 1, s, 3, 2))
        .collect();
    let labels: Vec<Labelled> = [(0, 1, 1.0), (2, 3, 0.0), (4, 5, 0.5), (1, 4, 0.0)]
        .iter()
        .map(|&(a, b, t)| Labelled {
            first: segs[a].clone(),
            second: segs[b].clone(),
            target: t,
        })
        .collect();
    // A normaliser that is not the identity.
    model.norm = ObsNorm::fit(segs.iter().map(|s| &**s), 3);
    let pairs: Vec<&Labelled> = labels.iter().collect();
    for m in 0..2 {
        // Chunks of at most 20 rows (one pair each here) and one chunk of all.
        for chunk in [20, 10_000] {
            let (got, loss, right, hard) = model.member_gradients(m, &pairs, chunk).unwrap();
            let mut s0 = Vec::new();
            let mut s1 = Vec::new();
            for l in &labels {
                for (seg, out) in [(&l.first, &mut s0), (&l.second, &mut s1)] {
                    let mut x = Vec::new();
                    model.push_segment(seg, &mut x);
                    let x = model.input_tensor(x).unwrap();
                    out.push(model.nets[m].net.forward(&x).unwrap().sum_all().unwrap());
                }
            }
            let (s0, s1) = (
                Tensor::stack(&s0, 0).unwrap(),
                Tensor::stack(&s1, 0).unwrap(),
            );
            let t = col(&labels.iter().map(|l| l.target).collect::<Vec<_>>());
            let want = bradley_terry_loss(&s0, &s1, &t).unwrap();
            let w = want.to_scalar::<f32>().unwrap() as f64;
            assert!((loss / 4.0 - w).abs() < 1e-5, "{loss} / 4 vs {w}");
            assert_eq!(hard, 3);
            let d: Vec<f32> = (s1 - s0).unwrap().to_vec1().unwrap();
            let want_right = [0, 1, 3]
                .iter()
                .filter(|&&i| (d[i] > 0.0) == (labels[i].target > 0.5))
                .count();
            assert_eq!(right, want_right);
            assert_same_gradients(&model.opts[m].vars, &got, &want.backward().unwrap());
        }
    }
}

#[test]
fn r_hat_is_the_mean_of_members_in_the_open_interval() {
    let mut model = RewardModel::new(small(5, &[32, 32]), 4, 2).unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(6);
    let segs = random_segments(&mut rng, 6, 10, 4, 2);
    let data: Vec<Labelled> = (0..3)
        .map(|i| Labelled {
            first: segs[2 * i].clone(),
            second: segs[2 * i + 1].clone(),
            target: 1.0,
        })
        .collect();
    model.train(&data).unwrap();
    assert!(model.trained());
    // Large observations too: the normaliser clips them.
    let obs: Vec<f32> = (0..50 * 4)
        .map(|i| ((i * 37 % 101) as f32 - 50.0) * 0.7)
        .collect();
    let act: Vec<f32> = (0..50 * 2)
        .map(|i| ((i * 13 % 7) as f32 - 3.0) * 0.6)
        .collect();
    let members = reference_rewards(&model, &obs, &act);
    let got = model.predict(&obs, &act, &[]).unwrap();
    for (k, g) in got.iter().enumerate() {
        let mean = members.iter().map(|m| m[k]).sum::<f32>() / 3.0;
        assert!((g - mean).abs() < 1e-5, "row {k}: {g} vs {mean}");
        assert!(*g > -1.0 && *g < 1.0);
        assert!(members.iter().all(|m| m[k] > -1.0 && m[k] < 1.0));
    }
    // The tensor path gives the same.
    let ot = Tensor::from_slice(&obs, (50, 4), &Device::Cpu).unwrap();
    let at = Tensor::from_slice(&act, (50, 2), &Device::Cpu).unwrap();
    let t = model.predict_tensor(&ot, &at, None).unwrap();
    assert_eq!(t.dims(), &[50, 1]);
    let t = t.flatten_all().unwrap().to_vec1::<f32>().unwrap();
    assert!(got.iter().zip(&t).all(|(a, b)| (a - b).abs() < 1e-6));
    // Returns are each member's sum; probabilities come from them.
    let seg = &segs[0];
    let per_member = reference_rewards(&model, &seg.obs, &seg.actions);
    let ret = model.returns(seg).unwrap();
    for (r, m) in ret.iter().zip(&per_member) {
        assert!((r - m.iter().sum::<f32>()).abs() < 1e-4);
    }
    let probs = model
        .preference_probs(&[(&segs[0], &segs[1]), (&segs[2], &segs[3])])
        .unwrap();
    assert_eq!((probs.len(), probs[0].len()), (3, 2));
    let r1 = model.returns(&segs[1]).unwrap();
    for m in 0..3 {
        let want = 1.0 / (1.0 + (ret[m] - r1[m]).exp());
        assert!((probs[m][0] - want).abs() < 1e-5);
    }
    // The model is Send, so it can be trained on another thread.
    fn send<T: Send>(_: &T) {}
    send(&model);
}

#[test]
fn members_draw_their_own_orders_deterministically() {
    for resample in [Resample::Bootstrap, Resample::Shuffle] {
        let cfg = RewardModelConfig {
            resample,
            ..small(11, &[8])
        };
        let mut a = RewardModel::new(cfg.clone(), 2, 1).unwrap();
        let mut b = RewardModel::new(cfg.clone(), 2, 1).unwrap();
        let oa = a.draw_orders(100);
        assert_eq!(
            oa,
            b.draw_orders(100),
            "{resample:?}: same seed, same orders"
        );
        assert_ne!(
            oa,
            a.draw_orders(100),
            "{resample:?}: a new epoch, new orders"
        );
        assert!(
            oa[0] != oa[1] && oa[1] != oa[2],
            "{resample:?}: members differ"
        );
        for o in &oa {
            assert_eq!(o.len(), 100);
            let mut sorted = o.clone();
            sorted.sort();
            sorted.dedup();
            match resample {
                Resample::Shuffle => assert_eq!(sorted, (0..100).collect::<Vec<_>>()),
                // P[no repeat in 100 draws of 100] = 100! / 100^100, about 1e-42.
                Resample::Bootstrap => assert!(sorted.len() < 100),
            }
        }
        let mut c = RewardModel::new(RewardModelConfig { seed: 12, ..cfg }, 2, 1).unwrap();
        assert_ne!(oa, c.draw_orders(100), "{resample:?}: another seed");
    }
    // Whole training sessions are deterministic per seed too.
    let mut rng = ChaCha8Rng::seed_from_u64(2);
    let segs = random_segments(&mut rng, 40, 5, 2, 1);
    let data: Vec<Labelled> = (0..20)
        .map(|i| Labelled {
            first: segs[2 * i].clone(),
            second: segs[2 * i + 1].clone(),
            target: (i % 3) as f32 / 2.0,
        })
        .collect();
    let cfg = RewardModelConfig {
        batch: 8,
        max_epochs: 3,
        ..small(13, &[8, 8])
    };
    let weights =
        |m: &RewardModel| -> Vec<_> { m.nets.iter().map(|n| export(&n.varmap).unwrap()).collect() };
    let mut a = RewardModel::new(cfg.clone(), 2, 1).unwrap();
    let mut b = RewardModel::new(cfg.clone(), 2, 1).unwrap();
    assert_eq!(a.train(&data).unwrap(), b.train(&data).unwrap());
    assert_eq!(weights(&a), weights(&b));
    let mut c = RewardModel::new(
        RewardModelConfig {
            resample: Resample::Shuffle,
            ..cfg
        },
        2,
        1,
    )
    .unwrap();
    c.train(&data).unwrap();
    assert_ne!(
        weights(&a),
        weights(&c),
        "shuffle trains otherwise than bootstrap"
    );
}

/// Pairs of `steps`-step segments with an oracle's labels under the true reward
/// `-|obs0|`: each segment's observations scatter (by +-0.5) around its own centre in
/// [-1, 1]^3, as whole trajectories differ; the action is noise.
fn oracle_pairs(rng: &mut impl Rng, n: usize, steps: usize) -> Vec<Labelled> {
    oracle_pairs_under(rng, n, steps, |o| -o[0].abs())
}

/// [`oracle_pairs`] under the true reward `reward` of each observation row.
fn oracle_pairs_under(
    rng: &mut impl Rng,
    n: usize,
    steps: usize,
    reward: impl Fn(&[f32]) -> f32,
) -> Vec<Labelled> {
    let mut segment = || {
        let c: Vec<f32> = (0..3).map(|_| rng.random_range(-1.0..1.0)).collect();
        let obs = (0..steps * 3)
            .map(|i| c[i % 3] + rng.random_range(-0.5..0.5))
            .collect();
        let actions = (0..steps).map(|_| rng.random_range(-1.0..1.0)).collect();
        Arc::new(Segment {
            obs,
            actions,
            features: Vec::new(),
        })
    };
    let ret = |s: &Segment| -> f32 { s.obs.chunks_exact(3).map(&reward).sum() };
    (0..n)
        .map(|_| {
            let (first, second) = (segment(), segment());
            let target = if ret(&second) > ret(&first) { 1.0 } else { 0.0 };
            Labelled {
                first,
                second,
                target,
            }
        })
        .collect()
}

#[test]
fn learns_an_oracle_preference_and_generalises() {
    let mut rng = ChaCha8Rng::seed_from_u64(100);
    let train = oracle_pairs(&mut rng, 200, 20);
    let held_out = oracle_pairs(&mut rng, 200, 20);
    let cfg = RewardModelConfig {
        batch: 32,
        lr: 1e-3,
        ..small(0, &[64, 64, 64])
    };
    let mut model = RewardModel::new(cfg, 3, 1).unwrap();
    let before = model.accuracy(&held_out).unwrap();
    let stats = model.train(&train).unwrap();
    let after = model.accuracy(&held_out).unwrap();
    println!("held-out accuracy {before:.3} -> {after:.3}, {stats:?}");
    assert!(after >= 0.9, "held-out accuracy {after} ({stats:?})");
    assert!(model.accuracy(&train).unwrap() >= 0.9);
}

#[test]
fn state_and_restore_continue_identically() {
    let mut rng = ChaCha8Rng::seed_from_u64(8);
    let d1 = oracle_pairs(&mut rng, 30, 6);
    let d2 = oracle_pairs(&mut rng, 45, 6);
    let cfg = RewardModelConfig {
        batch: 16,
        max_epochs: 4,
        ..small(1, &[16, 16])
    };
    let mut a = RewardModel::new(cfg.clone(), 3, 1).unwrap();
    a.train(&d1).unwrap();
    let state = a.state().unwrap();
    let mut b = RewardModel::new(RewardModelConfig { seed: 99, ..cfg }, 3, 1).unwrap();
    assert!(!b.trained());
    for ((name, from), (_, to)) in a.networks().into_iter().zip(b.networks()) {
        assert!(name.starts_with("reward_"));
        import(to, &export(from).unwrap()).unwrap();
    }
    // The state goes through serde as a checkpoint would.
    let state: RewardModelState =
        serde_json::from_str(&serde_json::to_string(&state).unwrap()).unwrap();
    b.restore(&state).unwrap();
    assert!(b.trained());
    let seg = &d2[0].first;
    assert_eq!(
        a.predict(&seg.obs, &seg.actions, &[]).unwrap(),
        b.predict(&seg.obs, &seg.actions, &[]).unwrap()
    );
    // A snapshot is the same model and trains apart.
    let mut c = a.snapshot().unwrap();
    let all: Vec<Labelled> = d1.iter().chain(&d2).cloned().collect();
    let (sa, sb, sc) = (
        a.train(&all).unwrap(),
        b.train(&all).unwrap(),
        c.train(&all).unwrap(),
    );
    assert_eq!((sa, sa), (sb, sc));
    let p = a.predict(&seg.obs, &seg.actions, &[]).unwrap();
    assert_eq!(p, b.predict(&seg.obs, &seg.actions, &[]).unwrap());
    assert_eq!(p, c.predict(&seg.obs, &seg.actions, &[]).unwrap());
    assert_eq!(a.state().unwrap(), b.state().unwrap());
    c.train(&d1).unwrap();
    assert_eq!(
        p,
        a.predict(&seg.obs, &seg.actions, &[]).unwrap(),
        "training the snapshot leaves the original"
    );
    // A state of another shape is refused.
    let mut bad = state.clone();
    bad.obs_mean.push(0.0);
    assert!(b.restore(&bad).is_err());
}

#[test]
fn max_pairs_bounds_a_training_and_cuts_its_last_epoch() {
    // D of 45 pairs, a bound of 100: epochs of 45, 45 and 10 pairs. Unbounded, all 5
    // epochs of 45 (the accuracy target of 2 is never reached).
    let mut rng = ChaCha8Rng::seed_from_u64(21);
    let data = oracle_pairs(&mut rng, 45, 6);
    let cfg = |max_pairs| RewardModelConfig {
        batch: 16,
        max_epochs: 5,
        stop_accuracy: 2.0,
        max_pairs,
        ..small(2, &[8, 8])
    };
    let mut bounded = RewardModel::new(cfg(100), 3, 1).unwrap();
    let stats = bounded.train(&data).unwrap();
    assert_eq!((stats.epochs, stats.pairs), (3, 100), "{stats:?}");
    let mut free = RewardModel::new(cfg(0), 3, 1).unwrap();
    let stats = free.train(&data).unwrap();
    assert_eq!((stats.epochs, stats.pairs), (5, 225), "{stats:?}");
    // A bound of one epoch's worth: exactly one epoch.
    let mut one = RewardModel::new(cfg(45), 3, 1).unwrap();
    let stats = one.train(&data).unwrap();
    assert_eq!((stats.epochs, stats.pairs), (1, 45), "{stats:?}");
}

#[test]
fn equal_labels_pull_toward_one_half() {
    let mut rng = ChaCha8Rng::seed_from_u64(17);
    let s = random_segments(&mut rng, 2, 10, 3, 1);
    let cfg = RewardModelConfig {
        batch: 1,
        lr: 1e-2,
        max_epochs: 30,
        // Never stop early: with only equal labels the accuracy is 1 from the start.
        stop_accuracy: 2.0,
        ..small(4, &[16, 16])
    };
    let mut model = RewardModel::new(cfg, 3, 1).unwrap();
    let label = |target| {
        vec![Labelled {
            first: s[0].clone(),
            second: s[1].clone(),
            target,
        }]
    };
    model.train(&label(1.0)).unwrap();
    let p = |m: &RewardModel| m.preference_probs(&[(&s[0], &s[1])]).unwrap();
    let sure = p(&model);
    assert!(sure.iter().all(|q| q[0] > 0.9), "{sure:?}");
    let stats = model.train(&label(0.5)).unwrap();
    assert_eq!(
        stats.accuracy, 1.0,
        "equal labels are left out of the accuracy"
    );
    let soft = p(&model);
    for (a, b) in sure.iter().zip(&soft) {
        assert!(
            (b[0] - 0.5).abs() < 0.5 * (a[0] - 0.5).abs(),
            "{sure:?} -> {soft:?}"
        );
    }
    assert_eq!(model.accuracy(&label(0.5)).unwrap(), 1.0);
}

#[test]
fn malformed_segments_and_targets_are_refused() {
    let mut model = RewardModel::new(small(0, &[4]), 3, 1).unwrap();
    let good = Arc::new(Segment {
        obs: vec![0.0; 6],
        actions: vec![0.0; 2],
        features: Vec::new(),
    });
    let bad = Arc::new(Segment {
        obs: vec![0.0; 6],
        actions: vec![0.0; 3],
        features: Vec::new(),
    });
    let l = |a: &Arc<Segment>, t| {
        vec![Labelled {
            first: good.clone(),
            second: a.clone(),
            target: t,
        }]
    };
    assert!(model.train(&l(&bad, 1.0)).is_err());
    assert!(model.train(&l(&good, 1.5)).is_err());
    assert!(model.predict(&[0.0; 5], &[0.0; 2], &[]).is_err());
    let stats = model.train(&[]).unwrap();
    assert_eq!(stats.epochs, 0);
    assert!(!model.trained());
}

#[test]
fn crops_are_equal_length_sub_snippets_within_each_side_and_golden_for_a_seed() {
    // Each step's observation is its own index (side 0: 0..50, side 1: 1000..1050).
    let side = |base: f32| {
        Arc::new(Segment {
            obs: (0..50).map(|k| base + k as f32).collect(),
            actions: vec![0.0; 50],
            features: Vec::new(),
        })
    };
    let data = vec![Labelled {
        first: side(0.0),
        second: side(1000.0),
        target: 1.0,
    }];
    let cfg = RewardModelConfig {
        crops: 5,
        ..small(4, &[8])
    };
    let mut model = RewardModel::new(cfg, 1, 1).unwrap();
    let out = model.with_crops(&data).unwrap();
    assert_eq!(out.len(), 6, "the label and its 5 crops");
    assert!(
        Arc::ptr_eq(&out[0].first, &data[0].first),
        "the label first, as it was"
    );
    let mut got = Vec::new();
    for c in &out[1..] {
        let (a, b) = (&c.first.obs, &c.second.obs);
        assert_eq!(a.len(), b.len(), "both sides one length");
        assert!((35..=45).contains(&a.len()), "0.7-0.9 of 50: {}", a.len());
        assert_eq!(c.target, 1.0);
        for s in [a, b] {
            assert!(s.windows(2).all(|w| w[1] == w[0] + 1.0), "contiguous steps");
        }
        assert!(a[0] >= 0.0 && *a.last().unwrap() < 50.0);
        assert!(b[0] >= 1000.0 && *b.last().unwrap() < 1050.0);
        got.push((a.len(), a[0] as usize, b[0] as usize - 1000));
    }
    // Golden: the crops a seed draws (a change here changes every run with crops).
    assert_eq!(got, GOLDEN_CROPS.to_vec());
    // Bad bounds are refused, named.
    model.cfg.crop_min = 0.0;
    let e = model.with_crops(&data).unwrap_err();
    assert!(e.to_string().contains("reward_crop_min"), "{e}");
}

const GOLDEN_CROPS: [(usize, usize, usize); 5] = [
    (36, 14, 12),
    (36, 13, 3),
    (40, 7, 10),
    (45, 0, 4),
    (45, 0, 1),
];

/// Pearson correlation (test helper).
fn corr(x: &[f32], y: &[f32]) -> f64 {
    let n = x.len() as f64;
    let (mx, my) = (
        x.iter().map(|&v| v as f64).sum::<f64>() / n,
        y.iter().map(|&v| v as f64).sum::<f64>() / n,
    );
    let (mut sxy, mut sxx, mut syy) = (0.0, 0.0, 0.0);
    for (&a, &b) in x.iter().zip(y) {
        let (a, b) = (a as f64 - mx, b as f64 - my);
        sxy += a * b;
        sxx += a * a;
        syy += b * b;
    }
    sxy / (sxx * syy).sqrt()
}

#[test]
fn the_anchor_adds_c_r_task_to_every_reward_and_return() {
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    let segs = random_segments(&mut rng, 3, 9, 4, 2);
    let plain = RewardModel::new(small(3, &[8, 8]), 4, 2).unwrap();
    let cfg = RewardModelConfig {
        anchor: 2.5,
        goal: Some([1, 2]),
        ..small(3, &[8, 8])
    };
    let anchored = RewardModel::new(cfg, 4, 2).unwrap();
    let task = |o: &[f32]| -> Vec<f32> {
        o.chunks_exact(4)
            .map(|r| -2.5 * (r[1] * r[1] + r[2] * r[2]).sqrt())
            .collect()
    };
    for s in &segs {
        let (p, a) = (
            plain.predict(&s.obs, &s.actions, &[]).unwrap(),
            anchored.predict(&s.obs, &s.actions, &[]).unwrap(),
        );
        let c = task(&s.obs);
        for i in 0..p.len() {
            assert!((a[i] - p[i] - c[i]).abs() < 1e-5, "row {i}");
        }
        let obs = Tensor::from_slice(&s.obs, (9, 4), &Device::Cpu).unwrap();
        let act = Tensor::from_slice(&s.actions, (9, 2), &Device::Cpu).unwrap();
        let t = anchored.predict_tensor(&obs, &act, None).unwrap();
        let t: Vec<f32> = t.flatten_all().unwrap().to_vec1().unwrap();
        for i in 0..p.len() {
            assert!((t[i] - a[i]).abs() < 1e-5, "tensor row {i}");
        }
        let c_sum: f32 = c.iter().sum();
        for (ra, rp) in anchored
            .returns(s)
            .unwrap()
            .iter()
            .zip(plain.returns(s).unwrap())
        {
            assert!((ra - rp - c_sum).abs() < 1e-4);
        }
    }
    // Off without a goal to read, out of the observation, or negative: refused by name.
    for (anchor, goal) in [(1.0, None), (1.0, Some([3, 2])), (-1.0, Some([1, 2]))] {
        let cfg = RewardModelConfig {
            anchor,
            goal,
            ..small(3, &[8])
        };
        let e = RewardModel::new(cfg, 4, 2)
            .err()
            .expect("refused")
            .to_string();
        assert!(e.contains("reward_anchor"), "{e}");
    }
}

/// With the task part of the teacher's reward known, r_hat learns the rest: labels from
/// `-|obs[1..3]| - |obs0|`, anchored on `obs[1..3]`, train an r_hat whose own part follows
/// `-|obs0|` per step, where the plain model's r_hat mixes both.
#[test]
fn an_anchored_model_learns_what_the_task_does_not_say() {
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    let task = |o: &[f32]| -(o[1] * o[1] + o[2] * o[2]).sqrt();
    let rest = |o: &[f32]| -o[0].abs();
    let data = oracle_pairs_under(&mut rng, 300, 20, |o| task(o) + rest(o));
    let probe: Vec<f32> = (0..3000).map(|_| rng.random_range(-1.5..1.5)).collect();
    let probe_act = vec![0.0f32; probe.len() / 3];
    let rows: Vec<&[f32]> = probe.chunks_exact(3).collect();
    let want_rest: Vec<f32> = rows.iter().map(|o| rest(o)).collect();
    let mut own = Vec::new();
    for anchor in [0.0, 1.0] {
        let cfg = RewardModelConfig {
            batch: 32,
            lr: 1e-3,
            anchor,
            goal: Some([1, 2]),
            ..small(0, &[64, 64])
        };
        let mut model = RewardModel::new(cfg, 3, 1).unwrap();
        model.train(&data).unwrap();
        let r = model.predict(&probe, &probe_act, &[]).unwrap();
        let r_hat: Vec<f32> = r
            .iter()
            .zip(&rows)
            .map(|(r, o)| r - anchor as f32 * task(o))
            .collect();
        own.push(corr(&r_hat, &want_rest));
    }
    println!(
        "per-step corr of r_hat with the rest: plain {:.3}, anchored {:.3}",
        own[0], own[1]
    );
    assert!(own[1] > 0.8, "anchored {}", own[1]);
    assert!(
        own[1] > own[0] + 0.1,
        "plain {} anchored {}",
        own[0],
        own[1]
    );
}

/// Pseudo-labels train, but the accuracy that stops a training and that it reports counts
/// the labels only: against their own flipped copies the labels' accuracy would read 0.5.
#[test]
fn pseudo_labels_do_not_count_in_the_accuracy() {
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let labels = oracle_pairs(&mut rng, 64, 10);
    let flipped: Vec<Labelled> = labels
        .iter()
        .map(|l| Labelled {
            target: 1.0 - l.target,
            ..l.clone()
        })
        .collect();
    // One epoch, every pair once, no step: the reported accuracy is the model's as it is.
    let cfg = RewardModelConfig {
        lr: 0.0,
        max_epochs: 1,
        resample: Resample::Shuffle,
        ..small(2, &[16])
    };
    let mut model = RewardModel::new(cfg.clone(), 3, 1).unwrap();
    let stats = model.train_with(&labels, &flipped).unwrap();
    // The normaliser was fitted to these segments as the training began; nothing else moved.
    let before = model.accuracy(&labels).unwrap();
    assert!(
        (stats.accuracy - before).abs() < 1e-12,
        "{} vs {before}",
        stats.accuracy
    );
    assert_eq!(stats.pairs, 128, "the pseudo-labels train");
    let mut plain = RewardModel::new(cfg, 3, 1).unwrap();
    let joined = [labels.clone(), flipped].concat();
    let all = plain.train(&joined).unwrap();
    assert!((all.accuracy - 0.5).abs() < 1e-12, "{}", all.accuracy);
    assert!((before - 0.5).abs() > 1e-6, "the check can tell: {before}");
}

/// `n` labelled pairs of `steps`-step segments with 3 observation numbers and the six
/// comfort features (sparse counts, speeds, forces, as the feeding world's), the oracle
/// preferring the higher return of `reward(obs row, feature row)`.
fn pairs_with_features(
    rng: &mut impl Rng,
    n: usize,
    steps: usize,
    reward: impl Fn(&[f32], &[f32]) -> f32,
) -> Vec<Labelled> {
    let mut segment = || {
        let c: Vec<f32> = (0..3).map(|_| rng.random_range(-1.0..1.0)).collect();
        let obs = (0..steps * 3)
            .map(|i| c[i % 3] + rng.random_range(-0.5..0.5))
            .collect();
        let actions = (0..steps).map(|_| rng.random_range(-1.0..1.0)).collect();
        let p_eat = rng.random_range(0.0..0.3);
        let features = (0..steps)
            .flat_map(|_| {
                let eaten = rng.random_bool(p_eat) as u8 as f32;
                let force = if rng.random_bool(0.2) {
                    rng.random_range(0.0..20.0)
                } else {
                    0.0
                };
                [
                    eaten,
                    rng.random_range(0.0..0.5),
                    force,
                    if force >= 10.0 { force } else { 0.0 },
                    rng.random_bool(0.05) as u8 as f32,
                    eaten * rng.random_range(0.0..0.5),
                ]
            })
            .collect();
        Arc::new(Segment {
            obs,
            actions,
            features,
        })
    };
    let ret = |s: &Segment| -> f32 {
        s.obs
            .chunks_exact(3)
            .zip(s.features.chunks_exact(FEATURES))
            .map(|(o, f)| reward(o, f))
            .sum()
    };
    (0..n)
        .map(|_| {
            let (first, second) = (segment(), segment());
            let target = if ret(&second) > ret(&first) { 1.0 } else { 0.0 };
            Labelled {
                first,
                second,
                target,
            }
        })
        .collect()
}

#[test]
fn comfort_features_are_read_beside_the_observation_and_required_when_on() {
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let data = pairs_with_features(&mut rng, 4, 9, |o, _| o[0]);
    let cfg = RewardModelConfig {
        features: true,
        ..small(3, &[8, 8])
    };
    let model = RewardModel::new(cfg, 3, 1).unwrap();
    assert_eq!(
        (model.feat_dim(), model.width()),
        (FEATURES, 3 + FEATURES + 1)
    );
    let plain = RewardModel::new(small(3, &[8, 8]), 3, 1).unwrap();
    for s in data.iter().flat_map(|l| [&l.first, &l.second]) {
        let host = model.predict(&s.obs, &s.actions, &s.features).unwrap();
        let t = |xs: &[f32], w: usize| Tensor::from_slice(xs, (9, w), &Device::Cpu).unwrap();
        let (obs, act, f) = (t(&s.obs, 3), t(&s.actions, 1), t(&s.features, FEATURES));
        let tensor: Vec<f32> = model
            .predict_tensor(&obs, &act, Some(&f))
            .unwrap()
            .flatten_all()
            .unwrap()
            .to_vec1()
            .unwrap();
        for (h, t) in host.iter().zip(&tensor) {
            assert!((h - t).abs() < 1e-5, "{h} vs {t}");
        }
        // The features change the reward (the network reads them).
        let zeros = vec![0.0; s.features.len()];
        let without = model.predict(&s.obs, &s.actions, &zeros).unwrap();
        assert!(host.iter().zip(&without).any(|(a, b)| (a - b).abs() > 1e-4));
        // A model without features ignores them.
        assert_eq!(
            plain.predict(&s.obs, &s.actions, &s.features).unwrap(),
            plain.predict(&s.obs, &s.actions, &[]).unwrap()
        );
        // A model with features refuses steps without them, by name.
        let e = model.predict(&s.obs, &s.actions, &[]).unwrap_err();
        assert!(e.to_string().contains("reward_features"), "{e}");
        assert!(model.returns(&s.cut(0, 9, 9)).is_ok());
        let bare = Segment {
            features: Vec::new(),
            ..(**s).clone()
        };
        let e = model.returns(&bare).unwrap_err();
        assert!(e.to_string().contains("reward_features"), "{e}");
        assert!(model.predict_tensor(&obs, &act, None).is_err());
    }
    // The squash keeps the sign and compresses the scale.
    assert_eq!(squash(0.0), 0.0);
    assert!((squash(-20.0) + 21f32.ln()).abs() < 1e-6);
}

/// The features make a taste written in them learnable from few labels, and a taste that
/// is not a function of them is learnt as well as without them: the model still reads the
/// observation.
#[test]
fn a_taste_in_the_features_is_learnt_and_one_outside_them_still_is() {
    let in_features = |_: &[f32], f: &[f32]| 5.0 * f[0] - 2.0 * f[1] - 0.1 * f[2];
    let outside = |o: &[f32], _: &[f32]| -o[0].abs();
    let accuracy = |reward: &dyn Fn(&[f32], &[f32]) -> f32, features: bool| {
        let mut rng = ChaCha8Rng::seed_from_u64(21);
        let train = pairs_with_features(&mut rng, 150, 20, reward);
        let held_out = pairs_with_features(&mut rng, 300, 20, reward);
        let cfg = RewardModelConfig {
            batch: 32,
            lr: 1e-3,
            features,
            ..small(0, &[64, 64])
        };
        let mut model = RewardModel::new(cfg, 3, 1).unwrap();
        model.train(&train).unwrap();
        model.accuracy(&held_out).unwrap()
    };
    let (inside_on, inside_off) = (accuracy(&in_features, true), accuracy(&in_features, false));
    let (outside_on, outside_off) = (accuracy(&outside, true), accuracy(&outside, false));
    println!(
        "held-out accuracy: taste in the features {inside_on:.3} with them, {inside_off:.3} \
         without; taste outside them {outside_on:.3} with, {outside_off:.3} without"
    );
    assert!(inside_on > 0.8, "{inside_on}");
    assert!(inside_on > inside_off + 0.2, "{inside_on} vs {inside_off}");
    assert!(outside_on > 0.85, "{outside_on}");
    assert!(
        outside_on > outside_off - 0.05,
        "{outside_on} vs {outside_off}"
    );
}
