//! Policies from outside rall: an ONNX network with its JSON sidecar runs in the
//! benchmarks like a checkpoint. A rall checkpoint and its own export give the
//! same env and, run through rall's own forward, the same TTF table bit for bit,
//! pushes included; other graphs run through tract. A sidecar asking for what
//! rall cannot produce is refused, naming the field.

use std::path::{Path, PathBuf};

use prost::Message;
use rall::env::OBS_DIM;
use rall::eval::ttf::TtfCell;
use rall::eval::{
    evaluate_ttf, Actor, GroundKind, Load, NamedPolicy, OnnxPolicy, OnnxRuntime, Policy,
    ScenarioParams, TtfOptions,
};
use rall::export::onnx::{encode, ModelProto};
use rall::export::{export, sidecar_path, ExportOptions};

fn trained_checkpoint() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("policies/flat-rall-eta0.5-s1-it1500.safetensors")
}

/// The shipped checkpoint exported into `dir`; (checkpoint, onnx) as benchmark policies.
fn checkpoint_and_export(dir: &Path) -> (NamedPolicy, NamedPolicy, PathBuf) {
    let onnx = dir.join("policy.onnx");
    export(&trained_checkpoint(), &onnx, &ExportOptions::default()).expect("export");
    let ckpt = NamedPolicy::load("ckpt", &trained_checkpoint()).expect("checkpoint loads");
    let outside = NamedPolicy::load("onnx", &onnx).expect("the export loads as an ONNX policy");
    (ckpt, outside, onnx)
}

/// The largest difference between the two policies' actions over `obs`.
fn max_action_diff(a: &dyn Actor, b: &dyn Actor, obs: &[f32]) -> f32 {
    let (x, y) = (a.actions(obs).unwrap(), b.actions(obs).unwrap());
    x.iter()
        .zip(&y)
        .map(|(p, q)| (p - q).abs())
        .fold(0.0, f32::max)
}

#[test]
fn an_export_runs_in_the_env_of_its_checkpoint_and_gives_the_same_ttf_with_pushes() {
    let dir = tempfile::tempdir().unwrap();
    let (ckpt, outside, _) = checkpoint_and_export(dir.path());
    // The sidecar carries every env setting a benchmark reads; rewards and risk
    // penalties (race returns only) are not part of it.
    let mut from_sidecar = outside.env.clone();
    from_sidecar.reward = ckpt.env.reward.clone();
    from_sidecar.risk = ckpt.env.risk.clone();
    assert_eq!(
        from_sidecar, ckpt.env,
        "the sidecar's env differs from the checkpoint's"
    );
    assert!(ckpt.policy.learner().is_some() && outside.policy.learner().is_none());
    let Policy::Onnx(onnx) = &outside.policy else {
        panic!("the export loaded as a checkpoint")
    };
    assert!(
        onnx.runs_on_rall_forward(),
        "rall's own export was not recognised: tract runs it"
    );

    // Pushes strong and frequent enough that robots fall: a fall under a push
    // amplifies the smallest difference in the actions (under tract, whose f32
    // matrix products sum in another order, 3 of 8 robots fell at other steps).
    let opts = TtfOptions {
        seeds: vec![0],
        repeats: 4,
        threads: 2,
        loads: vec![Load::Ball],
        terrains: vec![GroundKind::Flat, GroundKind::Rough],
        pushes: vec![false, true],
        params: ScenarioParams {
            episode_length_s: Some(6.0),
            push_force_n: 150.0,
            push_every_steps: 100,
            ..ScenarioParams::default()
        },
    };
    let run = |p: &NamedPolicy| {
        let one = NamedPolicy::load(&p.name, p.path.as_deref().unwrap()).unwrap();
        evaluate_ttf(&[one], &opts, |_| {}).expect("ttf")
    };
    let (a, b) = (run(&ckpt), run(&outside));
    assert_eq!(a.cells.len(), 4);
    assert_eq!(a.cells.len(), b.cells.len());
    let (mut robots, mut falls) = (0, 0);
    for (x, y) in a.cells.iter().zip(&b.cells) {
        eprintln!(
            "{} push {}: checkpoint TTF {} falls {} steps {:?} strict {:?}; onnx TTF {} falls {} steps {:?} strict {:?}",
            x.terrain, x.push, x.ttf, x.falls, x.steps_per_robot, x.strict_steps_per_robot,
            y.ttf, y.falls, y.steps_per_robot, y.strict_steps_per_robot
        );
        // every number of the cell, bit for bit (the policy's name aside)
        let y = TtfCell {
            policy: x.policy.clone(),
            ..y.clone()
        };
        assert_eq!(
            x, &y,
            "{} push {}: the checkpoint and its export differ",
            x.terrain, x.push
        );
        robots += x.robots;
        falls += x.falls;
    }
    eprintln!("{falls} of {robots} robots fell, each at the same step under both");
    assert!(
        a.cells.iter().any(|c| c.push && c.falls > 0),
        "no robot fell under the pushes: the comparison would not test a fall"
    );
}

