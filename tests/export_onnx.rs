//! `rall export` writes a standard ONNX policy that a runtime we did not
//! write (tract) runs to rall's actions within 1e-5, and a sidecar with what a
//! controller needs.

use std::path::{Path, PathBuf};

use rall::env::{ACT_DIM, OBS_DIM};
use rall::eval::{Actor, OnnxPolicy};
use rall::export::{export, export_learner, sidecar_path, ExportOptions, REFERENCE_TOLERANCE};
use rall::learn::{Learner, NamedTensor};
use rall::runner::load_policy;
use tract_onnx::prelude::*;

/// The trained RALL policy kept in the repository.
fn trained_checkpoint() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("policies/flat-rall-eta0.5-s1-it1500.safetensors")
}

fn rows(v: &serde_json::Value, width: usize) -> Vec<f32> {
    let rows = v.as_array().expect("array of rows");
    let mut out = Vec::new();
    for r in rows {
        let r = r.as_array().expect("row");
        assert_eq!(r.len(), width);
        out.extend(r.iter().map(|x| x.as_f64().expect("number") as f32));
    }
    out
}

/// Runs the ONNX file in tract on its inputs (each `n x width`, in graph order),
/// batch dimension left symbolic.
fn run_tract_inputs(path: &Path, inputs: &[(&[f32], usize)]) -> Vec<f32> {
    let n = inputs[0].0.len() / inputs[0].1;
    let model = tract_onnx::onnx()
        .model_for_path(path)
        .expect("tract reads the file")
        .into_optimized()
        .expect("tract optimises the graph")
        .into_runnable()
        .expect("runnable");
    let values: TVec<TValue> = inputs
        .iter()
        .map(|(rows, width)| {
            let a = tract_ndarray::Array2::from_shape_vec((n, *width), rows.to_vec()).unwrap();
            Tensor::from(a).into()
        })
        .collect();
    let out = model.run(values).expect("tract runs the model");
    let view = out[0].to_plain_array_view::<f32>().expect("f32 output");
    assert_eq!(view.shape(), &[n, ACT_DIM]);
    view.iter().copied().collect()
}

/// Runs the ONNX file in tract on `obs` (`n x OBS_DIM`).
fn run_tract(path: &Path, obs: &[f32]) -> Vec<f32> {
    run_tract_inputs(path, &[(obs, OBS_DIM)])
}

fn max_abs_diff(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len());
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max)
}

#[test]
fn tract_runs_the_exported_policy_to_rall_actions() {
    let dir = tempfile::tempdir().unwrap();
    let onnx = dir.path().join("policy.onnx");
    let ckpt = trained_checkpoint();
    let report = export(&ckpt, &onnx, &ExportOptions::default()).unwrap();
    assert_eq!(report.iteration, 1500);
    assert_eq!(report.sidecar_path, dir.path().join("policy.json"));
    let sidecar: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(sidecar_path(&onnx)).unwrap()).unwrap();

    let obs = rows(&sidecar["reference"]["observations"], OBS_DIM);
    let actions = rows(&sidecar["reference"]["actions"], ACT_DIM);
    assert_eq!(obs.len() / OBS_DIM, 8);
    // The references are rall's own actions for those observations...
    let learner = load_policy(&ckpt).unwrap().learner;
    assert!(max_abs_diff(&learner.act_mean(&obs), &actions) <= 1e-6);
    // ...and tract reproduces them, as a batch and one row at a time (dynamic batch).
    let batch = run_tract(&onnx, &obs);
    let d = max_abs_diff(&batch, &actions);
    assert!(
        d as f64 <= REFERENCE_TOLERANCE,
        "tract batch differs by {d}"
    );
    let one = run_tract(&onnx, &obs[OBS_DIM * 3..OBS_DIM * 4]);
    let d1 = max_abs_diff(&one, &actions[ACT_DIM * 3..ACT_DIM * 4]);
    assert!(
        d1 as f64 <= REFERENCE_TOLERANCE,
        "tract batch 1 differs by {d1}"
    );
    // The policy really acts (a graph of zeros would match a zero policy, not this one).
    assert!(actions.iter().any(|a| a.abs() > 0.05));

    // Observations past the first one differ (the rollout moved).
    assert!(max_abs_diff(&obs[..OBS_DIM], &obs[OBS_DIM * 7..]) > 1e-3);
    // First reference = the reset state: level trunk, default pose, no previous action.
    assert_eq!(&obs[6..9], &[0.0, 0.0, -1.0]);
    assert!(obs[12..24].iter().all(|&q| q == 0.0));
    assert!(obs[36..48].iter().all(|&a| a == 0.0));
}

