//! Risk measures on quantile functions and the quantile Huber loss.
//!
//! A distortion `beta: [0,1] -> [0,1]` gives the distorted value
//! `V_beta(s) = E_{tau ~ U[0,1]} [Z_{beta(tau)}(s)]` (paper, eq. for V_beta). We
//! evaluate it on a fixed midpoint grid `tau_k = (k + 1/2) / K`, so the value the
//! actor follows is deterministic: `V_beta ~= 1/K sum_k Z_{beta(tau_k)}(s)`.

use super::mat::{is_serial, with_simd};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

/// Taus of the interquartile range `IQR = Z_0.75 - Z_0.25` (paper, meta controller).
pub const IQR_TAUS: [f32; 2] = [0.25, 0.75];

/// The largest Wang lambda (in magnitude) a config may set.
pub const MAX_WANG_LAMBDA: f32 = 10.0;

/// A distortion risk measure.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "lowercase", deny_unknown_fields)]
pub enum Distortion {
    /// `CVaR_eta`: `beta(tau) = eta tau`, the mean of the lowest `eta` fraction of
    /// returns; `eta` in `(0, 1]`, `1` is risk neutral, RALL uses `0.5`.
    Cvar { eta: f32 },
    /// Wang (2000): `beta(tau) = Phi(Phi^-1(tau) + lambda)`; `lambda < 0` is
    /// risk averse, `0` risk neutral (IQN paper's sign convention); `lambda` in
    /// [-10, 10] (beyond, every distorted tau rounds to 0 or 1).
    Wang { lambda: f32 },
}

impl Distortion {
    /// Checks the parameter range.
    pub fn validate(&self) -> anyhow::Result<()> {
        match *self {
            Distortion::Cvar { eta } if !(eta > 0.0 && eta <= 1.0) => {
                anyhow::bail!("CVaR eta must be in (0, 1], got {eta}")
            }
            Distortion::Wang { lambda }
                if !(lambda.is_finite() && lambda.abs() <= MAX_WANG_LAMBDA) =>
            {
                anyhow::bail!(
                    "Wang lambda must be in [-{MAX_WANG_LAMBDA}, {MAX_WANG_LAMBDA}], got {lambda}: beyond, every distorted tau rounds to 0 or 1"
                )
            }
            _ => Ok(()),
        }
    }

    /// `beta(tau)`.
    pub fn beta(&self, tau: f32) -> f32 {
        match *self {
            Distortion::Cvar { eta } => eta * tau,
            Distortion::Wang { lambda } => {
                normal_cdf(normal_icdf(tau as f64) + lambda as f64) as f32
            }
        }
    }

    /// The `k` distorted taus `beta((i + 1/2) / k)`, `i = 0..k`, at which the
    /// distorted value is the plain mean of `Z`.
    pub fn grid(&self, k: usize) -> Vec<f32> {
        midpoint_taus(k).into_iter().map(|t| self.beta(t)).collect()
    }

    /// Distorted value of a quantile function `q`, on the `k`-point midpoint grid.
    pub fn value_of(&self, q: impl Fn(f32) -> f32, k: usize) -> f32 {
        let g = self.grid(k);
        g.iter().map(|&t| q(t)).sum::<f32>() / k as f32
    }
}

/// `(i + 1/2) / k` for `i = 0..k`.
pub fn midpoint_taus(k: usize) -> Vec<f32> {
    (0..k).map(|i| (i as f32 + 0.5) / k as f32).collect()
}

/// Huber function `L_kappa(delta)`.
#[inline]
pub fn huber(delta: f32, kappa: f32) -> f32 {
    let a = delta.abs();
    if a <= kappa {
        0.5 * delta * delta
    } else {
        kappa * (a - 0.5 * kappa)
    }
}

/// Quantile Huber loss `rho^kappa_tau(delta) = |tau - 1{delta < 0}| L_kappa(delta)`,
/// `delta = target - prediction` (paper, eq. for rho; no division by kappa).
#[inline]
pub fn quantile_huber(tau: f32, delta: f32, kappa: f32) -> f32 {
    let w = if delta < 0.0 { 1.0 - tau } else { tau };
    w * huber(delta, kappa)
}

/// `d rho^kappa_tau(target - pred) / d pred = -|tau - 1{delta<0}| clamp(delta, -kappa, kappa)`.
#[inline]
pub fn quantile_huber_grad_pred(tau: f32, delta: f32, kappa: f32) -> f32 {
    let w = if delta < 0.0 { 1.0 - tau } else { tau };
    -w * delta.clamp(-kappa, kappa)
}