#[test]
fn tract_and_rall_give_the_same_actions_on_the_reference_observations() {
    let dir = tempfile::tempdir().unwrap();
    let (ckpt, outside, onnx) = checkpoint_and_export(dir.path());
    let side: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(sidecar_path(&onnx)).unwrap()).unwrap();
    let obs: Vec<f32> = side["trace"]["obs"]
        .as_array()
        .unwrap()
        .iter()
        .flat_map(|r| {
            r.as_array()
                .unwrap()
                .iter()
                .map(|v| v.as_f64().unwrap() as f32)
        })
        .collect();
    // rall's forward on its own export: the checkpoint's actions exactly
    assert_eq!(
        ckpt.policy.actions(&obs).unwrap(),
        outside.policy.actions(&obs).unwrap()
    );
    // tract on the same graph: within float rounding
    let tract = OnnxPolicy::load_with(&onnx, OnnxRuntime::Tract).unwrap();
    assert!(!tract.runs_on_rall_forward());
    let d = max_action_diff(&ckpt.policy, &tract, &obs);
    eprintln!("max |rall - tract| over the trace's observations: {d:e}");
    assert!(d <= 1e-5, "tract differs from rall by {d}");
}

#[test]
fn a_graph_rall_does_not_write_runs_through_tract() {
    let dir = tempfile::tempdir().unwrap();
    let (ckpt, _, onnx) = checkpoint_and_export(dir.path());
    // ELU with another alpha: not the form of rall's exports, so tract runs it
    let mut model = ModelProto::decode(std::fs::read(&onnx).unwrap().as_slice()).unwrap();
    let graph = model.graph.as_mut().unwrap();
    let elu = graph.node.iter_mut().find(|n| n.op_type == "Elu").unwrap();
    elu.attribute[0].f = 0.5;
    let other = dir.path().join("other.onnx");
    std::fs::write(&other, encode(&model)).unwrap();
    std::fs::copy(sidecar_path(&onnx), sidecar_path(&other)).unwrap();
    let p = OnnxPolicy::load(&other).unwrap();
    assert!(!p.runs_on_rall_forward());
    let obs = vec![0.1f32; OBS_DIM];
    assert!(max_action_diff(&ckpt.policy, &p, &obs) > 0.0);
}

/// Writes the export's sidecar with `edit` applied; returns the load error.
fn load_error_after(edit: impl Fn(&mut serde_json::Value)) -> String {
    let dir = tempfile::tempdir().unwrap();
    let onnx = dir.path().join("p.onnx");
    export(&trained_checkpoint(), &onnx, &ExportOptions::default()).unwrap();
    let path = sidecar_path(&onnx);
    let mut side: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&path).unwrap()).unwrap();
    edit(&mut side);
    std::fs::write(&path, serde_json::to_string(&side).unwrap()).unwrap();
    match NamedPolicy::load("p", &onnx) {
        Ok(_) => panic!("the edited sidecar was accepted"),
        Err(e) => format!("{e:#}"),
    }
}

