//! The critic behind the PPO update: the [`Critic`] trait, and the registry that
//! maps `learner.critic = "<name>"` (configs, checkpoints, `--critic`) to a
//! constructor.
//!
//! A critic inside the crate is one file in this folder and one line in
//! [`BUILT_IN`]. A critic defined outside the crate calls [`register`] once,
//! before any config that names it is read. The update owns everything else
//! (advantage normalisation, the clipped surrogate, gradient clipping, Adam, the
//! sums across ranks); checkpoints store the critic's [`ParamSet`] as `critic.*`.

pub mod iqn;
pub mod scalar;

use super::learner::LearnerConfig;
use super::nets::{InputSel, ParamSet};
use super::ppo::{CriticLossConfig, PpoConfig};
use super::storage::Rollout;
use anyhow::{bail, ensure, Result};
use rand::RngCore;
use serde::{Deserialize, Deserializer, Serialize, Serializer};
use std::any::Any;
use std::fmt;
use std::sync::RwLock;

/// A value network the actor's advantages come from, trained by its own loss.
///
/// Observations are `n x obs_dim` row-major (already normalised when the learner
/// normalises). The update calls, per update, [`Critic::targets`] once over the
/// whole rollout, then per mini-batch [`Critic::draw_samples`] once and, on each
/// thread's share of its rows, [`Critic::forward_mini_batch`],
/// [`Critic::value_loss`] and [`Critic::backward_mini_batch`].
pub trait Critic: CloneCritic + Send + Sync + fmt::Debug {
    /// The trainable parameters (checkpointed as `critic.<entry name>`).
    fn params(&self) -> &ParamSet;
    fn params_mut(&mut self) -> &mut ParamSet;

    /// The value the actor follows, `n` values: a critic with quantiles averages
    /// `Z(s)` over `value_taus` (the distortion's fixed grid); one without returns `V(s)`.
    fn distorted_value(&self, obs: &[f32], n: usize, value_taus: &[f32]) -> Vec<f32>;

    /// `Z_tau(s)` for each observation and tau, `n x taus.len()` (the viewer and
    /// the IQR read it). Default, for a critic without a distribution: its value
    /// for every tau.
    fn value_quantiles(&self, obs: &[f32], n: usize, taus: &[f32]) -> Vec<f32> {
        self.distorted_value(obs, n, &[])
            .iter()
            .flat_map(|&v| std::iter::repeat_n(v, taus.len()))
            .collect()
    }

    /// Values, GAE advantages and the regression targets of every transition,
    /// from the collection-time critic. `cache` is this call's own, kept between updates.
    fn targets(
        &self,
        input: &TargetInput<'_>,
        cache: &mut CriticCache,
        rng: &mut dyn RngCore,
    ) -> Targets;

    /// Samples shared by every row of one mini-batch (IQN: its taus), pushed onto
    /// the empty `samples`. Default: none.
    fn draw_samples(
        &self,
        _samples: &mut Vec<f32>,
        _ccfg: &CriticLossConfig,
        _rng: &mut dyn RngCore,
    ) {
    }

    /// Forward pass over `n` rows, keeping what the loss and backward need in `cache`.
    fn forward_mini_batch(&self, obs: &[f32], n: usize, samples: &[f32], cache: &mut CriticCache);

    /// The loss of the rows of the last forward pass, as this shard's share of the
    /// mini-batch's mean, before `value_loss_coef`; `d_out` is set to its gradient
    /// with respect to the critic's outputs, times `value_loss_coef`, as a share of
    /// the mini-batch's mean gradient.
    fn value_loss(
        &self,
        input: &LossInput<'_>,
        cache: &mut CriticCache,
        d_out: &mut Vec<f32>,
    ) -> f64;

    /// Adds the gradient of the parameters to `grads`, from `d_out` of
    /// [`Critic::value_loss`] (may be used as scratch).
    fn backward_mini_batch(
        &self,
        grads: &mut [f32],
        obs: &[f32],
        n: usize,
        cache: &mut CriticCache,
        d_out: &mut Vec<f32>,
    );
}

/// `Box<dyn Critic>: Clone` for every `Critic + Clone`.
pub trait CloneCritic {
    fn clone_box(&self) -> Box<dyn Critic>;
}

impl<T: Critic + Clone + 'static> CloneCritic for T {
    fn clone_box(&self) -> Box<dyn Critic> {
        Box::new(self.clone())
    }
}

impl Clone for Box<dyn Critic> {
    fn clone(&self) -> Self {
        self.clone_box()
    }
}

/// What [`Critic::targets`] reads.
pub struct TargetInput<'a> {
    pub rollout: &'a Rollout,
    /// The time-outs' final observations (`rollout.final_obs`), rows concatenated.
    pub finals: &'a [f32],
    /// The distortion's fixed grid (`ActorCritic::value_taus`).
    pub value_taus: &'a [f32],
    pub cfg: &'a PpoConfig,
    pub ccfg: &'a CriticLossConfig,
}

/// Per-transition training targets, computed once per update.
pub struct Targets {
    /// GAE advantages (`T*E`).
    pub adv: Vec<f32>,
    /// The same number of regression targets per transition: scalar, `returns =
    /// A + V` (`T*E`); IQN, `N'` target samples per transition.
    pub value_targets: Vec<f32>,
}

/// What [`Critic::value_loss`] reads besides its forward cache.
pub struct LossInput<'a> {
    /// The mini-batch's [`Critic::draw_samples`].
    pub samples: &'a [f32],
    /// This shard's rows of [`Targets::value_targets`].
    pub targets: &'a [f32],
    /// Rows of this shard.
    pub rows: usize,
    /// Rows of the whole mini-batch.
    pub batch: usize,
    pub cfg: &'a PpoConfig,
    pub ccfg: &'a CriticLossConfig,
}

