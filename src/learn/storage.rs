//! Rollout storage, GAE, and the IQN critic targets.
//!
//! Layout: step-major, `[num_steps x num_envs x dim]` (index `(t * E + e) * dim`).
//! `dones[t, e]` means the episode of env `e` ended at step `t` (termination or
//! time-out); `time_outs[t, e]` (a subset) means it ended by the time limit. The
//! env auto-resets, so `obs[t + 1, e]` after a done belongs to the next episode:
//! for time-outs the rollout also keeps the TRUE final observation, from which
//! the value (distribution) is bootstrapped. Terminations do not bootstrap.
//!
//! # IQN targets (random-horizon lambda mixture)
//!
//! For each sample `(t, e)` we build `N'` target samples, one per target tau
//! `tau'_j = (j + 1/2) / N'` (undistorted, so the critic learns the whole
//! distribution), from the collection-time critic:
//!
//! `T_j = sum_{k=t}^{t+n_j-1} gamma^(k-t) r_k + gamma^(n_j) Z_{tau'_j}(s_{t+n_j})`,
//!
//! with an independent horizon `n_j ~ Geometric(1 - lambda)` (`P(n) = (1-lambda)
//! lambda^(n-1)`), cut at the end of the episode (termination: no bootstrap;
//! time-out: bootstrap from the stored final observation) or of the rollout
//! (bootstrap from the last observation). Each `T_j` is a sample from the
//! lambda-weighted mixture of n-step target distributions (the SR(lambda)
//! construction of GMAC, Nam et al. 2021, which the paper follows for `Z(S')`).
//! Because the quantile loss is linear in the target distribution, regressing on
//! such samples is unbiased for the mixture, whose mean is exactly the lambda-return;
//! a quantile-wise lambda-return (averaging quantile functions) would instead
//! shrink the spread. `lambda = 0` gives the paper's 1-step `r + gamma Z_tau'(s')`.
//! The scalar critic uses `returns = A + V` as rsl_rl.

use anyhow::{ensure, Result};
use rand::Rng;

/// What the actor produced for a batch of `n` observations.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ActOutput {
    /// Sampled actions, `n x act_dim` (unclipped; clip in the env if needed).
    pub actions: Vec<f32>,
    /// `log pi(a|s)`, `n`.
    pub log_probs: Vec<f32>,
    /// Policy mean, `n x act_dim`.
    pub action_mean: Vec<f32>,
    /// Policy std, `n x act_dim`.
    pub action_std: Vec<f32>,
}

/// One PPO rollout of `num_steps x num_envs` transitions.
#[derive(Clone, Debug)]
pub struct Rollout {
    pub num_steps: usize,
    pub num_envs: usize,
    pub obs_dim: usize,
    pub act_dim: usize,
    /// `[T x E x obs_dim]`
    pub obs: Vec<f32>,
    /// `[T x E x act_dim]`
    pub actions: Vec<f32>,
    /// `[T x E]`
    pub log_probs: Vec<f32>,
    /// `[T x E x act_dim]`
    pub action_mean: Vec<f32>,
    /// `[T x E x act_dim]`
    pub action_std: Vec<f32>,
    /// `[T x E]`
    pub rewards: Vec<f32>,
    /// `[T x E]` episode ended at this step (termination or time-out).
    pub dones: Vec<bool>,
    /// `[T x E]` episode ended by the time limit (implies `dones`).
    pub time_outs: Vec<bool>,
    /// `(t * E + e, obs_dim values)`: the true final observation of every time-out.
    pub final_obs: Vec<(usize, Vec<f32>)>,
    /// `[E x obs_dim]` observation after the last step (bootstrap at the rollout end).
    pub last_obs: Vec<f32>,
    step: usize,
}

impl Rollout {
    pub fn new(num_steps: usize, num_envs: usize, obs_dim: usize, act_dim: usize) -> Self {
        let n = num_steps * num_envs;
        Rollout {
            num_steps,
            num_envs,
            obs_dim,
            act_dim,
            obs: Vec::with_capacity(n * obs_dim),
            actions: Vec::with_capacity(n * act_dim),
            log_probs: Vec::with_capacity(n),
            action_mean: Vec::with_capacity(n * act_dim),
            action_std: Vec::with_capacity(n * act_dim),
            rewards: Vec::with_capacity(n),
            dones: Vec::with_capacity(n),
            time_outs: Vec::with_capacity(n),
            final_obs: Vec::new(),
            last_obs: Vec::new(),
            step: 0,
        }
    }

