//! The robustness scenarios load in MuJoCo 2.2.2 and do what they say.

use rall::env::state::{rotate, rotate_inverse};
use rall::env::{EnvConfig, OBS_DIM};
use rall::eval::scenario::ARM_JOINTS;
use rall::eval::{
    build_named_scenario, build_scenario, ScenarioParams, ScenarioSetup, ScenarioSpec,
};
use rall::sim::{mujoco_version, Data, ObjKind};

fn base_config() -> EnvConfig {
    EnvConfig {
        robot_mjcf: concat!(env!("CARGO_MANIFEST_DIR"), "/mjcf/aliengo.xml").into(),
        ..Default::default()
    }
}

fn scenario(name: &str) -> ScenarioSetup {
    build_named_scenario(name, &base_config(), 7).unwrap_or_else(|e| panic!("{name}: {e:#}"))
}

/// `steps` policy steps of zero actions (the PD holds the default pose).
fn stand(env: &mut rall::env::Env, hook: &mut rall::eval::ScenarioHook, steps: usize) -> usize {
    let mut obs = vec![0.0f32; OBS_DIM];
    let mut fin = vec![0.0f32; OBS_DIM];
    env.reset(&mut obs).unwrap();
    hook.on_reset(env);
    for s in 0..steps {
        hook.before_step(env);
        let r = env.step(&[0.0; 12], &mut obs, &mut fin);
        if r.done {
            return s + 1;
        }
    }
    steps
}

#[test]
fn every_scenario_loads_in_mujoco_222_and_steps() {
    assert_eq!(mujoco_version(), 222);
    for name in [
        "flat",
        "rough",
        "push",
        "ball",
        "frozen_arm",
        "moving_arm",
        "ball+rough+push",
        "frozen_arm+rough",
        "moving_arm+rough+push",
        "platform=0.40",
        "platform=0.45",
        "race",
    ] {
        let s = scenario(name);
        assert_eq!(ScenarioSpec::parse(&s.spec.name()).unwrap(), s.spec);
        let (mut env, mut hook) = s.single_env(3).unwrap();
        // A standing robot survives a second in every scenario (pushes start at step 300).
        let steps = stand(&mut env, &mut hook, 50);
        assert_eq!(steps, 50, "{name}: the standing robot ended its episode");
        assert_eq!(env.instabilities, 0, "{name}");
        let z = env.robot().base_pos_m()[2];
        let ground = s.spawn_m[2] - 0.39;
        assert!(
            (0.30..0.42).contains(&(z - ground)),
            "{name}: trunk {z:.3} m over ground {ground:.3} m"
        );
    }
}

#[test]
fn the_ball_rolls_in_the_container_when_the_trunk_tilts() {
    let s = scenario("ball");
    let m = &s.model;
    let ball = m.require_id(ObjKind::Body, "payload_ball").unwrap();
    let container = m.require_id(ObjKind::Body, "payload_container").unwrap();
    let root = m.require_id(ObjKind::Joint, "root").unwrap();
    let (qa, va) = (m.joint_qpos_adr(root), m.joint_dof_adr(root));
    // Ball position in the container's frame after holding the trunk at a pitch
    // angle (in the air, legs free) for 0.6 s.
    let roll_after = |pitch: f64| -> [f64; 3] {
        let mut d = Data::new(m).unwrap();
        d.reset_to_keyframe(m, "stand").unwrap();
        let q = [(pitch / 2.0).cos(), 0.0, (pitch / 2.0).sin(), 0.0];
        let hold = |d: &mut Data| {
            let qp = d.qpos_mut();
            qp[qa..qa + 3].copy_from_slice(&[0.0, 0.0, 1.0]);
            qp[qa + 3..qa + 7].copy_from_slice(&q);
            d.qvel_mut()[va..va + 6].fill(0.0);
        };
        // Start with the ball resting in the middle of the tilted container.
        hold(&mut d);
        let ball_free = m.require_id(ObjKind::Joint, "payload_ball").unwrap();
        let ba = m.joint_qpos_adr(ball_free);
        let start = rotate(q, [0.0, 0.0, 0.112]);
        d.qpos_mut()[ba..ba + 3].copy_from_slice(&[start[0], start[1], 1.0 + start[2]]);
        d.forward(m).unwrap();
        let rel = |d: &Data| {
            let (b, c) = (d.xpos()[ball], d.xpos()[container]);
            rotate_inverse(
                d.xquat()[container],
                [b[0] - c[0], b[1] - c[1], b[2] - c[2]],
            )
        };
        let before = rel(&d);
        for _ in 0..120 {
            hold(&mut d);
            d.step(m).unwrap();
        }
        let after = rel(&d);
        [
            after[0] - before[0],
            after[1] - before[1],
            after[2] - before[2],
        ]
    };
    let level = roll_after(0.0);
    assert!(
        level.iter().all(|x| x.abs() < 0.005),
        "level trunk: the ball stays put, moved {level:?}"
    );
    // Nose down (positive pitch about y): the ball rolls forward (+x in the
    // container) to the front wall (inner half-length 0.17 m, radius 0.05 m).
    let tilted = roll_after(0.25);
    assert!(tilted[0] > 0.08, "pitched trunk: the ball moved {tilted:?}");
    assert!(
        tilted[0] < 0.125,
        "the front wall stops the ball: {tilted:?}"
    );
    let back = roll_after(-0.25);
    assert!(back[0] < -0.08, "pitched up: the ball moved {back:?}");
}

