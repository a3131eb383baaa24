//! Means and order statistics, one definition for the evaluation (race quantiles, risk
//! thresholds) and the experiment (bootstrap intervals, pooled methods, run pace):
//! point estimates with their intervals, the percentile bootstrap over robots
//! (resample the units with replacement, recompute the statistic, take the two-sided
//! quantiles; seeded, so the same data give the same interval) and the Wilson score
//! interval of a rate; and the seed-level tests that decide whether one method beats
//! another.
//! - [`student_t`]: Student's t distribution (CDF and quantile).
//! - [`seed_test`]: Welch's t, the exact permutation test over seed labels, Holm's
//!   step-down and the power of a comparison, all on one number per seed.

pub mod seed_test;
pub mod student_t;

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use crate::hash::{fnv1a64_from, FNV1A64_OFFSET};

/// Mean of `values` (NaN for none).
pub fn mean(values: &[f64]) -> f64 {
    if values.is_empty() {
        f64::NAN
    } else {
        values.iter().sum::<f64>() / values.len() as f64
    }
}

/// Quantile `q` in [0, 1] of already sorted values: linear interpolation between the two
/// order statistics around position `q (n - 1)` (numpy's default method); NaN for none.
pub fn percentile(sorted: &[f64], q: f64) -> f64 {
    if sorted.is_empty() {
        return f64::NAN;
    }
    let pos = q.clamp(0.0, 1.0) * (sorted.len() - 1) as f64;
    let (i, frac) = (pos.floor() as usize, pos.fract());
    if i + 1 < sorted.len() {
        sorted[i] * (1.0 - frac) + sorted[i + 1] * frac
    } else {
        sorted[i]
    }
}

/// Quantile `q` in [0, 1] of unsorted values ([`percentile`] after a sort); NaN for none.
pub fn quantile(values: &[f64], q: f64) -> f64 {
    let mut sorted = values.to_vec();
    sorted.sort_by(f64::total_cmp);
    percentile(&sorted, q)
}

/// A point estimate with its confidence interval.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Estimate {
    pub value: f64,
    pub lo: f64,
    pub hi: f64,
}

impl Estimate {
    /// `value,lo,hi` with `digits` decimals (three CSV fields).
    pub fn csv(&self, digits: usize) -> String {
        format!(
            "{:.d$},{:.d$},{:.d$}",
            self.value,
            self.lo,
            self.hi,
            d = digits
        )
    }

    /// The same estimate in percent (a fraction times 100).
    pub fn percent(&self) -> Estimate {
        Estimate {
            value: 100.0 * self.value,
            lo: 100.0 * self.lo,
            hi: 100.0 * self.hi,
        }
    }

    /// A fraction as `4.7% [1.6, 9.4]`.
    pub fn show_percent(&self) -> String {
        let p = self.percent();
        format!("{:.1}% [{:.1}, {:.1}]", p.value, p.lo, p.hi)
    }

    /// `0.512 [0.45, 0.57]` with `digits` decimals.
    pub fn show(&self, digits: usize) -> String {
        format!(
            "{:.d$} [{:.d$}, {:.d$}]",
            self.value,
            self.lo,
            self.hi,
            d = digits
        )
    }
}

/// The bootstrap seed of one cell: `seed` mixed with the cell's name (FNV-1a, stable
/// across Rust versions), so a cell's interval depends on its own data only, not on
/// which other methods or cells the experiment evaluates.
pub fn cell_seed(seed: u64, cell: &str) -> u64 {
    fnv1a64_from(FNV1A64_OFFSET ^ seed, cell.bytes())
}

/// `statistic` of `units` with a percentile bootstrap interval at `level`: the
/// one-stratum case of [`bootstrap_strata`].
pub fn bootstrap<T: Clone>(
    units: &[T],
    statistic: impl Fn(&[T]) -> f64,
    resamples: usize,
    level: f64,
    seed: u64,
) -> Estimate {
    bootstrap_strata(
        &[units.to_vec()],
        |s| statistic(&s[0]),
        resamples,
        level,
        seed,
    )
}

/// `statistic` of `strata` (a method's seeds, each a list of robots) with a percentile
/// bootstrap that resamples units within each stratum: the seeds keep their sizes, so
/// a statistic weighting seeds equally stays so.
pub fn bootstrap_strata<T: Clone>(
    strata: &[Vec<T>],
    statistic: impl Fn(&[Vec<T>]) -> f64,
    resamples: usize,
    level: f64,
    seed: u64,
) -> Estimate {
    let value = statistic(strata);
    if strata.iter().map(Vec::len).sum::<usize>() < 2 {
        return Estimate {
            value,
            lo: value,
            hi: value,
        };
    }
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut stats = Vec::with_capacity(resamples);
    let mut sample: Vec<Vec<T>> = strata.iter().map(|s| Vec::with_capacity(s.len())).collect();
    for _ in 0..resamples {
        for (out, units) in sample.iter_mut().zip(strata) {
            out.clear();
            for _ in 0..units.len() {
                out.push(units[rng.gen_range(0..units.len())].clone());
            }
        }
        stats.push(statistic(&sample));
    }
    stats.sort_by(f64::total_cmp);
    let alpha = (1.0 - level) / 2.0;
    Estimate {
        value,
        lo: percentile(&stats, alpha),
        hi: percentile(&stats, 1.0 - alpha),
    }
}

/// The normal quantile of a two-sided 95% interval.
pub const Z_95: f64 = 1.959_963_984_540_054;

