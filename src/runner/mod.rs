//! The runner: the training loop, metrics and checkpoint files.

mod adapt;
pub mod metrics;
pub mod policy_file;
pub mod train;

pub use policy_file::{load_policy, save_policy, LoadedPolicy, Progress};
pub use train::{train, IterationObserver, RunDir, TrainSummary, LATEST};