#[test]
fn the_arm_adds_its_mass_and_the_ball_payload_its_own() {
    let robot = scenario("flat").total_mass_kg();
    assert!((robot - 20.637).abs() < 0.01, "robot {robot} kg");
    for name in ["frozen_arm", "moving_arm"] {
        let m = scenario(name).total_mass_kg();
        assert!(
            (m - robot - 4.419).abs() < 0.005,
            "{name}: {m} kg - robot {robot} kg"
        );
    }
    let ball = scenario("ball").total_mass_kg();
    assert!(
        (ball - robot - 2.1).abs() < 1e-6,
        "ball + container: {ball} kg"
    );
}

#[test]
fn the_frozen_arm_holds_home_and_the_moving_arm_tracks_new_targets() {
    let p = ScenarioParams::default();
    for (name, moving) in [("frozen_arm", false), ("moving_arm", true)] {
        let s = scenario(name);
        let m = &s.model;
        let adr: Vec<usize> = ARM_JOINTS
            .iter()
            .map(|j| m.joint_qpos_adr(m.require_id(ObjKind::Joint, j).unwrap()))
            .collect();
        let (mut env, mut hook) = s.single_env(5).unwrap();
        let resample = (p.arm_resample_s / 0.02).round() as usize;
        // Just before the first re-sampling: at home. 1 s after: tracking the new targets.
        assert_eq!(stand(&mut env, &mut hook, resample), resample);
        let q: Vec<f64> = adr.iter().map(|&a| env.robot().data().qpos()[a]).collect();
        for (i, (q, h)) in q.iter().zip(&p.arm_home_rad).enumerate() {
            assert!(
                (q - h).abs() < 0.05,
                "{name}: joint {} at {q}, home {h}",
                i + 1
            );
        }
        let mut obs = vec![0.0f32; OBS_DIM];
        let mut fin = vec![0.0f32; OBS_DIM];
        for _ in 0..50 {
            hook.before_step(&mut env);
            env.step(&[0.0; 12], &mut obs, &mut fin);
        }
        let q: Vec<f64> = adr.iter().map(|&a| env.robot().data().qpos()[a]).collect();
        if moving {
            assert_eq!(hook.arm_resamples, 1);
            assert!(hook
                .arm_targets
                .iter()
                .zip(&p.arm_home_rad)
                .any(|(t, h)| (t - h).abs() > 0.3));
            let err = q
                .iter()
                .zip(&hook.arm_targets)
                .map(|(q, t)| (q - t).abs())
                .fold(0.0, f64::max);
            assert!(
                err < 0.1,
                "{name}: 1 s after new targets, max error {err} rad"
            );
        } else {
            assert_eq!(hook.arm_resamples, 0);
            for (q, h) in q.iter().zip(&p.arm_home_rad) {
                assert!((q - h).abs() < 0.05, "{name}: arm moved to {q}, home {h}");
            }
        }
        assert_eq!(env.instabilities, 0);
    }
}

