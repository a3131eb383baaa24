//! Evaluation: command tracking, and the paper's robustness benchmarks.
//!
//! - [`scenario`]: the robustness scenarios by name (payloads, pushes, rough
//!   ground, platform, race course): env config + model + per-env hook.
//! - [`rollout`]: N robots of a scenario on a `VecEnv` under a policy's mean action.

pub mod ground;
pub mod mjcf;
pub mod rollout;
pub mod scenario;
pub mod tracking;

pub use rollout::{run_first_episodes, FirstEpisode, NamedPolicy, ScenarioRun};
pub use scenario::{
    build_named_scenario, build_scenario, GroundKind, Load, ScenarioHook, ScenarioParams,
    ScenarioSetup, ScenarioSpec,
};
pub use tracking::{evaluate_tracking, tracking_env, ActionMode, TrackingReport};