#[test]
fn a_sidecar_asking_for_what_rall_cannot_produce_is_refused_naming_the_field() {
    let e = load_error_after(|s| s["observation"]["fields"][0]["name"] = "base_height".into());
    assert!(
        e.contains("observation.fields[0].name") && e.contains("base_height"),
        "{e}"
    );
    let e = load_error_after(|s| s["observation"]["fields"][5]["scale"][3] = 0.1.into());
    assert!(e.contains("observation.fields[5].scale"), "{e}");
    let e = load_error_after(|s| s["joints"]["names"][0] = "FR_knee_joint".into());
    assert!(
        e.contains("joints.names[0]") && e.contains("FR_knee_joint"),
        "{e}"
    );
    // another joint order is followed, but the default pose must still be the keyframe's
    let e = load_error_after(|s| {
        s["joints"]["names"].as_array_mut().unwrap().swap(0, 3);
    });
    assert!(e.contains("joints.default_angles_rad_in_order[0]"), "{e}");
    let e = load_error_after(|s| s["joints"]["default_angles_rad_in_order"][2] = (-1.3).into());
    assert!(e.contains("joints.default_angles_rad_in_order[2]"), "{e}");
    let e = load_error_after(|s| s["commands"]["zero_threshold_applies_to_yaw"] = true.into());
    assert!(e.contains("commands.zero_threshold_applies_to_yaw"), "{e}");
    let e = load_error_after(|s| {
        s.as_object_mut().unwrap().remove("pd");
    });
    assert!(e.contains("pd.kp_nm_per_rad"), "{e}");
    // the network's input must be as wide as the sidecar's fields
    let e = load_error_after(|s| {
        let f = s["observation"]["fields"].as_array_mut().unwrap();
        f.pop();
        s["observation"]["dim"] = 36.into();
    });
    assert!(e.contains("48 wide") && e.contains("36"), "{e}");
}

#[test]
fn a_missing_sidecar_or_a_broken_onnx_file_is_a_clear_error() {
    let dir = tempfile::tempdir().unwrap();
    let onnx = dir.path().join("lonely.onnx");
    std::fs::write(&onnx, b"not a protobuf").unwrap();
    let e = format!(
        "{:#}",
        NamedPolicy::load("x", &onnx).err().expect("refused")
    );
    assert!(e.contains("lonely.json") && e.contains("sidecar"), "{e}");
    let (_, _, good) = checkpoint_and_export(dir.path());
    std::fs::copy(sidecar_path(&good), dir.path().join("lonely.json")).unwrap();
    let e = format!(
        "{:#}",
        NamedPolicy::load("x", &onnx).err().expect("refused")
    );
    assert!(e.contains("lonely.onnx"), "{e}");
}

#[test]
fn a_sidecar_in_legged_gym_joint_order_is_followed() {
    let dir = tempfile::tempdir().unwrap();
    let onnx = dir.path().join("p.onnx");
    export(&trained_checkpoint(), &onnx, &ExportOptions::default()).unwrap();
    let mut side: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(sidecar_path(&onnx)).unwrap()).unwrap();
    // legged_gym orders the Aliengo's joints FL, FR, RL, RR (its URDF's order)
    let sdk_of: Vec<usize> = vec![3, 4, 5, 0, 1, 2, 9, 10, 11, 6, 7, 8];
    let names: Vec<serde_json::Value> = sdk_of
        .iter()
        .map(|&j| side["joints"]["names"][j].clone())
        .collect();
    let angles: Vec<serde_json::Value> = sdk_of
        .iter()
        .map(|&j| side["joints"]["default_angles_rad_in_order"][j].clone())
        .collect();
    side["joints"]["names"] = names.into();
    side["joints"]["default_angles_rad_in_order"] = angles.into();
    let p = rall::eval::sidecar::sidecar_policy(&side).expect("a permutation rall can follow");
    assert_eq!(p.joint_order, sdk_of);
    // joint angles (offset 12 of rall's row) are gathered in the network's order
    let want: Vec<usize> = sdk_of.iter().map(|&j| 12 + j).collect();
    assert_eq!(&p.input_columns[12..24], &want[..]);
    assert_eq!(&p.input_columns[..12], &(0..12).collect::<Vec<_>>()[..]);
}
