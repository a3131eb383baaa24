//! Whether one method beats another, judged on one number per trained seed.
//!
//! A seed is the unit of a claim about methods: robots of one trained policy share its
//! training, so they say how that policy behaves, not how the method would behave with
//! another seed. Each function here takes one value per seed and per method:
//! - [`welch`]: Welch's two-sample t-test and its interval for the difference of means
//!   (unequal variances, Welch-Satterthwaite degrees of freedom); the verdict's test.
//! - [`permutation_p`]: the exact permutation test over seed labels (every split of the
//!   pooled seeds into groups of the two sizes), needing no normality; reported beside.
//! - [`holm`]: Holm's step-down adjustment of a family of p-values.
//! - [`power`] and [`seeds_for_power`]: how often Welch's test calls a true difference,
//!   by simulation from a between-seed spread.

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};

use super::{mean, student_t};

/// Welch's test of the difference of two methods' seed means.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Welch {
    /// Mean of the first method's seeds minus the second's.
    pub difference: f64,
    /// The two-sided interval at the requested level.
    pub lo: f64,
    pub hi: f64,
    /// Welch-Satterthwaite degrees of freedom (infinite when both spreads are 0).
    pub df: f64,
    /// Two-sided p-value of "no difference".
    pub p: f64,
}

/// The sample variance (n - 1 in the denominator).
fn sample_variance(v: &[f64]) -> f64 {
    let m = mean(v);
    v.iter().map(|x| (x - m).powi(2)).sum::<f64>() / (v.len() as f64 - 1.0)
}

/// Welch's t-test of `first` against `second` (one value per seed) with its
/// two-sided interval at `level` (0.95 for 95%); `None` with fewer than two seeds
/// on either side or a non-finite value.
pub fn welch(first: &[f64], second: &[f64], level: f64) -> Option<Welch> {
    if first.len() < 2 || second.len() < 2 || !first.iter().chain(second).all(|x| x.is_finite()) {
        return None;
    }
    let difference = mean(first) - mean(second);
    let (va, vb) = (
        sample_variance(first) / first.len() as f64,
        sample_variance(second) / second.len() as f64,
    );
    let se2 = va + vb;
    if se2 <= 0.0 {
        // every seed of both methods alike: the difference is exact
        let p = if difference == 0.0 { 1.0 } else { 0.0 };
        return Some(Welch {
            difference,
            lo: difference,
            hi: difference,
            df: f64::INFINITY,
            p,
        });
    }
    let df =
        se2 * se2 / (va * va / (first.len() as f64 - 1.0) + vb * vb / (second.len() as f64 - 1.0));
    let se = se2.sqrt();
    let half = student_t::quantile(0.5 + level / 2.0, df) * se;
    Some(Welch {
        difference,
        lo: difference - half,
        hi: difference + half,
        df,
        p: student_t::two_sided_p(difference / se, df),
    })
}

/// Splits of the pooled seeds enumerated exactly up to this many; beyond it,
/// [`permutation_p`] draws this many random splits instead.
const EXACT_SPLITS_MAX: u64 = 2_000_000;

/// C(n, k) (saturating).
fn binomial(n: u64, k: u64) -> u64 {
    (0..k.min(n - k)).fold(1u64, |c, i| c.saturating_mul(n - i) / (i + 1))
}

/// The two-sided p-value of the permutation test over seed labels: the share of
/// all splits of the pooled seed values into groups of `first.len()` and
/// `second.len()` whose difference of means is at least as far from 0 as the
/// observed one. Exact (every split, the observed one included) for up to two
/// million splits, else over that many random splits (seeded, so reproducible).
/// `None` when either side is empty.
pub fn permutation_p(first: &[f64], second: &[f64]) -> Option<f64> {
    let (na, nb) = (first.len(), second.len());
    if na == 0 || nb == 0 {
        return None;
    }
    let pooled: Vec<f64> = first.iter().chain(second).copied().collect();
    let total: f64 = pooled.iter().sum();
    let diff_of = |sum_a: f64| sum_a / na as f64 - (total - sum_a) / nb as f64;
    let observed = diff_of(first.iter().sum()).abs();
    // splits that tie with the observed one count as extreme (floating-point slack)
    let tol = 1e-12 * (1.0 + observed);
    let splits = binomial((na + nb) as u64, na as u64);
    let (extreme, count) = if splits <= EXACT_SPLITS_MAX {
        let mut extreme = 0u64;
        for_each_subset_sum(&pooled, na, &mut |s| {
            if diff_of(s).abs() >= observed - tol {
                extreme += 1;
            }
        });
        (extreme, splits)
    } else {
        let mut rng = ChaCha8Rng::seed_from_u64(0x5eed);
        let mut idx: Vec<usize> = (0..pooled.len()).collect();
        let mut extreme = 0u64;
        for _ in 0..EXACT_SPLITS_MAX {
            rand::seq::SliceRandom::partial_shuffle(&mut idx[..], &mut rng, na);
            let s: f64 = idx[..na].iter().map(|&i| pooled[i]).sum();
            if diff_of(s).abs() >= observed - tol {
                extreme += 1;
            }
        }
        (extreme, EXACT_SPLITS_MAX)
    };
    Some(extreme as f64 / count as f64)
}

