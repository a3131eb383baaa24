//! The environment layer: one robot ([`Env`]) and N in parallel ([`VecEnv`]).
//!
//! - `config`: the task as data (TOML), validated with the offending key named.
//! - `state`: a plain snapshot of the robot per policy step.
//! - `observation`, `reward`, `risk`: pure functions of that snapshot.
//! - `heightfield`: one height grid as a MuJoCo hfield (terrain and eval ground).
//! - `terrain`: heightfield tiles and the curriculum.
//! - `single`, `vec_env`: reset + step.

pub mod bench;
pub mod config;
pub mod heightfield;
pub mod observation;
pub mod privileged;
pub mod reward;
pub mod risk;
mod scene;
mod single;
pub mod snapshot;
pub mod state;
pub mod terrain;
mod vec_env;

pub use config::EnvConfig;
pub use observation::{obs_layout, ObsGroup, ACT_DIM, OBS_DIM, OBS_LAYOUT};
pub use scene::{build_scene, Scene};
pub use single::{Env, EpisodeDraw, EpisodeEnd, EpisodeSummary, ForcePush, StepResult};
pub use vec_env::{Batch, ModelSharing, StepTimes, VecEnv};
