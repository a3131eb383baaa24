//! `rall export`: a checkpoint's policy as ONNX + a JSON sidecar for a robot controller.

use std::path::PathBuf;

use anyhow::Result;
use clap::Args;

use crate::export::{export, ExportOptions};

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

#[derive(Debug, Args)]
#[command(after_long_help = ROBOT_LOOP)]
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
}

pub fn run(args: &ExportArgs) -> Result<()> {
    let opts = ExportOptions {
        reference_count: args.references,
        seed: args.seed,
    };
    let r = export(&args.checkpoint, &args.onnx, &opts)?;
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