/// Calls `f` with the sum of every subset of `k` of `values`.
fn for_each_subset_sum(values: &[f64], k: usize, f: &mut impl FnMut(f64)) {
    fn go(values: &[f64], start: usize, k: usize, sum: f64, f: &mut impl FnMut(f64)) {
        if k == 0 {
            f(sum);
            return;
        }
        for i in start..=values.len() - k {
            go(values, i + 1, k - 1, sum + values[i], f);
        }
    }
    go(values, 0, k, 0.0, f);
}

/// Holm's step-down adjustment: each p-value of a family made comparable with the
/// familywise level (reject the i-th smallest while `(m - i + 1) p` stays below it).
/// Adjusted values keep their input order; NaN stays NaN and is not counted.
pub fn holm(p: &[f64]) -> Vec<f64> {
    let mut order: Vec<usize> = (0..p.len()).filter(|&i| !p[i].is_nan()).collect();
    order.sort_by(|&a, &b| p[a].total_cmp(&p[b]));
    let m = order.len();
    let mut out = vec![f64::NAN; p.len()];
    let mut running = 0.0_f64;
    for (rank, &i) in order.iter().enumerate() {
        running = running.max(((m - rank) as f64 * p[i]).min(1.0));
        out[i] = running;
    }
    out
}

/// A verdict on a difference, first minus second.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Verdict {
    Ahead,
    Behind,
    Level,
}

impl Verdict {
    /// Ahead or behind (by the sign of `difference`) when `p` < `alpha`, else level.
    pub fn from_p(difference: f64, p: f64, alpha: f64) -> Verdict {
        if p < alpha && difference > 0.0 {
            Verdict::Ahead
        } else if p < alpha && difference < 0.0 {
            Verdict::Behind
        } else {
            Verdict::Level
        }
    }

    pub fn as_str(self) -> &'static str {
        match self {
            Verdict::Ahead => "ahead",
            Verdict::Behind => "behind",
            Verdict::Level => "level",
        }
    }
}

/// The share of `draws` simulated comparisons in which Welch's test at `alpha`
/// calls a difference, with `n_first` and `n_second` seeds drawn from normal
/// distributions `effect` apart with standard deviation `sd` (seeded).
pub fn power(
    n_first: usize,
    n_second: usize,
    effect: f64,
    sd: f64,
    alpha: f64,
    draws: usize,
    seed: u64,
) -> f64 {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let Ok(noise) = Normal::new(0.0, sd.max(0.0)) else {
        return f64::NAN;
    };
    let mut called = 0usize;
    let (mut a, mut b) = (vec![0.0; n_first], vec![0.0; n_second]);
    for _ in 0..draws {
        a.iter_mut()
            .for_each(|x| *x = effect + noise.sample(&mut rng));
        b.iter_mut().for_each(|x| *x = noise.sample(&mut rng));
        if welch(&a, &b, 1.0 - alpha).is_some_and(|w| w.p < alpha) {
            called += 1;
        }
    }
    called as f64 / draws as f64
}

/// The fewest seeds per method (2 to `max_seeds`) at which Welch's test at `alpha`
/// calls a true difference `effect` with at least `target` power, the seeds' spread
/// being `sd`; `None` when even `max_seeds` does not reach it.
pub fn seeds_for_power(
    effect: f64,
    sd: f64,
    alpha: f64,
    target: f64,
    max_seeds: usize,
) -> Option<usize> {
    (2..=max_seeds).find(|&n| power(n, n, effect, sd, alpha, 4000, n as u64) >= target)
}