/// `(rho^kappa_tau(delta), |tau - 1{delta<0}| clamp(delta, -kappa, kappa))`, branch-free.
#[inline(always)]
fn rho_and_slope(tau: f32, delta: f32, kappa: f32) -> (f32, f32) {
    let w = if delta < 0.0 { 1.0 - tau } else { tau };
    let a = delta.abs();
    let c = a.min(kappa);
    // c (a - c/2) = a^2/2 if a <= kappa, kappa (a - kappa/2) otherwise
    (w * c * (a - 0.5 * c), w * delta.max(-kappa).min(kappa))
}

/// One row of [`quantile_huber_loss`]: writes `d loss / d z_i` for the row's
/// predictions and returns the row's unscaled loss. Inlined into the caller's
/// SIMD frame ([`with_simd`]) so it vectorises for the CPU's widest level.
#[inline(always)]
fn huber_row(
    g_row: &mut [f32],
    z_row: &[f32],
    t_row: &[f32],
    taus: &[f32],
    kappa: f32,
    scale: f32,
) -> f64 {
    let mut loss = 0.0f32;
    for ((g, &z), &tau) in g_row.iter_mut().zip(z_row).zip(taus) {
        // LANES independent accumulators so the loop vectorises (no fast-math)
        let (mut l, mut d) = ([0.0f32; LANES], [0.0f32; LANES]);
        let chunks = t_row.chunks_exact(LANES);
        let rest = chunks.remainder();
        for c in chunks {
            for k in 0..LANES {
                let (lk, dk) = rho_and_slope(tau, c[k] - z, kappa);
                l[k] += lk;
                d[k] += dk;
            }
        }
        for &t in rest {
            let (lk, dk) = rho_and_slope(tau, t - z, kappa);
            l[0] += lk;
            d[0] += dk;
        }
        loss += l.iter().sum::<f32>();
        *g = -d.iter().sum::<f32>() * scale;
    }
    loss as f64
}

/// f32 lanes of one AVX-512 register: accumulators per target row in
/// [`quantile_huber_loss`] (also fills two AVX2 registers).
const LANES: usize = 16;

/// Critic loss (paper, eq. for L_critic) averaged over the batch:
/// `1/B sum_b sum_i 1/N' sum_j rho^kappa_{tau_i}(T_bj - Z_bi)`.
///
/// `pred`: `B x N` predictions `Z_{tau_i}(s_b)`; `taus`: the `N` taus of `pred`;
/// `targets`: `B x N'` target samples. Writes `d loss / d pred` into `grad`
/// (`B x N`) and returns the loss.
pub fn quantile_huber_loss(
    pred: &[f32],
    taus: &[f32],
    targets: &[f32],
    kappa: f32,
    grad: &mut [f32],
) -> f32 {
    let n = taus.len();
    let batch = pred.len() / n;
    assert!(batch > 0 && pred.len() == batch * n && grad.len() == pred.len());
    let n_t = targets.len() / batch;
    assert!(n_t > 0 && targets.len() == batch * n_t);
    let scale = 1.0 / (batch as f32 * n_t as f32);
    let row = |((g_row, z_row), t_row): ((&mut [f32], &[f32]), &[f32])| {
        with_simd(
            #[inline(always)]
            || huber_row(g_row, z_row, t_row, taus, kappa, scale),
        )
    };
    let loss: f64 = if is_serial() {
        grad.chunks_mut(n)
            .zip(pred.chunks(n))
            .zip(targets.chunks(n_t))
            .map(row)
            .sum()
    } else {
        grad.par_chunks_mut(n)
            .zip(pred.par_chunks(n))
            .zip(targets.par_chunks(n_t))
            .map(row)
            .sum()
    };
    (loss * scale as f64) as f32
}

/// Standard normal density.
pub fn normal_pdf(x: f64) -> f64 {
    (-0.5 * x * x).exp() / (2.0 * std::f64::consts::PI).sqrt()
}

