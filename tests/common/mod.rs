//! Helpers shared by the integration tests that train.

use rall::config::TrainConfig;
use rall::env::terrain::TerrainKind;
use rall::learn::CriticKind;

/// A run small enough for a test: 8 robots, short episodes, small networks,
/// 2 iterations checkpointed after each.
pub fn tiny_config(critic: CriticKind) -> TrainConfig {
    let mut c = TrainConfig::default();
    c.env.robot_mjcf = concat!(env!("CARGO_MANIFEST_DIR"), "/mjcf/aliengo.xml").into();
    c.env.terrain.kind = TerrainKind::Flat;
    c.env.episode.length_s = 0.5;
    c.learner.critic = critic;
    c.learner.actor_hidden = vec![32, 32];
    c.learner.critic_hidden = vec![32, 32];
    c.learner.num_taus = 8;
    c.learner.num_target_taus = 8;
    c.learner.num_value_taus = 8;
    c.runner.num_envs = 8;
    c.runner.steps_per_env = 8;
    c.runner.iterations = 2;
    c.runner.save_interval = 1;
    c.runner.threads = 2;
    c
}
