//! The paper's methods as configs: observation groups, DR parameters, RMA's
//! teacher and student, checkpoints that carry their layout, and one training
//! iteration of every method config.

mod common;

use std::path::Path;
use std::sync::atomic::AtomicBool;
use std::sync::Arc;

use rall::config::TrainConfig;
use rall::env::privileged::{EXTRINSICS_DIM, PRIVILEGED_DIM};
use rall::env::terrain::TerrainKind;
use rall::env::{build_scene, Env, EnvConfig, ObsGroup, OBS_DIM};
use rall::learn::{load_checkpoint, save_checkpoint, LatentSource, Learner};
use rall::runner::{load_policy, save_policy, train, Progress, TrainSummary};

const METHODS: [&str; 7] = [
    "baseline",
    "dr",
    "rma",
    "rma-extrinsics",
    "rma-critic-privileged",
    "rall",
    "rall-eta1",
];

/// `rall train` on `run` (resuming it when `resume`), never asked to stop, no observer.
fn train_to_end(cfg: TrainConfig, run: &Path, resume: bool) -> anyhow::Result<TrainSummary> {
    train(cfg, run, resume, Arc::new(AtomicBool::new(false)), &mut ())
}

fn repo(p: &str) -> std::path::PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join(p)
}

/// The DR config's env on flat ground with every group, 5 history steps.
fn dr_env_config() -> EnvConfig {
    let mut c = TrainConfig::from_toml_file(&repo("configs/dr.toml"))
        .unwrap()
        .env;
    c.robot_mjcf = repo("mjcf/aliengo.xml").display().to_string();
    c.terrain.kind = TerrainKind::Flat;
    c.observation.groups = vec![ObsGroup::Policy, ObsGroup::Privileged, ObsGroup::History];
    c.observation.history_steps = 5;
    c
}

fn env_of(cfg: &EnvConfig, seed: u64) -> Env {
    let scene = build_scene(cfg, 1).unwrap();
    Env::new(
        Arc::new(cfg.clone()),
        &scene.model,
        scene.terrain.clone(),
        seed,
        0,
    )
    .unwrap()
}

#[test]
fn the_privileged_group_holds_exactly_the_parameters_of_the_episode() {
    let cfg = dr_env_config();
    let mut env = env_of(&cfg, 7);
    let model_friction = env.robot().params().geom_friction().to_vec();
    let trunk = env.robot().layout.trunk_body;
    let base_mass = env.robot().params().body_mass_kg()[trunk];
    let base_ipos = env.robot().params().body_ipos_m()[trunk];
    let mut obs = vec![0.0; cfg.obs_width()];
    assert_eq!(obs.len(), OBS_DIM + PRIVILEGED_DIM + 5 * OBS_DIM);
    let mut draws = Vec::new();
    for _ in 0..4 {
        env.reset(&mut obs).unwrap();
        let d = env.draw;
        draws.push(d);
        let p = &obs[OBS_DIM..OBS_DIM + PRIVILEGED_DIM];
        // the values written are the draw, field by field
        let mut expected = vec![0.0; PRIVILEGED_DIM];
        env.privileged_state().write(&mut expected);
        assert_eq!(p, &expected[..]);
        assert_eq!(p[0], (d.friction.unwrap() - 1.0) as f32);
        assert_eq!(p[1], (d.added_base_mass_kg * 0.2) as f32);
        for (k, c) in d.com_offset_m.iter().enumerate() {
            assert_eq!(p[2 + k], (c * 10.0) as f32);
        }
        for (j, s) in d.motor_strength.iter().enumerate() {
            assert_eq!(p[5 + j], ((s - 1.0) * 5.0) as f32);
        }
        assert_eq!(p[17], ((d.kp_factor - 1.0) * 2.0) as f32);
        assert_eq!(p[18], ((d.kd_factor - 1.0) * 2.0) as f32);
        // the draws lie in the configured ranges ...
        let r = &cfg.randomization;
        let inside = |v: f64, range: Option<[f64; 2]>| {
            let [lo, hi] = range.unwrap();
            (lo..=hi).contains(&v)
        };
        assert!(inside(d.friction.unwrap(), r.friction));
        assert!(inside(d.added_base_mass_kg, r.added_base_mass_kg));
        assert!(d
            .motor_strength
            .iter()
            .all(|&s| inside(s, r.motor_strength)));
        assert!(inside(d.kp_factor, r.kp_factor) && inside(d.kd_factor, r.kd_factor));
        assert!(d.com_offset_m.iter().all(|&c| inside(c, r.com_offset_m)));
        // ... and are what the robot steps with
        let robot = env.robot();
        assert_eq!(robot.motor_strength, d.motor_strength);
        assert_eq!(
            robot.control.kp_nm_per_rad,
            cfg.control.kp_nm_per_rad * d.kp_factor
        );
        assert_eq!(
            robot.control.kd_nm_s_per_rad,
            cfg.control.kd_nm_s_per_rad * d.kd_factor
        );
        let params = robot.params();
        assert_eq!(
            params.body_mass_kg()[trunk],
            base_mass + d.added_base_mass_kg
        );
        for (g, base) in params.geom_friction().iter().zip(&model_friction) {
            assert_eq!(*g, [d.friction.unwrap(), base[1], base[2]]);
        }
        let ipos = params.body_ipos_m()[trunk];
        for ((p, b), c) in ipos.iter().zip(base_ipos).zip(d.com_offset_m) {
            assert_eq!(*p, b + c);
        }
        // the true velocity is the state's, without the policy group's noise
        let s = env.privileged_state();
        assert_eq!(s.base_lin_vel_body_mps, env.state().base_lin_vel_body_mps);
    }
    assert!(
        draws.windows(2).all(|w| w[0] != w[1]),
        "every episode draws anew"
    );
}