/// A policy trained with `learner.obs_normalization` exports with its normaliser
/// as the graph's first nodes: the graph reads raw observations, and rall's own
/// forward of the export gives the checkpoint's actions bit for bit.
#[test]
fn a_normalised_policy_exports_with_its_normaliser_in_the_graph() {
    let dir = tempfile::tempdir().unwrap();
    let onnx = dir.path().join("normalised.onnx");
    let ckpt = trained_checkpoint();
    let loaded = load_policy(&ckpt).unwrap();
    let mut config = loaded.config.clone();
    config.learner.obs_normalization = true;
    let mut learner =
        Learner::with_layout(&config.env.obs_layout(), ACT_DIM, &config.learner, 1).unwrap();
    let mut state = loaded.learner.state();
    let tensor = |name: &str, data: Vec<f32>| NamedTensor {
        name: name.into(),
        shape: vec![data.len()],
        data,
    };
    state.push(tensor(
        "obs_norm.mean",
        (0..OBS_DIM).map(|j| 0.05 * j as f32 - 1.0).collect(),
    ));
    state.push(tensor(
        "obs_norm.var",
        (0..OBS_DIM)
            .map(|j| (0.5 + 0.02 * j as f32).powi(2))
            .collect(),
    ));
    state.push(tensor("obs_norm.count", vec![0.0, 1000.0]));
    learner.load_state(&state).unwrap();
    export_learner(
        &learner,
        &config,
        &loaded.progress,
        &ckpt,
        &onnx,
        &ExportOptions::default(),
    )
    .unwrap();
    let sidecar: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(sidecar_path(&onnx)).unwrap()).unwrap();
    assert_eq!(sidecar["onnx"]["normalizer"]["kind"], "in_graph");
    let obs = rows(&sidecar["reference"]["observations"], OBS_DIM);
    let actions = rows(&sidecar["reference"]["actions"], ACT_DIM);
    assert!(max_abs_diff(&learner.act_mean(&obs), &actions) <= 1e-6);
    // the normaliser changes the actions, and tract reproduces the normalised ones
    assert!(max_abs_diff(&loaded.learner.act_mean(&obs), &actions) > 1e-2);
    let d = max_abs_diff(&run_tract(&onnx, &obs), &actions);
    assert!(d as f64 <= REFERENCE_TOLERANCE, "tract differs by {d}");
    let exact = OnnxPolicy::load(&onnx).unwrap();
    assert!(exact.runs_on_rall_forward());
    assert_eq!(exact.actions(&obs).unwrap(), learner.act_mean(&obs));
}

#[test]
fn the_sidecar_says_what_a_controller_needs() {
    let dir = tempfile::tempdir().unwrap();
    let onnx = dir.path().join("out/p.onnx");
    export(
        &trained_checkpoint(),
        &onnx,
        &ExportOptions {
            reference_count: 2,
            seed: 3,
        },
    )
    .unwrap();
    let s: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.path().join("out/p.json")).unwrap())
            .unwrap();
    assert_eq!(s["onnx"]["opset"], 13);
    assert_eq!(s["onnx"]["inputs"][0]["shape"][0], "batch");
    assert_eq!(s["onnx"]["inputs"][0]["shape"][1], 48);
    assert_eq!(s["onnx"]["normalizer"]["kind"], "identity");
    assert_eq!(s["checkpoint"]["iteration"], 1500);
    assert_eq!(s["checkpoint"]["config_hash"].as_str().unwrap().len(), 16);
    let names: Vec<&str> = s["joints"]["names"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_str().unwrap())
        .collect();
    assert_eq!(names[0], "FR_hip_joint");
    assert_eq!(names[4], "FL_thigh_joint");
    assert_eq!(names[11], "RL_calf_joint");
    let q0 = &s["joints"]["default_angles_rad"];
    assert_eq!(q0["FR_thigh_joint"], 0.8);
    assert_eq!(q0["RR_thigh_joint"], 1.0);
    assert_eq!(q0["FL_hip_joint"], 0.1);
    assert_eq!(q0["RL_calf_joint"], -1.5);
    assert_eq!(s["joints"]["torque_limits_nm"]["RL_calf_joint"], 55.0);
    assert_eq!(s["action"]["scale_rad"], 0.25);
    assert_eq!(s["pd"]["kp_nm_per_rad"], 50.0);
    assert_eq!(s["pd"]["kd_nm_s_per_rad"], 0.8);
    assert_eq!(s["rates"]["policy_rate_hz"], 50.0);
    assert_eq!(s["rates"]["decimation"], 4);
    let fields = s["observation"]["fields"].as_array().unwrap();
    assert_eq!(fields.len(), 7);
    assert_eq!(fields[0]["name"], "base_lin_vel_body");
    assert_eq!(fields[0]["scale"][0], 2.0);
    assert!(fields[2]["definition"].as_str().unwrap().contains("UNIT"));
    assert!(fields[6]["definition"]
        .as_str()
        .unwrap()
        .contains("BEFORE the clip"));
    assert_eq!(fields[5]["scale"][0], 0.05);
    let tensors = s["network"]["checkpoint_tensors"].as_array().unwrap();
    assert_eq!(tensors[0]["name"], "actor.l0.weight");
    assert_eq!(tensors[0]["shape"][0], 48);
    assert_eq!(s["reference"]["observations"].as_array().unwrap().len(), 2);
}

