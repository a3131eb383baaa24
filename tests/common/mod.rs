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

/// A method's config (`configs/<method>.toml`) made as small as [`tiny_config`]:
/// one iteration (RMA: one of each phase), terrain of two levels and types.
#[allow(dead_code)]
pub fn tiny_method(method: &str) -> TrainConfig {
    let mut c = TrainConfig::from_toml_file(
        &std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join(format!("configs/{method}.toml")),
    )
    .unwrap();
    let tiny = tiny_config(c.learner.critic);
    c.env.robot_mjcf = tiny.env.robot_mjcf.clone();
    c.env.episode.length_s = 0.5;
    c.env.observation.history_steps = 5;
    c.env.terrain.num_levels = 2;
    c.env.terrain.num_types = 2;
    c.env.terrain.max_init_level = 1;
    c.learner.actor_hidden = tiny.learner.actor_hidden.clone();
    c.learner.critic_hidden = tiny.learner.critic_hidden.clone();
    c.learner.num_taus = 8;
    c.learner.num_target_taus = 8;
    c.learner.num_value_taus = 8;
    if let Some(a) = &mut c.learner.adaptation {
        a.iterations = 1;
    }
    c.runner = tiny.runner.clone();
    c.runner.iterations = 1;
    c
}

/// Metrics rows without the timing columns (names ending in `_s`, and the rate).
#[allow(dead_code)]
pub fn metrics_without_timing(run: &std::path::Path) -> Vec<Vec<String>> {
    let text = std::fs::read_to_string(run.join("metrics.csv")).unwrap();
    let mut lines = text.lines();
    let head: Vec<&str> = lines.next().unwrap().split(',').collect();
    let keep: Vec<usize> = (0..head.len())
        .filter(|&i| !head[i].ends_with("_s") && head[i] != "env_steps_per_s")
        .collect();
    lines
        .map(|l| {
            let f: Vec<&str> = l.split(',').collect();
            keep.iter().map(|&i| f[i].to_string()).collect()
        })
        .collect()
}
