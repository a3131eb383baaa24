//! The PPO update (Schulman et al. 2017) with rsl_rl's defaults: clipped
//! surrogate, value loss (quantile Huber for IQN, MSE for the scalar critic),
//! entropy bonus, Adam with the adaptive-KL learning rate, global gradient-norm
//! clipping, per-mini-batch advantage normalisation.
//!
//! Data-parallel (N ranks, [`Collective`]): each rank holds its own rollout and
//! draws the same shuffles and taus (the update RNG is seeded alike), so rank
//! r's mini-batch k is its share of one global mini-batch of N x b rows. The
//! advantages are normalised with that global batch's mean and std (one sum
//! of every mini-batch's moments per epoch), and the
//! gradients, KL and loss statistics are averaged over the ranks before the
//! clip: every rank takes the same Adam step as one process would on the union.

use super::actor_critic::{ActorCritic, HALF_LN_2PI};
use super::adam::{AdamConfig, AdamState};
use super::collective::Collective;
use super::critic::{CriticCache, LossInput, TargetInput, Targets};
use super::mat::{add_assign, serial, with_precision, Precision};
use super::nets::MlpCache;
use super::storage::Rollout;
use anyhow::Result;
use rand::seq::SliceRandom;
use rand::Rng;
use rayon::prelude::*;
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

/// PPO hyper-parameters; `Default` = rsl_rl / the paper. Each key's accepted
/// range is in its comment; [`PpoConfig::validate`] refuses anything outside it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct PpoConfig {
    /// Passes over the rollout per update, 1..=1000.
    pub num_learning_epochs: usize,
    /// Mini-batches per epoch (1536 samples each at 256 envs x 24 steps),
    /// 1..=1,048,576 and at most `num_envs x steps_per_env`.
    pub num_mini_batches: usize,
    /// Surrogate clip epsilon, in [1e-6, 10].
    pub clip_param: f32,
    /// Discount, in [0, 1]. 0 is a legitimate (myopic) experiment: the critic
    /// and the actor learn from one-step rewards.
    pub gamma: f32,
    /// GAE lambda, in [0, 1] (0: one-step advantages).
    pub lam: f32,
    /// Weight of the critic's loss, in [0, 1e6] (0: the critic never learns,
    /// an ablation; the actor still does).
    pub value_loss_coef: f32,
    /// Weight of the entropy bonus, in [-1e3, 1e3].
    pub entropy_coef: f32,
    /// Initial Adam learning rate, in (0, 1]: 0 would never change a weight.
    pub learning_rate: f32,
    pub schedule: LrSchedule,
    /// Target KL(old || new) per sample for the adaptive schedule, in [1e-12, 1e3].
    pub desired_kl: f32,
    /// Floor of the adaptive schedule, in (0, 1] and at most `max_lr` (0 under
    /// `schedule = "adaptive"` would let the rate reach 0 and stay there;
    /// under `"fixed"` it is unused and may be 0).
    pub min_lr: f32,
    /// Ceiling of the adaptive schedule, in [1e-12, 1].
    pub max_lr: f32,
    /// Clip the L2 norm of the gradients to this (see `grad_clip`), in [1e-12, 1e12].
    pub max_grad_norm: f32,
    /// Over which parameters `max_grad_norm` applies.
    pub grad_clip: GradClip,
    /// Normalise advantages to zero mean, unit std within each mini-batch.
    pub normalize_advantage_per_mini_batch: bool,
    pub adam: AdamConfig,
    /// Precision of the update's matrix products (forward and backward of every
    /// mini-batch): `f32`, or inputs rounded to bf16 with sums in f32, `bf16` on
    /// AMX tiles or `bf16-avx512` on AVX512-BF16 (f32 on CPUs without them).
    /// Acting and evaluation stay f32.
    pub matmul: Precision,
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
            matmul: Precision::F32,
        }
    }
}

