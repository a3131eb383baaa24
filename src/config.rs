//! The one TOML file of a training run: `[env]`, `[learner]`, `[runner]`.

use std::path::Path;

use anyhow::{Context, Result};
use serde::{Deserialize, Serialize};

use crate::env::EnvConfig;
use crate::learn::LearnerConfig;

/// The training loop's own settings. Each key's accepted range is in its
/// comment; [`RunnerConfig::validate`] refuses anything outside it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RunnerConfig {
    /// Parallel environments (robots), 1..=1,048,576 ([`MAX_ENVS`]) and within
    /// the machine's memory.
    pub num_envs: usize,
    /// Policy steps per env per iteration (rsl_rl: 24), 1..=100,000.
    pub steps_per_env: usize,
    /// Iterations to train (a resumed run continues up to this number),
    /// 1..=100,000,000: 0 would train nothing.
    pub iterations: usize,
    /// Write a checkpoint every this many iterations, 1..=100,000,000.
    pub save_interval: usize,
    /// Print a log line every this many iterations, 1..=100,000,000.
    pub log_interval: usize,
    /// Env worker threads (0 = all cores), 0..=1024 ([`MAX_THREADS`]).
    pub threads: usize,
    /// Seed of the networks' initialisation, the envs and the update; any u64.
    pub seed: u64,
    /// Parent folder of run directories; not empty.
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
    /// Any iteration (a stage after the run's last iteration applies once the
    /// run is resumed with a larger target).
    pub after_iteration: usize,
    /// The new std in every action dimension, in [1e-9, 1e3].
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

/// The most environments one process may run.
pub const MAX_ENVS: usize = 1 << 20;
/// The most worker threads a config may ask for.
pub const MAX_THREADS: usize = 1024;
/// Resident memory of one environment in training (MuJoCo data, robot,
/// buffers), measured with `/usr/bin/time -v` (README: about 0.4 MB per env).
pub const ENV_MEMORY_BYTES: u64 = 400_000;

impl RunnerConfig {
    /// Refuses values outside their ranges, naming the dotted key.
    pub fn validate(&self) -> Result<()> {
        let count = crate::learn::ppo::check_count;
        count("runner.num_envs", self.num_envs, 1, MAX_ENVS)?;
        count("runner.steps_per_env", self.steps_per_env, 1, 100_000)?;
        count("runner.iterations", self.iterations, 1, 100_000_000)?;
        count("runner.save_interval", self.save_interval, 1, 100_000_000)?;
        count("runner.log_interval", self.log_interval, 1, 100_000_000)?;
        count("runner.threads", self.threads, 0, MAX_THREADS)?;
        anyhow::ensure!(
            !self.runs_dir.trim().is_empty(),
            "runner.runs_dir must name a folder"
        );
        if let Some(reset) = &self.action_std_reset {
            crate::learn::ppo::check_f32(
                "runner.action_std_reset.action_std",
                reset.action_std,
                1e-9,
                1e3,
            )?;
        }
        Ok(())
    }

    /// Estimated memory of this process's envs and rollout (bytes), with
    /// observation rows of `obs_width` values; `None` when it overflows.
    pub fn memory_estimate_bytes(&self, obs_width: usize) -> Option<u64> {
        // per step: observations (kept, normalised copy, final ones), actions,
        // means, log-probs, rewards, flags
        let row_bytes = (3 * obs_width as u64 + 3 * 12 + 8).checked_mul(4)?;
        let per_env = (self.steps_per_env as u64)
            .checked_mul(row_bytes)?
            .checked_add(ENV_MEMORY_BYTES)?;
        per_env.checked_mul(self.num_envs as u64)
    }

    /// Refuses (before anything is allocated) envs that cannot fit in this
    /// machine's available memory, with the estimate.
    pub fn check_memory(&self, obs_width: usize) -> Result<()> {
        let gb = |b: u64| b as f64 / 1e9;
        let Some(need) = self.memory_estimate_bytes(obs_width) else {
            anyhow::bail!(
                "runner.num_envs = {} x runner.steps_per_env = {} overflows a memory estimate",
                self.num_envs,
                self.steps_per_env
            );
        };
        let Some(avail) = available_memory_bytes() else {
            return Ok(());
        };
        anyhow::ensure!(
            need <= avail,
            "runner.num_envs = {} needs about {:.1} GB ({:.2} MB per env with its rollout of {} steps), but this machine has {:.1} GB available: use fewer envs (--envs)",
            self.num_envs,
            gb(need),
            need as f64 / self.num_envs as f64 / 1e6,
            self.steps_per_env,
            gb(avail)
        );
        Ok(())
    }
}

/// `MemAvailable` of /proc/meminfo (Linux), bytes.
fn available_memory_bytes() -> Option<u64> {
    let text = std::fs::read_to_string("/proc/meminfo").ok()?;
    let line = text.lines().find(|l| l.starts_with("MemAvailable:"))?;
    let kb: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    kb.checked_mul(1024)
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
    /// Reads and validates a TOML file; errors name the file and the key. A
    /// file without any section (empty, or comments only) is refused: it would
    /// silently train on the defaults.
    pub fn from_toml_file(path: &Path) -> Result<TrainConfig> {
        let text = std::fs::read_to_string(path)
            .with_context(|| format!("reading config {}", path.display()))?;
        let table: toml::Table = toml::from_str(&text)
            .map_err(|e| anyhow::anyhow!("{e}"))
            .with_context(|| format!("config {}", path.display()))?;
        anyhow::ensure!(
            !table.is_empty(),
            "config {} has no sections ([env], [learner], [runner]): an empty config would train on the defaults; start from configs/rall.toml",
            path.display()
        );
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
        anyhow::ensure!(
            self.learner.ppo.learning_rate > 0.0,
            "learner.ppo.learning_rate must be in (0, 1], got {}: a rate of 0 never changes a weight",
            self.learner.ppo.learning_rate
        );
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
        r.validate().context("invalid [runner] value")?;
        // the rollout's floats must be countable (checked, not wrapped)
        let batch = r.num_envs.checked_mul(r.steps_per_env);
        let floats = batch.and_then(|b| b.checked_mul(self.env.obs_width()));
        let (Some(batch), Some(_)) = (batch, floats) else {
            anyhow::bail!(
                "invalid [runner] value: runner.num_envs x runner.steps_per_env x the observation width overflows"
            );
        };
        anyhow::ensure!(
            batch >= self.learner.ppo.num_mini_batches,
            "invalid [runner] value: num_envs x steps_per_env = {batch} is smaller than learner.ppo.num_mini_batches"
        );
        Ok(())
    }
}
