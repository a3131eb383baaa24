//! Adam (Kingma & Ba 2015) over flat parameter vectors, with PyTorch's defaults
//! and bias correction. Written here rather than taken from dfdx because the
//! moments and step count must be exported to checkpoints (dfdx's `Adam` keeps
//! them private) and the networks are not dfdx modules (see `mat`).

use super::mat::with_simd;
use serde::{Deserialize, Serialize};

/// Adam hyper-parameters (the learning rate lives in the PPO schedule).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct AdamConfig {
    /// First-moment decay, in [0, 0.999999].
    pub beta1: f32,
    /// Second-moment decay, in [0, 0.9999999].
    pub beta2: f32,
    /// Added to the root of the second moment, in [1e-30, 1].
    pub eps: f32,
}

impl Default for AdamConfig {
    fn default() -> Self {
        AdamConfig {
            beta1: 0.9,
            beta2: 0.999,
            eps: 1e-8,
        }
    }
}

/// Moments for one parameter vector.
#[derive(Clone, Debug, PartialEq)]
pub struct AdamState {
    /// First moment, same length as the parameters.
    pub m: Vec<f32>,
    /// Second moment, same length as the parameters.
    pub v: Vec<f32>,
}

impl AdamState {
    pub fn new(len: usize) -> Self {
        AdamState {
            m: vec![0.0; len],
            v: vec![0.0; len],
        }
    }

    /// One update `p -= lr * mhat / (sqrt(vhat) + eps)`; `step` is the 1-based
    /// step count (shared by all parameter vectors of one optimizer).
    pub fn step(
        &mut self,
        cfg: &AdamConfig,
        lr: f32,
        step: u64,
        params: &mut [f32],
        grads: &[f32],
    ) {
        assert!(params.len() == self.m.len() && grads.len() == self.m.len());
        let bc1 = 1.0 - (cfg.beta1 as f64).powi(step as i32);
        let bc2 = 1.0 - (cfg.beta2 as f64).powi(step as i32);
        let step_size = (lr as f64 / bc1) as f32;
        let inv_sqrt_bc2 = (1.0 / bc2.sqrt()) as f32;
        let (b1, b2, eps) = (cfg.beta1, cfg.beta2, cfg.eps);
        with_simd(
            #[inline(always)]
            || {
                for (((p, g), m), v) in params
                    .iter_mut()
                    .zip(grads)
                    .zip(&mut self.m)
                    .zip(&mut self.v)
                {
                    *m = b1 * *m + (1.0 - b1) * g;
                    *v = b2 * *v + (1.0 - b2) * g * g;
                    *p -= step_size * *m / (v.sqrt() * inv_sqrt_bc2 + eps);
                }
            },
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn first_step_moves_by_lr_times_sign() {
        let cfg = AdamConfig::default();
        let mut st = AdamState::new(3);
        let mut p = vec![1.0, 1.0, 1.0];
        st.step(&cfg, 0.1, 1, &mut p, &[2.0, -0.5, 0.0]);
        assert!((p[0] - 0.9).abs() < 1e-5 && (p[1] - 1.1).abs() < 1e-5 && p[2] == 1.0);
    }

    #[test]
    fn minimises_a_quadratic() {
        let cfg = AdamConfig::default();
        let mut st = AdamState::new(2);
        let mut p = vec![3.0, -2.0];
        for t in 1..=2000 {
            let g = vec![2.0 * (p[0] - 1.0), 2.0 * (p[1] + 0.5)];
            st.step(&cfg, 0.01, t, &mut p, &g);
        }
        assert!(
            (p[0] - 1.0).abs() < 1e-2 && (p[1] + 0.5).abs() < 1e-2,
            "{p:?}"
        );
    }
}
