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
    // the export's reference pairs are its own network's: this one is refused
    std::fs::copy(sidecar_path(&onnx), sidecar_path(&other)).unwrap();
    let e = format!("{:#}", OnnxPolicy::load(&other).err().expect("refused"));
    assert!(
        e.contains("other.onnx") && e.contains("reference observation"),
        "{e}"
    );
    // without them, the sidecar describes the graph and tract runs it
    let mut side = read_json(&sidecar_path(&onnx));
    side.as_object_mut().unwrap().remove("reference");
    write_json(&sidecar_path(&other), &side);
    let p = OnnxPolicy::load(&other).unwrap();
    assert!(!p.runs_on_rall_forward());
    let obs = vec![0.1f32; OBS_DIM];
    assert!(max_action_diff(&ckpt.policy, &p, &obs) > 0.0);
}

fn read_json(path: &Path) -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap()
}

fn write_json(path: &Path, v: &serde_json::Value) {
    std::fs::write(path, serde_json::to_string(v).unwrap()).unwrap();
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
    // the export's trace and reference pairs are rall's network's, in rall's
    // joint order: a legged_gym sidecar carries neither
    let sections = side.as_object_mut().unwrap();
    sections.remove("trace");
    sections.remove("reference");
    let p = rall::eval::sidecar::sidecar_policy(&side).expect("a permutation rall can follow");
    assert_eq!(p.joint_order, sdk_of);
    // joint angles (offset 12 of rall's row) are gathered in the network's order
    let want: Vec<usize> = sdk_of.iter().map(|&j| 12 + j).collect();
    assert_eq!(&p.input_columns[12..24], &want[..]);
    assert_eq!(&p.input_columns[..12], &(0..12).collect::<Vec<_>>()[..]);
}

#[test]
fn a_sidecar_is_read_strictly_naming_the_key_and_the_nearest_valid_one() {
    // a misspelt key would silently drop that field's noise
    let e = load_error_after(|s| {
        let f = s["observation"]["fields"][0].as_object_mut().unwrap();
        let noise = f.remove("training_noise_std_physical_units").unwrap();
        f.insert("training_noise_std".into(), noise);
    });
    assert!(
        e.contains("observation.fields[0].training_noise_std`")
            && e.contains("observation.fields[0].training_noise_std_physical_units"),
        "{e}"
    );
    // a misspelt section would only have said "defaults used"
    let e = load_error_after(|s| {
        let m = s.as_object_mut().unwrap();
        let envelope = m.remove("training_envelope").unwrap();
        m.insert("training_envelop".into(), envelope);
    });
    assert!(
        e.contains("`training_envelop`") && e.contains("`training_envelope`"),
        "{e}"
    );
    let e = load_error_after(|s| s["pd"]["kp"] = 50.0.into());
    assert!(
        e.contains("`pd.kp`") && e.contains("`pd.kp_nm_per_rad`"),
        "{e}"
    );
    // a format this rall does not read
    let e = load_error_after(|s| s["format_version"] = 3.into());
    assert!(e.contains("format_version") && e.contains('3'), "{e}");
    let e = load_error_after(|s| {
        s.as_object_mut().unwrap().remove("format_version");
    });
    assert!(e.contains("format_version"), "{e}");
}

/// The export's sidecar with observation fields `a` and `b` swapped (offsets
/// renumbered so the list is valid): a layout rall can follow, but not the
/// network's.
fn swap_fields(s: &mut serde_json::Value, a: usize, b: usize) {
    let fields = s["observation"]["fields"].as_array_mut().unwrap();
    fields.swap(a, b);
    let mut offset = 0;
    for f in fields.iter_mut() {
        f["offset"] = offset.into();
        offset += f["length"].as_u64().unwrap();
    }
}

