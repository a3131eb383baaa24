//! The safe command envelope of an export: `rall eval commands`' safety map run
//! on the exported network, written into the sidecar (`command_envelope`), and
//! the rule `rall export` refuses an unsafe policy by (`safety`).
//!
//! The map runs as `rall eval commands` runs by default: flat ground, the
//! checkpoint's own observation noise, PD and randomisation draws, no pushes, no
//! payload, each command held for a whole episode. A cell is safe when it meets
//! [`SafetyThreshold`] (falls < 5% and linear tracking >= 0.8, point estimates).
//!
//! A policy is refused when its nominal trace ends in a fall, or when a cell
//! inside the command ranges it declares (the sidecar's `commands`: each axis
//! within its range, and a planar speed training did not zero) fails; failing
//! cells outside those ranges are reported, never refused.

use std::path::Path;

use anyhow::{anyhow, ensure, Result};
use serde_json::{json, Value};

use crate::env::config::CommandConfig;
use crate::env::EnvConfig;
use crate::eval::commands::{
    commanded_in_training, evaluate_command_map, AxisSpec, CellResult, CommandGrid, CommandMap,
    CommandMapOptions, SafetyThreshold,
};
use crate::eval::{Actor, FALL_DEFINITION};
use crate::stats::Estimate;

/// The default grid's cell counts (vx, vy, yaw rate), evenly spaced over the
/// policy's ranges with both ends and 0 on each axis: 5 x 5 x 5 = 125 cells,
/// for the default ranges {-1, -0.5, 0, 0.5, 1} on each axis. Coarser than
/// `rall eval commands`' 7 x 5 x 5 (175 cells) to keep an export fast: with
/// [`DEFAULT_ROBOTS`] robots and the checkpoint's 20 s episodes it runs at most
/// 125 x 16 x 1,000 = 2 M policy steps, about 1.5-2 minutes of wall time on two
/// idle cores for an Aliengo PPO checkpoint (`rall eval commands` ran 45 cells x 8
/// robots of it, 360,000 policy steps, in 18 s on two idle cores). The axes keep
/// what the full maps found failing: walking straight at half speed (vx 0.5, vy 0)
/// and turning in place (yaw rate -0.5 and -1).
pub const DEFAULT_CELLS: [usize; 3] = [5, 5, 5];

/// Robots per cell by default: 16, as `rall eval commands`, so with the same
/// seed a cell's numbers are those of that map's cell. A single fall fails a
/// cell (1 of 16 is 6.25%, not below 5%); a cell where none of 16 fell still has
/// a 95% Wilson interval up to 19%: a safe cell says "no fall seen", and the
/// sidecar gives each interval.
pub const DEFAULT_ROBOTS: usize = 16;

/// How the envelope is mapped.
#[derive(Debug, Clone, PartialEq)]
pub struct EnvelopeOptions {
    /// The vx, vy and yaw-rate axes of the grid.
    pub axes: [AxisSpec; 3],
    /// Robots per cell, one episode each.
    pub robots: usize,
    /// Episode length (s); `None`: the checkpoint's.
    pub episode_length_s: Option<f64>,
    /// Seed of the robots' draws and noise, the same for every cell.
    pub seed: u64,
    /// Worker threads (0: all cores); the numbers do not depend on it.
    pub threads: usize,
    pub threshold: SafetyThreshold,
}

impl Default for EnvelopeOptions {
    fn default() -> Self {
        let [x, y, w] = DEFAULT_CELLS;
        EnvelopeOptions {
            axes: [AxisSpec::Cells(x), AxisSpec::Cells(y), AxisSpec::Cells(w)],
            robots: DEFAULT_ROBOTS,
            episode_length_s: None,
            seed: 0,
            threads: 0,
            threshold: SafetyThreshold::default(),
        }
    }
}

impl EnvelopeOptions {
    /// The map's options (flat ground, no payload, the checkpoint's draws).
    pub fn map_options(&self) -> CommandMapOptions {
        CommandMapOptions {
            robots: self.robots,
            seed: self.seed,
            episode_length_s: self.episode_length_s,
            ..CommandMapOptions::default()
        }
    }

