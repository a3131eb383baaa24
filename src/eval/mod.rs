//! Evaluation: command tracking, and the paper's robustness benchmarks.

pub mod tracking;

pub use tracking::{evaluate_tracking, tracking_env, ActionMode, TrackingReport};