#[test]
fn bad_input_is_refused_with_the_cause() {
    let dir = tempfile::tempdir().unwrap();
    let missing = dir.path().join("nope.safetensors");
    let err = export(
        &missing,
        &dir.path().join("a.onnx"),
        &ExportOptions::default(),
    )
    .unwrap_err();
    assert!(format!("{err:#}").contains("nope.safetensors"), "{err:#}");
    let err = export(
        &trained_checkpoint(),
        &dir.path().join("a.txt"),
        &ExportOptions::default(),
    )
    .unwrap_err();
    assert!(err.to_string().contains(".onnx"), "{err}");
    let junk = dir.path().join("junk.safetensors");
    std::fs::write(&junk, b"not a checkpoint").unwrap();
    let err = export(&junk, &dir.path().join("b.onnx"), &ExportOptions::default()).unwrap_err();
    assert!(format!("{err:#}").contains("junk.safetensors"), "{err:#}");
    assert!(!dir.path().join("b.onnx").exists());
}

/// Runs a two-input (obs, history) student graph in tract.
fn run_tract_student(path: &Path, obs: &[f32], history: &[f32], hist_width: usize) -> Vec<f32> {
    run_tract_inputs(path, &[(obs, OBS_DIM), (history, hist_width)])
}

#[test]
fn an_rma_student_exports_with_its_history_input_and_tract_agrees() {
    use std::sync::atomic::AtomicBool;
    use std::sync::Arc;
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let mut cfg =
        rall::config::TrainConfig::from_toml_file(&root.join("configs/flat-rma.toml")).unwrap();
    cfg.env.robot_mjcf = root.join("mjcf/aliengo.xml").display().to_string();
    cfg.env.episode.length_s = 0.5;
    cfg.env.observation.history_steps = 6;
    cfg.learner.actor_hidden = vec![32, 32];
    cfg.learner.critic_hidden = vec![32, 32];
    cfg.learner.encoder.as_mut().unwrap().hidden = vec![16];
    let a = cfg.learner.adaptation.as_mut().unwrap();
    a.hidden = vec![24, 16];
    a.iterations = 1;
    cfg.runner.num_envs = 8;
    cfg.runner.steps_per_env = 8;
    cfg.runner.iterations = 1;
    cfg.runner.threads = 2;
    let dir = tempfile::tempdir().unwrap();
    let s = rall::runner::train(
        cfg,
        &dir.path().join("rma"),
        false,
        Arc::new(AtomicBool::new(false)),
        &mut (),
    )
    .unwrap();
    let onnx = dir.path().join("student.onnx");
    export(&s.last_checkpoint, &onnx, &ExportOptions::default()).unwrap();
    let side: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(sidecar_path(&onnx)).unwrap()).unwrap();
    assert_eq!(side["network"]["kind"], "rma_student");
    assert_eq!(side["history"]["steps"], 6);
    let width = 6 * OBS_DIM;
    assert_eq!(side["history"]["width"], width);
    let inputs: Vec<&str> = side["onnx"]["inputs"]
        .as_array()
        .unwrap()
        .iter()
        .map(|i| i["name"].as_str().unwrap())
        .collect();
    assert_eq!(inputs, ["obs", "history"]);
    let obs = rows(&side["reference"]["observations"], OBS_DIM);
    let hist = rows(&side["reference"]["history"], width);
    let want = rows(&side["reference"]["actions"], ACT_DIM);
    // the reference history starts with this step's obs (newest first)
    for (o, h) in obs.chunks(OBS_DIM).zip(hist.chunks(width)) {
        assert_eq!(o, &h[..OBS_DIM]);
    }
    let got = run_tract_student(&onnx, &obs, &hist, width);
    let d = max_abs_diff(&got, &want);
    assert!(
        d <= REFERENCE_TOLERANCE as f32,
        "tract differs from rall by {d}"
    );
    let one = run_tract_student(&onnx, &obs[..OBS_DIM], &hist[..width], width);
    assert!(max_abs_diff(&one, &want[..ACT_DIM]) <= REFERENCE_TOLERANCE as f32);
    assert!(
        want.iter().any(|a| a.abs() > 1e-3),
        "reference actions are all ~0"
    );
}