/// RMA's e_t: the `extrinsics` group repeats the privileged group's episode
/// factors and stays constant through the episode, while the privileged state
/// fields (true velocity, ground under the feet) move with the robot.
#[test]
fn the_extrinsics_group_is_the_episode_factors_and_constant_over_an_episode() {
    let mut cfg = dr_env_config();
    cfg.observation.groups = vec![ObsGroup::Policy, ObsGroup::Privileged, ObsGroup::Extrinsics];
    let mut env = env_of(&cfg, 11);
    let w = cfg.obs_width();
    assert_eq!(w, OBS_DIM + PRIVILEGED_DIM + EXTRINSICS_DIM);
    let privileged = OBS_DIM..OBS_DIM + PRIVILEGED_DIM;
    let extrinsics = privileged.end..w;
    let (mut obs, mut fin) = (vec![0.0; w], vec![0.0; w]);
    env.reset(&mut obs).unwrap();
    let first = obs.clone();
    assert_eq!(
        &first[extrinsics.clone()],
        &first[privileged.start..privileged.start + EXTRINSICS_DIM]
    );
    assert!(first[extrinsics.clone()].iter().any(|&v| v != 0.0));
    let action = vec![0.3f32; 12];
    for _ in 0..10 {
        assert!(!env.step(&action, &mut obs, &mut fin).done);
        assert_eq!(&obs[extrinsics.clone()], &first[extrinsics.clone()]);
    }
    assert_ne!(
        &obs[privileged.start + EXTRINSICS_DIM..privileged.end],
        &first[privileged.start + EXTRINSICS_DIM..privileged.end],
        "the privileged state fields move"
    );
    env.reset(&mut obs).unwrap();
    assert_ne!(
        &obs[extrinsics.clone()],
        &first[extrinsics],
        "a new episode draws anew"
    );
}