/// The pooled standard deviation of two groups' seed values (each group's sample
/// variance, weighted by its degrees of freedom); NaN with fewer than three values.
pub fn pooled_sd(first: &[f64], second: &[f64]) -> f64 {
    let dfs = first.len().saturating_sub(1) + second.len().saturating_sub(1);
    if dfs == 0 {
        return f64::NAN;
    }
    let ss = |v: &[f64]| {
        if v.len() < 2 {
            0.0
        } else {
            sample_variance(v) * (v.len() - 1) as f64
        }
    };
    ((ss(first) + ss(second)) / dfs as f64).sqrt()
}

#[cfg(test)]
mod tests {
    use super::*;

    // reference: scipy.stats.ttest_ind(a, b, equal_var=False)
    #[test]
    fn welch_matches_scipy() {
        let rall = [0.2292, 0.2396, 0.1940];
        let base = [0.1704, 0.1336, 0.1762];
        let w = welch(&rall, &base, 0.95).unwrap();
        assert!((w.difference - 0.060_866_666_666_666_6).abs() < 1e-12);
        assert!((w.df - 3.995_441_433_479_788_5).abs() < 1e-9, "{w:?}");
        assert!((w.p - 0.033_858_223_478_860_23).abs() < 1e-9, "{w:?}");
        assert!(w.lo > 0.0 && w.lo < w.difference && w.hi > w.difference);
        // the interval is symmetric and its half-width is t(0.975, df) x SE
        assert!(((w.hi - w.difference) - (w.difference - w.lo)).abs() < 1e-12);
        assert!(welch(&[1.0], &base, 0.95).is_none());
        assert!(welch(&[1.0, f64::NAN], &base, 0.95).is_none());
        let same = welch(&[0.5, 0.5], &[0.5, 0.5], 0.95).unwrap();
        assert_eq!((same.p, same.lo, same.hi), (1.0, 0.0, 0.0));
    }

    #[test]
    fn permutation_counts_every_split() {
        // 3 against 3, completely separated: 2 of the 20 splits are as extreme
        let p = permutation_p(&[3.0, 4.0, 5.0], &[0.0, 1.0, 2.0]).unwrap();
        assert!((p - 0.1).abs() < 1e-12, "{p}");
        // 5 against 5, separated: 2 of 252
        let p = permutation_p(&[5.0, 6.0, 7.0, 8.0, 9.0], &[0.0, 1.0, 2.0, 3.0, 4.0]).unwrap();
        assert!((p - 2.0 / 252.0).abs() < 1e-12, "{p}");
        // no difference at all: every split is as extreme
        assert_eq!(permutation_p(&[1.0, 1.0], &[1.0, 1.0]), Some(1.0));
        assert_eq!(permutation_p(&[], &[1.0]), None);
    }

    #[test]
    fn holm_steps_down_and_keeps_order() {
        let adj = holm(&[0.01, 0.04, 0.03, 0.005]);
        // sorted: 0.005 x4 = 0.02, 0.01 x3 = 0.03, 0.03 x2 = 0.06, 0.04 x1 -> max(0.06, 0.04)
        let want = [0.03, 0.06, 0.06, 0.02];
        for (a, w) in adj.iter().zip(want) {
            assert!((a - w).abs() < 1e-12, "{adj:?}");
        }
        let with_nan = holm(&[0.01, f64::NAN, 0.2]);
        assert!((with_nan[0] - 0.02).abs() < 1e-12 && with_nan[1].is_nan());
        assert!((holm(&[0.9, 0.8])[0] - 1.0).abs() < 1e-12);
    }

    #[test]
    fn power_grows_with_seeds_and_effect() {
        let p3 = power(3, 3, 0.05, 0.0235, 0.05, 4000, 1);
        let p8 = power(8, 8, 0.05, 0.0235, 0.05, 4000, 1);
        assert!(p8 > p3 && p8 > 0.9, "{p3} {p8}");
        let n = seeds_for_power(0.03, 0.0235, 0.05, 0.8, 50).unwrap();
        assert!((10..=14).contains(&n), "{n}");
        assert!(seeds_for_power(0.001, 0.0235, 0.05, 0.8, 10).is_none());
        assert!((pooled_sd(&[1.0, 3.0], &[2.0, 4.0]) - 2f64.sqrt()).abs() < 1e-12);
    }
}
