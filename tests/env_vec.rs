//! The env and VecEnv over MuJoCo: randomisation, pushes, episodes,
//! determinism across thread counts.

use std::sync::Arc;

use rall::env::config::PushConfig;
use rall::env::terrain::TerrainKind;
use rall::env::{build_scene, Env, EnvConfig, EpisodeEnd, ModelSharing, VecEnv, ACT_DIM, OBS_DIM};
use rall::sim::ObjKind;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

fn cfg() -> EnvConfig {
    EnvConfig {
        robot_mjcf: concat!(env!("CARGO_MANIFEST_DIR"), "/mjcf/aliengo.xml").into(),
        ..Default::default()
    }
}

fn random_actions(rng: &mut ChaCha8Rng, n: usize) -> Vec<f32> {
    (0..n * ACT_DIM).map(|_| rng.gen_range(-1.0..1.0)).collect()
}

#[test]
fn randomized_friction_and_mass_are_in_each_envs_own_parameters() {
    let c = cfg();
    let scene = build_scene(&c, 0).unwrap();
    let base_trunk =
        scene.model.body_mass_kg()[scene.model.require_id(ObjKind::Body, "trunk").unwrap()];
    let v = VecEnv::new(Arc::new(c), &scene.model, None, 8, 1, 7).unwrap();
    let mut frictions = Vec::new();
    for env in v.envs() {
        let m = env.robot().model();
        let p = env.robot().params();
        // The model is shared; each env's randomisation is its parameters.
        assert!(env.robot().shares_model());
        let draw = env.draw;
        let f = draw.friction.unwrap();
        assert!((0.5..=1.5).contains(&f));
        assert!((-0.5..=1.0).contains(&draw.added_base_mass_kg));
        let foot = m.require_id(ObjKind::Geom, "FL_foot").unwrap();
        let floor = m.require_id(ObjKind::Geom, "terrain").unwrap();
        assert_eq!(p.geom_friction()[foot][0], f);
        assert_eq!(p.geom_friction()[floor][0], f);
        let trunk = env.robot().layout.trunk_body;
        assert!((p.body_mass_kg()[trunk] - (base_trunk + draw.added_base_mass_kg)).abs() < 1e-12);
        let total: f64 = p.body_mass_kg().iter().sum();
        assert!(
            (p.body_subtree_mass_kg()[0] - total).abs() < 1e-9,
            "subtree mass kept consistent"
        );
        // What the model copy of a per-env-model env would hold.
        let copy = env.robot().model_copy().unwrap();
        assert_eq!(copy.geom_friction()[foot][0], f);
        assert!((copy.body_subtree_mass_kg()[0] - copy.total_mass_kg()).abs() < 1e-9);
        frictions.push(f);
    }
    frictions.dedup();
    assert!(frictions.len() > 4, "envs draw different frictions");
    // the shared base model is untouched
    assert_eq!(scene.model.body_mass_kg()[1], base_trunk);
}

#[test]
fn a_push_changes_the_base_velocity_by_the_sampled_amount() {
    let c = Arc::new(cfg());
    let scene = build_scene(&c, 0).unwrap();
    let mut env = Env::new(c, &scene.model, None, 3, 0).unwrap();
    let mut obs = [0.0f32; OBS_DIM];
    env.reset(&mut obs).unwrap();
    let a = env.robot().layout.root_dof_adr;
    let before = env.robot().data().qvel()[a..a + 3].to_vec();
    let dv = env.random_kick(1.0);
    let after = env.robot().data().qvel()[a..a + 3].to_vec();
    assert!(dv.iter().all(|d| d.abs() <= 1.0) && dv.iter().any(|d| d.abs() > 1e-3));
    assert!((after[0] - before[0] - dv[0]).abs() < 1e-12);
    assert!((after[1] - before[1] - dv[1]).abs() < 1e-12);
    assert_eq!(after[2], before[2]);
}