    /// The grid over the policy's command `ranges`, checked: a grid without a
    /// cell inside the ranges would check nothing, and is refused.
    pub fn grid(&self, ranges: &CommandConfig) -> Result<CommandGrid> {
        let [vx, vy, yaw] = &self.axes;
        let grid = CommandGrid::from_specs([vx, vy, yaw], ranges)?;
        ensure!(
            grid.commands()
                .iter()
                .any(|c| commanded_in_training(*c, ranges)),
            "the command grid (vx {:?} m/s, vy {:?} m/s, yaw rate {:?} rad/s) has no cell inside the policy's command ranges (vx {:?} m/s, vy {:?} m/s, yaw rate {:?} rad/s, planar speeds from {} m/s): its envelope would check nothing; give values inside them (--vx, --vy, --yaw) or leave the axes at their defaults",
            grid.vx_mps,
            grid.vy_mps,
            grid.yaw_rate_rad_s,
            ranges.vx_mps,
            ranges.vy_mps,
            ranges.yaw_rate_rad_s,
            ranges.zero_below_mps
        );
        Ok(grid)
    }

    /// Checks every option against the policy's `ranges` before anything runs.
    pub fn validate(&self, ranges: &CommandConfig) -> Result<()> {
        self.map_options().validate()?;
        self.grid(ranges).map(|_| ())
    }
}

/// A policy's measured command envelope.
#[derive(Debug, Clone)]
pub struct Envelope {
    pub map: CommandMap,
    pub threshold: SafetyThreshold,
    /// What acted in the map (the exported graph, or the checkpoint's actor).
    pub network: String,
    /// Policy step (s), to state the episode length.
    pub policy_dt_s: f64,
}

impl Envelope {
    /// Maps `policy` (trained in `env`) over the grid of `opts`; `network` says
    /// what `policy` is, for the sidecar.
    pub fn measure(
        policy: &(dyn Actor + Sync),
        env: &EnvConfig,
        opts: &EnvelopeOptions,
        network: &str,
    ) -> Result<Envelope> {
        opts.validate(&env.commands)?;
        let grid = opts.grid(&env.commands)?;
        let threads = crate::config::worker_threads(opts.threads);
        let map = evaluate_command_map(policy, env, &grid, &opts.map_options(), threads)?;
        Ok(Envelope {
            map,
            threshold: opts.threshold,
            network: network.to_string(),
            policy_dt_s: env.control.policy_dt_s(),
        })
    }

    /// Cells whose command the policy declares (its training ranges).
    pub fn declared_cells(&self) -> Vec<&CellResult> {
        self.map
            .cells
            .iter()
            .filter(|c| c.commanded_in_training)
            .collect()
    }

    /// Declared cells that fail the threshold, in grid order.
    pub fn declared_failures(&self) -> Vec<&CellResult> {
        self.declared_cells()
            .into_iter()
            .filter(|c| !c.is_safe(&self.threshold))
            .collect()
    }

    /// The episode length the cells ran, s.
    pub fn episode_length_s(&self) -> f64 {
        self.map.episode_steps as f64 * self.policy_dt_s
    }

    /// `rall eval commands` arguments that rerun this map on `checkpoint`.
    fn rerun_command(&self, checkpoint: &Path) -> String {
        let list = |v: &[f64]| {
            v.iter()
                .map(|x| x.to_string())
                .collect::<Vec<_>>()
                .join(",")
        };
        let g = &self.map.grid;
        format!(
            "rall eval commands --checkpoint {} --vx {} --vy {} --yaw {} --robots {} --seconds {} --seed {}",
            checkpoint.display(),
            list(&g.vx_mps),
            list(&g.vy_mps),
            list(&g.yaw_rate_rad_s),
            self.map.options.robots,
            self.episode_length_s(),
            self.map.options.seed
        )
    }

