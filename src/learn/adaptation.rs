//! RMA phase 2: the adaptation module `z_hat = phi(history)` regresses the
//! teacher encoder's `z = mu(privileged)` by mean squared error. Only the
//! adaptation parameters (`actor.adapt.*`, the tail of the actor's parameters)
//! move; the base policy and the encoder stay frozen.

use anyhow::{ensure, Result};
use rand::seq::SliceRandom;
use rand::Rng;

use super::adam::{AdamConfig, AdamState};
use super::layout::gather_columns;
use super::learner::AdaptationConfig;
use super::nets::{GaussianActor, MlpCache};

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

/// `epochs` passes of mini-batch Adam on `rows` observation rows (each holds the
/// encoder's and the adaptation module's input groups); returns the mean
/// mini-batch MSE before each step.
pub fn regress(
    actor: &mut GaussianActor,
    opt: &mut AdaptationOptimizer,
    cfg: &AdaptationConfig,
    obs: &[f32],
    rows: usize,
    rng: &mut impl Rng,
) -> Result<f32> {
    let offset = adaptation_offset(actor).ok_or_else(|| {
        anyhow::anyhow!("the actor has no adaptation module (learner.adaptation)")
    })?;
    ensure!(rows > 0, "no rows to regress on");
    let width = actor.obs_dim;
    // targets: the frozen encoder's z for every row, once
    let z = {
        let (enc, _) = modules(actor)?;
        actor.latent_of(enc, obs, rows)
    };
    let lw = actor.latent_dim();
    let mut idx: Vec<usize> = (0..rows).collect();
    let n_mb = cfg.mini_batches.clamp(1, rows);
    let (mut loss_sum, mut count) = (0.0f64, 0usize);
    let mut mb_obs = Vec::new();
    let mut mb_z = Vec::new();
    let mut xin = Vec::new();
    let mut cache = MlpCache::default();
    let mut grads = vec![0.0f32; actor.params.len() - offset];
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
            let (_, adapt) = modules(actor)?;
            gather_columns(&mb_obs, width, &adapt.input.ranges, &mut xin);
            adapt.mlp.forward(&actor.params.data, &xin, b, &mut cache);
            let zh = cache.output();
            loss_sum += mse(zh, &mb_z) as f64;
            count += 1;
            // d/dz_hat of mean (z_hat - z)^2
            let scale = 2.0 / (b * lw) as f32;
            let mut dz: Vec<f32> = zh.iter().zip(&mb_z).map(|(a, t)| scale * (a - t)).collect();
            full.iter_mut().for_each(|g| *g = 0.0);
            adapt.mlp.backward(
                &actor.params.data,
                &mut full,
                &xin,
                b,
                &mut cache,
                &mut dz,
                false,
            );
            grads.copy_from_slice(&full[offset..]);
            opt.step += 1;
            opt.adam.step(
                &AdamConfig::default(),
                cfg.learning_rate,
                opt.step,
                &mut actor.params.data[offset..],
                &grads,
            );
        }
    }
    Ok((loss_sum / count.max(1) as f64) as f32)
}