/// The rate `hits / trials` with its Wilson score interval at normal quantile `z`
/// ([`Z_95`]: 95%). Unlike the bootstrap it does not shrink to a point when every
/// trial went the same way: 0 falls of 16 robots is 0% [0, 19.4%]. No trials:
/// 0 within [0, 1] (nothing is known).
pub fn wilson(hits: usize, trials: usize, z: f64) -> Estimate {
    if trials == 0 {
        return Estimate {
            value: 0.0,
            lo: 0.0,
            hi: 1.0,
        };
    }
    let n = trials as f64;
    let p = hits.min(trials) as f64 / n;
    let z2 = z * z;
    let denominator = 1.0 + z2 / n;
    let centre = (p + z2 / (2.0 * n)) / denominator;
    let half = z * (p * (1.0 - p) / n + z2 / (4.0 * n * n)).sqrt() / denominator;
    Estimate {
        value: p,
        lo: (centre - half).max(0.0),
        hi: (centre + half).min(1.0),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn quantiles_interpolate_like_numpy() {
        let v = [4.0, 1.0, 3.0, 2.0];
        assert_eq!(quantile(&v, 0.0), 1.0);
        assert_eq!(quantile(&v, 1.0), 4.0);
        assert_eq!(quantile(&v, 0.5), 2.5);
        assert!((quantile(&v, 0.25) - 1.75).abs() < 1e-12);
        assert_eq!(quantile(&[7.0], 0.3), 7.0);
        assert!(quantile(&[], 0.5).is_nan());
        // out-of-range q clamps to the extremes
        assert_eq!(quantile(&v, -1.0), 1.0);
        assert_eq!(quantile(&v, 2.0), 4.0);
    }

    #[test]
    fn the_mean_of_nothing_is_nan() {
        assert_eq!(mean(&[1.0, 2.0, 6.0]), 3.0);
        assert!(mean(&[]).is_nan());
    }

    #[test]
    fn the_interval_covers_the_estimate_and_is_reproducible() {
        let units: Vec<f64> = (0..40).map(|i| (i % 7) as f64).collect();
        let a = bootstrap(&units, mean, 500, 0.95, 3);
        let b = bootstrap(&units, mean, 500, 0.95, 3);
        assert_eq!(a, b);
        assert!(a.lo <= a.value && a.value <= a.hi && a.lo < a.hi, "{a:?}");
        // the standard error of a mean of 40 values of sd ~2: the interval is ~ +-0.6
        assert!(a.hi - a.lo > 0.5 && a.hi - a.lo < 2.5, "{a:?}");
        let one = bootstrap(&[2.0], mean, 100, 0.95, 0);
        assert_eq!((one.lo, one.value, one.hi), (2.0, 2.0, 2.0));
    }

    #[test]
    fn a_cells_seed_depends_on_its_name_and_the_experiments_seed_only() {
        let a = cell_seed(0, "ttf/RALL/ball/flat/false");
        assert_eq!(a, cell_seed(0, "ttf/RALL/ball/flat/false"));
        assert_ne!(a, cell_seed(1, "ttf/RALL/ball/flat/false"));
        assert_ne!(a, cell_seed(0, "ttf/RALL/ball/flat/true"));
        assert_ne!(a, cell_seed(0, "ttf/DR/ball/flat/false"));
        // fixed value: committed results depend on it staying the same
        assert_eq!(cell_seed(0, ""), 0xcbf2_9ce4_8422_2325);
    }

    #[test]
    fn one_stratum_is_the_plain_bootstrap_and_strata_keep_their_weights() {
        let units: Vec<f64> = (0..30).map(|i| ((i * 7) % 11) as f64).collect();
        let plain = bootstrap(&units, mean, 400, 0.95, 9);
        let one = bootstrap_strata(std::slice::from_ref(&units), |s| mean(&s[0]), 400, 0.95, 9);
        assert_eq!(plain, one);
        // two seeds far apart: equal weight per seed whatever their sizes, and the
        // within-seed resampling never mixes them (every resample's mean stays ~5.5)
        let a = vec![1.0; 10];
        let b = vec![10.0; 40];
        let e = bootstrap_strata(&[a, b], |s| (mean(&s[0]) + mean(&s[1])) / 2.0, 200, 0.95, 1);
        assert_eq!((e.lo, e.value, e.hi), (5.5, 5.5, 5.5));
    }

    #[test]
    fn wilson_intervals_match_the_formula_and_mirror() {
        let none = wilson(0, 16, Z_95);
        assert_eq!((none.value, none.lo), (0.0, 0.0));
        assert!((none.hi - 0.193_607_680_5).abs() < 1e-9, "{none:?}");
        let most = wilson(7, 8, Z_95);
        assert!((most.lo - 0.529_111_817_8).abs() < 1e-9, "{most:?}");
        assert!((most.hi - 0.977_582_508_5).abs() < 1e-9, "{most:?}");
        // k of n and n - k of n are mirror images
        let few = wilson(1, 8, Z_95);
        assert!((few.lo - (1.0 - most.hi)).abs() < 1e-12);
        assert!((few.hi - (1.0 - most.lo)).abs() < 1e-12);
        let all = wilson(16, 16, Z_95);
        assert_eq!((all.value, all.hi), (1.0, 1.0));
        assert!((all.lo - (1.0 - none.hi)).abs() < 1e-12);
        assert_eq!(
            wilson(0, 0, Z_95),
            Estimate {
                value: 0.0,
                lo: 0.0,
                hi: 1.0
            }
        );
    }
}