#[test]
fn velocity_kicks_happen_every_interval() {
    let mut c = cfg();
    c.randomization.push = PushConfig::VelocityKick {
        interval_s: 1.0,
        max_mps: 0.5,
    };
    let c = Arc::new(c);
    let scene = build_scene(&c, 0).unwrap();
    let mut env = Env::new(c, &scene.model, None, 3, 0).unwrap();
    let (mut obs, mut fin) = ([0.0f32; OBS_DIM], [0.0f32; OBS_DIM]);
    env.reset(&mut obs).unwrap();
    let mut pushed_at = Vec::new();
    for _ in 0..120 {
        let r = env.step(&[0.0; ACT_DIM], &mut obs, &mut fin);
        if r.pushed {
            pushed_at.push(env.step_in_episode());
        }
        if r.done {
            break;
        }
    }
    // pushes are applied at the start of steps 50 and 100 (counted after the step)
    assert_eq!(pushed_at, vec![51, 101]);
}

#[test]
fn time_out_keeps_the_final_observation_and_resets() {
    let mut c = cfg();
    c.episode.length_s = 0.2; // 10 policy steps
    c.randomization.push = PushConfig::None;
    let c = Arc::new(c);
    let scene = build_scene(&c, 0).unwrap();
    let mut v = VecEnv::new(c, &scene.model, None, 2, 1, 0).unwrap();
    let zeros = vec![0.0f32; 2 * ACT_DIM];
    for step in 1..=10 {
        let b = v.step(&zeros);
        if step < 10 {
            assert!(b.dones.iter().all(|&d| !d));
        } else {
            assert_eq!(b.dones, vec![true, true]);
            assert_eq!(b.time_outs, vec![true, true]);
            // the final observation is of a standing robot mid-episode, the new one starts
            // with a zero previous action and differs from the final one
            assert_ne!(&b.final_obs[..OBS_DIM], &b.obs[..OBS_DIM]);
            assert!(
                (b.final_obs[8] + 1.0).abs() < 0.2,
                "gravity z of the final obs"
            );
        }
    }
    let eps: Vec<_> = v.drain_episodes().collect();
    assert_eq!(eps.len(), 2);
    assert!(eps
        .iter()
        .all(|e| e.steps == 10 && e.end == EpisodeEnd::TimeOut));
    assert!(
        eps[0].reward_terms[0] > 0.0,
        "lin vel tracking term accumulates"
    );
    assert_eq!(v.envs()[0].step_in_episode(), 0);
}

fn end_after_placing(roll_rad: f64, z_m: f64) -> Option<EpisodeEnd> {
    let mut c = cfg();
    c.randomization.push = PushConfig::None;
    let c = Arc::new(c);
    let scene = build_scene(&c, 0).unwrap();
    let mut env = Env::new(c, &scene.model, None, 0, 0).unwrap();
    let (mut obs, mut fin) = ([0.0f32; OBS_DIM], [0.0f32; OBS_DIM]);
    env.reset(&mut obs).unwrap();
    let a = env.robot().layout.root_qpos_adr;
    let q = env.robot_mut().data_mut().qpos_mut();
    q[a + 2] = z_m;
    q[a + 3..a + 7].copy_from_slice(&[(roll_rad / 2.0).cos(), (roll_rad / 2.0).sin(), 0.0, 0.0]);
    for _ in 0..50 {
        let r = env.step(&[0.0; ACT_DIM], &mut obs, &mut fin);
        if r.done {
            assert!(!r.time_out);
            return env.take_summary().map(|s| s.end);
        }
    }
    None
}

#[test]
fn tilting_past_the_limit_or_landing_on_the_trunk_terminates() {
    assert_eq!(end_after_placing(1.4, 0.6), Some(EpisodeEnd::Tilt));
    assert_eq!(
        end_after_placing(std::f64::consts::PI, 0.05),
        Some(EpisodeEnd::TrunkContact)
    );
    assert_eq!(
        end_after_placing(0.0, 0.39),
        None,
        "a standing robot does not terminate"
    );
}

fn rollout(threads: usize, terrain: TerrainKind) -> (Vec<u32>, Vec<u32>) {
    rollout_with(threads, terrain, ModelSharing::PerThread)
}

