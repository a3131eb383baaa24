//! The IQN critic: a value distribution `Z_tau(s)` (the network is
//! [`IqnCritic`]), trained by the quantile Huber loss against the random-horizon
//! targets of `storage`; the actor follows its distorted value.

use super::{Critic, CriticCache, CriticSpec, LossInput, TargetInput, Targets};
use crate::learn::learner::LearnerConfig;
use crate::learn::nets::{InputSel, IqnCache, IqnCritic, ParamSet};
use crate::learn::ppo::{scale, CriticLossConfig};
use crate::learn::risk::{midpoint_taus, quantile_huber_loss};
use crate::learn::storage::{gae, next_values, quantile_targets};
use anyhow::Result;
use rand::{Rng, RngCore};

pub const SPEC: CriticSpec = CriticSpec {
    name: "iqn",
    has_quantiles: true,
    build,
};

fn build(
    input: InputSel,
    cfg: &LearnerConfig,
    mut rng: &mut dyn RngCore,
) -> Result<Box<dyn Critic>> {
    Ok(Box::new(IqnCritic::with_input(
        input,
        &cfg.critic_hidden,
        cfg.num_cos,
        &mut rng,
    )))
}

/// The buffers of [`Critic::targets`]: one cache per batch (the rollout, the
/// states after it, the episodes' final states), so that each keeps its size
/// from update to update, and the taus of one pass.
#[derive(Default)]
struct TargetScratch {
    caches: [IqnCache; 3],
    taus: Vec<f32>,
}

impl Critic for IqnCritic {
    fn params(&self) -> &ParamSet {
        &self.params
    }
    fn params_mut(&mut self) -> &mut ParamSet {
        &mut self.params
    }

    fn distorted_value(&self, obs: &[f32], n: usize, value_taus: &[f32]) -> Vec<f32> {
        let k = value_taus.len();
        let z = self.quantiles(obs, n, value_taus);
        z.chunks_exact(k)
            .map(|r| r.iter().sum::<f32>() / k as f32)
            .collect()
    }

    fn value_quantiles(&self, obs: &[f32], n: usize, taus: &[f32]) -> Vec<f32> {
        self.quantiles(obs, n, taus)
    }

    fn targets(
        &self,
        input: &TargetInput<'_>,
        cache: &mut CriticCache,
        mut rng: &mut dyn RngCore,
    ) -> Targets {
        let TargetInput {
            rollout: r,
            finals,
            value_taus,
            cfg,
            ccfg,
        } = *input;
        let TargetScratch { caches, taus } = cache.get::<TargetScratch>();
        // one trunk pass per state: the value grid and the target grid together
        let k = value_taus.len();
        let nt = ccfg.num_target_taus;
        taus.clear();
        taus.extend(value_taus.iter().copied().chain(midpoint_taus(nt)));
        let split = |o: &[f32], cache: &mut IqnCache| {
            let z = self.forward(o, o.len() / r.obs_dim, taus, cache);
            let mut v = Vec::with_capacity(z.len() / (k + nt));
            let mut q = Vec::with_capacity(z.len() / (k + nt) * nt);
            for row in z.chunks_exact(k + nt) {
                v.push(row[..k].iter().sum::<f32>() / k as f32);
                q.extend_from_slice(&row[k..]);
            }
            (v, q)
        };
        let [i_rollout, i_last, i_finals] = caches;
        let (values, z) = split(&r.obs, i_rollout);
        let (last_v, last_z) = split(&r.last_obs, i_last);
        let (fin_v, fin_z) = split(finals, i_finals);
        let next = next_values(r, 1, &values, &last_v, &fin_v);
        let adv = gae(r, &values, &next, cfg.gamma, cfg.lam);
        let next_z = next_values(r, nt, &z, &last_z, &fin_z);
        let value_targets =
            quantile_targets(r, &next_z, nt, cfg.gamma, ccfg.target_lambda, &mut rng);
        Targets { adv, value_targets }
    }

    /// The mini-batch's `N` taus ~ U[0, 1].
    fn draw_samples(&self, samples: &mut Vec<f32>, ccfg: &CriticLossConfig, rng: &mut dyn RngCore) {
        samples.extend((0..ccfg.num_taus).map(|_| rng.gen::<f32>()));
    }

    fn forward_mini_batch(&self, obs: &[f32], n: usize, samples: &[f32], cache: &mut CriticCache) {
        self.forward(obs, n, samples, cache.get::<IqnCache>());
    }

    /// Quantile Huber loss.
    fn value_loss(
        &self,
        input: &LossInput<'_>,
        cache: &mut CriticCache,
        d_out: &mut Vec<f32>,
    ) -> f64 {
        let share = input.rows as f32 / input.batch as f32;
        let z = cache.get::<IqnCache>().output();
        d_out.clear();
        d_out.resize(z.len(), 0.0);
        // the loss averages over this shard's rows: rescale to the mini-batch
        let loss = quantile_huber_loss(z, input.samples, input.targets, input.ccfg.kappa, d_out);
        scale(d_out, input.cfg.value_loss_coef * share);
        (loss * share) as f64
    }

    fn backward_mini_batch(
        &self,
        grads: &mut [f32],
        obs: &[f32],
        n: usize,
        cache: &mut CriticCache,
        d_out: &mut Vec<f32>,
    ) {
        self.backward(grads, obs, n, cache.get::<IqnCache>(), d_out);
    }
}