    /// The sidecar's `command_envelope` section.
    pub fn json(&self, checkpoint: &Path) -> Value {
        let t = &self.threshold;
        let g = &self.map.grid;
        let cells: Vec<Value> = self.map.cells.iter().map(|c| cell_json(c, t)).collect();
        json!({
            "purpose": "where on the command grid this policy was measured safe: a controller clamps or refuses commands outside the safe cells (docs/deploy.md)",
            "conditions": {
                "ground": "flat (a plane, as trace.conditions.ground_xml)",
                "observation_noise": "the checkpoint's own (observation.noise_level and the fields' noise_std_physical_units)",
                "randomization": "the checkpoint's own draws per robot (training_envelope.randomization: friction, added mass, motor strength, PD gain factors, centre-of-mass offset)",
                "pushes": "none",
                "payload": "none",
                "command": "held fixed for the whole episode (no resampling), from start_state",
                "network": self.network,
            },
            "threshold": {
                "max_fall_rate": t.max_fall_rate,
                "min_lin_tracking": t.min_lin_tracking,
                "rule": format!("a cell is safe when {} (point estimates over its robots)", t.describe()),
            },
            "grid": {
                "vx_mps": g.vx_mps,
                "vy_mps": g.vy_mps,
                "yaw_rate_rad_s": g.yaw_rate_rad_s,
            },
            "robots_per_cell": self.map.options.robots,
            "episode_length_s": self.episode_length_s(),
            "episode_steps": self.map.episode_steps,
            "seed": self.map.options.seed,
            "fall": FALL_DEFINITION,
            "intervals": "fall_rate: 95% Wilson interval over robots; lin_tracking and yaw_tracking: `rall eval tracking`'s scores over each robot's steps before a fall, 95% percentile bootstrap over robots",
            "inside_declared_ranges": "whether the policy declares the cell's command: each axis within `commands`' range and a planar speed of 0 or at least commands.zero_below_mps",
            "reproduce": self.rerun_command(checkpoint),
            "cells": cells,
            "summary": self.summary_json(),
        })
    }

    /// Safe share, worst cell and whether every declared cell is safe.
    fn summary_json(&self) -> Value {
        let t = &self.threshold;
        let safe = self.map.safe_cells(t).len();
        let declared = self.declared_cells().len();
        json!({
            "cells": self.map.cells.len(),
            "safe_cells": safe,
            "safe_share": self.map.safe_share(t),
            "worst_cell": self.map.worst_cell().map(|c| cell_json(c, t)),
            "declared_cells": declared,
            "declared_cells_failing": self.declared_failures().len(),
            "all_declared_cells_safe": self.declared_failures().is_empty(),
        })
    }
}

fn estimate_json(e: &Estimate) -> Value {
    json!({"value": e.value, "lo": e.lo, "hi": e.hi})
}

/// One cell of the envelope: its command, falls, tracking and verdict under `t`.
pub fn cell_json(c: &CellResult, t: &SafetyThreshold) -> Value {
    json!({
        "vx_mps": c.vx_mps,
        "vy_mps": c.vy_mps,
        "yaw_rate_rad_s": c.yaw_rate_rad_s,
        "inside_declared_ranges": c.commanded_in_training,
        "robots": c.robots,
        "falls": c.falls,
        "fall_rate": estimate_json(&c.fall_rate),
        "lin_tracking": estimate_json(&c.lin_tracking),
        "yaw_tracking": estimate_json(&c.yaw_tracking),
        "safe": c.is_safe(t),
    })
}

/// `vx +0.30 m/s, vy +0.00 m/s, yaw rate +0.00 rad/s: falls 4 of 8 (50%), linear tracking 0.96`.
fn describe_cell(c: &CellResult) -> String {
    format!(
        "{}: falls {} of {} ({:.0}%), linear tracking {:.2}",
        c.describe_command(),
        c.falls,
        c.robots,
        100.0 * c.fall_rate.value,
        c.lin_tracking.value
    )
}

