//! Evaluation: command tracking, and the paper's robustness benchmarks.
//!
//! - [`scenario`]: the robustness scenarios by name (payloads, pushes, rough
//!   ground, platform, race course): env config + model + per-env hook.
//! - [`ttf`]: Time to Fall (paper table I); [`platform`]: platform drops
//!   (table II); [`race`]: race-track returns and the IQR meta controller (fig. 4).
//! - [`jobs`]: independent rollouts side by side, one thread each; [`cache`]:
//!   finished rollouts on disk, so a long evaluation resumes.
//! - [`rollout`]: N robots of a scenario on a `VecEnv` under a policy's mean action.
//! - [`severity`]: the severity ladder (rung 0 = the paper's protocol, harder above).
//! - [`commands`]: the command-space safety map (falls and tracking per fixed
//!   command over a grid of the policy's command ranges); [`commands_plot`]: its
//!   SVG heat map.

pub mod cache;
pub mod commands;
pub mod commands_plot;
pub mod falls;
pub mod ground;
pub mod jobs;
pub mod mjcf;
pub mod platform;
pub mod policy;
pub mod race;
pub mod rall_graph;
pub mod report;
pub mod risk_calibration;
pub mod rollout;
pub mod scenario;
pub mod severity;
pub mod sidecar;
pub mod tracking;
pub mod ttf;

pub use cache::{CacheUse, RolloutCache};
pub use commands::{
    evaluate_command_map, evaluate_command_map_cached, AxisSpec, CellResult, CommandGrid,
    CommandMap, CommandMapOptions, SafetyThreshold, SeverityRung,
};
pub use commands_plot::write_command_map_svg;
pub use falls::{critic_before_falls, FallReport, QuantileMeans, FALL_TAUS};
pub use platform::{evaluate_platform, DropOutcome, DropWatch, PlatformOptions, PlatformReport};
pub use policy::{is_onnx, Actor, OnnxPolicy, OnnxRuntime, Policy};
pub use race::{evaluate_race, MetaArg, MetaConfig, MetaSwitch, RaceOptions, RaceReport};
pub use rollout::{run_first_episodes, FirstEpisode, NamedPolicy, ScenarioRun};
pub use scenario::{
    build_named_scenario, build_scenario, GroundKind, Load, ScenarioHook, ScenarioParams,
    ScenarioSetup, ScenarioSpec,
};
pub use severity::{Ladder, Rung};
pub use tracking::{
    evaluate_tracking, evaluate_tracking_with_falls, fall_rate, lin_vel_score, tracking_env,
    with_randomization, yaw_rate_score, ActionMode, FallRecord, RobotTracking, TrackingReport,
};
pub use ttf::{evaluate_ttf, time_to_fall, TtfOptions, TtfReport, FALL_DEFINITION};
