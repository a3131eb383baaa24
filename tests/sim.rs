//! The simulation layer, the Aliengo model and PD standing.

use std::f64::consts::{FRAC_PI_2, FRAC_PI_3, FRAC_PI_6};

use rall::robot::{standing_check, ControlConfig, Part, Robot, LEGS, NUM_JOINTS};
use rall::sim::{Data, JointKind, Model, ObjKind, SimError};

const ALIENGO: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/mjcf/aliengo.xml");
const FLAT: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/mjcf/flat.xml");
/// Facts file, set A: trunk 9.041 + 4 x (1.993 + 0.639 + 0.207 + 0.060) (+ 0.001 IMU).
const FACTS_TOTAL_MASS_KG: f64 = 20.638;

fn flat_robot() -> Robot {
    Robot::load(FLAT, ControlConfig::default()).expect("flat scene loads")
}

#[test]
fn model_has_sdk_ordered_hinges_and_actuators_and_the_facts_mass() {
    let m = Model::from_xml_path(ALIENGO).unwrap();
    let hinges: Vec<usize> = (0..m.njnt())
        .filter(|&j| m.joint_kind(j) == JointKind::Hinge)
        .collect();
    assert_eq!(hinges.len(), 12);
    assert_eq!(m.nu(), 12);
    let mut expected = Vec::new();
    for leg in LEGS {
        for j in ["hip", "thigh", "calf"] {
            expected.push(format!("{leg}_{j}_joint"));
        }
    }
    for (i, name) in expected.iter().enumerate() {
        assert_eq!(m.name(ObjKind::Joint, hinges[i]), name, "joint order");
        assert_eq!(
            m.actuator_joint(i),
            Some(hinges[i]),
            "actuator {i} drives {name}"
        );
    }
    let limits: Vec<[f64; 2]> = (0..12).map(|a| m.actuator_ctrl_range(a).unwrap()).collect();
    for (i, l) in limits.iter().enumerate() {
        let expected = if i % 3 == 2 { 55.0 } else { 44.0 };
        assert_eq!(*l, [-expected, expected], "torque limit of actuator {i}");
    }
    let mass = m.total_mass_kg();
    assert!(
        (mass - FACTS_TOTAL_MASS_KG).abs() / FACTS_TOTAL_MASS_KG < 0.01,
        "total mass {mass}"
    );
    assert!(m.id(ObjKind::Key, "stand").is_some());
    // no cylinder collision geoms (slow in 2.2.2)
    for g in 0..m.ngeom() {
        assert_ne!(
            m.geom_shape(g),
            rall::sim::GeomShape::Cylinder,
            "geom {}",
            m.name(ObjKind::Geom, g)
        );
    }
}

/// Puts the trunk at (0, 0, 1) with identity orientation and the given joint angles.
fn pose(robot: &mut Robot, q: [f64; NUM_JOINTS]) {
    let a = robot.layout.root_qpos_adr;
    let qpos = robot.data_mut().qpos_mut();
    qpos[a..a + 7].copy_from_slice(&[0.0, 0.0, 1.0, 1.0, 0.0, 0.0, 0.0]);
    for (i, &v) in q.iter().enumerate() {
        let adr = robot.layout.qpos_adr[i];
        robot.data_mut().qpos_mut()[adr] = v;
    }
    robot.forward().unwrap();
}

fn foot_pos(robot: &Robot, leg: &str) -> [f64; 3] {
    let b = robot
        .model()
        .require_id(ObjKind::Body, &format!("{leg}_foot"))
        .unwrap();
    robot.data().xpos()[b]
}

fn assert_close(got: [f64; 3], want: [f64; 3], what: &str) {
    for k in 0..3 {
        assert!(
            (got[k] - want[k]).abs() < 1e-6,
            "{what}: got {got:?}, want {want:?}"
        );
    }
}

#[test]
fn legs_are_two_quarter_metre_segments() {
    let mut robot = flat_robot();
    pose(&mut robot, [0.0; NUM_JOINTS]);
    for (leg, (sx, sy)) in LEGS
        .iter()
        .zip([(1.0, -1.0), (1.0, 1.0), (-1.0, -1.0), (-1.0, 1.0)])
    {
        // hip axis at (+-0.2399, +-0.051, 0); thigh joint 0.083 further out; foot 0.5 below.
        let want = [sx * 0.2399, sy * (0.051 + 0.083), 1.0 - 0.5];
        assert_close(foot_pos(&robot, leg), want, leg);
        let thigh = robot
            .model()
            .require_id(ObjKind::Body, &format!("{leg}_thigh"))
            .unwrap();
        let calf = robot
            .model()
            .require_id(ObjKind::Body, &format!("{leg}_calf"))
            .unwrap();
        let xpos = robot.data().xpos();
        assert!((xpos[thigh][2] - xpos[calf][2] - 0.25).abs() < 1e-9);
    }
}