    /// Empties the buffer (keeps capacity).
    pub fn clear(&mut self) {
        self.obs.clear();
        self.actions.clear();
        self.log_probs.clear();
        self.action_mean.clear();
        self.action_std.clear();
        self.rewards.clear();
        self.dones.clear();
        self.time_outs.clear();
        self.final_obs.clear();
        self.last_obs.clear();
        self.step = 0;
    }

    /// Steps stored so far.
    pub fn len(&self) -> usize {
        self.step
    }
    pub fn is_empty(&self) -> bool {
        self.step == 0
    }
    /// All `num_steps` stored and `last_obs` set: ready for `Learner::update`.
    pub fn is_full(&self) -> bool {
        self.step == self.num_steps && self.last_obs.len() == self.num_envs * self.obs_dim
    }

    /// Stores one env step for all envs. `obs`: the observations `act` was called
    /// on (`E x obs_dim`); `rewards`, `dones`, `time_outs`: `E`; `final_obs`:
    /// `E x obs_dim`, read only in rows where `time_outs` is set (may be empty
    /// when there is no time-out).
    pub fn push(
        &mut self,
        obs: &[f32],
        act: &ActOutput,
        rewards: &[f32],
        dones: &[bool],
        time_outs: &[bool],
        final_obs: &[f32],
    ) -> Result<()> {
        let (e, o, a) = (self.num_envs, self.obs_dim, self.act_dim);
        ensure!(
            self.step < self.num_steps,
            "rollout is full ({} steps)",
            self.num_steps
        );
        ensure!(
            obs.len() == e * o,
            "obs: expected {} values, got {}",
            e * o,
            obs.len()
        );
        ensure!(
            act.actions.len() == e * a
                && act.action_mean.len() == e * a
                && act.action_std.len() == e * a
                && act.log_probs.len() == e,
            "act output does not match {e} envs x {a} actions"
        );
        ensure!(
            rewards.len() == e && dones.len() == e && time_outs.len() == e,
            "rewards/dones/time_outs must have {e} entries"
        );
        for env in 0..e {
            if time_outs[env] {
                ensure!(dones[env], "env {env}: time-out without done");
                ensure!(
                    final_obs.len() == e * o,
                    "final_obs: expected {} values when an env times out, got {}",
                    e * o,
                    final_obs.len()
                );
                let idx = self.step * e + env;
                self.final_obs
                    .push((idx, final_obs[env * o..(env + 1) * o].to_vec()));
            }
        }
        self.obs.extend_from_slice(obs);
        self.actions.extend_from_slice(&act.actions);
        self.log_probs.extend_from_slice(&act.log_probs);
        self.action_mean.extend_from_slice(&act.action_mean);
        self.action_std.extend_from_slice(&act.action_std);
        self.rewards.extend_from_slice(rewards);
        self.dones.extend_from_slice(dones);
        self.time_outs.extend_from_slice(time_outs);
        self.step += 1;
        Ok(())
    }

    /// Sets the observation after the last step (`E x obs_dim`).
    pub fn set_last_obs(&mut self, obs: &[f32]) -> Result<()> {
        ensure!(
            obs.len() == self.num_envs * self.obs_dim,
            "last_obs: wrong length"
        );
        self.last_obs = obs.to_vec();
        Ok(())
    }

    /// Checks that the rollout is complete and consistent.
    pub fn validate(&self) -> Result<()> {
        ensure!(
            self.step == self.num_steps,
            "rollout has {} of {} steps",
            self.step,
            self.num_steps
        );
        ensure!(
            self.last_obs.len() == self.num_envs * self.obs_dim,
            "rollout: last_obs not set"
        );
        Ok(())
    }

    /// Terminated (done and not a time-out): no bootstrap.
    pub fn terminated(&self, i: usize) -> bool {
        self.dones[i] && !self.time_outs[i]
    }
}