/// `Err("<key>: must be ..., got <v>")` unless `v` is finite and in `[lo, hi]`.
pub fn check_f32(key: &str, v: f32, lo: f32, hi: f32) -> anyhow::Result<()> {
    anyhow::ensure!(
        v.is_finite() && (lo..=hi).contains(&v),
        "{key} must be a finite number in [{lo:e}, {hi:e}], got {v}"
    );
    Ok(())
}

/// `Err` unless the count `v` is in `lo..=hi`.
pub fn check_count(key: &str, v: usize, lo: usize, hi: usize) -> anyhow::Result<()> {
    anyhow::ensure!(
        (lo..=hi).contains(&v),
        "{key} must be in {lo}..={hi}, got {v}"
    );
    Ok(())
}

impl PpoConfig {
    /// Refuses values outside their ranges, naming the dotted key.
    pub fn validate(&self) -> anyhow::Result<()> {
        check_count(
            "learner.ppo.num_learning_epochs",
            self.num_learning_epochs,
            1,
            1000,
        )?;
        check_count(
            "learner.ppo.num_mini_batches",
            self.num_mini_batches,
            1,
            1 << 20,
        )?;
        check_f32("learner.ppo.clip_param", self.clip_param, 1e-6, 10.0)?;
        check_f32("learner.ppo.gamma", self.gamma, 0.0, 1.0)?;
        check_f32("learner.ppo.lam", self.lam, 0.0, 1.0)?;
        check_f32(
            "learner.ppo.value_loss_coef",
            self.value_loss_coef,
            0.0,
            1e6,
        )?;
        check_f32("learner.ppo.entropy_coef", self.entropy_coef, -1e3, 1e3)?;
        // 0 is allowed here (a learner whose weights stay put is a test fixture);
        // a training run refuses it (`TrainConfig::validate`)
        check_f32("learner.ppo.learning_rate", self.learning_rate, 0.0, 1.0)?;
        check_f32("learner.ppo.desired_kl", self.desired_kl, 1e-12, 1e3)?;
        check_f32("learner.ppo.min_lr", self.min_lr, 0.0, 1.0)?;
        anyhow::ensure!(
            self.schedule == LrSchedule::Fixed || self.min_lr > 0.0,
            "learner.ppo.min_lr must be above 0 under schedule = \"adaptive\": a rate that reaches 0 stays there and nothing is learned"
        );
        check_f32("learner.ppo.max_lr", self.max_lr, 1e-12, 1.0)?;
        anyhow::ensure!(
            self.min_lr <= self.max_lr,
            "learner.ppo.min_lr ({}) must not exceed learner.ppo.max_lr ({})",
            self.min_lr,
            self.max_lr
        );
        check_f32("learner.ppo.max_grad_norm", self.max_grad_norm, 1e-12, 1e12)?;
        let a = &self.adam;
        check_f32("learner.ppo.adam.beta1", a.beta1, 0.0, 0.999_999)?;
        check_f32("learner.ppo.adam.beta2", a.beta2, 0.0, 0.999_999_9)?;
        check_f32("learner.ppo.adam.eps", a.eps, 1e-30, 1.0)?;
        Ok(())
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
    /// The adaptive rate after the update (the next update starts from it).
    pub learning_rate: f32,
    /// Mean of the rates the update's Adam steps used: the adaptive rule moves the
    /// rate x1.5 or /1.5 at every mini-batch, so the end value hides what did the work.
    #[serde(default)]
    pub learning_rate_mean: f32,
    /// Largest rate an Adam step of the update used.
    #[serde(default)]
    pub learning_rate_max: f32,
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
    /// Sums across ranks (advantage statistics, gradients); 0 in one process.
    pub comm_s: f64,
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
            + self.comm_s
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
    mb: MiniBatch,
    shards: Vec<Shard>,
    targets: TargetScratch,
    /// Gradients and statistics packed for one sum across ranks.
    reduce: Vec<f32>,
    /// Every mini-batch's advantage moments, summed across ranks.
    moments: Vec<f64>,
}

/// Buffers of the once-per-update critic pass over the whole rollout (kept:
/// fresh allocations of this size cost page faults every update).
#[derive(Clone, Debug, Default)]
struct TargetScratch {
    finals: Vec<f32>,
    critic: CriticCache,
}

/// One mini-batch gathered from the rollout (rows in shuffled order).
#[derive(Clone, Debug, Default)]
struct MiniBatch {
    obs: Vec<f32>,
    actions: Vec<f32>,
    old_mu: Vec<f32>,
    old_std: Vec<f32>,
    old_logp: Vec<f32>,
    /// Normalised advantages.
    adv: Vec<f32>,
    vtarget: Vec<f32>,
    /// The critic's samples shared by every row (IQN: the mini-batch's taus).
    critic_samples: Vec<f32>,
}

/// One thread's share of a mini-batch: a contiguous block of its rows, with
/// its own forward caches and gradients (summed over shards before the clip).
#[derive(Clone, Debug, Default)]
struct Shard {
    rows: std::ops::Range<usize>,
    actor_cache: MlpCache,
    critic_cache: CriticCache,
    std: Vec<f32>,
    d_mu: Vec<f32>,
    d_log_std: Vec<f32>,
    d_value: Vec<f32>,
    g_actor: Vec<f32>,
    g_critic: Vec<f32>,
    /// Sums over the shard's rows (divided by the mini-batch size later).
    kl: f64,
    policy_loss: f64,
    clipped: usize,
    /// Already weighted by the shard's share of the mini-batch.
    value_loss: f64,
    time: UpdateTimes,
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
pub(crate) fn scale(g: &mut [f32], s: f32) {
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
    scratch: &mut TargetScratch,
    rng: &mut impl Rng,
) -> Targets {
    let TargetScratch { finals, critic } = scratch;
    finals.clear();
    finals.extend(r.final_obs.iter().flat_map(|(_, o)| o.iter().copied()));
    let input = TargetInput {
        rollout: r,
        finals,
        value_taus: &ac.value_taus,
        cfg,
        ccfg,
    };
    ac.critic.targets(&input, critic, rng)
}

/// Seconds between the laps of the update's phases.
struct Stopwatch(Instant);

impl Stopwatch {
    fn start() -> Stopwatch {
        Stopwatch(Instant::now())
    }

