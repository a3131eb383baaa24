//! RMA phase 2: the adaptation module `z_hat = phi(history)` regresses the
//! teacher encoder's `z = mu(privileged)` by mean squared error. Only the
//! adaptation parameters (`actor.adapt.*`, the tail of the actor's parameters)
//! move; the base policy and the encoder stay frozen.

use anyhow::{ensure, Result};
use rand::seq::SliceRandom;
use rand::Rng;
use serde::{Deserialize, Serialize};

use super::adam::{AdamConfig, AdamState};
use super::layout::gather_columns;
use super::nets::{GaussianActor, MlpCache};

/// RMA phase 2: the adaptation module regresses the encoder's `z` from the
/// history, on rollouts its own estimate drives through the frozen base policy.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct AdaptationConfig {
    /// Observation group it reads (the proprioceptive history).
    pub input: String,
    /// Hidden sizes (ELU) of the MLP over the flattened history (walk-these-ways
    /// style): at most 16 layers, each 1..=8192.
    pub hidden: Vec<usize>,
    /// Phase-2 iterations (each: one rollout of num_envs x steps_per_env, then
    /// regression), 1..=100,000,000: 0 would leave the student untrained.
    pub iterations: usize,
    /// Adam's rate for the regression, in [1e-12, 1].
    pub learning_rate: f32,
    /// Passes over each rollout, 1..=1000.
    pub epochs: usize,
    /// Mini-batches per pass, 1..=1,048,576.
    pub mini_batches: usize,
}

impl Default for AdaptationConfig {
    fn default() -> Self {
        AdaptationConfig {
            input: "history".into(),
            hidden: vec![256, 128],
            iterations: 500,
            learning_rate: 5e-4,
            epochs: 4,
            mini_batches: 4,
        }
    }
}

/// Adam over the adaptation parameters, with its own step count.
#[derive(Clone, Debug, PartialEq)]
pub struct AdaptationOptimizer {
    pub adam: AdamState,
    pub step: u64,
}

/// Offset of the adaptation parameters in the actor's flat vector (they come last).
pub fn adaptation_offset(actor: &GaussianActor) -> Option<usize> {
    actor
        .params
        .entries
        .iter()
        .find(|e| e.name.starts_with("adapt."))
        .map(|e| e.offset)
}

/// Mean squared error of `z_hat` against `z` over `obs` rows (no update).
pub fn latent_mse(actor: &GaussianActor, obs: &[f32], rows: usize) -> Result<f32> {
    let (enc, adapt) = modules(actor)?;
    let z = actor.latent_of(enc, obs, rows);
    let zh = actor.latent_of(adapt, obs, rows);
    Ok(mse(&zh, &z))
}

fn modules(
    actor: &GaussianActor,
) -> Result<(&super::nets::LatentModule, &super::nets::LatentModule)> {
    match (actor.encoder(), actor.adaptation()) {
        (Some(e), Some(a)) => Ok((e, a)),
        _ => anyhow::bail!("the adaptation phase needs learner.encoder and learner.adaptation"),
    }
}

fn mse(a: &[f32], b: &[f32]) -> f32 {
    let n = a.len().max(1);
    a.iter()
        .zip(b)
        .map(|(x, y)| ((x - y) as f64).powi(2))
        .sum::<f64>() as f32
        / n as f32
}

/// Loss `mean (z_hat - z)^2` of `b` rows of `obs` against targets `z`
/// (`b x latent_dim`), and its gradient w.r.t. every actor parameter written into
/// `grads` (only the adaptation module's entries are non-zero).
pub fn latent_loss_and_grad(
    actor: &GaussianActor,
    obs: &[f32],
    z: &[f32],
    b: usize,
    grads: &mut [f32],
    cache: &mut MlpCache,
) -> Result<f32> {
    let (_, adapt) = modules(actor)?;
    ensure!(
        grads.len() == actor.params.len(),
        "gradient buffer of {} values for {} parameters",
        grads.len(),
        actor.params.len()
    );
    let mut xin = Vec::new();
    gather_columns(obs, actor.obs_dim, &adapt.input.ranges, &mut xin);
    adapt.mlp.forward(&actor.params.data, &xin, b, cache);
    let zh = cache.output();
    let loss = mse(zh, z);
    // d/dz_hat of mean (z_hat - z)^2
    let scale = 2.0 / zh.len().max(1) as f32;
    let mut dz: Vec<f32> = zh.iter().zip(z).map(|(a, t)| scale * (a - t)).collect();
    grads.iter_mut().for_each(|g| *g = 0.0);
    adapt
        .mlp
        .backward(&actor.params.data, grads, &xin, b, cache, &mut dz, false);
    Ok(loss)
}

/// What one regression did.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Regression {
    /// MSE of z_hat against z over all rows, before the first step.
    pub mse_before: f32,
    /// Mean mini-batch MSE, each taken before its step.
    pub mean_minibatch_mse: f32,
}

