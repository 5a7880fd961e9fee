//! Helpers of the learner's unit tests.

use candle_core::backprop::GradStore;
use candle_core::{Tensor, Var};

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