fn rollout_with(
    threads: usize,
    terrain: TerrainKind,
    sharing: ModelSharing,
) -> (Vec<u32>, Vec<u32>) {
    let mut c = cfg();
    c.terrain.kind = terrain;
    c.episode.length_s = 1.0;
    let c = Arc::new(c);
    let scene = build_scene(&c, 5).unwrap();
    let mut v = VecEnv::with_sharing(
        c,
        &scene.model,
        scene.terrain.clone(),
        6,
        threads,
        11,
        sharing,
    )
    .unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    let (mut obs_bits, mut rew_bits) = (Vec::new(), Vec::new());
    for _ in 0..120 {
        let a = random_actions(&mut rng, 6);
        let b = v.step(&a);
        obs_bits.extend(b.obs.iter().map(|x| x.to_bits()));
        rew_bits.extend(b.rewards.iter().map(|x| x.to_bits()));
    }
    (obs_bits, rew_bits)
}

#[test]
fn same_seed_gives_bit_identical_rollouts_with_one_or_two_threads() {
    for terrain in [TerrainKind::Flat, TerrainKind::Rough] {
        let one = rollout(1, terrain);
        let two = rollout(2, terrain);
        assert!(
            one.0 == two.0 && one.1 == two.1,
            "{terrain:?} rollouts differ across thread counts"
        );
    }
}

/// Robots left out of a step stand still, and the others step exactly as if
/// every robot had stepped.
#[test]
fn robots_left_out_of_a_step_stand_still_and_change_nothing_for_the_others() {
    let mut c = cfg();
    c.episode.length_s = 1.0;
    let c = Arc::new(c);
    let scene = build_scene(&c, 5).unwrap();
    let make = || VecEnv::new(c.clone(), &scene.model, None, 4, 2, 11).unwrap();
    let (mut all, mut some) = (make(), make());
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    // robot 2 stops after step 10; 60 steps cross an episode end (50 steps)
    for step in 0..60 {
        let a = random_actions(&mut rng, 4);
        let active = [true, true, step < 10, true];
        let before: Vec<f32> = some.batch().obs[2 * OBS_DIM..3 * OBS_DIM].to_vec();
        let full = all.step(&a).clone();
        let part = some.step_active(&a, Some(&active));
        for i in [0, 1, 3] {
            let row = i * OBS_DIM..(i + 1) * OBS_DIM;
            assert_eq!(
                full.obs[row.clone()],
                part.obs[row],
                "robot {i}, step {step}"
            );
            assert_eq!(full.rewards[i].to_bits(), part.rewards[i].to_bits());
            assert_eq!(full.dones[i], part.dones[i]);
        }
        if step >= 10 {
            assert_eq!(
                part.obs[2 * OBS_DIM..3 * OBS_DIM],
                before[..],
                "step {step}"
            );
            assert_eq!((part.rewards[2], part.dones[2]), (0.0, false));
        }
    }
    let ended = |v: &mut VecEnv| v.drain_episodes().map(|e| e.env_index).collect::<Vec<_>>();
    let (full_ends, part_ends) = (ended(&mut all), ended(&mut some));
    let count = |ends: &[usize], i: usize| ends.iter().filter(|&&e| e == i).count();
    for i in [0, 1, 3] {
        assert_eq!(count(&full_ends, i), count(&part_ends, i), "robot {i}");
    }
    // 60 steps of 50-step episodes: every stepping robot ended one; robot 2
    // only if it fell within its first 10 steps
    assert!(count(&full_ends, 2) >= 1);
    assert!(count(&part_ends, 2) < count(&full_ends, 2));
}

