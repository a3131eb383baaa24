//! The facade the runner calls: [`Learner`] owns the networks, the optimizer and
//! the update RNG; [`LearnerConfig`] holds every hyper-parameter.

use super::actor_critic::{ActorCritic, Critic};
use super::adam::AdamState;
use super::nets::{GaussianActor, IqnCritic, ParamSet, ScalarCritic};
use super::ppo::{self, CriticLossConfig, Optimizer, PpoConfig, UpdateStats, Workspace};
use super::risk::Distortion;
use super::storage::{ActOutput, Rollout};
use anyhow::{bail, ensure, Result};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

/// Which critic the actor follows.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum CriticKind {
    /// IQN value distribution `Z(s)`; the actor follows its distorted value (RALL).
    Iqn,
    /// Scalar `V(s)` (risk-neutral PPO baseline).
    Scalar,
}

/// RALL's CVaR level (the paper: eta 0.5).
pub const DEFAULT_CVAR_ETA: f32 = 0.5;

/// All learner hyper-parameters; `Default` = the paper / rsl_rl.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct LearnerConfig {
    pub ppo: PpoConfig,
    pub critic: CriticKind,
    /// CVaR level eta in (0, 1]; 0.5 = RALL, 1.0 = risk neutral (IQN critic only).
    /// Unset: [`DEFAULT_CVAR_ETA`] unless `distortion` is set; setting both is refused.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub cvar_eta: Option<f32>,
    /// Another distortion (e.g. Wang) instead of `cvar_eta` (IQN critic only).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub distortion: Option<Distortion>,
    /// Actor hidden sizes (ELU).
    pub actor_hidden: Vec<usize>,
    /// Critic hidden sizes (ELU); for IQN the last one is the merge width.
    pub critic_hidden: Vec<usize>,
    /// Initial action std.
    pub init_noise_std: f32,
    /// Cosine basis size of the tau embedding: `cos(pi i tau)`, `i = 0..num_cos`.
    pub num_cos: usize,
    /// `N`: taus ~ U[0,1] per mini-batch for the critic loss.
    pub num_taus: usize,
    /// `N'`: target samples per transition.
    pub num_target_taus: usize,
    /// `K`: points of the fixed grid of the distorted value.
    pub num_value_taus: usize,
    /// Huber threshold of the quantile loss.
    pub kappa: f32,
    /// Horizon parameter of the IQN targets (`storage` docs); 0 = 1-step targets.
    pub target_lambda: f32,
}

impl Default for LearnerConfig {
    fn default() -> Self {
        LearnerConfig {
            ppo: PpoConfig::default(),
            critic: CriticKind::Iqn,
            cvar_eta: None,
            distortion: None,
            actor_hidden: vec![512, 256, 128],
            critic_hidden: vec![512, 256, 128],
            init_noise_std: 1.0,
            num_cos: 64,
            num_taus: 64,
            num_target_taus: 64,
            num_value_taus: 64,
            kappa: 1.0,
            target_lambda: 0.95,
        }
    }
}

impl LearnerConfig {
    /// The distortion the actor follows: `distortion`, else `CVaR_cvar_eta`
    /// (`cvar_eta` defaults to [`DEFAULT_CVAR_ETA`]). The scalar critic has no
    /// distribution: it follows `V(s)`, i.e. `CVaR_1`.
    pub fn distortion(&self) -> Distortion {
        match (self.critic, self.distortion) {
            (CriticKind::Scalar, _) => Distortion::Cvar { eta: 1.0 },
            (CriticKind::Iqn, Some(d)) => d,
            (CriticKind::Iqn, None) => Distortion::Cvar {
                eta: self.cvar_eta.unwrap_or(DEFAULT_CVAR_ETA),
            },
        }
    }

    /// Short name of the risk measure, for run names and tables:
    /// `eta0.5`, `wang-0.75`, `scalar`.
    pub fn risk_label(&self) -> String {
        match self.distortion() {
            _ if self.critic == CriticKind::Scalar => "scalar".into(),
            Distortion::Cvar { eta } => format!("eta{eta}"),
            Distortion::Wang { lambda } => format!("wang{lambda}"),
        }
    }