#[test]
fn forward_kinematics_matches_hand_computation() {
    let mut robot = flat_robot();
    // FL: hip 0, thigh pi/2 (thigh points backwards), calf -pi/2 (calf points down):
    // knee at hip + (-0.25, 0.083, 0); foot 0.25 below the knee.
    let mut q = [0.0; NUM_JOINTS];
    q[3..6].copy_from_slice(&[0.0, FRAC_PI_2, -FRAC_PI_2]);
    // RR: hip pi/6, thigh pi/3, calf -2pi/3: in the hip frame the foot is at
    // (0, -0.083, -0.25) (the two segments' x cancel), then rotated by pi/6 about x:
    // y = -0.083 cos30 + 0.25 sin30 = 0.0531199, z = -0.083 sin30 - 0.25 cos30 = -0.2580064.
    q[6..9].copy_from_slice(&[FRAC_PI_6, FRAC_PI_3, -2.0 * FRAC_PI_3]);
    pose(&mut robot, q);
    assert_close(
        foot_pos(&robot, "FL"),
        [0.2399 - 0.25, 0.051 + 0.083, 1.0 - 0.25],
        "FL",
    );
    let y = -0.083 * FRAC_PI_6.cos() + 0.25 * FRAC_PI_6.sin();
    let z = -0.083 * FRAC_PI_6.sin() - 0.25 * FRAC_PI_6.cos();
    assert!((y - 0.0531199).abs() < 1e-6 && (z + 0.2580064).abs() < 1e-6);
    assert_close(foot_pos(&robot, "RR"), [-0.2399, -0.051 + y, 1.0 + z], "RR");
}

#[test]
fn pd_holds_the_stand_pose_for_ten_seconds_on_feet_only() {
    let mut robot = flat_robot();
    let report = standing_check(&mut robot, 10.0).unwrap();
    assert!(report.instability.is_none(), "{report:?}");
    assert_eq!(report.warnings, 0, "{report:?}");
    assert!(
        report.min_height_m >= 0.30 && report.max_height_m <= 0.45,
        "{report:?}"
    );
    assert!(report.other_contacts.is_empty(), "{report:?}");
    assert_eq!(report.feet_in_contact, 4, "{report:?}");
    assert!(robot.data().qpos().iter().all(|v| v.is_finite()));
    assert!(report.holds_pose());
}

#[test]
fn contact_forces_carry_the_robot_weight() {
    let mut robot = flat_robot();
    standing_check(&mut robot, 2.0).unwrap();
    let mut normal_n = 0.0;
    let contacts: Vec<_> = robot.data().contacts().collect();
    let model = robot.model_copy().unwrap();
    for c in &contacts {
        assert!(matches!(
            robot.layout.geom_parts[c.geom1],
            Part::Foot(_) | Part::Other
        ));
        normal_n += robot.data().contact_force(&model, c.index).unwrap()[0];
    }
    let weight_n = robot.model().total_mass_kg() * 9.81;
    assert!(
        (normal_n - weight_n).abs() / weight_n < 0.05,
        "normal {normal_n} vs weight {weight_n}"
    );
    assert!(robot.data().contact_force(&model, contacts.len()).is_err());
}

#[test]
fn missing_file_is_an_error_naming_the_path() {
    let e = Model::from_xml_path("/definitely/not/here.xml").unwrap_err();
    assert!(matches!(e, SimError::ModelFile { .. }));
    assert!(e.to_string().contains("/definitely/not/here.xml"), "{e}");
}

#[test]
fn malformed_xml_is_mujocos_error_naming_the_source() {
    let e = Model::from_xml_str("<mujoco><worldbody><body></mujoco>", "broken.xml").unwrap_err();
    let text = e.to_string();
    assert!(
        text.contains("broken.xml") && text.to_lowercase().contains("error"),
        "{text}"
    );
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("bad.xml");
    std::fs::write(&path, "<mujoco><option timestep=\"abc\"/></mujoco>").unwrap();
    let e = Model::from_xml_path(&path).unwrap_err();
    assert!(e.to_string().contains("bad.xml"), "{e}");
    // a 2.2.2-unsupported feature is refused, not crashed on
    let e = Model::from_xml_str(
        "<mujoco><option integrator=\"implicitfast\"/></mujoco>",
        "new.xml",
    );
    assert!(e.is_err());
}

