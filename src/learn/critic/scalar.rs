//! The scalar critic: `V(s)` (the network is [`ScalarCritic`]), trained by the
//! squared error to the GAE returns; the risk-neutral baseline.

use super::{Critic, CriticCache, CriticSpec, LossInput, TargetInput, Targets};
use crate::learn::learner::LearnerConfig;
use crate::learn::nets::{InputSel, MlpCache, ParamSet, ScalarCritic};
use crate::learn::storage::{gae, next_values};
use anyhow::Result;
use rand::RngCore;

pub const SPEC: CriticSpec = CriticSpec {
    name: "scalar",
    has_quantiles: false,
    build,
};

fn build(
    input: InputSel,
    cfg: &LearnerConfig,
    mut rng: &mut dyn RngCore,
) -> Result<Box<dyn Critic>> {
    Ok(Box::new(ScalarCritic::with_input(
        input,
        &cfg.critic_hidden,
        &mut rng,
    )))
}

impl Critic for ScalarCritic {
    fn params(&self) -> &ParamSet {
        &self.params
    }
    fn params_mut(&mut self) -> &mut ParamSet {
        &mut self.params
    }

    fn distorted_value(&self, obs: &[f32], n: usize, _value_taus: &[f32]) -> Vec<f32> {
        self.values(obs, n)
    }

    /// `returns = A + V`; one cache per batch (the rollout, the states after it,
    /// the episodes' final states), each keeping its size from update to update.
    fn targets(
        &self,
        input: &TargetInput<'_>,
        cache: &mut CriticCache,
        _rng: &mut dyn RngCore,
    ) -> Targets {
        let TargetInput {
            rollout: r,
            finals,
            cfg,
            ..
        } = *input;
        let v = |o: &[f32], cache: &mut MlpCache| {
            self.forward(o, o.len() / r.obs_dim, cache);
            cache.output().to_vec()
        };
        let [m_rollout, m_last, m_finals] = cache.get::<[MlpCache; 3]>();
        let values = v(&r.obs, m_rollout);
        let (last, fin) = (v(&r.last_obs, m_last), v(finals, m_finals));
        let next = next_values(r, 1, &values, &last, &fin);
        let adv = gae(r, &values, &next, cfg.gamma, cfg.lam);
        let returns = adv.iter().zip(&values).map(|(a, v)| a + v).collect();
        Targets {
            adv,
            value_targets: returns,
        }
    }

    fn forward_mini_batch(&self, obs: &[f32], n: usize, _samples: &[f32], cache: &mut CriticCache) {
        self.forward(obs, n, cache.get::<MlpCache>());
    }

    /// Mean squared error.
    fn value_loss(
        &self,
        input: &LossInput<'_>,
        cache: &mut CriticCache,
        d_out: &mut Vec<f32>,
    ) -> f64 {
        let b = input.batch;
        let v = cache.get::<MlpCache>().output();
        let mut loss = 0.0f64;
        d_out.clear();
        d_out.extend(v.iter().zip(input.targets).map(|(v, t)| {
            loss += ((t - v) * (t - v)) as f64;
            input.cfg.value_loss_coef * 2.0 * (v - t) / b as f32
        }));
        loss / b as f64
    }

    fn backward_mini_batch(
        &self,
        grads: &mut [f32],
        obs: &[f32],
        n: usize,
        cache: &mut CriticCache,
        d_out: &mut Vec<f32>,
    ) {
        self.backward(grads, obs, n, cache.get::<MlpCache>(), d_out);
    }
}