    pub fn validate(&self) -> Result<()> {
        if let (Some(eta), Some(d)) = (self.cvar_eta, self.distortion) {
            bail!(
                "learner.cvar_eta ({eta}) and learner.distortion ({d:?}) are both set: the actor follows one distortion; keep one of the two keys"
            );
        }
        if self.critic == CriticKind::Scalar {
            if let Some(d) = self.distortion {
                bail!(
                    "learner.critic = \"scalar\" has no value distribution, so learner.distortion ({d:?}) would be ignored: remove it or use critic = \"iqn\""
                );
            }
            if let Some(eta) = self.cvar_eta.filter(|&e| e != 1.0) {
                bail!(
                    "learner.critic = \"scalar\" follows V(s) (CVaR_1), so learner.cvar_eta = {eta} would be ignored: remove it or use critic = \"iqn\""
                );
            }
        }
        if let Some(eta) = self.cvar_eta {
            Distortion::Cvar { eta }
                .validate()
                .map_err(|e| anyhow::anyhow!("learner.cvar_eta: {e}"))?;
        }
        self.distortion().validate()?;
        ensure!(
            !self.critic_hidden.is_empty(),
            "critic_hidden must not be empty"
        );
        ensure!(
            self.num_cos > 0
                && self.num_taus > 0
                && self.num_target_taus > 0
                && self.num_value_taus > 0,
            "num_cos, num_taus, num_target_taus and num_value_taus must be positive"
        );
        ensure!(self.kappa > 0.0, "kappa must be positive");
        ensure!(self.init_noise_std > 0.0, "init_noise_std must be positive");
        ensure!(
            (0.0..=1.0).contains(&self.target_lambda),
            "target_lambda must be in [0, 1]"
        );
        ensure!(
            self.ppo.num_mini_batches > 0,
            "num_mini_batches must be positive"
        );
        Ok(())
    }
}

/// One named `f32` tensor of the learner state (row-major).
#[derive(Clone, Debug, PartialEq)]
pub struct NamedTensor {
    pub name: String,
    pub shape: Vec<usize>,
    pub data: Vec<f32>,
}

/// PPO learner: actor, critic, Adam state, learning rate, update RNG.
pub struct Learner {
    cfg: LearnerConfig,
    ac: ActorCritic,
    opt: Optimizer,
    rng: ChaCha8Rng,
    /// The update's buffers, reused between updates.
    ws: Workspace,
}

impl Learner {
    /// Builds the networks from `seed` (ChaCha8): same seed, same weights.
    pub fn new(obs_dim: usize, act_dim: usize, cfg: &LearnerConfig, seed: u64) -> Result<Self> {
        cfg.validate()?;
        ensure!(
            obs_dim > 0 && act_dim > 0,
            "obs_dim and act_dim must be positive"
        );
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let actor = GaussianActor::new(
            obs_dim,
            act_dim,
            &cfg.actor_hidden,
            cfg.init_noise_std,
            &mut rng,
        );
        let critic = match cfg.critic {
            CriticKind::Iqn => Critic::Iqn(IqnCritic::new(
                obs_dim,
                &cfg.critic_hidden,
                cfg.num_cos,
                &mut rng,
            )),
            CriticKind::Scalar => {
                Critic::Scalar(ScalarCritic::new(obs_dim, &cfg.critic_hidden, &mut rng))
            }
        };
        let opt = Optimizer {
            actor: AdamState::new(actor.params.len()),
            critic: AdamState::new(critic.params().len()),
            step: 0,
            lr: cfg.ppo.learning_rate,
        };
        let ac = ActorCritic::new(actor, critic, cfg.distortion(), cfg.num_value_taus);
        Ok(Learner {
            cfg: cfg.clone(),
            ac,
            opt,
            rng,
            ws: Workspace::default(),
        })
    }

    pub fn config(&self) -> &LearnerConfig {
        &self.cfg
    }
    pub fn obs_dim(&self) -> usize {
        self.ac.obs_dim()
    }
    pub fn act_dim(&self) -> usize {
        self.ac.act_dim()
    }
    /// Current Adam learning rate (changed by the adaptive schedule).
    pub fn learning_rate(&self) -> f32 {
        self.opt.lr
    }
    /// The networks (for inference-only users such as eval and viz).
    pub fn actor_critic(&self) -> &ActorCritic {
        &self.ac
    }

