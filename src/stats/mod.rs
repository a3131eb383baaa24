//! Means and order statistics, one definition for the evaluation (race quantiles, risk
//! thresholds) and the experiment (bootstrap intervals, pooled methods, run pace); and the
//! seed-level tests that decide whether one method beats another.
//! - [`student_t`]: Student's t distribution (CDF and quantile).
//! - [`seed_test`]: Welch's t, the exact permutation test over seed labels, Holm's
//!   step-down and the power of a comparison, all on one number per seed.

pub mod seed_test;
pub mod student_t;

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
}