    /// Seconds since the last lap.
    fn lap(&mut self) -> f64 {
        let now = Instant::now();
        let dt = (now - self.0).as_secs_f64();
        self.0 = now;
        dt
    }
}

/// One mini-batch's statistics: this rank's means, then their average over the ranks.
#[derive(Clone, Copy)]
struct MiniBatchMeans {
    kl: f32,
    policy_loss: f32,
    clip_fraction: f32,
    value_loss: f32,
}

/// One PPO update over a full rollout (this rank's, with `comm` the others').
#[allow(clippy::too_many_arguments)] // state, buffers, data, settings, randomness, ranks: all distinct
pub fn update(
    ac: &mut ActorCritic,
    opt: &mut Optimizer,
    ws: &mut Workspace,
    r: &Rollout,
    cfg: &PpoConfig,
    ccfg: &CriticLossConfig,
    rng: &mut impl Rng,
    comm: &dyn Collective,
) -> Result<UpdateStats> {
    check_rollout_fits(ac, r)?;
    let mut time = UpdateTimes::default();
    let mut watch = Stopwatch::start();
    let tg = targets(ac, r, cfg, ccfg, &mut ws.targets, rng);
    time.targets_s += watch.lap();
    let total = r.num_steps * r.num_envs;
    let n_mb = cfg.num_mini_batches.clamp(1, total);
    let mut stats = UpdateStats::default();
    let (mut count, mut clipped_steps) = (0usize, 0usize);
    let Workspace {
        idx,
        mb,
        shards,
        reduce,
        moments,
        ..
    } = ws;
    idx.clear();
    idx.extend(0..total);
    // one shard per thread: each runs forward, loss and backward of its rows
    // with single-threaded kernels (measured faster than splitting every GEMM)
    shards.resize_with(rayon::current_num_threads().max(1), Shard::default);
    let global_norm = cfg.normalize_advantage_per_mini_batch && comm.ranks() > 1;
    for _ in 0..cfg.num_learning_epochs {
        idx.shuffle(rng);
        if global_norm {
            // every mini-batch's advantage moments over all ranks: one sum per epoch
            time.gather_s += watch.lap();
            advantage_moments(moments, &tg.adv, idx, n_mb, comm);
            time.comm_s += watch.lap();
        }
        for k in 0..n_mb {
            let batch = &idx[k * total / n_mb..(k + 1) * total / n_mb];
            gather_mini_batch(mb, r, &tg, batch);
            let global = global_norm.then(|| &moments[3 * k..3 * k + 3]);
            normalize_advantages(&mut mb.adv, global, cfg.normalize_advantage_per_mini_batch);
            draw_critic_samples(&mut mb.critic_samples, ac, ccfg, rng);
            time.gather_s += watch.lap();

            let b = batch.len();
            let mut means = shard_gradients(ac, mb, shards, b, cfg, ccfg, &mut time);
            watch.lap();
            let sh0 = &mut shards[0];
            if comm.ranks() > 1 {
                let mut stats4 = [
                    means.kl,
                    means.policy_loss,
                    means.clip_fraction,
                    means.value_loss,
                ];
                average_across_ranks(
                    reduce,
                    &mut sh0.g_actor,
                    &mut sh0.g_critic,
                    &mut stats4,
                    comm,
                );
                [
                    means.kl,
                    means.policy_loss,
                    means.clip_fraction,
                    means.value_loss,
                ] = stats4;
                time.comm_s += watch.lap();
            }
            add_entropy_bonus(&mut sh0.g_actor, ac, cfg.entropy_coef);
            adapt_learning_rate(opt, means.kl, cfg);

            let (sq_a, sq_c) = (sum_sq(&sh0.g_actor), sum_sq(&sh0.g_critic));
            if clip_grads(
                cfg.grad_clip,
                cfg.max_grad_norm,
                &mut sh0.g_actor,
                &mut sh0.g_critic,
                sq_a,
                sq_c,
            ) {
                clipped_steps += 1;
            }
            time.clip_s += watch.lap();

            let entropy =
                ac.actor.log_std().iter().sum::<f32>() + r.act_dim as f32 * (0.5 + HALF_LN_2PI);
            adam_step(ac, opt, cfg, &sh0.g_actor, &sh0.g_critic);
            time.adam_s += watch.lap();

            add_mini_batch(&mut stats, &means, entropy, opt.lr, (sq_a, sq_c));
            count += 1;
        }
    }
    mean_over_mini_batches(&mut stats, count, clipped_steps);
    stats.learning_rate = opt.lr;
    stats.mean_std = ac.actor.log_std().iter().map(|l| l.exp()).sum::<f32>() / ac.act_dim() as f32;
    stats.time = time;
    Ok(stats)
}

/// Refuses a rollout that does not fit the networks.
fn check_rollout_fits(ac: &ActorCritic, r: &Rollout) -> Result<()> {
    r.validate()?;
    anyhow::ensure!(
        r.obs_dim == ac.obs_dim() && r.act_dim == ac.act_dim(),
        "rollout dims ({}, {}) do not match the networks ({}, {})",
        r.obs_dim,
        r.act_dim,
        ac.obs_dim(),
        ac.act_dim()
    );
    Ok(())
}

/// The rows `batch` of the rollout and its targets into `mb`.
fn gather_mini_batch(mb: &mut MiniBatch, r: &Rollout, tg: &Targets, batch: &[usize]) {
    let (od, ad) = (r.obs_dim, r.act_dim);
    let vt_width = tg.value_targets.len() / (r.num_steps * r.num_envs);
    gather_into(&mut mb.obs, &r.obs, od, batch);
    gather_into(&mut mb.actions, &r.actions, ad, batch);
    gather_into(&mut mb.old_mu, &r.action_mean, ad, batch);
    gather_into(&mut mb.old_std, &r.action_std, ad, batch);
    gather_into(&mut mb.old_logp, &r.log_probs, 1, batch);
    gather_into(&mut mb.adv, &tg.adv, 1, batch);
    gather_into(&mut mb.vtarget, &tg.value_targets, vt_width, batch);
}

/// Advantages to zero mean and unit (unbiased) std: with the global
/// mini-batch's moments when given (MPI), else this mini-batch's own.
fn normalize_advantages(adv: &mut [f32], global_moments: Option<&[f64]>, per_mini_batch: bool) {
    let b = adv.len();
    if let Some(m) = global_moments {
        normalize_with(adv, m);
    } else if per_mini_batch && b > 1 {
        let mean = adv.iter().sum::<f32>() / b as f32;
        let var = adv.iter().map(|a| (a - mean).powi(2)).sum::<f32>() / (b - 1) as f32;
        let inv = 1.0 / (var.sqrt() + 1e-8);
        adv.iter_mut().for_each(|a| *a = (*a - mean) * inv);
    }
}

/// The critic's samples for one mini-batch (IQN: `N` taus ~ U[0, 1]).
fn draw_critic_samples(
    samples: &mut Vec<f32>,
    ac: &ActorCritic,
    ccfg: &CriticLossConfig,
    rng: &mut impl Rng,
) {
    samples.clear();
    ac.critic.draw_samples(samples, ccfg, rng);
}

/// Forward, losses and backward of the mini-batch's `b` rows, one shard of rows
/// per thread; the gradients summed into `shards[0]`. Returns this rank's means.
fn shard_gradients(
    ac: &ActorCritic,
    mb: &MiniBatch,
    shards: &mut [Shard],
    b: usize,
    cfg: &PpoConfig,
    ccfg: &CriticLossConfig,
    time: &mut UpdateTimes,
) -> MiniBatchMeans {
    let n_shards = shards.len().min(b);
    for (s, shard) in shards.iter_mut().enumerate() {
        shard.rows = s * b / n_shards..((s + 1) * b / n_shards).min(b);
    }
    shards.par_iter_mut().for_each(|shard| {
        serial(|| with_precision(cfg.matmul, || shard_pass(ac, mb, shard, b, cfg, ccfg)))
    });
    let (first, rest) = shards.split_at_mut(1);
    let sh0 = &mut first[0];
    for other in rest.iter().filter(|s| !s.rows.is_empty()) {
        add_assign(&mut sh0.g_actor, &other.g_actor);
        add_assign(&mut sh0.g_critic, &other.g_critic);
        sh0.kl += other.kl;
        sh0.policy_loss += other.policy_loss;
        sh0.clipped += other.clipped;
        sh0.value_loss += other.value_loss;
    }
    // the slowest shard sets the wall time of each phase
    let phase = |f: fn(&UpdateTimes) -> f64| shards.iter().map(|s| f(&s.time)).fold(0.0, f64::max);
    time.forward_s += phase(|t| t.forward_s);
    time.loss_s += phase(|t| t.loss_s);
    time.backward_s += phase(|t| t.backward_s);
    let sh0 = &shards[0];
    MiniBatchMeans {
        kl: (sh0.kl / b as f64) as f32,
        policy_loss: (sh0.policy_loss / b as f64) as f32,
        clip_fraction: sh0.clipped as f32 / b as f32,
        value_loss: sh0.value_loss as f32,
    }
}

/// Entropy bonus: d(-c_e H)/d log_std = -c_e per dimension.
fn add_entropy_bonus(g_actor: &mut [f32], ac: &ActorCritic, entropy_coef: f32) {
    let off = ac.actor.log_std_offset();
    for g in &mut g_actor[off..off + ac.act_dim()] {
        *g -= entropy_coef;
    }
}

/// rsl_rl's adaptive schedule: `lr /= 1.5` above twice the desired KL, `lr *= 1.5`
/// below half of it.
fn adapt_learning_rate(opt: &mut Optimizer, kl: f32, cfg: &PpoConfig) {
    if cfg.schedule == LrSchedule::Adaptive {
        if kl > 2.0 * cfg.desired_kl {
            opt.lr = (opt.lr / 1.5).max(cfg.min_lr);
        } else if kl < cfg.desired_kl / 2.0 && kl > 0.0 {
            opt.lr = (opt.lr * 1.5).min(cfg.max_lr);
        }
    }
}

/// One Adam step of actor and critic at the current rate.
fn adam_step(
    ac: &mut ActorCritic,
    opt: &mut Optimizer,
    cfg: &PpoConfig,
    g_actor: &[f32],
    g_critic: &[f32],
) {
    opt.step += 1;
    opt.actor.step(
        &cfg.adam,
        opt.lr,
        opt.step,
        &mut ac.actor.params.data,
        g_actor,
    );
    opt.critic.step(
        &cfg.adam,
        opt.lr,
        opt.step,
        &mut ac.critic.params_mut().data,
        g_critic,
    );
}

/// Adds one mini-batch to the update's sums (`(sq_a, sq_c)`: squared gradient
/// norms of actor and critic before the clip).
fn add_mini_batch(
    stats: &mut UpdateStats,
    m: &MiniBatchMeans,
    entropy: f32,
    lr: f32,
    (sq_a, sq_c): (f64, f64),
) {
    stats.policy_loss += m.policy_loss;
    stats.value_loss += m.value_loss;
    stats.entropy += entropy;
    stats.approx_kl += m.kl;
    stats.clip_fraction += m.clip_fraction;
    stats.learning_rate_mean += lr;
    stats.learning_rate_max = stats.learning_rate_max.max(lr);
    stats.grad_norm += (sq_a + sq_c).sqrt() as f32;
    stats.actor_grad_norm += sq_a.sqrt() as f32;
    stats.critic_grad_norm += sq_c.sqrt() as f32;
}

/// The update's sums over `count` mini-batches divided into means.
fn mean_over_mini_batches(stats: &mut UpdateStats, count: usize, clipped_steps: usize) {
    let c = count.max(1) as f32;
    stats.policy_loss /= c;
    stats.value_loss /= c;
    stats.entropy /= c;
    stats.approx_kl /= c;
    stats.learning_rate_mean /= c;
    stats.clip_fraction /= c;
    stats.grad_norm /= c;
    stats.actor_grad_norm /= c;
    stats.critic_grad_norm /= c;
    stats.clipped_fraction = clipped_steps as f32 / c;
}

/// `m <- [sum, sum of squares, count]` of the advantages of each of the `n_mb`
/// mini-batches of `idx`, summed over the ranks (each rank's mini-batch k is
/// its share of the global mini-batch k).
fn advantage_moments(
    m: &mut Vec<f64>,
    adv: &[f32],
    idx: &[usize],
    n_mb: usize,
    comm: &dyn Collective,
) {
    let total = idx.len();
    m.clear();
    m.resize(3 * n_mb, 0.0);
    for k in 0..n_mb {
        let batch = &idx[k * total / n_mb..(k + 1) * total / n_mb];
        for &i in batch {
            let a = adv[i] as f64;
            m[3 * k] += a;
            m[3 * k + 1] += a * a;
        }
        m[3 * k + 2] = batch.len() as f64;
    }
    comm.sum_f64(m);
}

/// Normalises this rank's share of a global mini-batch to that batch's mean
/// and (unbiased) std from its summed `[sum, sum of squares, count]`.
fn normalize_with(adv: &mut [f32], moments: &[f64]) {
    let n = moments[2];
    if n < 2.0 {
        return;
    }
    let mean = moments[0] / n;
    let var = ((moments[1] - n * mean * mean) / (n - 1.0)).max(0.0);
    let inv = 1.0 / (var.sqrt() + 1e-8);
    adv.iter_mut()
        .for_each(|a| *a = ((*a as f64 - mean) * inv) as f32);
}

/// Replaces this rank's mini-batch gradients and statistics by their mean over
/// the ranks: one packed sum of `[g_actor, g_critic, stats]`.
fn average_across_ranks(
    buf: &mut Vec<f32>,
    g_actor: &mut [f32],
    g_critic: &mut [f32],
    stats: &mut [f32],
    comm: &dyn Collective,
) {
    buf.clear();
    buf.extend_from_slice(g_actor);
    buf.extend_from_slice(g_critic);
    buf.extend_from_slice(stats);
    comm.sum_f32(buf);
    let inv = 1.0 / comm.ranks() as f32;
    let (a, rest) = buf.split_at(g_actor.len());
    let (c, st) = rest.split_at(g_critic.len());
    for (dst, src) in [(g_actor, a), (g_critic, c), (stats, st)] {
        dst.iter_mut().zip(src).for_each(|(d, s)| *d = s * inv);
    }
}

/// Forward, losses and backward of one shard's rows of the mini-batch (`b`
/// rows in all). Per-sample gradients are scaled by `1 / b`, so summing the
/// shards' gradients gives the mini-batch's. Resets and fills `shard`'s
/// gradients, loss sums and phase times.
fn shard_pass(
    ac: &ActorCritic,
    mb: &MiniBatch,
    sh: &mut Shard,
    b: usize,
    cfg: &PpoConfig,
    ccfg: &CriticLossConfig,
) {
    let mut watch = Stopwatch::start();
    let (od, ad) = (ac.obs_dim(), ac.act_dim());
    let rows = sh.rows.clone();
    let n = rows.len();
    sh.g_actor.clear();
    sh.g_actor.resize(ac.actor.params.len(), 0.0);
    sh.g_critic.clear();
    sh.g_critic.resize(ac.critic.params().len(), 0.0);
    (sh.kl, sh.policy_loss, sh.clipped, sh.value_loss) = (0.0, 0.0, 0, 0.0);
    sh.time = UpdateTimes::default();
    if n == 0 {
        return;
    }
    let obs = &mb.obs[rows.start * od..rows.end * od];
    let vt_width = mb.vtarget.len() / b;
    let vtarget = &mb.vtarget[rows.start * vt_width..rows.end * vt_width];

    // ---- forward ----
    ac.actor.forward(obs, n, &mut sh.actor_cache);
    ac.critic
        .forward_mini_batch(obs, n, &mb.critic_samples, &mut sh.critic_cache);
    sh.time.forward_s = watch.lap();

    // ---- losses and their output gradients ----
    surrogate_and_kl(ac, mb, sh, b, cfg);
    value_loss_and_gradient(ac, mb, vtarget, sh, b, cfg, ccfg);
    sh.time.loss_s = watch.lap();

    // ---- backward ----
    ac.actor
        .backward(&mut sh.g_actor, obs, n, &mut sh.actor_cache, &mut sh.d_mu);
    let off = ac.actor.log_std_offset();
    for (g, d) in sh.g_actor[off..off + ad].iter_mut().zip(&sh.d_log_std) {
        *g += d;
    }
    ac.critic.backward_mini_batch(
        &mut sh.g_critic,
        obs,
        n,
        &mut sh.critic_cache,
        &mut sh.d_value,
    );
    sh.time.backward_s = watch.lap();
}

/// The clipped surrogate's sum and its gradients with respect to the mean
/// and log std of this shard's rows, and the KL(old || new) sum.
fn surrogate_and_kl(ac: &ActorCritic, mb: &MiniBatch, sh: &mut Shard, b: usize, cfg: &PpoConfig) {
    let ad = ac.act_dim();
    let rows = sh.rows.clone();
    let n = rows.len();
    let mu = sh.actor_cache.output();
    let log_std = ac.actor.log_std();
    sh.std.clear();
    sh.std.extend(log_std.iter().map(|l| l.exp()));
    let std = &sh.std;
    let sum_log_std: f32 = log_std.iter().sum();
    let at = |w: usize| rows.start * w..rows.end * w;
    let actions = &mb.actions[at(ad)];
    let old_mu = &mb.old_mu[at(ad)];
    let old_std = &mb.old_std[at(ad)];
    let old_logp = &mb.old_logp[rows.clone()];
    let adv = &mb.adv[rows.clone()];

    // KL(old || new) of diagonal Gaussians, the adaptive-lr signal (summed here)
    for i in 0..n * ad {
        let (s_new, s_old) = (std[i % ad], old_std[i]);
        let dm = old_mu[i] - mu[i];
        sh.kl +=
            ((s_new / s_old).ln() + (s_old * s_old + dm * dm) / (2.0 * s_new * s_new) - 0.5) as f64;
    }

    // clipped surrogate: L = mean_b max(-A r, -A clip(r, 1-e, 1+e)), r = exp(logp - logp_old)
    sh.d_mu.clear();
    sh.d_mu.resize(n * ad, 0.0);
    sh.d_log_std.clear();
    sh.d_log_std.resize(ad, 0.0);
    for s in 0..n {
        let row = s * ad..(s + 1) * ad;
        let mut sq = 0.0;
        for j in 0..ad {
            let z = (actions[row.start + j] - mu[row.start + j]) / std[j];
            sq += z * z;
        }
        let logp = -0.5 * sq - sum_log_std - ad as f32 * HALF_LN_2PI;
        // log-ratio capped so that a stale sample cannot overflow exp to inf
        let ratio = (logp - old_logp[s]).min(20.0).exp();
        let a = adv[s];
        let unclipped = -a * ratio;
        let clip = -a * ratio.clamp(1.0 - cfg.clip_param, 1.0 + cfg.clip_param);
        sh.policy_loss += unclipped.max(clip) as f64;
        if (ratio - 1.0).abs() > cfg.clip_param {
            sh.clipped += 1;
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
                sh.d_mu[row.start + j] = g * z / std[j]; // dlogp/dmu = (a - mu) / std^2
                sh.d_log_std[j] += g * (z * z - 1.0); // dlogp/dlog_std = z^2 - 1
            }
        }
    }
}

/// The critic's loss on this shard's rows (quantile Huber for IQN, MSE for the
/// scalar critic) and its gradient with respect to the critic's outputs.
fn value_loss_and_gradient(
    ac: &ActorCritic,
    mb: &MiniBatch,
    vtarget: &[f32],
    sh: &mut Shard,
    b: usize,
    cfg: &PpoConfig,
    ccfg: &CriticLossConfig,
) {
    let input = LossInput {
        samples: &mb.critic_samples,
        targets: vtarget,
        rows: sh.rows.len(),
        batch: b,
        cfg,
        ccfg,
    };
    sh.value_loss = ac
        .critic
        .value_loss(&input, &mut sh.critic_cache, &mut sh.d_value);
}

#[cfg(test)]
mod tests {
    use super::*;

