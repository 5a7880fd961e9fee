//! Helpers of the learner's unit tests.

use candle_core::backprop::GradStore;
use candle_core::{Device, Tensor, Var};
use rand::{Rng, SeedableRng};

/// Every variable's gradient in `got` is candle autodiff's in `want`, within a
/// tolerance relative to the largest entry; `vars` names them.
pub fn assert_same_gradients(vars: &[(String, Var)], got: &GradStore, want: &GradStore) {
    for (name, var) in vars {
        let w = want.get(var).expect("autodiff has every gradient");
        let g = got
            .get(var)
            .unwrap_or_else(|| panic!("no hand gradient for {name}"));
        assert_eq!(g.dims(), w.dims(), "{name}");
        let flat = |t: &Tensor| t.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        let (g, w) = (flat(g), flat(w));
        let scale = w.iter().fold(1e-6f32, |m, x| m.max(x.abs()));
        let worst = g
            .iter()
            .zip(&w)
            .map(|(a, b)| (a - b).abs())
            .fold(0f32, f32::max);
        assert!(
            worst <= 1e-4 * scale,
            "{name}: hand gradient off by {worst} (largest entry {scale})"
        );
    }
}

/// A maker of `[rows, cols]` tensors uniform in `(-k, k)`, from a seeded generator.
pub fn uniform_tensors(seed: u64) -> impl FnMut(usize, usize, f32) -> Tensor {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    move |rows, cols, k| {
        let v: Vec<f32> = (0..rows * cols).map(|_| rng.random_range(-k..k)).collect();
        Tensor::from_vec(v, (rows, cols), &Device::Cpu).unwrap()
    }
}