#[test]
fn the_history_shifts_one_step_per_step_and_clears_on_reset() {
    let cfg = dr_env_config();
    let mut env = env_of(&cfg, 3);
    let w = cfg.obs_width();
    let h0 = OBS_DIM + PRIVILEGED_DIM;
    let (mut obs, mut fin) = (vec![0.0; w], vec![0.0; w]);
    env.reset(&mut obs).unwrap();
    let check_fresh = |obs: &[f32]| {
        assert_eq!(
            &obs[h0..h0 + OBS_DIM],
            &obs[..OBS_DIM],
            "newest = this step"
        );
        assert!(
            obs[h0 + OBS_DIM..].iter().all(|&v| v == 0.0),
            "older slots cleared"
        );
    };
    check_fresh(&obs);
    let action = vec![0.1f32; 12];
    for step in 0..8 {
        let before = obs.clone();
        let done = env.step(&action, &mut obs, &mut fin).done;
        assert!(
            !done,
            "step {step}: the robot should not fall standing still"
        );
        assert_eq!(&obs[h0..h0 + OBS_DIM], &obs[..OBS_DIM]);
        // slot k now holds what slot k-1 held one step earlier
        assert_eq!(&obs[h0 + OBS_DIM..], &before[h0..w - OBS_DIM]);
        assert_eq!(env.history(), &obs[h0..]);
    }
    env.reset(&mut obs).unwrap();
    check_fresh(&obs);
}

/// A layout [policy 48 | privileged 31] learner whose adaptation module reads the
/// privileged group too, with the encoder's weights: the student is then fed the
/// teacher's true latent.
#[test]
fn a_student_fed_the_true_latent_acts_exactly_as_the_teacher() {
    let mut cfg = TrainConfig::from_toml_file(&repo("configs/rma.toml")).unwrap();
    cfg.env.observation.groups = vec![ObsGroup::Policy, ObsGroup::Privileged];
    let a = cfg.learner.adaptation.as_mut().unwrap();
    a.input = "privileged".into();
    a.hidden = cfg.learner.encoder.as_ref().unwrap().hidden.clone();
    let layout = cfg.env.obs_layout();
    let mut teacher = Learner::with_layout(&layout, 12, &cfg.learner, 5).unwrap();
    let mut state = teacher.state();
    let enc: Vec<(String, Vec<f32>)> = state
        .iter()
        .filter(|t| t.name.starts_with("actor.enc."))
        .map(|t| (t.name.replace("actor.enc.", "actor.adapt."), t.data.clone()))
        .collect();
    assert!(!enc.is_empty());
    for (name, data) in enc {
        let t = state.iter_mut().find(|t| t.name == name).unwrap();
        t.data = data;
    }
    teacher.load_state(&state).unwrap();
    use rand::{Rng, SeedableRng};
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(9);
    let obs: Vec<f32> = (0..16 * layout.width())
        .map(|_| rng.gen_range(-1.0..1.0))
        .collect();
    let teacher_actions = teacher.act_mean(&obs);
    let mut student = teacher;
    student.set_latent_source(LatentSource::Adaptation);
    assert_eq!(student.act_mean(&obs), teacher_actions);
    // with its own (different) weights the student acts differently
    let fresh = Learner::with_layout(&layout, 12, &cfg.learner, 6).unwrap();
    assert_ne!(fresh.act_mean(&obs), teacher_actions);
}

/// Each method config on flat ground, tiny, for tests.

#[test]
fn every_method_config_trains_one_iteration() {
    for m in METHODS {
        let cfg = common::tiny_method(m);
        let dir = tempfile::tempdir().unwrap();
        let run = dir.path().join(m);
        let s = train_to_end(cfg.clone(), &run, false).unwrap_or_else(|e| panic!("{m}: {e:#}"));
        let rma = cfg.learner.adaptation.is_some();
        assert_eq!(s.iterations_done, if rma { 2 } else { 1 }, "{m}");
        let rows = std::fs::read_to_string(run.join("metrics.csv")).unwrap();
        assert_eq!(rows.lines().count(), 2, "{m}: header + one PPO iteration");
        let loaded = load_policy(&s.last_checkpoint).unwrap();
        let mut groups = cfg.env.observation.groups.clone();
        if rma {
            // phase 2 adds the history the adaptation module reads
            groups.push(ObsGroup::History);
        }
        assert_eq!(loaded.config.env.observation.groups, groups, "{m}");
        if rma {
            let adapt = std::fs::read_to_string(run.join("adaptation.csv")).unwrap();
            assert_eq!(
                adapt.lines().count(),
                2,
                "{m}: header + one phase-2 iteration"
            );
            assert_eq!(loaded.learner.latent_source(), LatentSource::Adaptation);
        } else {
            assert_eq!(loaded.learner.latent_source(), LatentSource::Encoder);
        }
    }
}

