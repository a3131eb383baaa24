//! Empirical observation normaliser (rsl_rl 2.x's `EmpiricalNormalization`):
//! every network reads `(obs - mean) / (std + 0.01)` per column, with the mean and
//! variance of every observation the run has collected.
//!
//! The statistics are frozen within an iteration: the rollout is collected and
//! the update runs with the same ones (so PPO's ratio is exactly 1 at the first
//! mini-batch), and the rollout's observations are merged in after the update.
//! In a data-parallel run every rank merges the union of all ranks' rollouts.

use super::checkpoint::NamedTensor;
use super::collective::Collective;
use anyhow::{ensure, Result};

/// Added to the std before dividing (rsl_rl's `eps`): a column that never
/// varies is divided by 0.01, not by 0.
pub const STD_EPS: f32 = 1e-2;

/// Running per-column mean and (population) variance of the observations seen.
#[derive(Clone, Debug, PartialEq)]
pub struct EmpiricalNormalizer {
    mean: Vec<f32>,
    var: Vec<f32>,
    /// Observations merged so far.
    count: u64,
    /// `1 / (sqrt(var) + STD_EPS)`, kept in step with `var`.
    inv_std: Vec<f32>,
}

impl EmpiricalNormalizer {
    /// Mean 0, variance 1 (so the first rollout sees `obs / 1.01`), nothing seen.
    pub fn new(dim: usize) -> Self {
        let mut n = EmpiricalNormalizer {
            mean: vec![0.0; dim],
            var: vec![1.0; dim],
            count: 0,
            inv_std: Vec::new(),
        };
        n.refresh_inv_std();
        n
    }

    pub fn dim(&self) -> usize {
        self.mean.len()
    }
    pub fn mean(&self) -> &[f32] {
        &self.mean
    }
    /// `sqrt(var) + STD_EPS`: what a column is divided by.
    pub fn divisor(&self) -> Vec<f32> {
        self.inv_std.iter().map(|s| 1.0 / s).collect()
    }
    pub fn count(&self) -> u64 {
        self.count
    }

    fn refresh_inv_std(&mut self) {
        self.inv_std = self
            .var
            .iter()
            .map(|v| 1.0 / (v.sqrt() + STD_EPS))
            .collect();
    }

    /// Normalises `n x dim` rows in place.
    pub fn normalize_in_place(&self, rows: &mut [f32]) {
        for row in rows.chunks_exact_mut(self.dim()) {
            for ((x, m), s) in row.iter_mut().zip(&self.mean).zip(&self.inv_std) {
                *x = (*x - m) * s;
            }
        }
    }

    /// `rows`, normalised (a copy).
    pub fn normalized(&self, rows: &[f32]) -> Vec<f32> {
        let mut out = rows.to_vec();
        self.normalize_in_place(&mut out);
        out
    }

    /// Merges `rows` (`n x dim`, this rank's share) into the statistics: every rank
    /// passes the same number of rows and ends with the same statistics, those of
    /// all ranks' rows together (Chan et al.'s parallel update, in f64).
    pub fn update(&mut self, rows: &[f32], comm: &dyn Collective) {
        let d = self.dim();
        // sums over ranks, in f64: [n, sum x (d), sum x^2 (d)]
        let mut sums = vec![0.0f64; 1 + 2 * d];
        sums[0] = (rows.len() / d) as f64;
        for row in rows.chunks_exact(d) {
            for (j, &x) in row.iter().enumerate() {
                sums[1 + j] += x as f64;
                sums[1 + d + j] += x as f64 * x as f64;
            }
        }
        comm.sum_f64(&mut sums);
        let nb = sums[0];
        if nb == 0.0 {
            return;
        }
        let n = self.count as f64;
        let total = n + nb;
        for j in 0..d {
            let mb = sums[1 + j] / nb;
            let vb = (sums[1 + d + j] / nb - mb * mb).max(0.0);
            let (m, v) = (self.mean[j] as f64, self.var[j] as f64);
            let delta = mb - m;
            self.mean[j] = (m + delta * nb / total) as f32;
            self.var[j] = ((v * n + vb * nb + delta * delta * n * nb / total) / total) as f32;
        }
        self.count += nb as u64;
        self.refresh_inv_std();
    }

    /// `obs_norm.mean`, `obs_norm.var` (`[dim]`) and `obs_norm.count` (`[2]`: the
    /// count's high and low 24 bits, so that f32 holds it exactly up to 2^48).
    pub fn state(&self) -> Vec<NamedTensor> {
        let d = self.dim();
        let hi = (self.count >> 24) as f32;
        let lo = (self.count & 0xff_ffff) as f32;
        vec![
            NamedTensor {
                name: "obs_norm.mean".into(),
                shape: vec![d],
                data: self.mean.clone(),
            },
            NamedTensor {
                name: "obs_norm.var".into(),
                shape: vec![d],
                data: self.var.clone(),
            },
            NamedTensor {
                name: "obs_norm.count".into(),
                shape: vec![2],
                data: vec![hi, lo],
            },
        ]
    }