#[test]
fn unknown_keyframe_is_an_error_naming_it() {
    let m = Model::from_xml_path(FLAT).unwrap();
    let mut d = Data::new(&m).unwrap();
    let e = d.reset_to_keyframe(&m, "crouch").unwrap_err();
    assert!(e.to_string().contains("crouch"), "{e}");
    let control = ControlConfig {
        default_keyframe: "nope".into(),
        ..Default::default()
    };
    let e = Robot::new(m.try_clone().unwrap(), control)
        .err()
        .expect("refused");
    assert!(e.to_string().contains("nope"));
}

#[test]
fn nan_state_is_reported_as_instability_not_continued() {
    let mut robot = flat_robot();
    let dof = robot.layout.dof_adr[2];
    robot.data_mut().qvel_mut()[dof] = f64::NAN;
    let target = robot.default_q_rad;
    let e = robot.pd_substep(&target).unwrap_err();
    assert!(matches!(e, SimError::Unstable { .. }), "{e}");
    // MuJoCo reset the state; after our reset the robot steps fine again.
    robot.reset_to_default().unwrap();
    robot.pd_substep(&target).unwrap();
    assert!(robot.data().qpos().iter().all(|v| v.is_finite()));
}

#[test]
fn data_refuses_a_model_of_another_shape() {
    let robot = Model::from_xml_path(FLAT).unwrap();
    let ball = Model::from_xml_str(
        "<mujoco><worldbody><body><freejoint/><geom type=\"sphere\" size=\"0.1\"/></body></worldbody></mujoco>",
        "ball",
    )
    .unwrap();
    let mut d = Data::new(&ball).unwrap();
    assert!(matches!(d.step(&robot), Err(SimError::ModelMismatch(_))));
}

#[test]
fn data_runs_only_with_its_own_model_family() {
    let a = Model::from_xml_path(FLAT).unwrap();
    // The same file loaded again: same sizes, another model. A size check would
    // accept it; the family check refuses it exactly.
    let b = Model::from_xml_path(FLAT).unwrap();
    let clone = a.try_clone().unwrap();
    assert_eq!(a.family(), clone.family());
    assert_ne!(a.family(), b.family());
    let mut d = Data::new(&a).unwrap();
    assert!(matches!(d.step(&b), Err(SimError::ModelMismatch(_))));
    assert!(matches!(d.forward(&b), Err(SimError::ModelMismatch(_))));
    assert!(matches!(d.reset(&b), Err(SimError::ModelMismatch(_))));
    assert!(matches!(
        d.reset_to_keyframe(&b, "stand"),
        Err(SimError::ModelMismatch(_))
    ));
    d.step(&a).unwrap();
    d.step(&clone).unwrap();
}

/// A free ball over a plane, with `size` as its `<size .../>` attributes.
fn ball_xml(size: &str) -> String {
    format!(
        "<mujoco><size {size}/><worldbody>\
         <geom type=\"plane\" size=\"0 0 1\"/>\
         <body pos=\"0 0 0.3\"><freejoint/><geom type=\"box\" size=\"0.1 0.1 0.1\"/></body>\
         </worldbody></mujoco>"
    )
}

#[test]
fn a_mujoco_error_leaves_mujoco_as_a_typed_error_and_the_process_goes_on() {
    // The stack the robot scene needs at its reference pose (legs through the
    // floor: 20 contacts) is far more than 200 mjtNums: MuJoCo's engine raises
    // "Stack overflow" (here inside the compiler's own check of the model).
    let xml = std::fs::read_to_string(FLAT).unwrap();
    let aliengo = std::fs::read_to_string(ALIENGO).unwrap();
    let small = aliengo.replace("<size ", "<size nstack=\"200\" ");
    assert_ne!(small, aliengo, "aliengo.xml has a <size> element");
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("aliengo.xml"), small).unwrap();
    std::fs::write(dir.path().join("flat.xml"), xml).unwrap();
    match Model::from_xml_path(dir.path().join("flat.xml")) {
        Err(SimError::Load { message, .. }) => {
            assert!(message.contains("Stack overflow"), "{message}")
        }
        Err(other) => panic!("unexpected error {other}"),
        Ok(_) => panic!("a model whose stack cannot hold its reference pose loaded"),
    }
    // The process carries on: the same thread loads and steps a sound model.
    let mut robot = flat_robot();
    let target = robot.default_q_rad;
    for _ in 0..100 {
        robot.pd_substep(&target).unwrap();
    }
    // And a bad model is a typed load error, on another thread too.
    let e = std::thread::spawn(|| {
        Model::from_xml_str(
            "<mujoco><worldbody><geom type=\"mesh\" mesh=\"nope\"/></worldbody></mujoco>",
            "bad.xml",
        )
    })
    .join()
    .unwrap()
    .unwrap_err();
    assert!(matches!(e, SimError::Load { .. }), "{e}");
}

