//! The learner: networks, risk measures, rollout storage and the PPO update.
//! Compiles without MuJoCo (`cargo check --no-default-features --lib`) and uses
//! no other module of this crate.
//!
//! - [`nets`]: Gaussian actor, IQN critic, scalar critic (hand-written backward
//!   over [`mat`]'s GEMM; see `mat` for why not dfdx autograd).
//! - [`critic`]: the [`Critic`] trait the update trains, and the registry of
//!   critics by name (`learner.critic`).
//! - [`risk`]: distortions (CVaR, Wang), IQR, quantile Huber loss.
//! - [`storage`]: rollout buffer, GAE, IQN targets (construction documented there).
//! - [`ppo`]: the update.
//! - [`learner`]: the [`Learner`] facade and [`LearnerConfig`].
//! - [`checkpoint`]: atomic safetensors files with metadata.
//! - [`collective`]: sums across the ranks of a data-parallel run.
//! - [`normalizer`]: the empirical observation normaliser (opt-in).
//!
//! Cost at the defaults (obs 48, act 12, 256 envs x 24 steps, 5 x 4 mini-batches
//! of 1536; `benches/ppo.rs`, 2 cores with AVX-512): one update is ~71 GFLOP of
//! matmul and takes ~0.45-0.5 s with either critic (~140-170 GFLOP/s; plain GEMMs
//! of the same shapes reach ~210-280). Each mini-batch is split into one shard of
//! rows per thread (single-threaded kernels inside, gradients summed), see `ppo`.
//!
//! Typical loop (the runner's):
//! ```no_run
//! # use rall::learn::*;
//! # fn env_step(_: &[f32]) -> (Vec<f32>, Vec<f32>, Vec<bool>, Vec<bool>, Vec<f32>) { unimplemented!() }
//! # fn main() -> anyhow::Result<()> {
//! let cfg = LearnerConfig::default();
//! let (envs, steps, obs_dim, act_dim) = (256, 24, 48, 12);
//! let mut learner = Learner::new(obs_dim, act_dim, &cfg, 0)?;
//! let mut rng = rand::thread_rng();
//! let mut rollout = Rollout::new(steps, envs, obs_dim, act_dim);
//! let mut obs = vec![0.0; envs * obs_dim];
//! for _ in 0..steps {
//!     let out = learner.act(&obs, &mut rng);
//!     let (next, rew, done, time_out, final_obs) = env_step(&out.actions);
//!     rollout.push(&obs, &out, &rew, &done, &time_out, &final_obs)?;
//!     obs = next;
//! }
//! rollout.set_last_obs(&obs)?;
//! let stats = learner.update(&rollout)?;
//! # Ok(()) }
//! ```

pub mod actor_critic;
pub mod adam;
pub mod adaptation;
pub mod amx;
pub mod bf16_avx512;
pub mod checkpoint;
pub mod collective;
pub mod critic;
pub mod layout;
pub mod learner;
pub mod mat;
pub mod nets;
pub mod normalizer;
pub mod ppo;
pub mod risk;
pub mod storage;

pub use actor_critic::ActorCritic;
pub use checkpoint::{
    decode_checkpoint, load_checkpoint, parse_checkpoint, read_checkpoint, save_checkpoint,
    save_checkpoint_with, Checkpoint, CHECKSUM_PREFIX,
};
pub use collective::{Collective, SingleProcess};
pub use critic::{register, Critic, CriticKind, CriticSpec};
pub use layout::{gather_columns, relayout_rows, ObsLayout};
pub use learner::{AdaptationConfig, EncoderConfig, Learner, LearnerConfig, NamedTensor};
pub use nets::LatentSource;
pub use normalizer::EmpiricalNormalizer;
pub use ppo::{GradClip, LrSchedule, PpoConfig, UpdateStats, UpdateTimes};
pub use risk::{Distortion, IQR_TAUS};
pub use storage::{ActOutput, Rollout};
