//! `rall calibrate-risk`: per-joint risk thresholds from a walking policy's gait,
//! written into a copy of a run config.

use std::path::PathBuf;

use anyhow::{Context, Result};
use clap::Args;

use crate::config::{worker_threads, TrainConfig};
use crate::eval::risk_calibration::{calibrate_risk, CALIBRATED_TERMS};
use crate::runner::load_policy;

#[derive(Debug, Args)]
pub struct CalibrateRiskArgs {
    /// A walking policy (checkpoint written by `rall train`); its training env (terrain at
    /// its stored curriculum levels, pushes, randomisation) is where the gait is measured.
    #[arg(long)]
    pub checkpoint: PathBuf,
    /// Each joint's threshold: this quantile of the quantity's absolute value.
    #[arg(long, default_value_t = 0.999)]
    pub quantile: f64,
    /// The config the thresholds go into (its text is kept; the tables are appended).
    #[arg(long)]
    pub config: PathBuf,
    /// Where the new config is written (refused if it exists, unless --force).
    #[arg(long)]
    pub out: PathBuf,
    #[arg(long)]
    pub force: bool,
    #[arg(long, default_value_t = 256)]
    pub robots: usize,
    /// Policy steps each robot walks (episodes restart after a fall or time-out).
    #[arg(long, default_value_t = 750)]
    pub steps: usize,
    #[arg(long, default_value_t = 4242)]
    pub seed: u64,
    /// Worker threads (0 = all cores).
    #[arg(long, default_value_t = 0)]
    pub threads: usize,
}

pub fn run(a: &CalibrateRiskArgs) -> Result<()> {
    anyhow::ensure!(
        a.force || !a.out.exists(),
        "{} exists: choose another --out or add --force",
        a.out.display()
    );
    let text = std::fs::read_to_string(&a.config)
        .with_context(|| format!("reading --config {}", a.config.display()))?;
    let base = TrainConfig::from_toml_str(&text)
        .with_context(|| format!("--config {}", a.config.display()))?;
    for name in CALIBRATED_TERMS {
        anyhow::ensure!(
            !text.contains(&format!("[env.risk.{name}]")),
            "--config {} already sets [env.risk.{name}]: start from a config without it",
            a.config.display()
        );
    }
    let p = load_policy(&a.checkpoint)?;
    let cal = calibrate_risk(
        &p.learner,
        &p.config,
        p.progress.terrain_levels.as_deref(),
        (a.robots, a.steps),
        a.quantile,
        worker_threads(a.threads),
        a.seed,
    )?;
    println!(
        "{} robot-steps of {} (iteration {}), quantile {}",
        cal.states,
        a.checkpoint.display(),
        p.progress.iteration,
        cal.quantile
    );
    let names = crate::env::risk::RISK_TERM_NAMES;
    for (name, share) in names.iter().zip(cal.crossed_before) {
        println!(
            "  {name:<20} crossed in {:.2}% of robot-steps at {}'s thresholds",
            100.0 * share,
            a.config.display()
        );
    }
    for ((name, per), after) in CALIBRATED_TERMS
        .iter()
        .zip(&cal.per_joint)
        .zip(cal.crossed_after)
    {
        let v: Vec<String> = per.iter().map(|x| format!("{x:.1}")).collect();
        println!(
            "  {name:<20} per joint: {} (any joint crosses in {:.2}% of robot-steps)",
            v.join(" "),
            100.0 * after
        );
    }
    let provenance = format!(
        "`rall calibrate-risk --checkpoint {} --quantile {} --robots {} --steps {} --seed {}`",
        a.checkpoint.display(),
        a.quantile,
        a.robots,
        a.steps,
        a.seed
    );
    let out_text = format!(
        "{}\n{}",
        text.trim_end(),
        cal.toml_tables(&base, &provenance)
    );
    TrainConfig::from_toml_str(&out_text)
        .context("the calibrated config does not parse (a bug: please report it)")?;
    crate::fsio::write_atomic(&a.out, out_text.as_bytes())?;
    println!("wrote {}", a.out.display());
    Ok(())
}