    /// Refuses statistics [`Self::load`] would refuse, changing nothing.
    pub fn check(mean: &[f32], var: &[f32], count: &[f32]) -> Result<()> {
        ensure!(
            mean.iter().chain(var).all(|v| v.is_finite()) && var.iter().all(|&v| v >= 0.0),
            "obs_norm.mean / obs_norm.var hold a non-finite or negative value"
        );
        ensure!(
            count.len() == 2 && count.iter().all(|c| *c >= 0.0 && c.fract() == 0.0),
            "obs_norm.count is not a pair of non-negative integers"
        );
        Ok(())
    }

    /// Restores [`Self::state`]'s three tensors (already shape-checked), refusing
    /// negative or non-finite statistics.
    pub fn load(&mut self, mean: &[f32], var: &[f32], count: &[f32]) -> Result<()> {
        Self::check(mean, var, count)?;
        self.mean.copy_from_slice(mean);
        self.var.copy_from_slice(var);
        self.count = ((count[0] as u64) << 24) + count[1] as u64;
        self.refresh_inv_std();
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::learn::collective::threads::ThreadRanks;
    use crate::learn::SingleProcess;

    fn rows(n: usize, d: usize, seed: u32) -> Vec<f32> {
        (0..n * d)
            .map(|i| {
                let h = (i as u32 ^ seed).wrapping_mul(2_654_435_761);
                (h >> 8) as f32 / (1 << 24) as f32 * 4.0 - 1.0 + (i % d) as f32
            })
            .collect()
    }

    fn direct_stats(x: &[f32], d: usize) -> (Vec<f64>, Vec<f64>) {
        let n = (x.len() / d) as f64;
        let mean: Vec<f64> = (0..d)
            .map(|j| x.chunks_exact(d).map(|r| r[j] as f64).sum::<f64>() / n)
            .collect();
        let var = (0..d)
            .map(|j| {
                x.chunks_exact(d)
                    .map(|r| (r[j] as f64 - mean[j]).powi(2))
                    .sum::<f64>()
                    / n
            })
            .collect();
        (mean, var)
    }

    #[test]
    fn batches_merged_one_by_one_give_the_statistics_of_all_rows() {
        let d = 5;
        let all = [rows(300, d, 1), rows(7, d, 2), rows(1000, d, 3)].concat();
        let mut norm = EmpiricalNormalizer::new(d);
        let mut at = 0;
        for n in [300, 7, 1000] {
            norm.update(&all[at * d..(at + n) * d], &SingleProcess);
            at += n;
        }
        let (mean, var) = direct_stats(&all, d);
        assert_eq!(norm.count(), 1307);
        for j in 0..d {
            assert!((norm.mean()[j] as f64 - mean[j]).abs() < 1e-5, "mean {j}");
            assert!((norm.var[j] as f64 - var[j]).abs() < 1e-5, "var {j}");
        }
        // normalised rows then have mean ~0 and std ~1 / (1 + eps / std)
        let mut x = all.clone();
        norm.normalize_in_place(&mut x);
        let (m2, v2) = direct_stats(&x, d);
        for j in 0..d {
            assert!(m2[j].abs() < 1e-4);
            let s = var[j].sqrt();
            assert!((v2[j].sqrt() - s / (s + STD_EPS as f64)).abs() < 1e-4);
        }
    }

    #[test]
    fn ranks_end_with_the_statistics_of_their_union() {
        let d = 3;
        let shares = [rows(64, d, 10), rows(64, d, 11)];
        let handles = ThreadRanks::group(2);
        let results: Vec<EmpiricalNormalizer> = std::thread::scope(|s| {
            let jobs: Vec<_> = handles
                .into_iter()
                .zip(&shares)
                .map(|(h, share)| {
                    s.spawn(move || {
                        let mut n = EmpiricalNormalizer::new(d);
                        n.update(share, &h);
                        n
                    })
                })
                .collect();
            jobs.into_iter().map(|j| j.join().unwrap()).collect()
        });
        assert_eq!(results[0], results[1]);
        let mut one = EmpiricalNormalizer::new(d);
        one.update(&shares.concat(), &SingleProcess);
        for j in 0..d {
            assert!((one.mean[j] - results[0].mean[j]).abs() < 1e-6);
            assert!((one.var[j] - results[0].var[j]).abs() < 1e-5);
        }
        assert_eq!(results[0].count(), 128);
    }

    #[test]
    fn state_round_trips_exactly_including_large_counts() {
        let mut a = EmpiricalNormalizer::new(4);
        a.update(&rows(50, 4, 7), &SingleProcess);
        a.count = (1 << 40) + 12_345;
        let s = a.state();
        let mut b = EmpiricalNormalizer::new(4);
        b.load(&s[0].data, &s[1].data, &s[2].data).unwrap();
        assert_eq!(a, b);
        let err = b.load(&s[0].data, &[-1.0; 4], &s[2].data).unwrap_err();
        assert!(err.to_string().contains("negative"), "{err}");
    }
}
