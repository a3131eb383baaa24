//! The facade the runner calls: [`Learner`] owns the networks, the optimizer and
//! the update RNG; [`LearnerConfig`] holds every hyper-parameter.

use super::actor_critic::ActorCritic;
use super::adam::AdamState;
pub use super::adaptation::AdaptationConfig;
use super::adaptation::{self, adaptation_offset, AdaptationOptimizer, Regression};
pub use super::checkpoint::NamedTensor;
use super::collective::{Collective, SingleProcess};
use super::critic::CriticKind;
use super::layout::ObsLayout;
use super::nets::{GaussianActor, InputSel, LatentSource, ParamSet};
use super::normalizer::EmpiricalNormalizer;
use super::ppo::{
    self, check_count, check_f32, CriticLossConfig, Optimizer, PpoConfig, UpdateStats, Workspace,
};
use super::risk::Distortion;
use super::storage::{ActOutput, Rollout};
use anyhow::{bail, ensure, Result};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

/// RMA's encoder: `z = MLP(group)`, appended to the actor's inputs (phase 1).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct EncoderConfig {
    /// Observation group the encoder reads (RMA: the privileged environment factors).
    pub input: String,
    /// Hidden sizes (ELU); RMA's code: 256-128. At most 16 layers, each 1..=8192.
    pub hidden: Vec<usize>,
    /// Latent size; RMA: 8. 1..=8192.
    pub latent_dim: usize,
}

impl Default for EncoderConfig {
    fn default() -> Self {
        EncoderConfig {
            input: "privileged".into(),
            hidden: vec![256, 128],
            latent_dim: 8,
        }
    }
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
    /// Actor hidden sizes (ELU): at most 16 layers, each 1..=8192.
    pub actor_hidden: Vec<usize>,
    /// Critic hidden sizes (ELU); for IQN the last one is the merge width. 1 to
    /// 16 layers, each 1..=8192.
    pub critic_hidden: Vec<usize>,
    /// Initial action std, in [1e-12, 1e3].
    pub init_noise_std: f32,
    /// The actor's output layer (weights and bias) is multiplied by this after
    /// PyTorch's default init: 0.01 starts every robot near the default pose
    /// (Andrychowicz et al. 2021). 1 = rsl_rl's init. In (0, 1e3].
    #[serde(skip_serializing_if = "is_one")]
    pub actor_output_init_scale: f32,
    /// Cosine basis size of the tau embedding: `cos(pi i tau)`, `i = 0..num_cos`;
    /// 1..=8192.
    pub num_cos: usize,
    /// `N`: taus ~ U[0,1] per mini-batch for the critic loss; 1..=8192.
    pub num_taus: usize,
    /// `N'`: target samples per transition; 1..=8192.
    pub num_target_taus: usize,
    /// `K`: points of the fixed grid of the distorted value; 1..=8192.
    pub num_value_taus: usize,
    /// Huber threshold of the quantile loss, in [1e-12, 1e6].
    pub kappa: f32,
    /// Horizon parameter of the IQN targets (`storage` docs); 0 = 1-step
    /// targets. In [0, 1].
    pub target_lambda: f32,
    /// Observation groups the actor reads directly, in order.
    pub actor_inputs: Vec<String>,
    /// Observation groups the critic reads, in order (e.g. add "privileged" for
    /// an asymmetric critic).
    pub critic_inputs: Vec<String>,
    /// RMA's encoder of privileged information (phase 1); `None`: no latent.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub encoder: Option<EncoderConfig>,
    /// RMA's adaptation module (phase 2); needs `encoder`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub adaptation: Option<AdaptationConfig>,
    /// Normalise every observation column by the running mean and std of the
    /// observations collected so far (rsl_rl 2.x's `empirical_normalization`;
    /// see `normalizer`). Off: the networks read the observation scales of
    /// `env.observation` (legged_gym's) directly.
    #[serde(skip_serializing_if = "is_false")]
    pub obs_normalization: bool,
}