#[test]
fn checkpoints_of_every_method_round_trip_and_other_groups_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    for m in METHODS {
        let cfg = common::tiny_method(m);
        let layout = cfg.env.obs_layout();
        let learner = Learner::with_layout(&layout, 12, &cfg.learner, 3).unwrap();
        let path = dir.path().join(format!("{m}.safetensors"));
        save_policy(&path, &learner, &cfg, &Progress::default()).unwrap();
        let back = load_policy(&path).unwrap();
        assert_eq!(back.learner.state(), learner.state(), "{m}");
        let obs = vec![0.25f32; 3 * layout.width()];
        assert_eq!(back.learner.act_mean(&obs), learner.act_mean(&obs), "{m}");
    }
    // a checkpoint whose privileged group is narrower than this build's
    let path = dir.path().join("rma.safetensors");
    let (tensors, mut meta) = load_checkpoint(&path).unwrap();
    let groups = meta["obs_groups"].clone();
    assert!(
        groups.contains(&format!("privileged:{PRIVILEGED_DIM}")),
        "{groups}"
    );
    meta.insert(
        "obs_groups".into(),
        groups.replace(
            &format!("privileged:{PRIVILEGED_DIM}"),
            &format!("privileged:{}", PRIVILEGED_DIM - 1),
        ),
    );
    let bad = dir.path().join("narrow.safetensors");
    save_checkpoint(&bad, &tensors, &meta).unwrap();
    let e = format!("{:#}", load_policy(&bad).err().unwrap());
    assert!(e.contains("\"privileged\"") && e.contains("wide"), "{e}");
    // same widths, different fields
    let (tensors, mut meta) = load_checkpoint(&path).unwrap();
    meta.insert("obs_group.privileged".into(), "friction:31*1@0".into());
    save_checkpoint(&bad, &tensors, &meta).unwrap();
    let e = format!("{:#}", load_policy(&bad).err().unwrap());
    assert!(
        e.contains("\"privileged\"") && e.contains("friction:31"),
        "{e}"
    );
    // a policy-only checkpoint against a config that adds groups
    let (tensors, mut meta) = load_checkpoint(&dir.path().join("baseline.safetensors")).unwrap();
    meta.insert("obs_groups".into(), "policy:48,history:240".into());
    save_checkpoint(&bad, &tensors, &meta).unwrap();
    let e = format!("{:#}", load_policy(&bad).err().unwrap());
    assert!(e.contains("\"history\""), "{e}");
}

#[test]
fn a_network_reading_a_group_the_env_does_not_write_is_refused_by_name() {
    let text = "[learner]\nactor_inputs = [\"policy\", \"privileged\"]\n";
    let e = format!("{:#}", TrainConfig::from_toml_str(text).unwrap_err());
    assert!(
        e.contains("privileged") && e.contains("learner.actor_inputs"),
        "{e}"
    );
    let text = "[env.observation]\ngroups = [\"privileged\"]\n";
    let e = format!("{:#}", TrainConfig::from_toml_str(text).unwrap_err());
    assert!(
        e.contains("observation.groups") && e.contains("policy"),
        "{e}"
    );
}

/// A tiny RMA run trained through `adapt_iterations` of phase 2, a checkpoint at
/// every iteration: its config, directory and the temp dir holding it.
fn trained_tiny_rma(
    adapt_iterations: usize,
) -> (TrainConfig, std::path::PathBuf, tempfile::TempDir) {
    let mut cfg = common::tiny_method("rma");
    cfg.learner.adaptation.as_mut().unwrap().iterations = adapt_iterations;
    cfg.runner.save_interval = 1;
    let dir = tempfile::tempdir().unwrap();
    let run = dir.path().join("rma");
    let s = train_to_end(cfg.clone(), &run, false).unwrap();
    assert_eq!(s.iterations_done, 1 + adapt_iterations);
    (cfg, run, dir)
}

