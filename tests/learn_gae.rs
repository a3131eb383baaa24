//! GAE with a time-out and a termination, and the IQN targets, against hand values.

use rall::learn::storage::{gae, next_values, quantile_targets, ActOutput, Rollout};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

/// One env, 5 steps: rewards 1..5; step 1 times out (true final obs has value
/// 10), step 3 terminates; the observation after step 4 has value 3.
fn rollout() -> Rollout {
    let mut r = Rollout::new(5, 1, 1, 1);
    let dones = [false, true, false, true, false];
    let time_outs = [false, true, false, false, false];
    for t in 0..5 {
        let out = ActOutput {
            actions: vec![0.0],
            log_probs: vec![0.0],
            action_mean: vec![0.0],
            action_std: vec![1.0],
        };
        let final_obs = if time_outs[t] { vec![-7.0] } else { vec![] };
        r.push(
            &[t as f32],
            &out,
            &[t as f32 + 1.0],
            &[dones[t]],
            &[time_outs[t]],
            &final_obs,
        )
        .unwrap();
    }
    r.set_last_obs(&[5.0]).unwrap();
    r
}

const VALUES: [f32; 5] = [0.5, 1.0, 1.5, 2.0, 2.5];

#[test]
fn gae_with_time_out_and_termination() {
    let r = rollout();
    assert!(r.is_full());
    assert_eq!(r.final_obs, vec![(1, vec![-7.0])]);
    let (gamma, lambda) = (0.9, 0.8);
    let next = next_values(&r, 1, &VALUES, &[3.0], &[10.0]);
    // V(s1) | V(final obs) on the time-out | V(s3) | 0 on the termination | V(last obs)
    assert_eq!(next, vec![1.0, 10.0, 2.0, 0.0, 3.0]);
    let adv = gae(&r, &VALUES, &next, gamma, lambda);
    // delta = r + 0.9 next - V: [1.4, 10.0, 3.3, 2.0, 5.2]
    // A4 = 5.2; A3 = 2.0 (done); A2 = 3.3 + 0.72 * 2.0; A1 = 10.0 (done); A0 = 1.4 + 0.72 * 10
    let want = [8.6, 10.0, 4.74, 2.0, 5.2];
    for (a, w) in adv.iter().zip(want) {
        assert!((a - w).abs() < 1e-5, "{adv:?} vs {want:?}");
    }
}

#[test]
fn one_step_and_full_horizon_quantile_targets() {
    let r = rollout();
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    // two target taus; Z(next) per step: Z(s_{t+1}) = [v, v + 1], final obs [10, 12], last [3, 4]
    let cur: Vec<f32> = VALUES.iter().flat_map(|&v| [v, v + 1.0]).collect();
    let next_z = next_values(&r, 2, &cur, &[3.0, 4.0], &[10.0, 12.0]);
    // lambda = 0: r + gamma Z_j(s'), no bootstrap after the termination
    let t0 = quantile_targets(&r, &next_z, 2, 0.9, 0.0, &mut rng);
    let want0 = [1.9, 2.8, 11.0, 12.8, 4.8, 5.7, 4.0, 4.0, 7.7, 8.6];
    for (a, w) in t0.iter().zip(want0) {
        assert!((a - w).abs() < 1e-5, "{t0:?} vs {want0:?}");
    }
    // lambda = 1: the whole segment, bootstrapped at its end
    let t1 = quantile_targets(&r, &next_z, 2, 0.9, 1.0, &mut rng);
    let want1 = [
        1.0 + 0.9 * 2.0 + 0.81 * 10.0,
        1.0 + 0.9 * 2.0 + 0.81 * 12.0,
        11.0,
        12.8,
        3.0 + 0.9 * 4.0,
        3.0 + 0.9 * 4.0,
        4.0,
        4.0,
        7.7,
        8.6,
    ];
    for (a, w) in t1.iter().zip(want1) {
        assert!((a - w).abs() < 1e-4, "{t1:?} vs {want1:?}");
    }
}

#[test]
fn random_horizon_targets_average_to_the_lambda_return() {
    // With a degenerate Z (all target quantiles = V), the mean target is the
    // lambda-return A + V of GAE.
    let r = rollout();
    let n = 20_000;
    let (gamma, lambda) = (0.9, 0.8);
    let next = next_values(&r, 1, &VALUES, &[3.0], &[10.0]);
    let adv = gae(&r, &VALUES, &next, gamma, lambda);
    let cur: Vec<f32> = VALUES
        .iter()
        .flat_map(|&v| std::iter::repeat_n(v, n))
        .collect();
    let next_z = next_values(&r, n, &cur, &vec![3.0; n], &vec![10.0; n]);
    let targets = quantile_targets(
        &r,
        &next_z,
        n,
        gamma,
        lambda,
        &mut ChaCha8Rng::seed_from_u64(1),
    );
    for t in 0..5 {
        let mean = targets[t * n..(t + 1) * n]
            .iter()
            .map(|&x| x as f64)
            .sum::<f64>()
            / n as f64;
        let want = (adv[t] + VALUES[t]) as f64;
        assert!(
            (mean - want).abs() < 0.02 * want.abs(),
            "t {t}: {mean} vs {want}"
        );
    }
}