fn is_false(b: &bool) -> bool {
    !*b
}

fn is_one(x: &f32) -> bool {
    *x == 1.0
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
            actor_output_init_scale: 1.0,
            num_cos: 64,
            num_taus: 64,
            num_target_taus: 64,
            num_value_taus: 64,
            kappa: 1.0,
            target_lambda: 0.95,
            actor_inputs: vec!["policy".into()],
            critic_inputs: vec!["policy".into()],
            encoder: None,
            adaptation: None,
            obs_normalization: false,
        }
    }
}

impl LearnerConfig {
    /// The distortion the actor follows: `distortion`, else `CVaR_cvar_eta`
    /// (`cvar_eta` defaults to [`DEFAULT_CVAR_ETA`]). A critic without quantiles
    /// (the scalar one) has no distribution: it follows `V(s)`, i.e. `CVaR_1`.
    pub fn distortion(&self) -> Distortion {
        match self.distortion {
            _ if !self.critic.has_quantiles() => Distortion::Cvar { eta: 1.0 },
            Some(d) => d,
            None => Distortion::Cvar {
                eta: self.cvar_eta.unwrap_or(DEFAULT_CVAR_ETA),
            },
        }
    }

    /// Short name of the risk measure, for run names and tables:
    /// `eta0.5`, `wang-0.75`, or the name of a critic without quantiles (`scalar`).
    pub fn risk_label(&self) -> String {
        match self.distortion() {
            _ if !self.critic.has_quantiles() => self.critic.name().into(),
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
        if !self.critic.has_quantiles() {
            let critic = self.critic;
            if let Some(d) = self.distortion {
                bail!(
                    "learner.critic = \"{critic}\" has no value distribution, so learner.distortion ({d:?}) would be ignored: remove it or use critic = \"iqn\""
                );
            }
            if let Some(eta) = self.cvar_eta.filter(|&e| e != 1.0) {
                bail!(
                    "learner.critic = \"{critic}\" follows V(s) (CVaR_1), so learner.cvar_eta = {eta} would be ignored: remove it or use critic = \"iqn\""
                );
            }
        }
        if let Some(eta) = self.cvar_eta {
            Distortion::Cvar { eta }
                .validate()
                .map_err(|e| anyhow::anyhow!("learner.cvar_eta: {e}"))?;
        }
        self.distortion().validate()?;
        self.ppo.validate()?;
        ensure!(
            !self.critic_hidden.is_empty(),
            "critic_hidden must not be empty"
        );
        self.validate_sizes()?;
        check_f32("learner.kappa", self.kappa, 1e-12, 1e6)?;
        check_f32("learner.init_noise_std", self.init_noise_std, 1e-12, 1e3)?;
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
            self.actor_output_init_scale.is_finite()
                && self.actor_output_init_scale > 0.0
                && self.actor_output_init_scale <= 1e3,
            "learner.actor_output_init_scale must be in (0, 1e3] (1 = rsl_rl's init), got {}",
            self.actor_output_init_scale
        );
        ensure!(
            (0.0..=1.0).contains(&self.target_lambda),
            "target_lambda must be in [0, 1]"
        );
        ensure!(
            self.ppo.num_mini_batches > 0,
            "num_mini_batches must be positive"
        );
        ensure!(
            !self.actor_inputs.is_empty() && !self.critic_inputs.is_empty(),
            "learner.actor_inputs and learner.critic_inputs must name at least one observation group"
        );
        if let Some(e) = &self.encoder {
            ensure!(
                e.latent_dim > 0,
                "learner.encoder.latent_dim must be positive"
            );
        }
        ensure!(
            !(self.obs_normalization && self.encoder.is_some()),
            "learner.obs_normalization is not supported with RMA's encoder yet: its phase 2 adds the history group, which the statistics of phase 1 do not cover; remove one of the two"
        );
        if let Some(a) = &self.adaptation {
            ensure!(
                self.encoder.is_some(),
                "learner.adaptation regresses the encoder's latent: it needs learner.encoder"
            );
            ensure!(
                a.learning_rate > 0.0 && a.epochs > 0 && a.mini_batches > 0,
                "learner.adaptation: learning_rate, epochs and mini_batches must be positive"
            );
        }
        Ok(())
    }
}

