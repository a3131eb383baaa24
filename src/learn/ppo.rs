//! The PPO update (Schulman et al. 2017) with rsl_rl's defaults: clipped
//! surrogate, value loss (quantile Huber for IQN, MSE for the scalar critic),
//! entropy bonus, Adam with the adaptive-KL learning rate, global gradient-norm
//! clipping, per-mini-batch advantage normalisation.

use super::actor_critic::{ActorCritic, Critic, HALF_LN_2PI};
use super::adam::{AdamConfig, AdamState};
use super::nets::{IqnCache, MlpCache};
use super::risk::{midpoint_taus, quantile_huber_loss};
use super::storage::{gae, next_values, quantile_targets, Rollout};
use anyhow::Result;
use rand::seq::SliceRandom;
use rand::Rng;
use serde::{Deserialize, Serialize};
use std::time::Instant;

/// Learning-rate schedule.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum LrSchedule {
    /// rsl_rl: `lr /= 1.5` if `kl > 2 desired_kl`, `lr *= 1.5` if `kl < desired_kl / 2`.
    Adaptive,
    Fixed,
}

/// Scope of the gradient-norm clip.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum GradClip {
    /// One norm over actor and critic together (rsl_rl: one optimizer over both).
    /// The critic's gradient is usually ~100x the actor's, so the clip scales the
    /// actor gradient by the critic's norm; Adam's normalisation mostly cancels
    /// that (measured on the point-mass test: near-identical runs).
    Global,
    /// Actor and critic each clipped to `max_grad_norm` on their own.
    PerNetwork,
}

/// PPO hyper-parameters; `Default` = rsl_rl / the paper.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct PpoConfig {
    /// Passes over the rollout per update.
    pub num_learning_epochs: usize,
    /// Mini-batches per epoch (1536 samples each at 256 envs x 24 steps).
    pub num_mini_batches: usize,
    /// Surrogate clip epsilon.
    pub clip_param: f32,
    /// Discount.
    pub gamma: f32,
    /// GAE lambda.
    pub lam: f32,
    pub value_loss_coef: f32,
    pub entropy_coef: f32,
    /// Initial Adam learning rate.
    pub learning_rate: f32,
    pub schedule: LrSchedule,
    /// Target KL(old || new) per sample for the adaptive schedule.
    pub desired_kl: f32,
    pub min_lr: f32,
    pub max_lr: f32,
    /// Clip the L2 norm of the gradients to this (see `grad_clip`).
    pub max_grad_norm: f32,
    /// Over which parameters `max_grad_norm` applies.
    pub grad_clip: GradClip,
    /// Normalise advantages to zero mean, unit std within each mini-batch.
    pub normalize_advantage_per_mini_batch: bool,
    pub adam: AdamConfig,
}

impl Default for PpoConfig {
    fn default() -> Self {
        PpoConfig {
            num_learning_epochs: 5,
            num_mini_batches: 4,
            clip_param: 0.2,
            gamma: 0.99,
            lam: 0.95,
            value_loss_coef: 1.0,
            entropy_coef: 0.01,
            learning_rate: 1e-3,
            schedule: LrSchedule::Adaptive,
            desired_kl: 0.01,
            min_lr: 1e-5,
            max_lr: 1e-2,
            max_grad_norm: 1.0,
            grad_clip: GradClip::Global,
            normalize_advantage_per_mini_batch: true,
            adam: AdamConfig::default(),
        }
    }
}

/// Critic-loss settings the update needs besides [`PpoConfig`].
#[derive(Clone, Debug)]
pub struct CriticLossConfig {
    /// `N`: taus ~ U[0, 1] per mini-batch (shared by its samples) for the prediction.
    pub num_taus: usize,
    /// `N'`: target samples per transition, at `tau'_j = (j + 1/2) / N'`.
    pub num_target_taus: usize,
    /// Huber threshold kappa.
    pub kappa: f32,
    /// Horizon parameter of the IQN targets (see `storage`).
    pub target_lambda: f32,
}