/// The iterations `adaptation.csv` logs, in order (its first column).
fn adaptation_iterations(run: &std::path::Path) -> Vec<String> {
    let rows = std::fs::read_to_string(run.join("adaptation.csv")).unwrap();
    rows.lines()
        .skip(1)
        .map(|l| l.split(',').next().unwrap().to_string())
        .collect()
}

#[test]
fn rma_resumes_inside_phase_two_without_repeating_rows() {
    let (cfg, run, _dir) = trained_tiny_rma(3);
    // lose the last two checkpoints: the newest left is phase 2's first iteration
    for it in [3, 4] {
        std::fs::remove_file(run.join(format!("checkpoints/model_{it:06}.safetensors"))).unwrap();
    }
    std::fs::remove_file(run.join("latest.safetensors")).unwrap();
    let s = train_to_end(cfg, &run, true).unwrap();
    assert_eq!(s.iterations_done, 4);
    assert_eq!(adaptation_iterations(&run), ["2", "3", "4"]);
    let metrics = std::fs::read_to_string(run.join("metrics.csv")).unwrap();
    assert_eq!(
        metrics.lines().count(),
        2,
        "phase 1's one row, kept: {metrics}"
    );
    let loaded = load_policy(&s.last_checkpoint).unwrap();
    assert_eq!(loaded.learner.latent_source(), LatentSource::Adaptation);
    assert!(loaded
        .config
        .env
        .observation
        .groups
        .contains(&ObsGroup::History));
    assert!(
        !run.join("train.lock").exists(),
        "the lock goes with the trainer"
    );
}

#[test]
fn rma_phase_two_restarts_on_the_frozen_teacher_keeping_what_it_discards() {
    use rall::runner::{restart_adaptation, RunDir};
    let (cfg, run, dir) = trained_tiny_rma(2);
    let before = load_policy(&run.join("latest.safetensors")).unwrap();
    let rd = RunDir { root: run.clone() };
    assert_eq!(restart_adaptation(&rd).unwrap(), 1);
    let rewound = load_policy(&run.join("latest.safetensors")).unwrap();
    assert_eq!(rewound.progress.iteration, 1);
    // the teacher is carried over exactly, the adaptation module starts afresh
    let tensors = |p: &rall::runner::LoadedPolicy| p.learner.state();
    let (old, new) = (tensors(&before), tensors(&rewound));
    let mut adapt_changed = false;
    for t in &new {
        let o = old.iter().find(|o| o.name == t.name).unwrap();
        if t.name.contains("adapt") {
            adapt_changed |= o.data != t.data;
        } else {
            assert_eq!(o.data, t.data, "{} changed", t.name);
        }
    }
    assert!(adapt_changed, "the adaptation module was not reset");
    // nothing is deleted: phase 2's checkpoints are kept aside
    for f in [
        "model_000002.safetensors",
        "model_000003.safetensors",
        "latest-at-3.safetensors",
    ] {
        assert!(run.join("discarded-adaptation").join(f).exists(), "{f}");
    }
    assert!(!run.join("checkpoints/model_000003.safetensors").exists());
    // a run at the end of phase 1 has nothing to restart
    let e = format!("{:#}", restart_adaptation(&rd).unwrap_err());
    assert!(e.contains("nothing to restart"), "{e}");
    // phase 2 trains again, its log without the discarded rows
    let s = train_to_end(cfg, &run, true).unwrap();
    assert_eq!(s.iterations_done, 3);
    assert_eq!(adaptation_iterations(&run), ["2", "3"]);
    // a run without phase 2 is refused by name
    let mut ppo = common::tiny_method("baseline");
    ppo.runner.save_interval = 1;
    let plain = dir.path().join("baseline");
    train_to_end(ppo, &plain, false).unwrap();
    let e = format!(
        "{:#}",
        restart_adaptation(&RunDir { root: plain }).unwrap_err()
    );
    assert!(e.contains("not an RMA run"), "{e}");
}