    /// Samples actions for `n` observations (`obs`: `n x obs_dim`); see [`ActOutput`].
    pub fn act<R: Rng + ?Sized>(&self, obs: &[f32], rng: &mut R) -> ActOutput {
        self.ac.act(obs, rng)
    }
    /// Deterministic actions (policy mean), `n x act_dim`.
    pub fn act_mean(&self, obs: &[f32]) -> Vec<f32> {
        self.ac.act_mean(obs)
    }
    /// `Z_tau(s)`, `n x taus.len()` (the scalar critic repeats `V(s)`).
    pub fn value_quantiles(&self, obs: &[f32], taus: &[f32]) -> Vec<f32> {
        self.ac.value_quantiles(obs, taus)
    }
    /// The value the actor follows (`CVaR_eta(Z(s))`, or `V(s)`), `n`.
    pub fn distorted_value(&self, obs: &[f32]) -> Vec<f32> {
        self.ac.distorted_value(obs)
    }
    /// `Z_0.75(s) - Z_0.25(s)`, `n` (0 for the scalar critic).
    pub fn iqr(&self, obs: &[f32]) -> Vec<f32> {
        self.ac.iqr(obs)
    }

    /// One PPO update (epochs x mini-batches) on a full rollout.
    pub fn update(&mut self, rollout: &Rollout) -> Result<UpdateStats> {
        let ccfg = CriticLossConfig {
            num_taus: self.cfg.num_taus,
            num_target_taus: self.cfg.num_target_taus,
            kappa: self.cfg.kappa,
            target_lambda: self.cfg.target_lambda,
        };
        ppo::update(
            &mut self.ac,
            &mut self.opt,
            &mut self.ws,
            rollout,
            &self.cfg.ppo,
            &ccfg,
            &mut self.rng,
        )
    }

    /// Everything needed to resume: weights (`actor.*`, `critic.*`), Adam moments
    /// (`adam.m.*`, `adam.v.*`), `adam.step` and `lr` (shape `[1]`).
    /// (The update RNG is not included: a resumed run reseeds it.)
    pub fn state(&self) -> Vec<NamedTensor> {
        let mut out = Vec::new();
        let groups: [(&str, &ParamSet, &AdamState); 2] = [
            ("actor", &self.ac.actor.params, &self.opt.actor),
            ("critic", self.ac.critic.params(), &self.opt.critic),
        ];
        for (prefix, ps, adam) in groups {
            for (kind, data) in [("", &ps.data), ("adam.m.", &adam.m), ("adam.v.", &adam.v)] {
                for e in &ps.entries {
                    out.push(NamedTensor {
                        name: format!("{kind}{prefix}.{}", e.name),
                        shape: e.shape.clone(),
                        data: data[e.offset..e.offset + e.len()].to_vec(),
                    });
                }
            }
        }
        out.push(NamedTensor {
            name: "adam.step".into(),
            shape: vec![1],
            data: vec![self.opt.step as f32],
        });
        out.push(NamedTensor {
            name: "lr".into(),
            shape: vec![1],
            data: vec![self.opt.lr],
        });
        out
    }

    /// Restores [`Self::state`]. Refuses (changing nothing) a missing tensor or a
    /// shape mismatch, naming the tensor and both shapes. Extra tensors (e.g. the
    /// runner's own) are ignored.
    pub fn load_state(&mut self, tensors: &[NamedTensor]) -> Result<()> {
        let expected = self.state();
        let find = |name: &str| tensors.iter().find(|t| t.name == name);
        let mut picked = Vec::with_capacity(expected.len());
        for e in &expected {
            let Some(t) = find(&e.name) else {
                bail!(
                    "checkpoint is missing tensor `{}` (expected shape {:?})",
                    e.name,
                    e.shape
                );
            };
            if t.shape != e.shape || t.data.len() != e.data.len() {
                bail!(
                    "tensor `{}` has shape {:?} in the checkpoint but {:?} in this learner",
                    e.name,
                    t.shape,
                    e.shape
                );
            }
            picked.push(t);
        }
        let mut it = picked.into_iter();
        let Learner { ac, opt, .. } = self;
        let groups: [(&mut ParamSet, &mut AdamState); 2] = [
            (&mut ac.actor.params, &mut opt.actor),
            (ac.critic.params_mut(), &mut opt.critic),
        ];
        for (ps, adam) in groups {
            for which in 0..3 {
                for e in &ps.entries {
                    let t = it.next().expect("same order as state()");
                    let dst = match which {
                        0 => &mut ps.data,
                        1 => &mut adam.m,
                        _ => &mut adam.v,
                    };
                    dst[e.offset..e.offset + e.len()].copy_from_slice(&t.data);
                }
            }
        }
        opt.step = it.next().expect("adam.step").data[0] as u64;
        opt.lr = it.next().expect("lr").data[0];
        Ok(())
    }
}