/// Averages over all mini-batches of one update (lr and std: after the update).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct UpdateStats {
    /// Clipped surrogate loss.
    pub policy_loss: f32,
    /// Quantile Huber (IQN) or MSE (scalar) loss, before the coefficient.
    pub value_loss: f32,
    /// Entropy of the policy per sample (nats).
    pub entropy: f32,
    /// Mean KL(old || new) per sample, measured before each step.
    pub approx_kl: f32,
    pub learning_rate: f32,
    /// Mean action std.
    pub mean_std: f32,
    /// Fraction of samples with `|ratio - 1| > clip`.
    pub clip_fraction: f32,
    /// Global gradient norm before clipping.
    pub grad_norm: f32,
    /// Actor part of `grad_norm` (the critic's quantile loss, a sum over `N`
    /// taus, can dominate the global clip; watch the two).
    pub actor_grad_norm: f32,
    /// Critic part of `grad_norm`.
    pub critic_grad_norm: f32,
    /// Fraction of mini-batches whose gradient the clip scaled down.
    pub clipped_fraction: f32,
    /// Where the update's wall time went (seconds, summed over mini-batches).
    pub time: UpdateTimes,
}

/// Wall time of the phases of one update, in seconds.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct UpdateTimes {
    /// Values, advantages and critic targets from the collection-time critic.
    pub targets_s: f64,
    /// Mini-batch gathering and advantage normalisation.
    pub gather_s: f64,
    /// Forward passes of actor and critic.
    pub forward_s: f64,
    /// Surrogate, KL, entropy and critic losses with their output gradients.
    pub loss_s: f64,
    /// Backward passes of actor and critic.
    pub backward_s: f64,
    /// Gradient norms and clipping.
    pub clip_s: f64,
    /// Adam steps.
    pub adam_s: f64,
}

impl UpdateTimes {
    pub fn total_s(&self) -> f64 {
        self.targets_s
            + self.gather_s
            + self.forward_s
            + self.loss_s
            + self.backward_s
            + self.clip_s
            + self.adam_s
    }
}

/// Adam state for actor and critic, the shared step count, and the current lr.
#[derive(Clone, Debug)]
pub struct Optimizer {
    pub actor: AdamState,
    pub critic: AdamState,
    /// Adam steps taken (bias correction).
    pub step: u64,
    pub lr: f32,
}

/// Buffers of the update, kept between mini-batches and updates so that a
/// steady-state mini-batch allocates nothing.
#[derive(Clone, Debug, Default)]
pub struct Workspace {
    idx: Vec<usize>,
    obs: Vec<f32>,
    actions: Vec<f32>,
    old_mu: Vec<f32>,
    old_std: Vec<f32>,
    old_logp: Vec<f32>,
    adv: Vec<f32>,
    vtarget: Vec<f32>,
    std: Vec<f32>,
    d_mu: Vec<f32>,
    d_log_std: Vec<f32>,
    d_value: Vec<f32>,
    taus: Vec<f32>,
    g_actor: Vec<f32>,
    g_critic: Vec<f32>,
    actor_cache: MlpCache,
    scalar_cache: MlpCache,
    iqn_cache: IqnCache,
}

/// Per-transition training targets computed once per update.
struct Targets {
    adv: Vec<f32>,
    /// Scalar: `returns = A + V` (`T*E`); IQN: `N'` target samples per transition.
    value_targets: Vec<f32>,
}

/// `out = src[idx[k]]` rows of `width` values (reusing `out`'s capacity).
fn gather_into(out: &mut Vec<f32>, src: &[f32], width: usize, idx: &[usize]) {
    out.clear();
    for &i in idx {
        out.extend_from_slice(&src[i * width..(i + 1) * width]);
    }
}

/// Sum of squares in f64 (gradient norms).
fn sum_sq(g: &[f32]) -> f64 {
    g.iter().map(|g| (*g as f64) * (*g as f64)).sum()
}

/// Scales `g` by `s`.
fn scale(g: &mut [f32], s: f32) {
    g.iter_mut().for_each(|g| *g *= s);
}

/// Clips the gradients as `mode` says; returns whether anything was scaled.
fn clip_grads(
    mode: GradClip,
    max_norm: f32,
    g_actor: &mut [f32],
    g_critic: &mut [f32],
    sq_a: f64,
    sq_c: f64,
) -> bool {
    match mode {
        GradClip::Global => {
            let norm = (sq_a + sq_c).sqrt() as f32;
            if norm > max_norm {
                let s = max_norm / (norm + 1e-6);
                scale(g_actor, s);
                scale(g_critic, s);
                return true;
            }
            false
        }
        GradClip::PerNetwork => {
            let mut any = false;
            for (g, sq) in [(g_actor, sq_a), (g_critic, sq_c)] {
                let norm = sq.sqrt() as f32;
                if norm > max_norm {
                    scale(g, max_norm / (norm + 1e-6));
                    any = true;
                }
            }
            any
        }
    }
}