#[test]
fn the_push_force_is_on_for_exactly_50_of_every_300_steps() {
    let mut cfg = base_config();
    // Never end the episode: count the pushes over four periods.
    cfg.episode.length_s = 100.0;
    cfg.episode.max_tilt_rad = 100.0;
    cfg.episode.terminate_on_trunk_contact = false;
    let spec = ScenarioSpec::parse("push").unwrap();
    let s = build_scenario(&spec, &cfg, &ScenarioParams::default(), 1).unwrap();
    let (mut env, mut hook) = s.single_env(2).unwrap();
    let trunk = env.robot().layout.trunk_body;
    let mut obs = vec![0.0f32; OBS_DIM];
    let mut fin = vec![0.0f32; OBS_DIM];
    env.reset(&mut obs).unwrap();
    hook.on_reset(&mut env);
    let mut on = Vec::new();
    for _ in 0..1200 {
        hook.before_step(&mut env);
        let r = env.step(&[0.0; 12], &mut obs, &mut fin);
        assert!(!r.done);
        let f = env.robot().data().xfrc_applied()[trunk];
        let norm = (f[0] * f[0] + f[1] * f[1] + f[2] * f[2]).sqrt();
        assert!(norm == 0.0 || (norm - 100.0).abs() < 1e-9, "force {f:?}");
        if norm > 0.0 {
            // along +-x or +-y, horizontal, no torque
            assert_eq!(f[2], 0.0);
            assert!(f[0] == 0.0 || f[1] == 0.0);
            assert!(f[3..].iter().all(|&t| t == 0.0));
        }
        on.push(norm > 0.0);
    }
    for period in 0..4 {
        let w = &on[period * 300..(period + 1) * 300];
        let count = w.iter().filter(|&&x| x).count();
        if period == 0 {
            assert_eq!(count, 0, "no push in the first 300 steps");
        } else {
            assert_eq!(count, 50, "period {period}");
            assert!(
                w[..50].iter().all(|&x| x),
                "held from the period's first step"
            );
        }
    }
    assert_eq!(on.iter().filter(|&&x| x).count(), 150);
}

#[test]
fn the_platform_has_the_requested_height() {
    for h in [0.40, 0.45] {
        let s = scenario(&format!("platform={h}"));
        let m = &s.model;
        let g = m.require_id(ObjKind::Geom, "platform").unwrap();
        let top = m.geom_pos()[g][2] + m.geom_size()[g][2];
        assert!((top - h).abs() < 1e-9, "platform top {top}, asked {h}");
        let geo = s.platform.unwrap();
        assert_eq!(geo.height_m, h);
        let front = m.geom_pos()[g][0] + m.geom_size()[g][0];
        assert!((front - geo.edge_x_m).abs() < 1e-9);
        // The robot spawns on it and stands there.
        let (mut env, mut hook) = s.single_env(0).unwrap();
        assert_eq!(stand(&mut env, &mut hook, 50), 50);
        let z = env.robot().base_pos_m()[2];
        assert!(
            (z - h - 0.36).abs() < 0.04,
            "trunk at {z} on a {h} m platform"
        );
    }
}

#[test]
fn the_race_track_mixes_hazards_and_starts_on_its_platform() {
    let s = scenario("race");
    let g = s.ground.as_ref().unwrap();
    let p = &s.params.race;
    assert!((s.spawn_m[2] - p.drop_height_m - 0.39).abs() < 1e-6);
    let kinds: Vec<_> = g.segments().iter().map(|s| s.kind).collect();
    use rall::eval::ground::SegmentKind::*;
    assert_eq!(kinds[0], Platform);
    assert!(kinds.contains(&Obstacles) && kinds.contains(&Rough) && kinds.contains(&Flat));
    assert!(matches!(
        s.env.randomization.push,
        rall::env::config::PushConfig::Force { .. }
    ));
    // The heights reached MuJoCo: the hfield spans the ground's range.
    let hf = s.model.id(ObjKind::Hfield, "ground").unwrap();
    let (lo, hi) = g.height_range_m();
    assert!((s.model.hfield_size(hf)[2] - (hi - lo)).abs() < 1e-9);
    let data = s.model.hfield_data(hf);
    assert!(data.iter().any(|&x| x > 0.99) && data.iter().any(|&x| x < 0.01));
}
