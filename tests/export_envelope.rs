//! `rall export` maps the exported network's command envelope into the sidecar,
//! refuses an unsafe policy (writing nothing) unless `--allow-unsafe`, which the
//! sidecar then records, and states the simulator; a fall planted at one command
//! is caught, and a planted fall outside the declared ranges is reported but not
//! refused.

use std::path::{Path, PathBuf};
use std::process::Command;

use rall::env::{ACT_DIM, OBS_DIM};
use rall::eval::commands::AxisSpec;
use rall::eval::{evaluate_command_map, Actor, CommandGrid, NamedPolicy, Policy};
use rall::export::envelope::{judge, Envelope, EnvelopeOptions};
use serde_json::Value;

const RALL: &str = env!("CARGO_BIN_EXE_rall");

fn repo(path: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join(path)
}

/// The shipped walking policy of flat ground.
fn walking_checkpoint() -> PathBuf {
    repo("policies/time-to-walk.safetensors")
}

/// The checkpoint CI exports: its envelope fails at one corner of the ranges.
fn ci_checkpoint() -> PathBuf {
    repo("policies/flat-rall-eta0.5-s1-it1500.safetensors")
}

/// A shipped checkpoint that walks at 1 m/s but falls at 0.3-0.5 m/s straight
/// ahead; its nominal trace falls too.
fn falling_checkpoint() -> PathBuf {
    repo("policies/campaign-2/rall-eta0.5-s1/checkpoints/model_004500.safetensors")
}