/// Values, advantages and critic targets from the collection-time critic.
fn targets(
    ac: &ActorCritic,
    r: &Rollout,
    cfg: &PpoConfig,
    ccfg: &CriticLossConfig,
    rng: &mut impl Rng,
) -> Targets {
    let finals: Vec<f32> = r
        .final_obs
        .iter()
        .flat_map(|(_, o)| o.iter().copied())
        .collect();
    match &ac.critic {
        Critic::Scalar(c) => {
            let v = |o: &[f32]| c.values(o, o.len() / r.obs_dim);
            let values = v(&r.obs);
            let next = next_values(r, 1, &values, &v(&r.last_obs), &v(&finals));
            let adv = gae(r, &values, &next, cfg.gamma, cfg.lam);
            let returns = adv.iter().zip(&values).map(|(a, v)| a + v).collect();
            Targets {
                adv,
                value_targets: returns,
            }
        }
        Critic::Iqn(c) => {
            // one trunk pass per state: the value grid and the target grid together
            let k = ac.value_taus.len();
            let nt = ccfg.num_target_taus;
            let taus: Vec<f32> = ac
                .value_taus
                .iter()
                .copied()
                .chain(midpoint_taus(nt))
                .collect();
            let split = |o: &[f32]| {
                let z = c.quantiles(o, o.len() / r.obs_dim, &taus);
                let mut v = Vec::with_capacity(z.len() / (k + nt));
                let mut q = Vec::with_capacity(z.len() / (k + nt) * nt);
                for row in z.chunks_exact(k + nt) {
                    v.push(row[..k].iter().sum::<f32>() / k as f32);
                    q.extend_from_slice(&row[k..]);
                }
                (v, q)
            };
            let (values, z) = split(&r.obs);
            let (last_v, last_z) = split(&r.last_obs);
            let (fin_v, fin_z) = split(&finals);
            let next = next_values(r, 1, &values, &last_v, &fin_v);
            let adv = gae(r, &values, &next, cfg.gamma, cfg.lam);
            let next_z = next_values(r, nt, &z, &last_z, &fin_z);
            let value_targets =
                quantile_targets(r, &next_z, nt, cfg.gamma, ccfg.target_lambda, rng);
            Targets { adv, value_targets }
        }
    }
}