/// Standard normal CDF (erfc rational approximation, relative error < 1.2e-7).
pub fn normal_cdf(x: f64) -> f64 {
    let z = (x / std::f64::consts::SQRT_2).abs();
    let t = 1.0 / (1.0 + 0.5 * z);
    let poly = -z * z - 1.265_512_23
        + t * (1.000_023_68
            + t * (0.374_091_96
                + t * (0.096_784_18
                    + t * (-0.186_288_06
                        + t * (0.278_868_07
                            + t * (-1.135_203_98
                                + t * (1.488_515_87 + t * (-0.822_152_23 + t * 0.170_872_77))))))));
    let erfc = t * poly.exp();
    if x >= 0.0 {
        1.0 - 0.5 * erfc
    } else {
        0.5 * erfc
    }
}

/// Standard normal quantile function (Acklam's algorithm, relative error ~1e-9).
pub fn normal_icdf(p: f64) -> f64 {
    const A: [f64; 6] = [
        -3.969_683_028_665_376e1,
        2.209_460_984_245_205e2,
        -2.759_285_104_469_687e2,
        1.383_577_518_672_69e2,
        -3.066_479_806_614_716e1,
        2.506_628_277_459_239,
    ];
    const B: [f64; 5] = [
        -5.447_609_879_822_406e1,
        1.615_858_368_580_409e2,
        -1.556_989_798_598_866e2,
        6.680_131_188_771_972e1,
        -1.328_068_155_288_572e1,
    ];
    const C: [f64; 6] = [
        -7.784_894_002_430_293e-3,
        -3.223_964_580_411_365e-1,
        -2.400_758_277_161_838,
        -2.549_732_539_343_734,
        4.374_664_141_464_968,
        2.938_163_982_698_783,
    ];
    const D: [f64; 4] = [
        7.784_695_709_041_462e-3,
        3.224_671_290_700_398e-1,
        2.445_134_137_142_996,
        3.754_408_661_907_416,
    ];
    let p = p.clamp(1e-300, 1.0 - 1e-16);
    let tail = |q: f64| {
        (((((C[0] * q + C[1]) * q + C[2]) * q + C[3]) * q + C[4]) * q + C[5])
            / ((((D[0] * q + D[1]) * q + D[2]) * q + D[3]) * q + 1.0)
    };
    const P_LOW: f64 = 0.02425;
    if p < P_LOW {
        tail((-2.0 * p.ln()).sqrt())
    } else if p <= 1.0 - P_LOW {
        let q = p - 0.5;
        let r = q * q;
        (((((A[0] * r + A[1]) * r + A[2]) * r + A[3]) * r + A[4]) * r + A[5]) * q
            / (((((B[0] * r + B[1]) * r + B[2]) * r + B[3]) * r + B[4]) * r + 1.0)
    } else {
        -tail((-2.0 * (1.0 - p).ln()).sqrt())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn normal_helpers_roundtrip() {
        for &p in &[1e-6, 0.01, 0.1, 0.25, 0.5, 0.8, 0.99] {
            let x = normal_icdf(p);
            assert!((normal_cdf(x) - p).abs() < 2e-7 * p.max(1e-2), "{p} {x}");
        }
        assert!((normal_icdf(0.975) - 1.959_963_985).abs() < 1e-6);
    }

    #[test]
    fn loss_matches_pointwise_definition() {
        let taus = [0.1, 0.9];
        let pred = [0.0, 1.0, -1.0, 2.0]; // B = 2, N = 2
        let targets = [0.5, -3.0, 2.0, 0.0, 1.0, 1.0]; // N' = 3
        let mut grad = [0.0; 4];
        let l = quantile_huber_loss(&pred, &taus, &targets, 1.0, &mut grad);
        let mut want = 0.0;
        for b in 0..2 {
            for i in 0..2 {
                let mut g = 0.0;
                for j in 0..3 {
                    let d = targets[b * 3 + j] - pred[b * 2 + i];
                    want += quantile_huber(taus[i], d, 1.0) / 6.0;
                    g += quantile_huber_grad_pred(taus[i], d, 1.0) / 6.0;
                }
                assert!((grad[b * 2 + i] - g).abs() < 1e-6);
            }
        }
        assert!((l - want).abs() < 1e-6);
    }

    #[test]
    fn wang_zero_is_neutral_and_negative_is_averse() {
        let q = |t: f32| t * 10.0;
        let neutral = Distortion::Wang { lambda: 0.0 }.value_of(q, 64);
        assert!((neutral - 5.0).abs() < 1e-4);
        assert!(Distortion::Wang { lambda: -0.75 }.value_of(q, 64) < 4.0);
        assert!(Distortion::Cvar { eta: 0.0 }.validate().is_err());
        assert!(Distortion::Cvar { eta: 1.0 }.validate().is_ok());
    }
}
