//! `rall play`: run a checkpoint's policy (mean action) and show it in rerun.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use clap::{ArgGroup, Args};
use serde::Deserialize;

use crate::env::EnvConfig;
use crate::runner::load_policy;
use crate::viz::{self, PlayOptions, RerunTarget};

#[derive(Debug, Args)]
#[command(group(
    ArgGroup::new("target").required(true).args(["save", "spawn", "connect", "write_blueprints"])
))]
pub struct PlayArgs {
    /// Checkpoint to play (e.g. runs/<run>/latest.safetensors).
    #[arg(long, required_unless_present = "write_blueprints")]
    pub checkpoint: Option<PathBuf>,
    /// TOML file whose [env] table replaces the checkpoint's env config (a scenario);
    /// default: the checkpoint's own env (noise, PD and pushes as in training).
    #[arg(long, value_name = "FILE")]
    pub config: Option<PathBuf>,
    /// Play an evaluation scenario by name instead of the training scene: a load
    /// (ball, frozen_arm, moving_arm), a ground (flat, rough, platform[=H], race) and
    /// push, joined by `+`, e.g. `moving_arm+rough+push`.
    #[arg(long, value_name = "NAME")]
    pub scenario: Option<String>,
    #[arg(long, default_value_t = 1)]
    pub episodes: usize,
    /// Seed of the env (commands, randomisation, noise, pushes).
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Cut every episode after this many policy steps (default: the env's episode length).
    #[arg(long, value_name = "N")]
    pub steps_per_episode: Option<usize>,
    /// Terrain level on rough ground (the terrain type changes with every episode).
    #[arg(long, default_value_t = 0)]
    pub terrain_level: usize,
    /// Write the recording to an .rrd file (no viewer needed; open it with `rerun FILE`).
    #[arg(long, value_name = "FILE")]
    pub save: Option<PathBuf>,
    /// Start a rerun viewer (`rerun` on PATH) and stream to it.
    #[arg(long)]
    pub spawn: bool,
    /// Stream to a running viewer (default 127.0.0.1:9876; or rerun+http://HOST:PORT/proxy).
    #[arg(long, value_name = "ADDR", num_args = 0..=1, default_missing_value = "127.0.0.1:9876")]
    pub connect: Option<String>,
    /// Open the recording at its last frame (the viewer follows the latest data)
    /// instead of playing it from the start: where the episode ended, or a screenshot
    /// of it (`viz/screenshot.sh`).
    #[arg(long)]
    pub open_at_end: bool,
    /// Write the viewer layouts (rall-play.rbl, rall-train.rbl) into DIR and exit.
    #[arg(long, value_name = "DIR")]
    pub write_blueprints: Option<PathBuf>,
}

#[derive(Deserialize)]
struct EnvOnly {
    env: Option<EnvConfig>,
}

/// The `[env]` table of a TOML file (other tables are ignored).
pub fn env_config_from_file(path: &Path) -> Result<EnvConfig> {
    let text =
        std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    let table: toml::Table =
        toml::from_str(&text).with_context(|| format!("parsing {}", path.display()))?;
    let env_only: EnvOnly = toml::Value::Table(table)
        .try_into()
        .map_err(|e| anyhow::anyhow!("{}: [env]: {e}", path.display()))?;
    let Some(env) = env_only.env else {
        bail!("{} has no [env] table", path.display())
    };
    env.validate()
        .map_err(|e| anyhow::anyhow!("{}: invalid [env] value: {e}", path.display()))?;
    Ok(env)
}

pub fn run(args: &PlayArgs) -> Result<()> {
    if let Some(dir) = &args.write_blueprints {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
        let play = dir.join("rall-play.rbl");
        let train = dir.join("rall-train.rbl");
        viz::write_blueprint_file(&play, viz::PLAY_APP_ID, viz::play_blueprint())?;
        viz::write_blueprint_file(&train, viz::TRAIN_APP_ID, viz::train_blueprint())?;
        println!("wrote {} and {}", play.display(), train.display());
        return Ok(());
    }
    let checkpoint = args
        .checkpoint
        .as_deref()
        .context("--checkpoint is required")?;
    let target = RerunTarget::from_flags(args.save.as_deref(), args.spawn, args.connect.as_deref())
        .context("choose --save FILE, --spawn or --connect [ADDR]")?;
    let loaded = load_policy(checkpoint)?;
    if loaded.actor_only {
        eprintln!(
            "note: {} is an actor-only copy: the robot acts as trained, but the value distribution, mean, CVaR and IQR shown come from an untrained critic",
            checkpoint.display()
        );
    }
    let env_cfg = match &args.config {
        Some(path) => env_config_from_file(path)?,
        None => loaded.config.env.clone(),
    };
    let name = format!(
        "{} (iteration {})",
        checkpoint.display(),
        loaded.progress.iteration
    );
    let layout = match args.open_at_end {
        true => viz::play_blueprint().opened_at_end(),
        false => viz::play_blueprint(),
    };
    let rec = viz::open_recording(viz::PLAY_APP_ID, &name, &target, layout)?;
    let opts = PlayOptions {
        episodes: args.episodes,
        seed: args.seed,
        scene_seed: loaded.config.runner.seed,
        max_steps: args.steps_per_episode,
        terrain_level: args.terrain_level,
        scenario: args.scenario.clone(),
        ..PlayOptions::default()
    };
    let (report, rec) = match viz::play(&loaded.learner, &env_cfg, &opts, Some(rec)) {
        Ok(played) => played,
        Err(e) => {
            // a recording cut short (e.g. the scene did not build) is not left behind
            if let RerunTarget::Save(path) = &target {
                if std::fs::remove_file(path).is_ok() {
                    return Err(e.context(format!("nothing recorded: removed {}", path.display())));
                }
            }
            return Err(e);
        }
    };
    if let Some(rec) = rec {
        viz::finish_recording(rec)?;
    }
    for (i, e) in report.episodes.iter().enumerate() {
        let end = e.end.map_or("cut".to_string(), |end| format!("{end:?}"));
        println!(
            "episode {}: {} steps, return {:.3}, end {end}, risk penalties {}, pushes {}",
            i + 1,
            e.steps,
            e.total_reward,
            e.risk_penalties,
            e.pushes
        );
    }
    match &target {
        RerunTarget::Save(path) => {
            let bytes = std::fs::metadata(path).map(|m| m.len()).unwrap_or(0);
            println!(
                "{:.1} s simulated -> {} ({:.2} MB); open it with `rerun {}` ({})",
                report.sim_time_s,
                path.display(),
                bytes as f64 / 1e6,
                path.display(),
                viz::sink::VIEWER_PIP
            );
        }
        _ => println!(
            "{:.1} s simulated, streamed to the viewer",
            report.sim_time_s
        ),
    }
    Ok(())
}