/// `rall export ARGS` (one thread): (success, stdout, stderr).
fn rall_export(args: &[&str]) -> (bool, String, String) {
    let out = Command::new(RALL)
        .arg("export")
        .args(args)
        .args(["--threads", "1"])
        .output()
        .expect("rall runs");
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

fn read_json(path: &Path) -> Value {
    serde_json::from_str(&std::fs::read_to_string(path).expect("the sidecar exists"))
        .expect("the sidecar is JSON")
}

/// The files in `dir`.
fn files_in(dir: &Path) -> Vec<String> {
    std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect()
}

/// (vx, vy, yaw rate) of a cell of the sidecar.
fn command_of(cell: &Value) -> [f64; 3] {
    ["vx_mps", "vy_mps", "yaw_rate_rad_s"].map(|k| cell[k].as_f64().expect("a number"))
}

#[test]
fn a_safe_policy_exports_its_envelope_with_every_cell_safe() {
    let dir = tempfile::tempdir().unwrap();
    let onnx = dir.path().join("walk.onnx");
    let ckpt = walking_checkpoint();
    let (ok, out, err) = rall_export(&[
        "--checkpoint",
        ckpt.to_str().unwrap(),
        "--onnx",
        onnx.to_str().unwrap(),
        "--vx",
        "0,0.3",
        "--vy",
        "0,0.5",
        "--yaw",
        "0",
        "--robots",
        "8",
        "--seconds",
        "6",
    ]);
    assert!(ok, "{out}\n{err}");
    assert!(out.contains("4 of 4 cells safe"), "{out}");
    let side = read_json(&dir.path().join("walk.json"));
    let e = &side["command_envelope"];
    assert_eq!(e["threshold"]["max_fall_rate"], 0.05);
    assert_eq!(e["threshold"]["min_lin_tracking"], 0.8);
    assert_eq!(e["robots_per_cell"], 8);
    assert_eq!(e["episode_length_s"], 6.0);
    assert_eq!(e["episode_steps"], 300);
    assert_eq!(e["seed"], 0);
    assert_eq!(e["grid"]["vy_mps"], serde_json::json!([0.0, 0.5]));
    let cells = e["cells"].as_array().unwrap();
    assert_eq!(cells.len(), 4);
    for c in cells {
        assert_eq!(c["safe"], true, "{c}");
        assert_eq!(c["inside_declared_ranges"], true, "{c}");
        let f = &c["fall_rate"];
        assert!(f["lo"].as_f64() <= f["value"].as_f64() && f["value"].as_f64() <= f["hi"].as_f64());
    }
    assert_eq!(e["summary"]["safe_share"], 1.0);
    assert_eq!(e["summary"]["all_declared_cells_safe"], true);
    let s = &side["safety"];
    assert_eq!(
        (
            &s["checked"],
            &s["allowed_unsafe"],
            &s["nominal_trace_fell_at_step"]
        ),
        (&Value::Bool(true), &Value::Bool(false), &Value::Null)
    );
    assert_eq!(s["failing_cells"], serde_json::json!([]));

    // the cells are the map of the checkpoint itself (the export is its network)
    let p = NamedPolicy::load("walking", &ckpt).unwrap();
    let grid = CommandGrid::new(vec![0.0, 0.3], vec![0.0, 0.5], vec![0.0]).unwrap();
    let opts = EnvelopeOptions {
        robots: 8,
        episode_length_s: Some(6.0),
        ..EnvelopeOptions::default()
    };
    let map = evaluate_command_map(&p.policy, &p.env, &grid, &opts.map_options(), 1).unwrap();
    for (c, m) in cells.iter().zip(&map.cells) {
        assert_eq!(command_of(c), m.command());
        assert_eq!(c["falls"], m.falls);
        assert_eq!(c["lin_tracking"]["value"], m.lin_tracking.value);
        assert_eq!(c["yaw_tracking"]["value"], m.yaw_tracking.value);
    }

    // the simulator: the linked MuJoCo, and the grounds' generators
    let sim = &side["simulator"];
    assert_eq!(sim["mujoco_version"], "2.2.2");
    assert_eq!(sim["mujoco_version"], rall::sim::mujoco_version_string());
    assert_eq!(sim["mujoco_version_number"], 222);
    let note = sim["heightfield_note"].as_str().unwrap();
    assert!(
        note.contains("53%") && note.contains("7%") && note.contains("MuJoCo 2.2.2"),
        "{note}"
    );
    assert_eq!(sim["training_ground"]["kind"], "flat");
    let rough = &sim["rough_ground"];
    assert_eq!(rough["horizontal_scale_m"], 0.1);
    assert_eq!(rough["vertical_scale_m"], 0.005);
    assert_eq!(rough["params"]["amplitude_m"], 0.05);
    assert!(rough["noise"].as_str().unwrap().contains("uniform"));
    assert!(rough["seed_convention"]
        .as_str()
        .unwrap()
        .contains("ChaCha8Rng"));
    assert!(rough["generator"]
        .as_str()
        .unwrap()
        .contains("Ground::rough"));

    // rall reads the sidecar back (its new sections are descriptions)
    let back = NamedPolicy::load("export", &onnx).expect("rall reads its own export");
    assert_eq!(back.env.commands, p.env.commands);
}

#[test]
fn a_failing_cell_is_refused_writing_nothing_unless_allowed() {
    let dir = tempfile::tempdir().unwrap();
    let onnx = dir.path().join("p.onnx");
    let ckpt = ci_checkpoint();
    // its full envelope (16 robots, seed 0) fails at the corner vx -1, vy +1: the
    // same 16 robots run every cell, so this small grid finds the same cell
    let args = [
        "--checkpoint",
        ckpt.to_str().unwrap(),
        "--onnx",
        onnx.to_str().unwrap(),
        "--vx",
        "-1,0",
        "--vy",
        "1",
        "--yaw",
        "0",
    ];
    let (ok, out, err) = rall_export(&args);
    assert!(!ok, "an unsafe policy was exported:\n{out}\n{err}");
    for want in [
        "refusing to export",
        "1 of its 2 command cells inside the ranges it declares fail",
        "vx -1.00 m/s, vy +1.00 m/s, yaw rate +0.00 rad/s: falls 2 of 16",
        "--allow-unsafe",
        "Nothing was written",
    ] {
        assert!(err.contains(want), "{want:?} missing:\n{err}");
    }
    assert_eq!(files_in(dir.path()), Vec::<String>::new());

    let mut allowed = args.to_vec();
    allowed.push("--allow-unsafe");
    let (ok, out, err) = rall_export(&allowed);
    assert!(ok, "{out}\n{err}");
    assert!(err.contains("warning: writing an UNSAFE policy"), "{err}");
    let side = read_json(&dir.path().join("p.json"));
    let s = &side["safety"];
    assert_eq!(s["allowed_unsafe"], true);
    assert_eq!(s["nominal_trace_fell_at_step"], Value::Null);
    let failing = s["failing_cells"].as_array().unwrap();
    assert_eq!(failing.len(), 1, "{s}");
    assert_eq!(command_of(&failing[0]), [-1.0, 1.0, 0.0]);
    assert_eq!(failing[0]["falls"], 2);
    let cells = side["command_envelope"]["cells"].as_array().unwrap();
    let safe: Vec<bool> = cells.iter().map(|c| c["safe"].as_bool().unwrap()).collect();
    assert_eq!(safe, [false, true]);
    assert_eq!(side["command_envelope"]["robots_per_cell"], 16);
    assert_eq!(side["command_envelope"]["episode_length_s"], 20.0);
    let summary = &side["command_envelope"]["summary"];
    assert_eq!(summary["all_declared_cells_safe"], false);
    assert_eq!(command_of(&summary["worst_cell"]), [-1.0, 1.0, 0.0]);
    NamedPolicy::load("allowed", &onnx).expect("rall reads an allowed export");
}

#[test]
fn a_nominal_trace_that_falls_is_refused_unless_allowed() {
    let dir = tempfile::tempdir().unwrap();
    let onnx = dir.path().join("p.onnx");
    let ckpt = falling_checkpoint();
    let args = [
        "--checkpoint",
        ckpt.to_str().unwrap(),
        "--onnx",
        onnx.to_str().unwrap(),
        "--vx",
        "0.3,1.0",
        "--vy",
        "0",
        "--yaw",
        "0",
        "--robots",
        "8",
    ];
    let (ok, out, err) = rall_export(&args);
    assert!(!ok, "an unsafe policy was exported:\n{out}\n{err}");
    assert!(
        err.contains("nominal trace") && err.contains("ends in a fall at policy step 86 of 100"),
        "{err}"
    );
    assert!(
        err.contains("--allow-unsafe") && err.contains("Nothing was written"),
        "{err}"
    );
    assert_eq!(files_in(dir.path()), Vec::<String>::new());

    let mut allowed = args.to_vec();
    allowed.push("--allow-unsafe");
    let (ok, out, err) = rall_export(&allowed);
    assert!(ok, "{out}\n{err}");
    let side = read_json(&dir.path().join("p.json"));
    let s = &side["safety"];
    assert_eq!(s["allowed_unsafe"], true);
    assert_eq!(s["nominal_trace_fell_at_step"], 86);
    assert_eq!(side["trace"]["steps"], 86);
    // its map fails walking slowly straight ahead, not at 1 m/s
    let failing: Vec<[f64; 3]> = s["failing_cells"]
        .as_array()
        .unwrap()
        .iter()
        .map(command_of)
        .collect();
    assert_eq!(failing, vec![[0.3, 0.0, 0.0]]);
    // a policy trained on rough ground states its terrain generator
    let ground = &side["simulator"]["training_ground"];
    assert_eq!(ground["kind"], "rough");
    assert_eq!(ground["horizontal_scale_m"], 0.1);
    assert_eq!(ground["vertical_scale_m"], 0.005);
    assert!(ground["seed"].is_u64());
    assert!(ground["ground_xml"]
        .as_str()
        .unwrap()
        .contains("type=\"hfield\""));
    assert!(ground["seed_convention"]
        .as_str()
        .unwrap()
        .contains("set_stream"));
    NamedPolicy::load("allowed", &onnx).expect("rall reads an allowed export");
}

/// Where the command sits in rall's observation row (after base linear and
/// angular velocity and gravity, 3 each).
const COMMAND_COLUMN: usize = 9;

/// Where the previous action sits in the observation row.
const PREVIOUS_ACTION_COLUMN: usize = 36;

/// The walking policy, except at one command: there every joint's target swings
/// between its limits from one step to the next.
struct PlantedFall {
    walking: Policy,
    /// The planted command as it appears in the observation (times the scales).
    observed: [f32; 3],
}

impl PlantedFall {
    fn new(p: NamedPolicy, command: [f64; 3]) -> PlantedFall {
        let scale = p.env.observation.command_scale;
        PlantedFall {
            walking: p.policy,
            observed: [0, 1, 2].map(|k| (command[k] * scale[k]) as f32),
        }
    }
}

impl Actor for PlantedFall {
    fn actions(&self, obs: &[f32]) -> anyhow::Result<Vec<f32>> {
        let mut actions = self.walking.actions(obs)?;
        for (row, out) in obs
            .chunks_exact(OBS_DIM)
            .zip(actions.chunks_exact_mut(ACT_DIM))
        {
            let command = &row[COMMAND_COLUMN..COMMAND_COLUMN + 3];
            if command
                .iter()
                .zip(&self.observed)
                .all(|(a, b)| (a - b).abs() < 1e-6)
            {
                let swing = if row[PREVIOUS_ACTION_COLUMN] > 0.0 {
                    -40.0
                } else {
                    40.0
                };
                out.fill(swing);
            }
        }
        Ok(actions)
    }
}

/// A small envelope: these vx values x vy 0 x these yaw rates, 4 robots, 3 s.
fn small_envelope(vx: &[f64], yaw: &[f64]) -> EnvelopeOptions {
    EnvelopeOptions {
        axes: [
            AxisSpec::Values(vx.to_vec()),
            AxisSpec::Values(vec![0.0]),
            AxisSpec::Values(yaw.to_vec()),
        ],
        robots: 4,
        episode_length_s: Some(3.0),
        seed: 3,
        threads: 1,
        ..EnvelopeOptions::default()
    }
}

#[test]
fn a_fall_planted_at_one_command_is_caught_and_refused() {
    let walking = NamedPolicy::load("walking", &walking_checkpoint()).unwrap();
    let env = walking.env.clone();
    let opts = small_envelope(&[0.0, 0.5], &[0.0, 0.5]);
    let ckpt = walking_checkpoint();
    // the walking policy alone passes this grid
    let clean = Envelope::measure(&walking.policy, &env, &opts, "walking").unwrap();
    assert!(
        clean.declared_failures().is_empty(),
        "{}",
        clean.map.table(&clean.threshold)
    );
    let verdict = judge(&ckpt, None, &clean, false).unwrap();
    assert_eq!(verdict["allowed_unsafe"], false);

    let planted_at = [0.5, 0.0, 0.0];
    let planted = PlantedFall::new(walking, planted_at);
    let e = Envelope::measure(&planted, &env, &opts, "planted").unwrap();
    let failing: Vec<[f64; 3]> = e.declared_failures().iter().map(|c| c.command()).collect();
    assert_eq!(failing, vec![planted_at], "{}", e.map.table(&e.threshold));
    let err = format!("{:#}", judge(&ckpt, None, &e, false).unwrap_err());
    assert!(
        err.contains("1 of its 4 command cells")
            && err.contains("vx +0.50 m/s, vy +0.00 m/s, yaw rate +0.00 rad/s: falls 4 of 4")
            && err.contains("--allow-unsafe"),
        "{err}"
    );
    let safety = judge(&ckpt, None, &e, true).unwrap();
    assert_eq!(safety["allowed_unsafe"], true);
    let listed: Vec<[f64; 3]> = safety["failing_cells"]
        .as_array()
        .unwrap()
        .iter()
        .map(command_of)
        .collect();
    assert_eq!(listed, vec![planted_at]);
    let side = e.json(&ckpt);
    let unsafe_cells: Vec<[f64; 3]> = side["cells"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|c| c["safe"] == false)
        .map(command_of)
        .collect();
    assert_eq!(unsafe_cells, vec![planted_at]);
    assert_eq!(side["summary"]["safe_share"], 0.75);
    assert_eq!(command_of(&side["summary"]["worst_cell"]), planted_at);
    // a nominal trace that fell is refused even when the map passes
    let err = format!("{:#}", judge(&ckpt, Some(42), &clean, false).unwrap_err());
    assert!(
        err.contains("nominal trace") && err.contains("step 42"),
        "{err}"
    );
    let safety = judge(&ckpt, Some(42), &clean, true).unwrap();
    assert_eq!(safety["nominal_trace_fell_at_step"], 42);
    assert_eq!(safety["allowed_unsafe"], true);
}

#[test]
fn a_fall_outside_the_declared_ranges_is_reported_not_refused() {
    let walking = NamedPolicy::load("walking", &walking_checkpoint()).unwrap();
    let env = walking.env.clone();
    // the policy declares vx in [-1, 1] m/s: 1.5 m/s is outside
    let planted_at = [1.5, 0.0, 0.0];
    let planted = PlantedFall::new(walking, planted_at);
    let e = Envelope::measure(
        &planted,
        &env,
        &small_envelope(&[0.0, 1.5], &[0.0]),
        "planted",
    )
    .unwrap();
    let cell = e.map.cell(planted_at).unwrap();
    assert!(
        !cell.is_safe(&e.threshold) && !cell.commanded_in_training,
        "{cell:?}"
    );
    assert!(e.declared_failures().is_empty());
    let safety = judge(&walking_checkpoint(), None, &e, false).unwrap();
    assert_eq!(safety["allowed_unsafe"], false);
    let side = e.json(&walking_checkpoint());
    assert_eq!(side["summary"]["all_declared_cells_safe"], true);
    assert_eq!(side["summary"]["safe_share"], 0.5);
    assert_eq!(side["cells"][1]["inside_declared_ranges"], false);
}

#[test]
fn bad_envelope_flags_are_refused_naming_them() {
    let dir = tempfile::tempdir().unwrap();
    let onnx = dir.path().join("x.onnx");
    let ckpt = walking_checkpoint();
    for (args, want) in [
        (&["--robots", "0"][..], "--robots 0"),
        (&["--vx-cells", "0"][..], "--vx-cells 0"),
        (&["--seconds", "-1"][..], "--seconds -1"),
        (&["--vx", "0.5,0.5"][..], "twice"),
        (
            &["--vx", "5", "--vy", "0", "--yaw", "0"][..],
            "no cell inside",
        ),
    ] {
        let mut all = vec![
            "--checkpoint",
            ckpt.to_str().unwrap(),
            "--onnx",
            onnx.to_str().unwrap(),
        ];
        all.extend_from_slice(args);
        let (ok, out, err) = rall_export(&all);
        assert!(!ok, "{args:?} was accepted:\n{out}");
        assert!(err.contains(want), "{args:?}: {want:?} missing:\n{err}");
        assert!(!err.contains("panicked"), "{err}");
    }
    assert_eq!(files_in(dir.path()), Vec::<String>::new());
}