/// A resumed rough-ground run puts every robot back on its stored level.
#[test]
fn terrain_levels_are_restored_for_a_resume() {
    let mut c = cfg();
    c.terrain.kind = TerrainKind::Rough;
    let c = Arc::new(c);
    let scene = build_scene(&c, 5).unwrap();
    let mut v = VecEnv::new(c.clone(), &scene.model, scene.terrain.clone(), 6, 1, 11).unwrap();
    let top = scene.terrain.as_ref().unwrap().config().num_levels - 1;
    let stored = vec![0, top, 1, top, 2, 0];
    v.restore_terrain_levels(&stored).unwrap();
    assert_eq!(v.terrain_levels().unwrap(), stored);
    let mean = stored.iter().sum::<usize>() as f64 / 6.0;
    assert!((v.mean_terrain_level() - mean).abs() < 1e-12);
    assert!(v
        .envs()
        .iter()
        .zip(&stored)
        .all(|(e, &l)| e.terrain_level == l));
    // wrong length or a level beyond the terrain: refused, levels unchanged
    assert!(v.restore_terrain_levels(&[0, 1]).is_err());
    assert!(v.restore_terrain_levels(&[top + 1; 6]).is_err());
    assert_eq!(v.terrain_levels().unwrap(), stored);
    // flat ground has no curriculum to restore
    let flat = Arc::new(cfg());
    let scene = build_scene(&flat, 5).unwrap();
    let mut f = VecEnv::new(flat, &scene.model, None, 2, 1, 1).unwrap();
    assert!(f.terrain_levels().is_none() && f.restore_terrain_levels(&[0, 0]).is_err());
}

#[test]
fn a_shared_model_gives_the_trajectories_of_per_env_model_copies() {
    // Randomised friction and mass differ per env and per episode (1 s episodes:
    // several resets in 120 steps); with one model per thread each env's values
    // are written in before its step. Bit-identical to a model copy per env,
    // with one and two threads, on flat and rough ground.
    for terrain in [TerrainKind::Flat, TerrainKind::Rough] {
        let copies = rollout_with(1, terrain, ModelSharing::PerEnv);
        for threads in [1, 2] {
            let shared = rollout_with(threads, terrain, ModelSharing::PerThread);
            assert!(
                shared.0 == copies.0 && shared.1 == copies.1,
                "{terrain:?}, {threads} thread(s): shared model differs from per-env copies"
            );
        }
    }
}

/// Runs one env with every risk term firing at every step until its episode
/// ends; returns the episode's summary.
fn episode_with_every_penalty_firing(
    length_s: f64,
    max_tilt_rad: f64,
) -> rall::env::EpisodeSummary {
    let mut c = cfg();
    c.episode.length_s = length_s;
    c.episode.max_tilt_rad = max_tilt_rad;
    c.risk.probability = 1.0;
    c.risk.base_pitch.threshold = 0.0;
    c.risk.base_roll.threshold = 0.0;
    c.risk.joint_velocity.threshold = 0.0;
    c.risk.joint_acceleration.threshold = 0.0;
    c.risk.joint_torque.threshold = 0.0;
    let c = Arc::new(c);
    let scene = build_scene(&c, 0).unwrap();
    let mut env = Env::new(c, &scene.model, None, 3, 0).unwrap();
    let (mut obs, mut fin) = ([0.0f32; OBS_DIM], [0.0f32; OBS_DIM]);
    env.reset(&mut obs).unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    for _ in 0..10_000 {
        // random actions while tilt must end the episode, standing still otherwise
        let scale = if max_tilt_rad < 0.1 { 1.0 } else { 0.0 };
        let a: Vec<f32> = (0..ACT_DIM)
            .map(|_| scale * rng.gen_range(-1.0f32..1.0))
            .collect();
        if env.step(&a, &mut obs, &mut fin).done {
            return env.take_summary().unwrap();
        }
    }
    panic!("the episode never ended");
}

#[test]
fn firings_in_the_last_second_before_a_fall_are_counted_and_a_time_out_counts_none() {
    // tilt past 1e-6 rad ends the episode almost at once: every firing is within 1 s
    let fell = episode_with_every_penalty_firing(20.0, 1e-6);
    assert_ne!(fell.end, EpisodeEnd::TimeOut);
    assert!(fell.steps <= 50, "{} steps", fell.steps);
    assert!(fell.risk_fired.iter().any(|&n| n > 0));
    assert_eq!(fell.risk_fired_before_fall, fell.risk_fired);
    // a 2 s episode that times out: firings, none before a fall
    let timed_out = episode_with_every_penalty_firing(2.0, 3.0);
    assert_eq!(timed_out.end, EpisodeEnd::TimeOut);
    assert!(timed_out.risk_fired.iter().all(|&n| n > 50));
    assert_eq!(timed_out.risk_fired_before_fall, [0; 5]);
}
