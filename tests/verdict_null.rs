//! The verdict keeps its error rate: two methods drawn from one seed distribution
//! (no true difference) are called ahead or behind in at most 6% of 4,000
//! simulated comparisons at 3, 5 and 8 seeds per method, and a planted difference
//! is found as often as the power calculation says.
//!
//! Each simulated seed is a trained policy: a seed effect drawn with the
//! between-seed spread measured at rung 4 of the severity ladder (TTF standard
//! deviation 0.0235 of the seed values of RALL and the Baseline, seeds 1-3),
//! then its robots (144) around it with a TTF's robot-to-robot spread (0.15),
//! which adds a little more spread than was measured. The seed's value is the
//! mean over its robots, as `rall experiment` computes it.

use rall::experiment::verdicts::seed_verdict;
use rall::stats::seed_test::{power, Verdict};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};

const SEED_SD: f64 = 0.0235;
const ROBOT_SD: f64 = 0.15;
const ROBOTS: usize = 144;
const COMPARISONS: usize = 4000;

/// One simulated method's seed values: `n` seeds around `centre`.
fn method(n: usize, centre: f64, rng: &mut ChaCha8Rng) -> Vec<f64> {
    let seed = Normal::new(centre, SEED_SD).unwrap();
    let robot = Normal::new(0.0, ROBOT_SD).unwrap();
    (0..n)
        .map(|_| {
            let s = seed.sample(rng);
            (0..ROBOTS).map(|_| s + robot.sample(rng)).sum::<f64>() / ROBOTS as f64
        })
        .collect()
}

/// The share of comparisons called ahead or behind, `effect` apart.
fn called_rate(n: usize, effect: f64, seed: u64) -> f64 {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let called = (0..COMPARISONS)
        .filter(|_| {
            let a = method(n, 0.2 + effect, &mut rng);
            let b = method(n, 0.2, &mut rng);
            seed_verdict(&a, &b, 0.05) != Verdict::Level
        })
        .count();
    called as f64 / COMPARISONS as f64
}

#[test]
fn no_true_difference_is_called_in_at_most_six_percent() {
    for n in [3, 5, 8] {
        let rate = called_rate(n, 0.0, 1000 + n as u64);
        println!(
            "{n} seeds per method, no difference: called in {:.1}%",
            100.0 * rate
        );
        assert!(rate <= 0.06, "{n} seeds: {rate}");
        // and not by being blind: some comparisons are called by chance
        assert!(rate >= 0.02, "{n} seeds: {rate}");
    }
}

#[test]
fn a_planted_difference_is_found_with_the_predicted_power() {
    // the total spread of a seed's value: seed spread and robots' mean noise
    let sd = (SEED_SD.powi(2) + ROBOT_SD.powi(2) / ROBOTS as f64).sqrt();
    for (n, effect) in [(3, 0.061), (5, 0.061), (5, 0.03), (8, 0.03)] {
        let found = called_rate(n, effect, 2000 + n as u64);
        let predicted = power(n, n, effect, sd, 0.05, 4000, 7);
        println!(
            "{n} seeds per method, planted +{effect}: found in {:.1}% (predicted {:.1}%)",
            100.0 * found,
            100.0 * predicted
        );
        assert!(
            (found - predicted).abs() < 0.04,
            "{n} {effect}: {found} vs {predicted}"
        );
    }
    // more seeds, more power
    assert!(called_rate(8, 0.03, 3) > called_rate(3, 0.03, 3));
}
