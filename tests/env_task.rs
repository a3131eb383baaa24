//! Observation, reward and risk terms on hand-built states.

use std::f64::consts::FRAC_PI_2;

use rall::env::config::{ObservationConfig, RewardConfig, RiskConfig};
use rall::env::observation::{write_observation, OBS_DIM};
use rall::env::reward::{raw_terms, reward_terms, RewardInputs, REWARD_TERM_NAMES};
use rall::env::risk::{evaluate_risk, risk_measures};
use rall::env::state::{roll_pitch_yaw, rotate, rotate_inverse, RobotState};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

fn yaw_quat(yaw: f64) -> [f64; 4] {
    [(yaw / 2.0).cos(), 0.0, 0.0, (yaw / 2.0).sin()]
}

#[test]
fn yawed_robot_moving_forward_sees_forward_velocity_and_level_gravity() {
    // Yawed +90 deg: the body's forward (x) axis is world +y. Moving at 1 m/s
    // along world +y is 1 m/s forward in the body frame.
    let q = yaw_quat(FRAC_PI_2);
    let v = rotate_inverse(q, [0.0, 1.0, 0.0]);
    assert!(
        (v[0] - 1.0).abs() < 1e-12 && v[1].abs() < 1e-12 && v[2].abs() < 1e-12,
        "{v:?}"
    );
    let g = rotate_inverse(q, [0.0, 0.0, -1.0]);
    assert!((g[2] + 1.0).abs() < 1e-12 && g[0].abs() < 1e-12);
    // moving along world +x is moving to the body's right (-y)
    let v = rotate_inverse(q, [1.0, 0.0, 0.0]);
    assert!((v[1] + 1.0).abs() < 1e-12, "{v:?}");
    assert!((rotate(q, [1.0, 0.0, 0.0])[1] - 1.0).abs() < 1e-12);
    // pitched nose-down by 0.3 rad: gravity gains a +x component sin(0.3)
    let pitch = [(0.15f64).cos(), 0.0, (0.15f64).sin(), 0.0];
    let g = rotate_inverse(pitch, [0.0, 0.0, -1.0]);
    assert!((g[0] - (0.3f64).sin()).abs() < 1e-12, "{g:?}");
    let rpy = roll_pitch_yaw(pitch);
    assert!((rpy[1] - 0.3).abs() < 1e-12);
}

#[test]
fn observation_layout_and_scales() {
    let mut s = RobotState {
        base_lin_vel_body_mps: [1.0, -0.5, 0.1],
        base_ang_vel_body_rad_s: [0.4, -0.8, 2.0],
        gravity_body: [0.0, 0.0, -1.0],
        ..Default::default()
    };
    let default_q = [0.3; 12];
    for i in 0..12 {
        s.q_rad[i] = 0.3 + 0.01 * i as f64;
        s.qd_rad_s[i] = -(i as f64);
    }
    let prev_action: Vec<f32> = (0..12).map(|i| i as f32 * 0.5).collect();
    let mut obs = [0.0f32; OBS_DIM];
    let cfg = ObservationConfig::default();
    write_observation::<ChaCha8Rng>(
        &s,
        &[0.8, -0.4, 1.0],
        &prev_action,
        &default_q,
        &cfg,
        None,
        &mut obs,
    );
    let expect_head = [
        2.0, -1.0, 0.2, 0.1, -0.2, 0.5, 0.0, 0.0, -1.0, 1.6, -0.8, 0.25,
    ];
    for (i, e) in expect_head.iter().enumerate() {
        assert!((obs[i] - e).abs() < 1e-6, "obs[{i}] = {} want {e}", obs[i]);
    }
    for i in 0..12 {
        assert!((obs[12 + i] - 0.01 * i as f32).abs() < 1e-6, "dof_pos {i}");
        assert!((obs[24 + i] + 0.05 * i as f32).abs() < 1e-6, "dof_vel {i}");
        assert_eq!(obs[36 + i], prev_action[i], "action {i}");
    }
}

#[test]
fn observation_noise_has_the_configured_std_and_spares_commands_and_actions() {
    let s = RobotState {
        gravity_body: [0.0, 0.0, -1.0],
        ..Default::default()
    };
    let cfg = ObservationConfig::default();
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let n = 20_000;
    let mut sum_sq = [0.0f64; OBS_DIM];
    let mut obs = [0.0f32; OBS_DIM];
    for _ in 0..n {
        write_observation(
            &s,
            &[0.5, 0.0, 0.0],
            &[0.25; 12],
            &[0.0; 12],
            &cfg,
            Some(&mut rng),
            &mut obs,
        );
        assert_eq!(&obs[9..12], &[1.0, 0.0, 0.0], "commands are not noised");
        assert!(
            obs[36..].iter().all(|&a| a == 0.25),
            "actions are not noised"
        );
        for i in 0..OBS_DIM {
            let clean = if i == 8 {
                -1.0
            } else if i == 9 {
                1.0
            } else if i >= 36 {
                0.25
            } else {
                0.0
            };
            sum_sq[i] += (obs[i] as f64 - clean).powi(2);
        }
    }
    // lin vel: std 0.1 * scale 2.0; dof_vel: 1.5 * 0.05
    let std = |i: usize| (sum_sq[i] / n as f64).sqrt();
    assert!((std(0) - 0.2).abs() < 0.01, "{}", std(0));
    assert!((std(24) - 0.075).abs() < 0.004, "{}", std(24));
    assert!((std(6) - 0.05).abs() < 0.003, "{}", std(6));
}

