//! Viewing policies in rerun: the robot, its terrain, the
//! commands and, step by step, the critic's value distribution and its IQR.
//!
//! - [`convert`]: MuJoCo -> rerun conventions as pure functions (geoms, heightfields).
//! - [`value`]: one critic evaluation per step gives the quantiles, mean, CVaR, IQR.
//! - [`episode`]: logs a robot step by step (entity paths in its docs).
//! - [`play`]: runs a policy's mean action, with or without a recording (`rall play`).
//! - [`train`]: the training observer (`rall train --rerun-*`).
//! - [`blueprint`]: the viewer layouts, sent with every recording.
//! - [`sink`]: file / spawned viewer / running viewer, failing fast without a viewer.
//! - [`rrd`]: reading a recording back (tests).

pub mod blueprint;
pub mod convert;
pub mod episode;
pub mod play;
pub mod rrd;
pub mod sink;
pub mod train;
pub mod value;

pub use blueprint::{
    play_blueprint, train_blueprint, Layout, FOLLOWED_ENTITY, PLAY_APP_ID, TRAIN_APP_ID,
};
pub use episode::EpisodeLogger;
pub use play::{play, run_episode, PlayOptions, PlayReport, PlayedEpisode, ViewerEnv};
pub use rrd::{summarize_rrd, EntitySummary, RrdSummary};
pub use sink::{finish_recording, open_recording, write_blueprint_file, RerunTarget};
pub use train::{TrainRecorder, TrainRecordingOptions};
pub use value::{ValueProbe, ValueReading};