#[test]
fn data_interrupted_by_an_error_is_refused_until_reset() {
    // Measure the stack a box needs in the air and on the ground...
    let roomy = Model::from_xml_str(&ball_xml("nstack=\"100000\""), "box").unwrap();
    let mut d = Data::new(&roomy).unwrap();
    let in_air = d.arena_use().stack;
    let mut landed = None;
    for i in 0..400 {
        d.step(&roomy).unwrap();
        if d.ncon() > 0 {
            landed = Some(i);
            d.step(&roomy).unwrap();
            break;
        }
    }
    let landed = landed.expect("the box lands");
    let on_ground = d.arena_use().stack;
    assert!(on_ground > in_air + 2, "air {in_air} ground {on_ground}");
    // ... then give it a stack between the two: it falls fine and fails on landing.
    let tight = format!("nstack=\"{}\"", (in_air + on_ground) / 2);
    let m = Model::from_xml_str(&ball_xml(&tight), "tight box").unwrap();
    let mut d = Data::new(&m).unwrap();
    let mut failed_at = None;
    for i in 0..=landed + 1 {
        match d.step(&m) {
            Ok(()) => {}
            Err(SimError::MuJoCo { call, message }) => {
                assert_eq!(call, "mj_step");
                assert!(message.contains("Stack overflow"), "{message}");
                failed_at = Some(i);
                break;
            }
            Err(other) => panic!("unexpected error {other}"),
        }
    }
    assert!(failed_at.is_some(), "the landing overflows the stack");
    // The interrupted state is not stepped again...
    assert!(matches!(d.step(&m), Err(SimError::NeedsReset(_))));
    assert!(matches!(d.forward(&m), Err(SimError::NeedsReset(_))));
    // ... until a reset, after which it falls again.
    d.reset(&m).unwrap();
    d.step(&m).unwrap();
    assert!(d.time_s() > 0.0);
}

#[test]
fn models_and_data_work_from_other_threads_and_copies_are_independent() {
    let base = Model::from_xml_path(FLAT).unwrap();
    let mut copy = base.try_clone().unwrap();
    let floor = copy.require_id(ObjKind::Geom, "floor").unwrap();
    copy.geom_friction_mut()[floor][0] = 0.3;
    assert_eq!(
        base.geom_friction()[floor][0],
        1.0,
        "copies do not share memory"
    );
    let handle = std::thread::spawn(move || {
        let mut robot = Robot::new(copy, ControlConfig::default()).unwrap();
        for _ in 0..50 {
            robot.policy_step(&[0.0; 12]).unwrap();
        }
        robot.data().time_s()
    });
    let t = handle.join().unwrap();
    assert!((t - 50.0 * 0.02).abs() < 1e-9);
}

#[test]
fn pd_law_clips_to_torque_limits() {
    let c = ControlConfig::default();
    let target = [10.0; NUM_JOINTS];
    let tau = c.pd_torques(&target, &[0.0; NUM_JOINTS], &[0.0; NUM_JOINTS]);
    for (i, t) in tau.iter().enumerate() {
        assert_eq!(*t, [44.0, 44.0, 55.0][i % 3]);
    }
    // tau = 50 * (0.1 - 0.0) - 0.8 * 2.0 = 3.4
    let tau = c.pd_torques(&[0.1; NUM_JOINTS], &[0.0; NUM_JOINTS], &[2.0; NUM_JOINTS]);
    assert!((tau[0] - 3.4).abs() < 1e-12);
    let targets = c.joint_targets(&[0.5; NUM_JOINTS], &[2.0; 12]);
    assert!((targets[0] - (0.5 + 0.25 * 2.0)).abs() < 1e-12);
    assert!(ControlConfig {
        decimation: 0,
        ..c.clone()
    }
    .validate()
    .unwrap_err()
    .contains("decimation"));
}