#[test]
fn fields_listed_in_another_order_than_the_network_reads_are_refused() {
    // base_lin_vel_body <-> base_ang_vel_body; joint_pos <-> joint_vel; gravity <-> command
    for (a, b) in [(0, 1), (4, 5), (2, 3), (5, 6)] {
        let e = load_error_after(|s| swap_fields(s, a, b));
        assert!(
            e.contains("not listed in the order the network reads them"),
            "fields {a} and {b} swapped: {e}"
        );
    }
    // reference pairs alone (no trace) catch a swap that moves gravity
    let e = load_error_after(|s| {
        s.as_object_mut().unwrap().remove("trace");
        swap_fields(s, 1, 2);
    });
    assert!(
        e.contains("reference.observations") && e.contains("gravity_body"),
        "{e}"
    );
    // and a reference action the network does not return
    let e = load_error_after(|s| {
        let a = s["reference"]["actions"][3][5].as_f64().unwrap();
        s["reference"]["actions"][3][5] = (a + 0.01).into();
    });
    assert!(
        e.contains("reference observation 3") && e.contains("action 5"),
        "{e}"
    );
}

#[test]
fn a_graph_with_a_fixed_batch_of_one_runs_robot_by_robot() {
    use rall::export::onnx::{Dimension, DimensionValue};
    let dir = tempfile::tempdir().unwrap();
    let (_, _, onnx) = checkpoint_and_export(dir.path());
    // what torch.onnx.export writes without dynamic_axes: batch 1 in and out;
    // ELU's alpha changed so that tract, not rall's forward, runs the graph
    let fixed = |batch: i64| {
        let mut model = ModelProto::decode(std::fs::read(&onnx).unwrap().as_slice()).unwrap();
        let graph = model.graph.as_mut().unwrap();
        for io in graph.input.iter_mut().chain(graph.output.iter_mut()) {
            let t = io.r#type.as_mut().unwrap().tensor_type.as_mut().unwrap();
            t.shape.as_mut().unwrap().dim[0] = Dimension {
                value: Some(DimensionValue::DimValue(batch)),
            };
        }
        let elu = graph.node.iter_mut().find(|n| n.op_type == "Elu").unwrap();
        elu.attribute[0].f = 0.5;
        let path = dir.path().join(format!("batch{batch}.onnx"));
        std::fs::write(&path, encode(&model)).unwrap();
        let mut side = read_json(&sidecar_path(&onnx));
        side.as_object_mut().unwrap().remove("reference");
        write_json(&sidecar_path(&path), &side);
        path
    };
    let one = OnnxPolicy::load(&fixed(1)).expect("a batch of 1 loads");
    assert!(!one.runs_on_rall_forward());
    let obs: Vec<f32> = (0..4 * OBS_DIM).map(|i| (i % 7) as f32 * 0.05).collect();
    let all = one
        .actions(&obs)
        .expect("four robots through a graph of batch 1");
    for (r, row) in obs.chunks_exact(OBS_DIM).enumerate() {
        let alone = one.actions(row).unwrap();
        assert_eq!(&all[r * 12..(r + 1) * 12], &alone[..], "robot {r}");
    }
    // another fixed batch is refused at load, naming the file and the cause
    let e = format!(
        "{:#}",
        OnnxPolicy::load(&fixed(2)).err().expect("batch 2 refused")
    );
    assert!(
        e.contains("batch2.onnx") && e.contains("fixed batch of 2"),
        "{e}"
    );
}

#[test]
fn the_hand_written_sidecar_of_the_docs_is_read() {
    let doc = std::fs::read_to_string(
        Path::new(env!("CARGO_MANIFEST_DIR")).join("docs/outside-policies.md"),
    )
    .unwrap();
    let json = doc
        .split("```json\n")
        .nth(1)
        .and_then(|rest| rest.split("\n```").next())
        .expect("docs/outside-policies.md has a JSON sidecar");
    let side: serde_json::Value = serde_json::from_str(json).unwrap();
    let p = rall::eval::sidecar::sidecar_policy(&side).unwrap_or_else(|e| panic!("{e:#}"));
    assert!(p.defaulted.is_empty() && p.reference.is_none());
}