/// The refusal of a policy whose nominal trace falls at policy step `step`.
pub fn trace_refusal(checkpoint: &Path, step: usize) -> anyhow::Error {
    anyhow!(
        "refusing to export {}: its nominal trace (vx {} m/s, vy {} m/s, yaw rate {} rad/s on flat ground, nominal friction and mass, no noise) ends in a fall at policy step {step} of {}: a robot running it would fall. Export a checkpoint that walks (e.g. a later one), or pass --allow-unsafe to write it anyway (its sidecar then records `safety.allowed_unsafe: true` and the step). Nothing was written",
        checkpoint.display(),
        super::deploy::TRACE_COMMAND[0],
        super::deploy::TRACE_COMMAND[1],
        super::deploy::TRACE_COMMAND[2],
        super::deploy::TRACE_STEPS
    )
}

/// The refusal of a policy whose envelope fails inside its declared ranges.
pub fn envelope_refusal(checkpoint: &Path, envelope: &Envelope) -> anyhow::Error {
    const SHOWN: usize = 10;
    let failing = envelope.declared_failures();
    let mut lines: Vec<String> = failing
        .iter()
        .take(SHOWN)
        .map(|c| format!("  {}", describe_cell(c)))
        .collect();
    if failing.len() > SHOWN {
        lines.push(format!("  and {} more", failing.len() - SHOWN));
    }
    anyhow!(
        "refusing to export {}: {} of its {} command cells inside the ranges it declares fail {} ({} robots per cell, {:.1} s episodes, flat ground, seed {}):\n{}\nA robot sent these commands may fall. Export another checkpoint, or pass --allow-unsafe to write it anyway: its sidecar then lists these cells (`safety.failing_cells`) for a controller that refuses them, and `command_envelope` holds every cell. Nothing was written",
        checkpoint.display(),
        failing.len(),
        envelope.declared_cells().len(),
        envelope.threshold.describe(),
        envelope.map.options.robots,
        envelope.episode_length_s(),
        envelope.map.options.seed,
        lines.join("\n")
    )
}

/// The sidecar's `safety` section of a checked export, or the refusal when the
/// policy is unsafe (its nominal trace fell at `trace_fell_at_step`, or a declared
/// cell of `envelope` fails) and `allow_unsafe` is not given.
pub fn judge(
    checkpoint: &Path,
    trace_fell_at_step: Option<usize>,
    envelope: &Envelope,
    allow_unsafe: bool,
) -> Result<Value> {
    if !allow_unsafe {
        if let Some(step) = trace_fell_at_step {
            return Err(trace_refusal(checkpoint, step));
        }
        if !envelope.declared_failures().is_empty() {
            return Err(envelope_refusal(checkpoint, envelope));
        }
    }
    let t = &envelope.threshold;
    let failing: Vec<Value> = envelope
        .declared_failures()
        .iter()
        .map(|c| cell_json(c, t))
        .collect();
    let unsafe_policy = trace_fell_at_step.is_some() || !failing.is_empty();
    Ok(json!({
        "checked": true,
        "rule": "`rall export` refuses a policy whose nominal trace (`trace`) ends in a fall or whose `command_envelope` has a failing cell inside the command ranges it declares; `--allow-unsafe` writes it anyway and this section says so",
        "allowed_unsafe": allow_unsafe && unsafe_policy,
        "allow_unsafe_given": allow_unsafe,
        "nominal_trace_fell_at_step": trace_fell_at_step,
        "failing_cells": failing,
    }))
}

/// The `safety` section of an export written without the checks (rall's library
/// `export`, which the test suite calls); `rall export` always checks.
pub fn unchecked_json(trace_fell_at_step: Option<usize>) -> Value {
    json!({
        "checked": false,
        "rule": "written without the command map: no `command_envelope`; `rall export` maps commands and refuses an unsafe policy",
        "allowed_unsafe": Value::Null,
        "nominal_trace_fell_at_step": trace_fell_at_step,
    })
}