/// The largest hidden layer, latent or tau basis a config may ask for.
pub const MAX_LAYER_WIDTH: usize = 8192;
/// The most hidden layers a network may have.
pub const MAX_HIDDEN_LAYERS: usize = 16;

fn check_hidden(key: &str, sizes: &[usize]) -> Result<()> {
    ensure!(
        sizes.len() <= MAX_HIDDEN_LAYERS,
        "{key} has {} layers, at most {MAX_HIDDEN_LAYERS}",
        sizes.len()
    );
    for (i, &w) in sizes.iter().enumerate() {
        check_count(&format!("{key}[{i}]"), w, 1, MAX_LAYER_WIDTH)?;
    }
    Ok(())
}

impl LearnerConfig {
    /// Layer widths and sample counts within their bounds (named by key).
    fn validate_sizes(&self) -> Result<()> {
        check_hidden("learner.actor_hidden", &self.actor_hidden)?;
        check_hidden("learner.critic_hidden", &self.critic_hidden)?;
        for (key, v) in [
            ("learner.num_cos", self.num_cos),
            ("learner.num_taus", self.num_taus),
            ("learner.num_target_taus", self.num_target_taus),
            ("learner.num_value_taus", self.num_value_taus),
        ] {
            check_count(key, v, 1, MAX_LAYER_WIDTH)?;
        }
        if let Some(e) = &self.encoder {
            check_hidden("learner.encoder.hidden", &e.hidden)?;
            check_count(
                "learner.encoder.latent_dim",
                e.latent_dim,
                1,
                MAX_LAYER_WIDTH,
            )?;
        }
        if let Some(a) = &self.adaptation {
            check_hidden("learner.adaptation.hidden", &a.hidden)?;
            check_f32(
                "learner.adaptation.learning_rate",
                a.learning_rate,
                1e-12,
                1.0,
            )?;
            check_count("learner.adaptation.epochs", a.epochs, 1, 1000)?;
            check_count(
                "learner.adaptation.mini_batches",
                a.mini_batches,
                1,
                1 << 20,
            )?;
            check_count(
                "learner.adaptation.iterations",
                a.iterations,
                1,
                100_000_000,
            )?;
        }
        Ok(())
    }
}

/// `rollout` with every observation (rows, time-outs' final ones, the last ones)
/// normalised by `norm`, copied into `slot`'s buffers (kept between updates).
fn normalized_rollout<'a>(
    slot: &'a mut Option<Rollout>,
    rollout: &Rollout,
    norm: &EmpiricalNormalizer,
) -> &'a Rollout {
    let copy = match slot {
        Some(copy) => {
            copy.clone_from(rollout);
            copy
        }
        None => slot.insert(rollout.clone()),
    };
    norm.normalize_in_place(&mut copy.obs);
    norm.normalize_in_place(&mut copy.last_obs);
    for (_, o) in &mut copy.final_obs {
        norm.normalize_in_place(o);
    }
    copy
}

/// Layout tag of [`Learner::exact_state`] and its length in bytes.
const EXACT_STATE_TAG: &[u8; 8] = b"rall-ls1";
const EXACT_STATE_LEN: usize = 8 + 32 + 8 + 16 + 8 + 8;

/// PPO learner: actor, critic, Adam state, learning rate, update RNG.
pub struct Learner {
    cfg: LearnerConfig,
    ac: ActorCritic,
    opt: Optimizer,
    rng: ChaCha8Rng,
    /// The update's buffers, reused between updates.
    ws: Workspace,
    /// RMA phase 2's optimizer (with `adaptation` configured).
    adapt_opt: Option<AdaptationOptimizer>,
    /// The rollout with normalised observations, reused between updates
    /// (with `obs_normalization`).
    normalized: Option<Rollout>,
}