/// `epochs` passes of mini-batch Adam on `rows` observation rows (each holds the
/// encoder's and the adaptation module's input groups).
pub fn regress(
    actor: &mut GaussianActor,
    opt: &mut AdaptationOptimizer,
    cfg: &AdaptationConfig,
    obs: &[f32],
    rows: usize,
    rng: &mut impl Rng,
) -> Result<Regression> {
    let offset = adaptation_offset(actor).ok_or_else(|| {
        anyhow::anyhow!("the actor has no adaptation module (learner.adaptation)")
    })?;
    ensure!(rows > 0, "no rows to regress on");
    let width = actor.obs_dim;
    // targets: the frozen encoder's z for every row, once
    let (z, mse_before) = {
        let (enc, adapt) = modules(actor)?;
        let z = actor.latent_of(enc, obs, rows);
        let before = mse(&actor.latent_of(adapt, obs, rows), &z);
        (z, before)
    };
    let lw = actor.latent_dim();
    let mut idx: Vec<usize> = (0..rows).collect();
    let n_mb = cfg.mini_batches.clamp(1, rows);
    let (mut loss_sum, mut count) = (0.0f64, 0usize);
    let mut mb_obs = Vec::new();
    let mut mb_z = Vec::new();
    let mut cache = MlpCache::default();
    let mut full = vec![0.0f32; actor.params.len()];
    for _ in 0..cfg.epochs {
        idx.shuffle(rng);
        for k in 0..n_mb {
            let batch = &idx[k * rows / n_mb..(k + 1) * rows / n_mb];
            let b = batch.len();
            mb_obs.clear();
            mb_z.clear();
            for &i in batch {
                mb_obs.extend_from_slice(&obs[i * width..(i + 1) * width]);
                mb_z.extend_from_slice(&z[i * lw..(i + 1) * lw]);
            }
            let loss = latent_loss_and_grad(actor, &mb_obs, &mb_z, b, &mut full, &mut cache)?;
            loss_sum += loss as f64;
            count += 1;
            opt.step += 1;
            opt.adam.step(
                &AdamConfig::default(),
                cfg.learning_rate,
                opt.step,
                &mut actor.params.data[offset..],
                &full[offset..],
            );
        }
    }
    Ok(Regression {
        mse_before,
        mean_minibatch_mse: (loss_sum / count.max(1) as f64) as f32,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::learn::nets::InputSel;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    /// Row: [policy 3 | privileged 2 | history 4]; z = encoder(privileged).
    fn student(seed: u64) -> GaussianActor {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let sel = |r: std::ops::Range<usize>| InputSel {
            ranges: vec![r],
            row_width: 9,
        };
        let mut a = GaussianActor::with_inputs(sel(0..3), 2, 2, &[6], 1.0, &mut rng);
        a.add_encoder(sel(3..5), &[5], &mut rng);
        a.add_adaptation(sel(5..9), &[16, 16], &mut rng);
        a
    }

    fn rows(n: usize, seed: u64) -> Vec<f32> {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut out = Vec::with_capacity(n * 9);
        for _ in 0..n {
            let h: Vec<f32> = (0..4).map(|_| rng.gen_range(-1.0..1.0)).collect();
            let pol: Vec<f32> = (0..3).map(|_| rng.gen_range(-1.0..1.0)).collect();
            // the privileged factors are a fixed function of the history
            let p = [0.8 * h[0] - 0.3 * h[1], (h[2] * h[3]).tanh()];
            out.extend_from_slice(&pol);
            out.extend_from_slice(&p);
            out.extend_from_slice(&h);
        }
        out
    }

    #[test]
    fn adaptation_gradient_matches_finite_differences() {
        let mut actor = student(3);
        let (b, obs) = (7, rows(7, 4));
        let enc = actor.encoder().unwrap().clone();
        let z = actor.latent_of(&enc, &obs, b);
        let mut g = vec![0.0; actor.params.len()];
        let mut cache = MlpCache::default();
        latent_loss_and_grad(&actor, &obs, &z, b, &mut g, &mut cache).unwrap();
        let off = adaptation_offset(&actor).unwrap();
        assert!(
            g[..off].iter().all(|&v| v == 0.0),
            "only adapt.* may get gradient"
        );
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        for _ in 0..60 {
            let i = rng.gen_range(off..actor.params.len());
            let old = actor.params.data[i];
            let h = 1e-2f32;
            let mut loss_at = |v: f32| {
                actor.params.data[i] = v;
                let mut scratch = vec![0.0; actor.params.len()];
                let l =
                    latent_loss_and_grad(&actor, &obs, &z, b, &mut scratch, &mut cache).unwrap();
                l as f64
            };
            let numeric = (loss_at(old + h) - loss_at(old - h)) / (2.0 * h as f64);
            actor.params.data[i] = old;
            let a = g[i] as f64;
            assert!(
                (numeric - a).abs() <= 2e-2 * a.abs().max(numeric.abs()) + 2e-3,
                "param {i}: analytic {a}, numeric {numeric}"
            );
        }
    }

    #[test]
    fn adaptation_learns_a_known_latent_from_history() {
        let mut actor = student(11);
        let n = 512;
        let obs = rows(n, 12);
        let before = latent_mse(&actor, &obs, n).unwrap();
        let frozen: Vec<f32> = actor.params.data[..adaptation_offset(&actor).unwrap()].to_vec();
        let mut opt = AdaptationOptimizer {
            adam: AdamState::new(actor.params.len() - adaptation_offset(&actor).unwrap()),
            step: 0,
        };
        let cfg = AdaptationConfig {
            learning_rate: 3e-3,
            epochs: 300,
            mini_batches: 4,
            ..Default::default()
        };
        let mut rng = ChaCha8Rng::seed_from_u64(13);
        regress(&mut actor, &mut opt, &cfg, &obs, n, &mut rng).unwrap();
        // held-out rows
        let test = rows(256, 14);
        let after = latent_mse(&actor, &test, 256).unwrap();
        let enc = actor.encoder().unwrap().clone();
        let z = actor.latent_of(&enc, &test, 256);
        let mean = z.iter().sum::<f32>() / z.len() as f32;
        let var = z.iter().map(|v| (v - mean).powi(2)).sum::<f32>() / z.len() as f32;
        assert!(
            after < 0.02 * var && after < 0.05 * before,
            "held-out MSE {after} (before training {before}, variance of z {var})"
        );
        // the base policy and the encoder did not move
        assert_eq!(&actor.params.data[..frozen.len()], &frozen[..]);
    }
}
