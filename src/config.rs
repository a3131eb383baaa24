//! The one TOML file of a training run: `[env]`, `[learner]`, `[runner]`.

use std::path::Path;

use anyhow::{Context, Result};
use serde::{Deserialize, Serialize};

use crate::env::EnvConfig;
use crate::learn::LearnerConfig;

/// The training loop's own settings.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RunnerConfig {
    /// Parallel environments (robots).
    pub num_envs: usize,
    /// Policy steps per env per iteration (rsl_rl: 24).
    pub steps_per_env: usize,
    /// Iterations to train (a resumed run continues up to this number).
    pub iterations: usize,
    /// Write a checkpoint every this many iterations.
    pub save_interval: usize,
    /// Print a log line every this many iterations.
    pub log_interval: usize,
    /// Env worker threads (0 = all cores).
    pub threads: usize,
    pub seed: u64,
    /// Parent folder of run directories.
    pub runs_dir: String,
    /// A last training stage at lower exploration noise (none by default).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub action_std_reset: Option<ActionStdReset>,
}

/// After iteration `after_iteration`, the policy's action std is set to
/// `action_std` in every dimension (its Adam moments start again from zero),
/// and PPO goes on from there: a stage that trains the policy's mean under the
/// noise it will be judged closer to. Applied once, at the start of iteration
/// `after_iteration + 1`, so a run resumed from any checkpoint applies it exactly
/// as an uninterrupted one.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ActionStdReset {
    pub after_iteration: usize,
    pub action_std: f32,
}

impl RunnerConfig {
    /// Takes on `stage` when this run (at `iteration`) has none; refused when the
    /// run has already passed it. A run that has a stage keeps its own.
    pub fn add_action_std_reset(
        &mut self,
        stage: Option<ActionStdReset>,
        iteration: usize,
    ) -> Result<()> {
        if let (None, Some(stage)) = (self.action_std_reset, stage) {
            anyhow::ensure!(
                stage.after_iteration >= iteration,
                "runner.action_std_reset.after_iteration = {} is before the checkpoint's iteration {iteration}: the stage can only be added to a run that has not passed it",
                stage.after_iteration
            );
            self.action_std_reset = Some(stage);
        }
        Ok(())
    }
}

impl Default for RunnerConfig {
    fn default() -> Self {
        RunnerConfig {
            num_envs: 256,
            steps_per_env: 24,
            iterations: 1500,
            save_interval: 50,
            log_interval: 10,
            threads: 0,
            seed: 1,
            runs_dir: "runs".into(),
            action_std_reset: None,
        }
    }
}

/// Worker threads for a `threads` setting where 0 means all cores.
pub fn worker_threads(requested: usize) -> usize {
    if requested == 0 {
        std::thread::available_parallelism().map_or(1, |n| n.get())
    } else {
        requested
    }
}

/// Everything a run needs; saved in every checkpoint.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, Default)]
#[serde(deny_unknown_fields, default)]
pub struct TrainConfig {
    pub env: EnvConfig,
    pub learner: LearnerConfig,
    pub runner: RunnerConfig,
}

impl TrainConfig {
    /// Reads and validates a TOML file; errors name the file and the key.
    pub fn from_toml_file(path: &Path) -> Result<TrainConfig> {
        let text = std::fs::read_to_string(path)
            .with_context(|| format!("reading config {}", path.display()))?;
        TrainConfig::from_toml_str(&text).with_context(|| format!("config {}", path.display()))
    }

    pub fn from_toml_str(text: &str) -> Result<TrainConfig> {
        let cfg: TrainConfig = toml::from_str(text).map_err(|e| anyhow::anyhow!("{e}"))?;
        cfg.validate()?;
        Ok(cfg)
    }

    pub fn to_toml(&self) -> String {
        toml::to_string_pretty(self).unwrap_or_else(|e| format!("# config not serialisable: {e}"))
    }

    /// Refuses impossible values, naming the key.
    pub fn validate(&self) -> Result<()> {
        self.env
            .validate()
            .map_err(|e| anyhow::anyhow!("invalid [env] value: {e}"))?;
        self.learner.validate().context("invalid [learner] value")?;
        // every group a network reads must be one the env writes
        let layout = self.env.obs_layout();
        let l = &self.learner;
        let reads = l
            .actor_inputs
            .iter()
            .map(|g| (g, "learner.actor_inputs"))
            .chain(l.critic_inputs.iter().map(|g| (g, "learner.critic_inputs")))
            .chain(
                l.encoder
                    .iter()
                    .map(|e| (&e.input, "learner.encoder.input")),
            );
        for (group, key) in reads {
            layout
                .require(group, key)
                .context("invalid [learner] value")?;
        }
        // the adaptation module's group may be absent: phase 2 adds it
        if let Some(a) = &l.adaptation {
            anyhow::ensure!(
                layout.range(&a.input).is_some() || a.input == "history",
                "invalid [learner] value: learner.adaptation.input = {:?} is not an observation group the env writes (phase 2 can add only \"history\")",
                a.input
            );
        }
        let r = &self.runner;
        anyhow::ensure!(
            r.num_envs > 0,
            "invalid [runner] value: runner.num_envs must be at least 1"
        );
        anyhow::ensure!(
            r.steps_per_env > 0,
            "invalid [runner] value: runner.steps_per_env must be at least 1"
        );
        anyhow::ensure!(
            r.save_interval > 0,
            "invalid [runner] value: runner.save_interval must be at least 1"
        );
        anyhow::ensure!(
            r.log_interval > 0,
            "invalid [runner] value: runner.log_interval must be at least 1"
        );
        if let Some(reset) = &r.action_std_reset {
            anyhow::ensure!(
                reset.action_std.is_finite() && reset.action_std > 0.0,
                "invalid [runner] value: runner.action_std_reset.action_std must be a positive number, got {}",
                reset.action_std
            );
        }
        let batch = r.num_envs * r.steps_per_env;
        anyhow::ensure!(
            batch >= self.learner.ppo.num_mini_batches,
            "invalid [runner] value: num_envs x steps_per_env = {batch} is smaller than learner.ppo.num_mini_batches"
        );
        Ok(())
    }
}