impl Learner {
    /// Builds the networks from `seed` (ChaCha8): same seed, same weights. The
    /// observation row is one group, "policy", of `obs_dim` values.
    pub fn new(obs_dim: usize, act_dim: usize, cfg: &LearnerConfig, seed: u64) -> Result<Self> {
        Learner::with_layout(&ObsLayout::policy_only(obs_dim), act_dim, cfg, seed)
    }

    /// Builds the networks over an observation row of named groups: each network
    /// reads the groups its config names (an unknown group is refused, named).
    pub fn with_layout(
        layout: &ObsLayout,
        act_dim: usize,
        cfg: &LearnerConfig,
        seed: u64,
    ) -> Result<Self> {
        cfg.validate()?;
        let obs_dim = layout.width();
        ensure!(
            obs_dim > 0 && act_dim > 0,
            "obs_dim and act_dim must be positive"
        );
        let select = |groups: &[String], who: &str| -> Result<InputSel> {
            let ranges = groups
                .iter()
                .map(|g| layout.require(g, who))
                .collect::<Result<Vec<_>>>()?;
            Ok(InputSel {
                ranges,
                row_width: obs_dim,
            })
        };
        let actor_in = select(&cfg.actor_inputs, "learner.actor_inputs")?;
        let critic_in = select(&cfg.critic_inputs, "learner.critic_inputs")?;
        let encoder_in = match &cfg.encoder {
            Some(e) => Some(select(
                std::slice::from_ref(&e.input),
                "learner.encoder.input",
            )?),
            None => None,
        };
        // the adaptation module exists once its input does (RMA: the history
        // group is added to the observation for phase 2)
        let adaptation_in = match &cfg.adaptation {
            Some(a) if layout.range(&a.input).is_some() => Some(select(
                std::slice::from_ref(&a.input),
                "learner.adaptation.input",
            )?),
            _ => None,
        };
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let latent_dim = cfg.encoder.as_ref().map_or(0, |e| e.latent_dim);
        let mut actor = GaussianActor::with_inputs(
            actor_in,
            latent_dim,
            act_dim,
            &cfg.actor_hidden,
            cfg.init_noise_std,
            &mut rng,
        );
        let critic = cfg.critic.build(critic_in, cfg, &mut rng)?;
        if cfg.actor_output_init_scale != 1.0 {
            actor.scale_output_layer(cfg.actor_output_init_scale);
        }
        // after the critic, so that configs without them keep their initial weights
        if let (Some(e), Some(input)) = (&cfg.encoder, encoder_in) {
            actor.add_encoder(input, &e.hidden, &mut rng);
        }
        if let (Some(a), Some(input)) = (&cfg.adaptation, adaptation_in) {
            actor.add_adaptation(input, &a.hidden, &mut rng);
        }
        let opt = Optimizer {
            actor: AdamState::new(actor.params.len()),
            critic: AdamState::new(critic.params().len()),
            step: 0,
            lr: cfg.ppo.learning_rate,
        };
        let adapt_opt = adaptation_offset(&actor).map(|off| AdaptationOptimizer {
            adam: AdamState::new(actor.params.len() - off),
            step: 0,
        });
        let mut ac = ActorCritic::new(actor, critic, cfg.distortion(), cfg.num_value_taus);
        if cfg.obs_normalization {
            ac.obs_norm = Some(EmpiricalNormalizer::new(obs_dim));
        }
        Ok(Learner {
            cfg: cfg.clone(),
            ac,
            opt,
            rng,
            ws: Workspace::default(),
            adapt_opt,
            normalized: None,
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
    /// Sets the action std to `std` in every dimension and clears the Adam
    /// moments of the log-std, so its updates start afresh at the new level.
    pub fn reset_action_std(&mut self, std: f32) {
        let off = self.ac.actor.log_std_offset();
        let dims = off..off + self.ac.act_dim();
        self.ac.actor.params.data[dims.clone()].fill(std.ln());
        self.opt.actor.m[dims.clone()].fill(0.0);
        self.opt.actor.v[dims].fill(0.0);
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

    /// Where the actor's latent comes from (RMA: encoder for the teacher,
    /// adaptation module for the student).
    pub fn latent_source(&self) -> LatentSource {
        self.ac.actor.latent_source()
    }
    pub fn set_latent_source(&mut self, source: LatentSource) {
        self.ac.actor.set_latent_source(source);
    }

    /// RMA phase 2: regresses the adaptation module's z on the encoder's over
    /// `obs` (`rows x obs_dim`).
    pub fn regress_latent(&mut self, obs: &[f32], rows: usize) -> Result<Regression> {
        let (Some(cfg), Some(opt)) = (&self.cfg.adaptation, &mut self.adapt_opt) else {
            bail!("this learner has no adaptation module (learner.adaptation)");
        };
        adaptation::regress(&mut self.ac.actor, opt, cfg, obs, rows, &mut self.rng)
    }

    /// Mean squared error of the adaptation module's z against the encoder's.
    pub fn latent_mse(&self, obs: &[f32], rows: usize) -> Result<f32> {
        adaptation::latent_mse(&self.ac.actor, obs, rows)
    }

    /// One PPO update (epochs x mini-batches) on a full rollout.
    pub fn update(&mut self, rollout: &Rollout) -> Result<UpdateStats> {
        self.update_with(rollout, &SingleProcess)
    }

    /// [`Self::update`] as one rank of a data-parallel run: every rank calls it
    /// on its own rollout (same shape) and takes the same step (see `ppo`).
    pub fn update_with(&mut self, rollout: &Rollout, comm: &dyn Collective) -> Result<UpdateStats> {
        let ccfg = CriticLossConfig {
            num_taus: self.cfg.num_taus,
            num_target_taus: self.cfg.num_target_taus,
            kappa: self.cfg.kappa,
            target_lambda: self.cfg.target_lambda,
        };
        // with a normaliser the update reads what the actor read at collection: the
        // rollout normalised with the same statistics; they learn from it afterwards
        let input = match &self.ac.obs_norm {
            Some(norm) => normalized_rollout(&mut self.normalized, rollout, norm),
            None => rollout,
        };
        let stats = ppo::update(
            &mut self.ac,
            &mut self.opt,
            &mut self.ws,
            input,
            &self.cfg.ppo,
            &ccfg,
            &mut self.rng,
            comm,
        )?;
        if let Some(norm) = &mut self.ac.obs_norm {
            norm.update(&rollout.obs, comm);
        }
        Ok(stats)
    }

    /// The observation normaliser (`learner.obs_normalization`), if any.
    pub fn obs_normalizer(&self) -> Option<&EmpiricalNormalizer> {
        self.ac.obs_norm.as_ref()
    }

    /// Everything needed to resume: weights (`actor.*`, `critic.*`), Adam moments
    /// (`adam.m.*`, `adam.v.*`), `adam.step` and `lr` (shape `[1]`).
    /// (The update RNG and the integer step counts are [`Self::exact_state`].)
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
        if let Some(a) = &self.adapt_opt {
            for (name, data) in [("adapt_adam.m", &a.adam.m), ("adapt_adam.v", &a.adam.v)] {
                out.push(NamedTensor {
                    name: name.into(),
                    shape: vec![data.len()],
                    data: data.clone(),
                });
            }
            out.push(NamedTensor {
                name: "adapt_adam.step".into(),
                shape: vec![1],
                data: vec![a.step as f32],
            });
        }
        if let Some(n) = &self.ac.obs_norm {
            out.extend(n.state());
        }
        out
    }

    /// What a bit-identical resume needs beyond [`Self::state`], as bytes: the
    /// update RNG (ChaCha8 seed, stream, word position) and the optimisers' step
    /// counts as integers ([`Self::state`] keeps `adam.step` as f32 for older readers).
    pub fn exact_state(&self) -> Vec<u8> {
        let mut out = Vec::with_capacity(EXACT_STATE_LEN);
        out.extend_from_slice(EXACT_STATE_TAG);
        out.extend_from_slice(&self.rng.get_seed());
        out.extend_from_slice(&self.rng.get_stream().to_le_bytes());
        out.extend_from_slice(&self.rng.get_word_pos().to_le_bytes());
        out.extend_from_slice(&self.opt.step.to_le_bytes());
        let adapt_step = self.adapt_opt.as_ref().map_or(0, |a| a.step);
        out.extend_from_slice(&adapt_step.to_le_bytes());
        out
    }

    /// Restores [`Self::exact_state`] (after [`Self::load_state`]).
    pub fn load_exact_state(&mut self, bytes: &[u8]) -> Result<()> {
        ensure!(
            bytes.len() == EXACT_STATE_LEN && bytes.starts_with(EXACT_STATE_TAG),
            "the learner's exact state has {} bytes, expected {EXACT_STATE_LEN} starting with {:?}",
            bytes.len(),
            String::from_utf8_lossy(EXACT_STATE_TAG)
        );
        let rest = &bytes[EXACT_STATE_TAG.len()..];
        let seed: [u8; 32] = rest[..32].try_into().expect("length checked");
        let u64_at = |at: usize| u64::from_le_bytes(rest[at..at + 8].try_into().expect("checked"));
        let word_pos = u128::from_le_bytes(rest[40..56].try_into().expect("length checked"));
        let mut rng = ChaCha8Rng::from_seed(seed);
        rng.set_stream(u64_at(32));
        rng.set_word_pos(word_pos);
        self.rng = rng;
        self.opt.step = u64_at(56);
        if let Some(a) = &mut self.adapt_opt {
            a.step = u64_at(64);
        }
        Ok(())
    }

    /// Restores [`Self::state`]. Refuses (changing nothing) a missing tensor or a
    /// shape mismatch, naming the tensor and both shapes. Extra tensors (e.g. the
    /// runner's own) are ignored.
    /// [`Self::load_state`], keeping this learner's own values for the tensors
    /// `tensors` lacks whose name `keep_own` accepts (e.g. a module added since
    /// the checkpoint: RMA's adaptation module at the start of phase 2).
    pub fn load_state_keeping(
        &mut self,
        tensors: &[NamedTensor],
        keep_own: impl Fn(&str) -> bool,
    ) -> Result<()> {
        let mut merged = Vec::new();
        for own in self.state() {
            match tensors.iter().find(|t| t.name == own.name) {
                Some(t) => merged.push(t.clone()),
                None if keep_own(&own.name) => merged.push(own),
                None => bail!(
                    "checkpoint is missing tensor `{}` (expected shape {:?})",
                    own.name,
                    own.shape
                ),
            }
        }
        self.load_state(&merged)
    }

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
        if self.ac.obs_norm.is_some() {
            let [mean, var, count] = &picked[picked.len() - 3..] else {
                unreachable!("state() ends with the normaliser's three tensors")
            };
            EmpiricalNormalizer::check(&mean.data, &var.data, &count.data)?;
        }
        let mut it = picked.into_iter();
        let Learner {
            ac, opt, adapt_opt, ..
        } = self;
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
        if let Some(a) = adapt_opt {
            a.adam
                .m
                .copy_from_slice(&it.next().expect("adapt_adam.m").data);
            a.adam
                .v
                .copy_from_slice(&it.next().expect("adapt_adam.v").data);
            a.step = it.next().expect("adapt_adam.step").data[0] as u64;
        }
        if let Some(n) = &mut ac.obs_norm {
            let (mean, var, count) = (
                it.next().expect("obs_norm.mean"),
                it.next().expect("obs_norm.var"),
                it.next().expect("obs_norm.count"),
            );
            n.load(&mean.data, &var.data, &count.data)?;
        }
        Ok(())
    }
}
