//! `rall export`: a checkpoint's policy as ONNX + a JSON sidecar for a robot controller.

use std::path::PathBuf;

use anyhow::Result;
use clap::Args;

use crate::eval::commands::{parse_axis_values, AxisSpec};
use crate::export::envelope::{EnvelopeOptions, DEFAULT_CELLS, DEFAULT_ROBOTS};
use crate::export::{export_checked, ExportOptions, SafetyCheck};

/// How to run the exported policy (shown by `rall export --help`).
const ROBOT_LOOP: &str = "\
Running the exported policy on a robot (50 Hz policy, 200 Hz PD):

  every 20 ms:
    obs (1 x 48, float32) = concatenation, each value times its scale, then clipped to +-100:
      [0:3]   trunk linear velocity in the BODY frame (m/s, of the trunk origin) x 2.0
      [3:6]   trunk angular velocity in the BODY frame (rad/s, gyroscope)       x 0.25
      [6:9]   gravity direction in the body frame, a UNIT vector ((0,0,-1) level; not m/s^2)
      [9:12]  command vx, vy (m/s, body frame), yaw rate (rad/s)                 x 2, 2, 0.25
      [12:24] joint angle - default angle (rad), order FR, FL, RR, RL x hip, thigh, calf
      [24:36] joint velocity (rad/s)                                           x 0.05
      [36:48] previous action: the RAW network output of the last step (before clip
              and scale; zeros at start)
    a = onnx(obs)            input `obs`, output `actions` (1 x 12): keep a for the next obs
    q_target = default + 0.25 * clip(a, -100, 100)
  every 5 ms until the next policy step:
    tau = clip(50 * (q_target - q) - 0.8 * qdot, +-[44, 44, 55] N m per hip/thigh/calf)

Default angles (rad): hip FR -0.1, FL 0.1, RR -0.1, RL 0.1; thigh FR 0.8, FL 0.8,
RR 1.0, RL 1.0 (front and rear differ); calf -1.5. The numbers above are the defaults:
the sidecar OUT.json holds the checkpoint's own values (scales, gains, limits, rates,
default angles by joint name, field definitions), the network's tensor names and
layout, and reference observations with the actions rall computes for them (check
your runtime against them to 1e-5). See docs/deploy.md.

An RMA student (an RMA checkpoint after phase 2) has a second input,
`history` (1 x 50*48): the last 50 obs, newest first (slot 0 = this step's obs), zeros
at the start of an episode; each step: history = [obs, history minus its last 48 values],
then a = onnx(obs, history). The sidecar's `history` section gives its length.";

/// How `rall export` checks the policy (shown by `rall export --help`).
const SAFETY: &str = "\
Before writing, rall export checks the policy and refuses an unsafe one (non-zero exit,
nothing written): its nominal trace (vx 0.5 m/s on flat ground, no noise) must not fall,
and its command map (rall eval commands on the exported network: flat ground, the
checkpoint's own noise, PD and randomisation, no pushes, no payload) must have no failing
cell (falls >= 5% or linear tracking < 0.8) inside the command ranges the policy declares.
The map goes into the sidecar as `command_envelope`, the verdict as `safety`.
--allow-unsafe writes an unsafe policy anyway and records it (`safety.allowed_unsafe`).";

#[derive(Debug, Args)]
#[command(after_long_help = format!("{ROBOT_LOOP}\n\n{SAFETY}"))]
pub struct ExportArgs {
    /// Checkpoint to export (e.g. runs/<run>/latest.safetensors).
    #[arg(long)]
    pub checkpoint: PathBuf,
    /// Output ONNX file (opset 13, dynamic batch); the sidecar is written beside it with
    /// the extension .json.
    #[arg(long, value_name = "OUT.onnx")]
    pub onnx: PathBuf,
    /// Number of reference observation/action pairs in the sidecar.
    #[arg(long, default_value_t = 8)]
    pub references: usize,
    /// Seed of the rollout the reference observations come from.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Envelope: forward speeds evenly spaced over the policy's vx range, both ends
    /// included (and 0 when the range spans it).
    #[arg(long, value_name = "N", default_value_t = DEFAULT_CELLS[0], value_parser = parse_count, allow_hyphen_values = true)]
    pub vx_cells: usize,
    /// Envelope: lateral speeds evenly spaced over the policy's vy range.
    #[arg(long, value_name = "N", default_value_t = DEFAULT_CELLS[1], value_parser = parse_count, allow_hyphen_values = true)]
    pub vy_cells: usize,
    /// Envelope: yaw rates evenly spaced over the policy's yaw-rate range.
    #[arg(long, value_name = "N", default_value_t = DEFAULT_CELLS[2], value_parser = parse_count, allow_hyphen_values = true)]
    pub yaw_cells: usize,
    /// Envelope: forward speeds to map instead (m/s), e.g. -1,-0.5,0,0.5,1.
    #[arg(
        long,
        value_name = "LIST",
        conflicts_with = "vx_cells",
        allow_hyphen_values = true
    )]
    pub vx: Option<String>,
    /// Envelope: lateral speeds to map instead (m/s).
    #[arg(
        long,
        value_name = "LIST",
        conflicts_with = "vy_cells",
        allow_hyphen_values = true
    )]
    pub vy: Option<String>,
    /// Envelope: yaw rates to map instead (rad/s).
    #[arg(
        long,
        value_name = "LIST",
        conflicts_with = "yaw_cells",
        allow_hyphen_values = true
    )]
    pub yaw: Option<String>,
    /// Envelope: robots per cell, one episode each.
    #[arg(long, value_name = "N", default_value_t = DEFAULT_ROBOTS, value_parser = parse_count, allow_hyphen_values = true)]
    pub robots: usize,
    /// Envelope: episode length in seconds (default: the checkpoint's).
    #[arg(long, value_name = "S", allow_hyphen_values = true)]
    pub seconds: Option<f64>,
    /// Worker threads of the envelope (0 = all cores); the numbers do not depend on it.
    #[arg(long, default_value_t = 0)]
    pub threads: usize,
    /// Write the policy even when it is unsafe (its nominal trace falls, or a cell
    /// inside its declared command ranges fails); the sidecar records it.
    #[arg(long)]
    pub allow_unsafe: bool,
}

