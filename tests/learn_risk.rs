//! Quantile Huber loss, distortions (CVaR, Wang) and their closed forms.

use proptest::prelude::*;
use rall::learn::risk::{
    huber, normal_icdf, quantile_huber, quantile_huber_grad_pred, quantile_huber_loss, Distortion,
};

/// (tau, delta = target - prediction, kappa, rho, d rho / d prediction), by hand.
const CASES: [(f32, f32, f32, f32, f32); 6] = [
    // |delta| <= kappa: |tau - 1{delta<0}| * delta^2 / 2
    (0.25, 0.5, 1.0, 0.25 * 0.125, -0.25 * 0.5),
    (0.25, -0.5, 1.0, 0.75 * 0.125, 0.75 * 0.5),
    // |delta| > kappa: |tau - 1{delta<0}| * kappa (|delta| - kappa / 2)
    (0.9, 3.0, 1.0, 0.9 * 2.5, -0.9),
    (0.9, -2.0, 1.0, 0.1 * 1.5, 0.1),
    (0.3, -3.0, 2.0, 0.7 * 4.0, 0.7 * 2.0),
    (0.6, 0.01, 0.005, 0.6 * 0.005 * 0.0075, -0.6 * 0.005),
];

#[test]
fn quantile_huber_matches_hand_values() {
    for (tau, delta, kappa, rho, grad) in CASES {
        assert!(
            (quantile_huber(tau, delta, kappa) - rho).abs() < 1e-6,
            "{tau} {delta}"
        );
        assert!((quantile_huber_grad_pred(tau, delta, kappa) - grad).abs() < 1e-6);
        // through the batched loss: one sample, one tau, one target
        let pred = 1.25f32;
        let mut g = [0.0];
        let l = quantile_huber_loss(&[pred], &[tau], &[pred + delta], kappa, &mut g);
        assert!((l - rho).abs() < 1e-5, "loss {l} vs {rho}");
        assert!((g[0] - grad).abs() < 1e-5, "grad {} vs {grad}", g[0]);
        // and the gradient agrees with a central difference of the loss
        let h = 1e-3 * kappa.min(1.0);
        let f = |p: f32| quantile_huber_loss(&[p], &[tau], &[pred + delta], kappa, &mut [0.0]);
        let numeric = (f(pred + h) - f(pred - h)) / (2.0 * h);
        assert!(
            (numeric - grad).abs() < 2e-2 * grad.abs().max(0.01),
            "fd {numeric} vs {grad}"
        );
    }
    assert_eq!(huber(0.0, 1.0), 0.0);
}

#[test]
fn loss_is_sum_over_taus_of_mean_over_targets() {
    // B = 1, N = 2, N' = 2: (rho(t1, d11) + rho(t1, d12)) / 2 + (rho(t2, d21) + rho(t2, d22)) / 2
    let (taus, pred, targets) = ([0.2f32, 0.7], [0.0f32, 1.0], [0.5f32, 3.0]);
    let want = (quantile_huber(0.2, 0.5, 1.0) + quantile_huber(0.2, 3.0, 1.0)) / 2.0
        + (quantile_huber(0.7, -0.5, 1.0) + quantile_huber(0.7, 2.0, 1.0)) / 2.0;
    let l = quantile_huber_loss(&pred, &taus, &targets, 1.0, &mut [0.0; 2]);
    assert!((l - want).abs() < 1e-6);
}

#[test]
fn cvar_of_uniform_matches_closed_form() {
    // U(a, b): q(tau) = a + (b - a) tau, CVaR_eta = a + (b - a) eta / 2
    let (a, b) = (-1.0f32, 3.0f32);
    for (eta, want) in [(0.3, -0.4), (0.5, 0.0), (1.0, 1.0)] {
        let v = Distortion::Cvar { eta }.value_of(|t| a + (b - a) * t, 64);
        assert!((v - want).abs() < 1e-5, "eta {eta}: {v} vs {want}");
    }
}