#[test]
fn the_meta_controller_drives_an_rma_student_beside_a_policy_only_critic() {
    let dir = tempfile::tempdir().unwrap();
    let mut trained = Vec::new();
    for m in ["rall-eta1", "rma"] {
        let mut cfg = common::tiny_method(m);
        cfg.env.terrain.kind = TerrainKind::Flat;
        let s = train_to_end(cfg, &dir.path().join(m), false).unwrap();
        trained.push(s.last_checkpoint);
    }
    let risky = rall::eval::NamedPolicy::load("eta1", &trained[0]).unwrap();
    let student = rall::eval::NamedPolicy::load("student", &trained[1]).unwrap();
    assert_eq!(
        student.critic().unwrap().latent_source(),
        LatentSource::Adaptation
    );
    let meta = rall::eval::MetaConfig {
        name: "meta".into(),
        risky: "eta1".into(),
        safe: "student".into(),
        // below any IQR: the student acts from the first step
        threshold: -1e9,
        hysteresis: 0.0,
        min_safe_steps: 1,
    };
    let opts = rall::eval::RaceOptions {
        agents: 2,
        episodes: 1,
        threads: 2,
        seed: 0,
        course_seed: 0,
        params: rall::eval::ScenarioParams {
            episode_length_s: Some(1.0),
            ..Default::default()
        },
    };
    let report = rall::eval::evaluate_race(
        &[risky, student],
        std::slice::from_ref(&meta),
        &opts,
        |_| {},
    )
    .unwrap();
    let m = report.rows.iter().find(|r| r.name == "meta").unwrap();
    let log = m.meta.as_ref().unwrap();
    assert!(
        log.safe_fraction > 0.99,
        "the student acted: {}",
        log.safe_fraction
    );
    assert_eq!(m.episodes, 2);
}

#[test]
fn a_chosen_teacher_is_installed_only_between_the_two_phases() {
    use rall::runner::{install_teacher, PhaseOneOnly, RunDir};
    let mut cfg = common::tiny_method("rma");
    cfg.runner.iterations = 2;
    let dir = tempfile::tempdir().unwrap();
    let run = dir.path().join("rma");
    let stop = Arc::new(AtomicBool::new(false));
    let s = train(cfg.clone(), &run, false, stop, &mut PhaseOneOnly(&mut ())).unwrap();
    assert_eq!((s.iterations_done, s.interrupted), (2, false));
    let at_end = load_policy(&run.join("latest.safetensors")).unwrap();
    assert_eq!(at_end.learner.latent_source(), LatentSource::Encoder);
    let tensors = |p: &rall::runner::LoadedPolicy| -> Vec<(String, Vec<f32>)> {
        p.learner
            .state()
            .into_iter()
            .map(|t| (t.name, t.data))
            .collect()
    };
    // the teacher of iteration 1 goes into the run standing at iteration 2
    let rd = RunDir { root: run.clone() };
    let first = run.join("checkpoints/model_000001.safetensors");
    let one = load_policy(&first).unwrap();
    assert_ne!(tensors(&one), tensors(&at_end));
    for _ in 0..2 {
        install_teacher(&rd, &first).unwrap();
        let installed = load_policy(&run.join("latest.safetensors")).unwrap();
        assert_eq!(installed.progress.iteration, 2);
        assert_eq!(tensors(&installed), tensors(&one));
    }
    // the numbered checkpoint of iteration 2 is left as trained
    let two = load_policy(&run.join("checkpoints/model_000002.safetensors")).unwrap();
    assert_eq!(tensors(&two), tensors(&at_end));
    // phase 2 runs on it; once it has, no teacher can be installed
    let s = train_to_end(cfg, &run, true).unwrap();
    assert_eq!(s.iterations_done, 3);
    let e = format!("{:#}", install_teacher(&rd, &first).unwrap_err());
    assert!(e.contains("not at the end of its phase 1"), "{e}");
    // a run without phase 2 has no teacher
    let plain = dir.path().join("baseline");
    train_to_end(common::tiny_method("baseline"), &plain, false).unwrap();
    let e = format!(
        "{:#}",
        install_teacher(
            &RunDir {
                root: plain.clone()
            },
            &plain.join("latest.safetensors")
        )
        .unwrap_err()
    );
    assert!(e.contains("not an RMA run"), "{e}");
}
