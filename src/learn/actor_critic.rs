//! The policy and value networks together, with the inference calls the runner,
//! the evaluator and the viewer use. Observations are `n x obs_dim` row-major.

use super::critic::Critic;
use super::nets::GaussianActor;
use super::normalizer::EmpiricalNormalizer;
use super::risk::{Distortion, IQR_TAUS};
use super::storage::ActOutput;
use rand::Rng;
use rand_distr::StandardNormal;
use std::borrow::Cow;

/// `0.5 ln(2 pi)`.
pub const HALF_LN_2PI: f32 = 0.918_938_5;

/// Actor, critic, and the fixed tau grid of the distorted value.
#[derive(Clone, Debug)]
pub struct ActorCritic {
    pub actor: GaussianActor,
    pub critic: Box<dyn Critic>,
    /// `beta((k + 1/2) / K)`, `k = 0..K`: the distorted value is the mean of `Z` here.
    pub value_taus: Vec<f32>,
    /// The empirical observation normaliser every inference call applies first
    /// (`learner.obs_normalization`); `None`: the networks read raw observations.
    /// The update's forward passes read rows the learner normalised already.
    pub obs_norm: Option<EmpiricalNormalizer>,
}

impl ActorCritic {
    pub fn new(
        actor: GaussianActor,
        critic: Box<dyn Critic>,
        distortion: Distortion,
        num_value_taus: usize,
    ) -> Self {
        ActorCritic {
            actor,
            critic,
            value_taus: distortion.grid(num_value_taus),
            obs_norm: None,
        }
    }

    /// What the networks read for `obs`: normalised when there is a normaliser.
    fn input<'a>(&self, obs: &'a [f32]) -> Cow<'a, [f32]> {
        match &self.obs_norm {
            Some(n) => Cow::Owned(n.normalized(obs)),
            None => Cow::Borrowed(obs),
        }
    }

    pub fn obs_dim(&self) -> usize {
        self.actor.obs_dim
    }
    pub fn act_dim(&self) -> usize {
        self.actor.act_dim
    }

    fn rows(&self, obs: &[f32]) -> usize {
        let d = self.obs_dim();
        assert!(
            obs.len().is_multiple_of(d),
            "observation slice of {} values is not a multiple of obs_dim {d}",
            obs.len()
        );
        obs.len() / d
    }

    /// Samples `a = mean + std * eps`, `eps ~ N(0, I)` drawn from `rng` in
    /// row-major order, with `log pi(a|s)`. (No critic pass: the update
    /// evaluates the critic on the whole rollout at once.)
    pub fn act<R: Rng + ?Sized>(&self, obs: &[f32], rng: &mut R) -> ActOutput {
        let n = self.rows(obs);
        let a = self.act_dim();
        let action_mean = self.actor.mean(&self.input(obs), n);
        let log_std = self.actor.log_std();
        let std: Vec<f32> = log_std.iter().map(|l| l.exp()).collect();
        let sum_log_std: f32 = log_std.iter().sum();
        let mut actions = Vec::with_capacity(n * a);
        let mut log_probs = Vec::with_capacity(n);
        for row in action_mean.chunks_exact(a) {
            let mut sq = 0.0;
            for (m, s) in row.iter().zip(&std) {
                let eps: f32 = rng.sample(StandardNormal);
                actions.push(m + s * eps);
                sq += eps * eps;
            }
            log_probs.push(-0.5 * sq - sum_log_std - a as f32 * HALF_LN_2PI);
        }
        ActOutput {
            actions,
            log_probs,
            action_std: std.repeat(n),
            action_mean,
        }
    }

    /// Deterministic action (the policy mean), `n x act_dim`.
    pub fn act_mean(&self, obs: &[f32]) -> Vec<f32> {
        self.actor.mean(&self.input(obs), self.rows(obs))
    }

    /// `Z_tau(s)` for each observation and tau: `n x taus.len()`. The scalar
    /// critic has no distribution: it returns `V(s)` for every tau.
    pub fn value_quantiles(&self, obs: &[f32], taus: &[f32]) -> Vec<f32> {
        let n = self.rows(obs);
        self.critic.value_quantiles(&self.input(obs), n, taus)
    }

    /// The value the actor follows: `V_beta(s)` (e.g. `CVaR_eta(Z(s))`) on the fixed
    /// grid for the IQN critic, `V(s)` for the scalar critic. `n` values.
    pub fn distorted_value(&self, obs: &[f32]) -> Vec<f32> {
        let n = self.rows(obs);
        self.critic
            .distorted_value(&self.input(obs), n, &self.value_taus)
    }

    /// `IQR(s) = Z_0.75(s) - Z_0.25(s)` (0 for the scalar critic), `n` values.
    pub fn iqr(&self, obs: &[f32]) -> Vec<f32> {
        self.value_quantiles(obs, &IQR_TAUS)
            .chunks_exact(2)
            .map(|q| q[1] - q[0])
            .collect()
    }
}
