//! The runner: the training loop (alone or as MPI ranks), metrics and checkpoint files.

mod adapt;
pub mod checkpoint_kinds;
pub mod dist;
mod faults;
pub mod identity;
mod job;
pub mod manifest;
pub mod metrics;
mod resume;
pub mod run_dir;
pub mod scaling;
mod setup;
mod status;
pub mod train;

pub use adapt::{install_teacher, restart_adaptation};
pub use checkpoint_kinds::{load_policy, load_policy_bytes, save_policy, LoadedPolicy, Progress};
pub use dist::World;
pub use identity::{RunIdentity, IDENTITY_FILE};
pub use run_dir::{RunDir, LATEST};
pub use train::{train, train_in, IterationObserver, PhaseOneOnly, TrainSummary, Trainer};