    fn norm(g: &[f32]) -> f64 {
        sum_sq(g).sqrt()
    }

    #[test]
    fn global_clip_scales_both_networks_by_one_factor() {
        let (mut a, mut c) = (vec![0.3f32, 0.4], vec![3.0f32, 4.0]); // norms 0.5 and 5
        let (sa, sc) = (sum_sq(&a), sum_sq(&c));
        assert!(clip_grads(GradClip::Global, 1.0, &mut a, &mut c, sa, sc));
        let total = (norm(&a).powi(2) + norm(&c).powi(2)).sqrt();
        assert!((total - 1.0).abs() < 1e-5, "{total}");
        assert!((norm(&a) / norm(&c) - 0.1).abs() < 1e-6); // ratio kept
    }

    #[test]
    fn per_network_clip_leaves_a_small_actor_gradient_alone() {
        let (mut a, mut c) = (vec![0.3f32, 0.4], vec![3.0f32, 4.0]);
        let (sa, sc) = (sum_sq(&a), sum_sq(&c));
        assert!(clip_grads(
            GradClip::PerNetwork,
            1.0,
            &mut a,
            &mut c,
            sa,
            sc
        ));
        assert_eq!(a, vec![0.3, 0.4]);
        assert!((norm(&c) - 1.0).abs() < 1e-5);
        let (mut a, mut c) = (vec![0.3f32], vec![0.4f32]);
        let (sa, sc) = (sum_sq(&a), sum_sq(&c));
        assert!(!clip_grads(
            GradClip::PerNetwork,
            1.0,
            &mut a,
            &mut c,
            sa,
            sc
        ));
    }
}