/// A critic's buffers of one kind of call (forward caches), kept between calls
/// so that a steady-state update allocates nothing. A clone starts empty.
#[derive(Default)]
pub struct CriticCache(Option<Box<dyn Any + Send + Sync>>);

impl CriticCache {
    /// The buffers as a `T`, a default one on first use.
    pub fn get<T: Default + Send + Sync + 'static>(&mut self) -> &mut T {
        if !self.0.as_ref().is_some_and(|b| b.is::<T>()) {
            self.0 = Some(Box::<T>::default());
        }
        self.0
            .as_mut()
            .and_then(|b| b.downcast_mut())
            .expect("set to a T above")
    }
}

impl Clone for CriticCache {
    fn clone(&self) -> Self {
        CriticCache::default()
    }
}

impl fmt::Debug for CriticCache {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str("CriticCache")
    }
}

/// Builds a critic reading the `input` columns of the observation row, its
/// initial weights drawn from `rng`.
pub type BuildCritic =
    fn(input: InputSel, cfg: &LearnerConfig, rng: &mut dyn RngCore) -> Result<Box<dyn Critic>>;

/// One entry of the registry.
#[derive(Clone, Copy)]
pub struct CriticSpec {
    /// The value of `learner.critic` (lowercase letters, digits, `-`, `_`).
    pub name: &'static str,
    /// The critic predicts quantiles `Z_tau(s)`: the actor follows the configured
    /// distortion of them and the meta controller can read their IQR. Without:
    /// the actor follows `V(s)` (`CVaR_1`) and a distortion is refused.
    pub has_quantiles: bool,
    pub build: BuildCritic,
}

/// The critics of this crate.
const BUILT_IN: [CriticSpec; 2] = [iqn::SPEC, scalar::SPEC];

/// The critics registered from outside the crate.
static REGISTERED: RwLock<Vec<CriticSpec>> = RwLock::new(Vec::new());

fn all_specs() -> Vec<CriticSpec> {
    let registered = REGISTERED.read().unwrap_or_else(|e| e.into_inner());
    BUILT_IN.iter().chain(registered.iter()).copied().collect()
}

fn find(name: &str) -> Option<CriticSpec> {
    all_specs().into_iter().find(|s| s.name == name)
}

/// Adds a critic to the registry, so that `learner.critic = "<spec.name>"`
/// builds it. Refuses a name already taken (built in or registered) and a name
/// that is not lowercase letters, digits, `-` and `_`.
pub fn register(spec: CriticSpec) -> Result<CriticKind> {
    let name = spec.name;
    ensure!(
        !name.is_empty()
            && name
                .bytes()
                .all(|b| b.is_ascii_lowercase() || b.is_ascii_digit() || b == b'-' || b == b'_'),
        "critic name {name:?}: use lowercase letters, digits, '-' and '_'"
    );
    let mut registered = REGISTERED.write().unwrap_or_else(|e| e.into_inner());
    if BUILT_IN
        .iter()
        .chain(registered.iter())
        .any(|s| s.name == name)
    {
        bail!("critic name {name:?} is already taken: register the critic under another name");
    }
    registered.push(spec);
    Ok(CriticKind(name))
}

/// The critic a config names: one of the registry's names (`"iqn"`, `"scalar"`,
/// or a registered one), in TOML as `learner.critic = "iqn"`.
#[derive(Clone, Copy, PartialEq, Eq, Hash)]
pub struct CriticKind(&'static str);

#[allow(non_upper_case_globals)] // named like the variants they were
impl CriticKind {
    /// IQN value distribution `Z(s)`; the actor follows its distorted value (RALL).
    pub const Iqn: CriticKind = CriticKind(iqn::SPEC.name);
    /// Scalar `V(s)` (risk-neutral PPO baseline).
    pub const Scalar: CriticKind = CriticKind(scalar::SPEC.name);
}

impl CriticKind {
    /// The registered critic named `name`; an unknown name is refused, naming it
    /// and the known ones.
    pub fn from_name(name: &str) -> Result<CriticKind> {
        match find(name) {
            Some(spec) => Ok(CriticKind(spec.name)),
            None => {
                let names: Vec<&str> = all_specs().iter().map(|s| s.name).collect();
                let (last, rest) = names.split_last().expect("built-in critics");
                bail!("unknown critic {name:?}: use {} or {last}", rest.join(", "))
            }
        }
    }

    pub fn name(self) -> &'static str {
        self.0
    }

    /// Its registry entry (a `CriticKind` exists only for a registered name).
    pub fn spec(self) -> CriticSpec {
        find(self.0).expect("a CriticKind names a registered critic")
    }

    /// See [`CriticSpec::has_quantiles`].
    pub fn has_quantiles(self) -> bool {
        self.spec().has_quantiles
    }

    /// The critic, reading `input`, initialised from `rng`.
    pub fn build(
        self,
        input: InputSel,
        cfg: &LearnerConfig,
        rng: &mut dyn RngCore,
    ) -> Result<Box<dyn Critic>> {
        (self.spec().build)(input, cfg, rng)
    }
}

impl fmt::Debug for CriticKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.0)
    }
}

impl fmt::Display for CriticKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.0)
    }
}

impl Serialize for CriticKind {
    fn serialize<S: Serializer>(&self, s: S) -> std::result::Result<S::Ok, S::Error> {
        s.serialize_str(self.0)
    }
}

impl<'de> Deserialize<'de> for CriticKind {
    fn deserialize<D: Deserializer<'de>>(d: D) -> std::result::Result<Self, D::Error> {
        let name = String::deserialize(d)?;
        CriticKind::from_name(&name).map_err(serde::de::Error::custom)
    }
}