#[test]
fn cvar_of_normal_matches_closed_form() {
    // N(1, 2^2): CVaR_eta = mu - sigma phi(Phi^-1(eta)) / eta
    // eta 0.5: 1 - 2 * 0.398942 / 0.5; eta 0.1: 1 - 2 * 0.175498 / 0.1; eta 1: mu
    let q = |t: f32| 1.0 + 2.0 * normal_icdf(t as f64) as f32;
    for (eta, want, k, tol) in [
        (0.5, -0.595_769, 1024, 2e-3),
        (0.1, -2.509_96, 1024, 5e-3),
        (1.0, 1.0, 64, 1e-4),
        (0.5, -0.595_769, 64, 2e-2),
    ] {
        let v = Distortion::Cvar { eta }.value_of(q, k);
        assert!((v - want).abs() < tol, "eta {eta}, K {k}: {v} vs {want}");
    }
}

proptest! {
    #[test]
    fn cvar_is_non_decreasing_in_eta(
        mut knots in proptest::collection::vec(-50.0f32..50.0, 2..20),
        e1 in 0.01f32..1.0,
        e2 in 0.01f32..1.0,
    ) {
        knots.sort_by(|a, b| a.partial_cmp(b).unwrap());
        // piecewise-linear non-decreasing quantile function through the knots
        let n = knots.len();
        let q = |t: f32| {
            let x = t * (n - 1) as f32;
            let i = (x.floor() as usize).min(n - 2);
            knots[i] + (knots[i + 1] - knots[i]) * (x - i as f32)
        };
        let (lo, hi) = if e1 <= e2 { (e1, e2) } else { (e2, e1) };
        let v_lo = Distortion::Cvar { eta: lo }.value_of(q, 64);
        let v_hi = Distortion::Cvar { eta: hi }.value_of(q, 64);
        prop_assert!(v_lo <= v_hi + 1e-4, "CVaR_{lo} = {v_lo} > CVaR_{hi} = {v_hi}");
        let neutral = Distortion::Cvar { eta: 1.0 }.value_of(q, 64);
        prop_assert!(v_hi <= neutral + 1e-4, "CVaR_{hi} = {v_hi} > mean {neutral}");
    }
}

#[test]
fn batched_loss_at_default_shapes_is_fast_and_consistent() {
    // B = 1536, N = N' = 64 as one PPO mini-batch; compare with the pointwise sum on a few rows
    let (b, n, nt) = (1536, 64, 64);
    let taus: Vec<f32> = (0..n).map(|i| (i as f32 + 0.5) / n as f32).collect();
    let pred: Vec<f32> = (0..b * n)
        .map(|i| ((i * 7919) % 1000) as f32 / 100.0 - 5.0)
        .collect();
    let targets: Vec<f32> = (0..b * nt)
        .map(|i| ((i * 104_729) % 1000) as f32 / 50.0 - 10.0)
        .collect();
    let mut grad = vec![0.0; b * n];
    let mut loss = 0.0;
    let mut best = std::time::Duration::MAX;
    for _ in 0..5 {
        let t = std::time::Instant::now();
        loss = quantile_huber_loss(&pred, &taus, &targets, 1.0, &mut grad);
        best = best.min(t.elapsed());
    }
    eprintln!("quantile Huber loss, 1536 x 64 x 64: {best:?}");
    let mut want = 0.0f64;
    for r in 0..b {
        for i in 0..n {
            let mut g = 0.0f64;
            for j in 0..nt {
                let d = targets[r * nt + j] - pred[r * n + i];
                want += quantile_huber(taus[i], d, 1.0) as f64;
                g += quantile_huber_grad_pred(taus[i], d, 1.0) as f64;
            }
            let g = g / (b * nt) as f64;
            assert!(
                (grad[r * n + i] as f64 - g).abs() < 1e-6 * g.abs().max(1e-3),
                "row {r} tau {i}"
            );
        }
    }
    let want = want / (b * nt) as f64;
    assert!((loss as f64 - want).abs() < 1e-4 * want, "{loss} vs {want}");
}