/// A count flag: a whole number, not negative.
fn parse_count(s: &str) -> std::result::Result<usize, String> {
    match s.trim().parse::<i64>() {
        Ok(n) if n < 0 => Err("a count cannot be negative".into()),
        Ok(n) => usize::try_from(n).map_err(|e| e.to_string()),
        Err(_) => Err("expected a whole number".into()),
    }
}

/// The envelope's options from the flags.
fn safety_check(args: &ExportArgs) -> Result<SafetyCheck> {
    let axis = |values: &Option<String>, flag: &str, cells: usize| -> Result<AxisSpec> {
        Ok(match values {
            Some(text) => AxisSpec::Values(parse_axis_values(flag, text)?),
            None => AxisSpec::Cells(cells),
        })
    };
    Ok(SafetyCheck {
        envelope: EnvelopeOptions {
            axes: [
                axis(&args.vx, "--vx", args.vx_cells)?,
                axis(&args.vy, "--vy", args.vy_cells)?,
                axis(&args.yaw, "--yaw", args.yaw_cells)?,
            ],
            robots: args.robots,
            episode_length_s: args.seconds,
            threads: args.threads,
            ..EnvelopeOptions::default()
        },
        allow_unsafe: args.allow_unsafe,
    })
}

pub fn run(args: &ExportArgs) -> Result<()> {
    let opts = ExportOptions {
        reference_count: args.references,
        seed: args.seed,
    };
    let r = export_checked(&args.checkpoint, &args.onnx, &opts, &safety_check(args)?)?;
    if let Some(e) = &r.envelope {
        println!(
            "command envelope: {} of {} cells safe, {} failing inside the declared command ranges",
            e.safe_cells, e.cells, e.declared_failures
        );
        if e.allowed_unsafe {
            eprintln!(
                "warning: writing an UNSAFE policy (--allow-unsafe): {}{} failing cells inside its declared command ranges; its sidecar records them under `safety`",
                e.trace_fell_at_step
                    .map_or(String::new(), |s| format!("its nominal trace falls at step {s}; ")),
                e.declared_failures
            );
        }
    }
    println!(
        "wrote {} ({} bytes, iteration {}, config hash {}) and {} ({} reference pairs)",
        r.onnx_path.display(),
        r.onnx_bytes,
        r.iteration,
        r.config_hash,
        r.sidecar_path.display(),
        r.reference_count
    );
    Ok(())
}