/// For each transition `i = t * E + e`, the `width` values to bootstrap from
/// after it: `cur[i + E]` (the next state) when the episode goes on, `last[e]` at
/// the rollout end, `finals[k]` (the k-th entry of `final_obs`) on a time-out,
/// zeros on a termination. `cur`: `[T x E x width]`, `last`: `[E x width]`,
/// `finals`: `[final_obs.len() x width]`.
pub fn next_values(
    r: &Rollout,
    width: usize,
    cur: &[f32],
    last: &[f32],
    finals: &[f32],
) -> Vec<f32> {
    let (t_n, e_n) = (r.num_steps, r.num_envs);
    assert_eq!(cur.len(), t_n * e_n * width);
    assert_eq!(last.len(), e_n * width);
    assert_eq!(finals.len(), r.final_obs.len() * width);
    let mut next = vec![0.0; t_n * e_n * width];
    for t in 0..t_n {
        for e in 0..e_n {
            let i = t * e_n + e;
            if r.dones[i] {
                continue; // terminations stay 0; time-outs filled below
            }
            let src = if t + 1 < t_n {
                &cur[(i + e_n) * width..(i + e_n + 1) * width]
            } else {
                &last[e * width..(e + 1) * width]
            };
            next[i * width..(i + 1) * width].copy_from_slice(src);
        }
    }
    for (k, (i, _)) in r.final_obs.iter().enumerate() {
        next[i * width..(i + 1) * width].copy_from_slice(&finals[k * width..(k + 1) * width]);
    }
    next
}

/// GAE (Schulman et al. 2016) on the scalar value the actor follows:
/// `delta_t = r_t + gamma V_next_t - V(s_t)` (`V_next` from [`next_values`], 0 on
/// termination), `A_t = delta_t + gamma lambda (1 - done_t) A_{t+1}`.
/// Returns the advantages `[T x E]`.
pub fn gae(r: &Rollout, values: &[f32], next: &[f32], gamma: f32, lambda: f32) -> Vec<f32> {
    let (t_n, e_n) = (r.num_steps, r.num_envs);
    let mut adv = vec![0.0; t_n * e_n];
    for e in 0..e_n {
        let mut acc = 0.0;
        for t in (0..t_n).rev() {
            let i = t * e_n + e;
            let delta = r.rewards[i] + gamma * next[i] - values[i];
            let keep = if r.dones[i] { 0.0 } else { 1.0 };
            acc = delta + gamma * lambda * keep * acc;
            adv[i] = acc;
        }
    }
    adv
}

/// IQN targets `[T x E x N']` by the random-horizon construction in the module
/// docs. `next_z`: [`next_values`] of the collection-time quantiles at the `N'`
/// target taus (`[T x E x N']`).
pub fn quantile_targets(
    r: &Rollout,
    next_z: &[f32],
    n_targets: usize,
    gamma: f32,
    lambda: f32,
    rng: &mut impl Rng,
) -> Vec<f32> {
    let (t_n, e_n) = (r.num_steps, r.num_envs);
    assert_eq!(next_z.len(), t_n * e_n * n_targets);
    let mut out = vec![0.0; t_n * e_n * n_targets];
    let ln_lambda = (lambda as f64).ln();
    // last step of the current episode segment within the rollout, per (t, e)
    let mut seg_end = vec![0usize; t_n * e_n];
    for e in 0..e_n {
        let mut end = t_n - 1;
        for t in (0..t_n).rev() {
            if r.dones[t * e_n + e] {
                end = t;
            }
            seg_end[t * e_n + e] = end;
        }
    }
    let mut ret = vec![0.0f32; t_n + 1];
    for e in 0..e_n {
        for t in 0..t_n {
            let i = t * e_n + e;
            let end = seg_end[i];
            // ret[k - t] = discounted reward sum over steps t..k-1 (k - t terms)
            ret[0] = 0.0;
            let mut disc = 1.0f32;
            for k in t..=end {
                ret[k - t + 1] = ret[k - t] + disc * r.rewards[k * e_n + e];
                disc *= gamma;
            }
            for j in 0..n_targets {
                // n ~ Geometric(1 - lambda) on {1, 2, ...}
                let n = if lambda <= 0.0 {
                    1
                } else if lambda >= 1.0 {
                    t_n // always reaches the segment end
                } else {
                    let u: f64 = 1.0 - rng.gen::<f64>(); // (0, 1]
                    1 + (u.ln() / ln_lambda).floor().min(1e6) as usize
                };
                let k_last = (t + n - 1).min(end);
                let len = k_last - t + 1;
                let k_i = k_last * e_n + e;
                let boot = next_z[k_i * n_targets + j]; // 0 after a termination
                out[i * n_targets + j] = ret[len] + gamma.powi(len as i32) * boot;
            }
        }
    }
    out
}