/// One PPO update over a full rollout.
pub fn update(
    ac: &mut ActorCritic,
    opt: &mut Optimizer,
    ws: &mut Workspace,
    r: &Rollout,
    cfg: &PpoConfig,
    ccfg: &CriticLossConfig,
    rng: &mut impl Rng,
) -> Result<UpdateStats> {
    r.validate()?;
    anyhow::ensure!(
        r.obs_dim == ac.obs_dim() && r.act_dim == ac.act_dim(),
        "rollout dims ({}, {}) do not match the networks ({}, {})",
        r.obs_dim,
        r.act_dim,
        ac.obs_dim(),
        ac.act_dim()
    );
    let mut time = UpdateTimes::default();
    let mut clock = Instant::now();
    // seconds since the last lap
    let mut lap = || {
        let now = Instant::now();
        let dt = (now - clock).as_secs_f64();
        clock = now;
        dt
    };
    let tg = targets(ac, r, cfg, ccfg, rng);
    time.targets_s += lap();
    let total = r.num_steps * r.num_envs;
    let n_mb = cfg.num_mini_batches.clamp(1, total);
    let (od, ad) = (r.obs_dim, r.act_dim);
    let vt_width = tg.value_targets.len() / total;
    let mut stats = UpdateStats::default();
    let mut count = 0usize;
    let mut clipped_steps = 0usize;
    ws.idx.clear();
    ws.idx.extend(0..total);
    ws.g_actor.resize(ac.actor.params.len(), 0.0);
    ws.g_critic.resize(ac.critic.params().len(), 0.0);
    for _ in 0..cfg.num_learning_epochs {
        ws.idx.shuffle(rng);
        for mb in 0..n_mb {
            let batch = &ws.idx[mb * total / n_mb..(mb + 1) * total / n_mb];
            let b = batch.len();
            gather_into(&mut ws.obs, &r.obs, od, batch);
            gather_into(&mut ws.actions, &r.actions, ad, batch);
            gather_into(&mut ws.old_mu, &r.action_mean, ad, batch);
            gather_into(&mut ws.old_std, &r.action_std, ad, batch);
            gather_into(&mut ws.old_logp, &r.log_probs, 1, batch);
            gather_into(&mut ws.adv, &tg.adv, 1, batch);
            gather_into(&mut ws.vtarget, &tg.value_targets, vt_width, batch);
            let adv = &mut ws.adv;
            if cfg.normalize_advantage_per_mini_batch && b > 1 {
                let mean = adv.iter().sum::<f32>() / b as f32;
                let var = adv.iter().map(|a| (a - mean).powi(2)).sum::<f32>() / (b - 1) as f32;
                let inv = 1.0 / (var.sqrt() + 1e-8);
                adv.iter_mut().for_each(|a| *a = (*a - mean) * inv);
            }
            time.gather_s += lap();

            // ---- forward ----
            ac.actor.forward(&ws.obs, b, &mut ws.actor_cache);
            match &ac.critic {
                Critic::Iqn(c) => {
                    ws.taus.clear();
                    ws.taus.extend((0..ccfg.num_taus).map(|_| rng.gen::<f32>()));
                    c.forward(&ws.obs, b, &ws.taus, &mut ws.iqn_cache);
                }
                Critic::Scalar(c) => c.forward(&ws.obs, b, &mut ws.scalar_cache),
            }
            time.forward_s += lap();

            // ---- losses and their output gradients ----
            let mu = ws.actor_cache.output();
            let log_std = ac.actor.log_std();
            ws.std.clear();
            ws.std.extend(log_std.iter().map(|l| l.exp()));
            let std = &ws.std;
            let sum_log_std: f32 = log_std.iter().sum();
            let (actions, old_mu, old_std) = (&ws.actions, &ws.old_mu, &ws.old_std);

            // KL(old || new) of diagonal Gaussians, the adaptive-lr signal
            let mut kl = 0.0f64;
            for i in 0..b * ad {
                let (s_new, s_old) = (std[i % ad], old_std[i]);
                let dm = old_mu[i] - mu[i];
                kl += ((s_new / s_old).ln() + (s_old * s_old + dm * dm) / (2.0 * s_new * s_new)
                    - 0.5) as f64;
            }
            let kl = (kl / b as f64) as f32;
            if cfg.schedule == LrSchedule::Adaptive {
                if kl > 2.0 * cfg.desired_kl {
                    opt.lr = (opt.lr / 1.5).max(cfg.min_lr);
                } else if kl < cfg.desired_kl / 2.0 && kl > 0.0 {
                    opt.lr = (opt.lr * 1.5).min(cfg.max_lr);
                }
            }

            // clipped surrogate: L = mean_b max(-A r, -A clip(r, 1-e, 1+e)), r = exp(logp - logp_old)
            let d_mu = &mut ws.d_mu;
            d_mu.clear();
            d_mu.resize(b * ad, 0.0);
            let d_log_std = &mut ws.d_log_std;
            d_log_std.clear();
            d_log_std.resize(ad, -cfg.entropy_coef); // d(-c_e H)/d log_std
            let (mut pol_loss, mut clipped) = (0.0f64, 0usize);
            for s in 0..b {
                let row = s * ad..(s + 1) * ad;
                let mut sq = 0.0;
                for j in 0..ad {
                    let z = (actions[row.start + j] - mu[row.start + j]) / std[j];
                    sq += z * z;
                }
                let logp = -0.5 * sq - sum_log_std - ad as f32 * HALF_LN_2PI;
                // log-ratio capped so that a stale sample cannot overflow exp to inf
                let ratio = (logp - ws.old_logp[s]).min(20.0).exp();
                let a = ws.adv[s];
                let unclipped = -a * ratio;
                let clip = -a * ratio.clamp(1.0 - cfg.clip_param, 1.0 + cfg.clip_param);
                pol_loss += unclipped.max(clip) as f64;
                if (ratio - 1.0).abs() > cfg.clip_param {
                    clipped += 1;
                }
                // d L_s / d logp: the unclipped branch carries the gradient when it is the max
                let g = if unclipped >= clip {
                    -a * ratio / b as f32
                } else {
                    0.0
                };
                if g != 0.0 {
                    for j in 0..ad {
                        let z = (actions[row.start + j] - mu[row.start + j]) / std[j];
                        d_mu[row.start + j] = g * z / std[j]; // dlogp/dmu = (a - mu) / std^2
                        d_log_std[j] += g * (z * z - 1.0); // dlogp/dlog_std = z^2 - 1
                    }
                }
            }
            let entropy = sum_log_std + ad as f32 * (0.5 + HALF_LN_2PI);
            let value_loss = match &ac.critic {
                Critic::Iqn(_) => {
                    let z = ws.iqn_cache.output();
                    ws.d_value.clear();
                    ws.d_value.resize(z.len(), 0.0);
                    let loss =
                        quantile_huber_loss(z, &ws.taus, &ws.vtarget, ccfg.kappa, &mut ws.d_value);
                    scale(&mut ws.d_value, cfg.value_loss_coef);
                    loss
                }
                Critic::Scalar(_) => {
                    let v = ws.scalar_cache.output();
                    let mut loss = 0.0;
                    ws.d_value.clear();
                    ws.d_value.extend(v.iter().zip(&ws.vtarget).map(|(v, t)| {
                        loss += (t - v) * (t - v);
                        cfg.value_loss_coef * 2.0 * (v - t) / b as f32
                    }));
                    loss / b as f32
                }
            };
            time.loss_s += lap();

            // ---- backward ----
            ws.g_actor.fill(0.0);
            ws.g_critic.fill(0.0);
            ac.actor.backward(
                &mut ws.g_actor,
                &ws.obs,
                b,
                &mut ws.actor_cache,
                &mut ws.d_mu,
            );
            let off = ac.actor.log_std_offset();
            for (g, d) in ws.g_actor[off..off + ad].iter_mut().zip(&ws.d_log_std) {
                *g += d;
            }
            match &ac.critic {
                Critic::Iqn(c) => {
                    c.backward(&mut ws.g_critic, &ws.obs, b, &mut ws.iqn_cache, &ws.d_value)
                }
                Critic::Scalar(c) => c.backward(
                    &mut ws.g_critic,
                    &ws.obs,
                    b,
                    &mut ws.scalar_cache,
                    &mut ws.d_value,
                ),
            }
            time.backward_s += lap();

            // ---- gradient-norm clip ----
            let (sq_a, sq_c) = (sum_sq(&ws.g_actor), sum_sq(&ws.g_critic));
            if clip_grads(
                cfg.grad_clip,
                cfg.max_grad_norm,
                &mut ws.g_actor,
                &mut ws.g_critic,
                sq_a,
                sq_c,
            ) {
                clipped_steps += 1;
            }
            time.clip_s += lap();

            // ---- Adam ----
            opt.step += 1;
            opt.actor.step(
                &cfg.adam,
                opt.lr,
                opt.step,
                &mut ac.actor.params.data,
                &ws.g_actor,
            );
            opt.critic.step(
                &cfg.adam,
                opt.lr,
                opt.step,
                &mut ac.critic.params_mut().data,
                &ws.g_critic,
            );
            time.adam_s += lap();

            stats.policy_loss += (pol_loss / b as f64) as f32;
            stats.value_loss += value_loss;
            stats.entropy += entropy;
            stats.approx_kl += kl;
            stats.clip_fraction += clipped as f32 / b as f32;
            stats.grad_norm += (sq_a + sq_c).sqrt() as f32;
            stats.actor_grad_norm += sq_a.sqrt() as f32;
            stats.critic_grad_norm += sq_c.sqrt() as f32;
            count += 1;
        }
    }
    let c = count.max(1) as f32;
    stats.policy_loss /= c;
    stats.value_loss /= c;
    stats.entropy /= c;
    stats.approx_kl /= c;
    stats.clip_fraction /= c;
    stats.grad_norm /= c;
    stats.actor_grad_norm /= c;
    stats.critic_grad_norm /= c;
    stats.clipped_fraction = clipped_steps as f32 / c;
    stats.learning_rate = opt.lr;
    stats.mean_std = ac.actor.log_std().iter().map(|l| l.exp()).sum::<f32>() / ac.act_dim() as f32;
    stats.time = time;
    Ok(stats)
}