#[test]
fn each_reward_term_on_a_hand_built_state() {
    let mut s = RobotState {
        base_lin_vel_body_mps: [0.5, 0.0, 0.2],
        base_ang_vel_body_rad_s: [0.1, 0.2, 0.5],
        penalised_contacts: 2,
        ..Default::default()
    };
    s.qdd_rad_s2[0] = 100.0;
    s.torques_nm[0] = 10.0;
    s.torques_nm[1] = -5.0;
    let prev_tau = [0.0; 12];
    let action = [0.5f32; 12];
    let prev_action = [0.0f32; 12];
    let cmd = [1.0, 0.0, 0.0];
    let air = [0.0, 0.7, 0.0, 0.3];
    let x = RewardInputs {
        state: &s,
        previous_torques_nm: &prev_tau,
        action: &action,
        previous_action: &prev_action,
        command: &cmd,
        touchdown_air_time_s: &air,
    };
    let cfg = RewardConfig::default();
    let raw = raw_terms(&x, &cfg);
    let want = [
        (-0.25f64 / 0.25).exp(), // |(1,0) - (0.5,0)|^2 = 0.25
        (-0.25f64 / 0.25).exp(), // (0 - 0.5)^2
        0.04,
        0.05,
        10_000.0,
        125.0,
        3.0, // 12 * 0.25
        2.0,
        3.0,
        125.0,
        (0.7 - 0.5) + (0.3 - 0.5),
    ];
    for i in 0..raw.len() {
        assert!(
            (raw[i] - want[i]).abs() < 1e-9,
            "{}: {} vs {}",
            REWARD_TERM_NAMES[i],
            raw[i],
            want[i]
        );
    }
    let weighted = reward_terms(&x, &cfg, 0.02);
    let weights = [
        5.0, 0.5, -1.0, -0.05, -2.5e-7, -2e-5, -0.01, -1e-3, -0.01, -3e-4, 2.0,
    ];
    for i in 0..raw.len() {
        assert!(
            (weighted.0[i] - want[i] * weights[i] * 0.02).abs() < 1e-12,
            "{}",
            REWARD_TERM_NAMES[i]
        );
    }
    // no air-time reward for a standing command
    let still = [0.0, 0.0, 0.5];
    let x2 = RewardInputs {
        command: &still,
        ..x
    };
    assert_eq!(raw_terms(&x2, &cfg)[10], 0.0);
}

#[test]
fn risk_thresholds_are_detected_per_term() {
    let cfg = RiskConfig {
        probability: 1.0,
        ..Default::default()
    };
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    let mut s = RobotState::default();
    assert_eq!(evaluate_risk(&s, &cfg, &mut rng).penalty, 0.0);
    s.pitch_rad = -0.6;
    s.roll_rad = 0.9; // below 1 rad
    s.qd_rad_s[4] = -11.0;
    s.qdd_rad_s2[7] = 999.0; // below
    s.torques_nm[11] = 41.0;
    assert_eq!(risk_measures(&s), [0.6, 0.9, 11.0, 999.0, 41.0]);
    let out = evaluate_risk(&s, &cfg, &mut rng);
    assert_eq!(out.exceeded, [true, false, true, false, true]);
    assert_eq!(out.fired, out.exceeded);
    assert_eq!(out.penalty, 20.0 + 100.0 + 150.0);
}

#[test]
fn penalty_fires_at_rate_p_within_binomial_bounds() {
    let cfg = RiskConfig::default(); // p = 1e-4
    let mut rng = ChaCha8Rng::seed_from_u64(42);
    let s = RobotState {
        roll_rad: 1.5,
        ..Default::default()
    };
    let n = 2_000_000u64;
    let mut fired = 0u64;
    for _ in 0..n {
        let out = evaluate_risk(&s, &cfg, &mut rng);
        assert!(out.exceeded[1]);
        fired += out.fired[1] as u64;
    }
    let mean = n as f64 * 1e-4; // 200
    let sd = (n as f64 * 1e-4 * (1.0 - 1e-4)).sqrt(); // ~14.1
    assert!(
        (fired as f64 - mean).abs() < 5.0 * sd,
        "fired {fired}, expected {mean} +- {sd}"
    );
}
