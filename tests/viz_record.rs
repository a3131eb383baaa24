//! Recordings read back: `play` to an .rrd holds the robot (static geoms, one
//! transform per step per body), the terrain, the plots and one bar chart per step;
//! the training observer logs metrics per iteration and evaluation episodes; the CLI
//! fails fast without a viewer. When a `rerun` CLI is on PATH (pip rerun-sdk), the
//! files also pass `rerun rrd verify`.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::atomic::AtomicBool;
use std::sync::Arc;

use rall::config::TrainConfig;
use rall::env::terrain::{TerrainKind, TerrainProportions};
use rall::env::{ACT_DIM, OBS_DIM};
use rall::learn::{CriticKind, Learner};
use rall::runner::{save_policy, Progress};
use rall::viz::episode::{bar_widths, centred, VALUE_EVERY_FRAMES};
use rall::viz::{
    self, PlayOptions, RerunTarget, RrdSummary, TrainRecorder, TrainRecordingOptions, ValueProbe,
};

const BODIES: [&str; 10] = [
    "trunk", "FR_hip", "FR_thigh", "FR_calf", "FL_hip", "FL_thigh", "FL_calf", "RR_hip",
    "RR_thigh", "RR_calf",
];

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// A small, fast config: tiny nets, 1 s episodes, flat ground.
fn small_cfg(critic: CriticKind) -> TrainConfig {
    let mut cfg = TrainConfig::default();
    cfg.env.robot_mjcf = root().join("mjcf/aliengo.xml").display().to_string();
    cfg.env.terrain.kind = TerrainKind::Flat;
    cfg.env.episode.length_s = 1.0;
    cfg.learner.critic = critic;
    cfg.learner.actor_hidden = vec![32, 32];
    cfg.learner.critic_hidden = vec![32, 32];
    cfg.learner.num_cos = 16;
    cfg.learner.num_taus = 8;
    cfg.learner.num_target_taus = 8;
    cfg.learner.num_value_taus = 16;
    cfg.runner.num_envs = 4;
    cfg.runner.steps_per_env = 8;
    cfg.runner.threads = 1;
    cfg.runner.iterations = 2;
    cfg
}

/// A small rough terrain (4 levels x 2 types, 1 m border) around the same robot.
fn rough_cfg() -> TrainConfig {
    let mut cfg = small_cfg(CriticKind::Iqn);
    let t = &mut cfg.env.terrain;
    t.kind = TerrainKind::Rough;
    t.num_levels = 4;
    t.num_types = 2;
    t.border_size_m = 1.0;
    t.max_init_level = 1;
    t.proportions = TerrainProportions {
        smooth_slope: 0.0,
        rough_slope: 0.5,
        stairs_up: 0.0,
        stairs_down: 0.0,
        discrete: 0.5,
        flat: 0.0,
    };
    cfg
}

fn learner(cfg: &TrainConfig) -> Learner {
    Learner::new(OBS_DIM, ACT_DIM, &cfg.learner, 0).expect("learner")
}

fn checkpoint(dir: &Path, cfg: &TrainConfig) -> PathBuf {
    let path = dir.join("policy.safetensors");
    save_policy(&path, &learner(cfg), cfg, &Progress::default()).expect("checkpoint");
    path
}

/// Runs `rerun rrd verify` when the pip CLI is installed; says why not otherwise.
fn verify_with_rerun_cli(path: &Path) {
    if !viz::sink::on_path("rerun") {
        println!(
            "skipped `rerun rrd verify {}`: no `rerun` on PATH ({})",
            path.display(),
            viz::sink::VIEWER_PIP
        );
        return;
    }
    let out = Command::new("rerun")
        .args(["rrd", "verify"])
        .arg(path)
        .output()
        .expect("running rerun");
    assert!(
        out.status.success(),
        "rerun rrd verify {} failed:\n{}\n{}",
        path.display(),
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
}

fn record_play(
    cfg: &TrainConfig,
    opts: &PlayOptions,
    path: &Path,
) -> (viz::PlayReport, RrdSummary) {
    let l = learner(cfg);
    let rec = viz::open_recording(
        viz::PLAY_APP_ID,
        "test",
        &RerunTarget::Save(path.into()),
        viz::play_blueprint(),
    )
    .expect("recording");
    let (report, rec) = viz::play(&l, &cfg.env, opts, Some(rec)).expect("play");
    viz::finish_recording(rec.expect("the recording comes back")).expect("finish");
    (report, viz::summarize_rrd(path).expect("read back"))
}

#[test]
fn play_recording_has_a_transform_per_step_and_a_bar_chart_every_fifth_frame() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("play.rrd");
    let cfg = small_cfg(CriticKind::Iqn);
    let opts = PlayOptions {
        episodes: 2,
        max_steps: Some(20),
        flush_steps: 7,
        ..PlayOptions::default()
    };
    let (report, s) = record_play(&cfg, &opts, &path);
    assert_eq!(report.episodes.len(), 2);
    // One frame at each reset plus one per step.
    let frames: u64 = report.episodes.iter().map(|e| e.steps as u64 + 1).sum();
    assert!(frames >= 4, "episodes too short: {report:?}");
    for body in BODIES.iter().chain(&["RL_hip", "RL_thigh", "RL_calf"]) {
        let e = s
            .entity(&format!("world/robot/{body}"))
            .unwrap_or_else(|| panic!("no entity for body {body}"));
        assert_eq!(e.temporal_rows, frames, "transforms of {body}");
        assert!(
            e.components.iter().any(|c| c.contains("Transform3D")),
            "{body}: {:?}",
            e.components
        );
        assert!(
            e.timelines.contains("sim_time") && e.timelines.contains("step"),
            "{body}: {:?}",
            e.timelines
        );
    }
    // Static geometry under the bodies: trunk box, hip spheres, thigh/calf boxes, feet.
    let trunk = s.entity("world/robot/trunk/trunk").expect("trunk geom");
    assert!(trunk.static_rows >= 1 && trunk.temporal_rows == 0);
    assert!(
        trunk.components.iter().any(|c| c.starts_with("Boxes3D")),
        "{:?}",
        trunk.components
    );
    // What the 3D view's eye tracks: rerun tracks an entity's own geometry, so the
    // followed entity carries points (under the trunk, so they move with it).
    let follow = s.entity(viz::FOLLOWED_ENTITY).expect("followed entity");
    assert!(follow.static_rows >= 1 && follow.temporal_rows == 0);
    assert!(
        follow.components.iter().any(|c| c.starts_with("Points3D")),
        "{:?}",
        follow.components
    );
    assert!(viz::FOLLOWED_ENTITY.starts_with("world/robot/trunk/"));
    // A foot is welded to its calf: drawn under the calf's transform, it needs none.
    assert!(s.entity("world/robot/FR_foot").is_none());
    let foot = s.entity("world/robot/FR_calf/FR_foot").expect("foot geom");
    assert!(
        foot.components
            .iter()
            .any(|c| c.starts_with("Ellipsoids3D")),
        "{:?}",
        foot.components
    );
    assert!(s.entity("world/ground").expect("ground").static_rows >= 1);
    // The critic: a bar chart, CVaR/mean and IQR series on every 5th frame (10 Hz).
    let value_frames = frames.div_ceil(VALUE_EVERY_FRAMES as u64);
    let bars = s.entity("value/quantiles").expect("bar chart");
    assert_eq!(bars.temporal_rows, value_frames);
    assert!(
        bars.components.iter().any(|c| c.starts_with("BarChart")),
        "{:?}",
        bars.components
    );
    assert!(
        bars.components.iter().any(|c| c.contains("widths")),
        "the bars need widths: {:?}",
        bars.components
    );
    for p in ["value/stats", "value/iqr"] {
        let e = s.entity(p).unwrap_or_else(|| panic!("no {p}"));
        assert_eq!(e.temporal_rows, value_frames, "{p}");
        assert!(e.static_rows >= 1, "{p} has no series names");
    }
    for p in [
        "plots/velocity/vx",
        "plots/velocity/vy",
        "plots/velocity/yaw_rate",
    ] {
        let e = s.entity(p).unwrap_or_else(|| panic!("no {p}"));
        assert_eq!(e.temporal_rows, frames, "{p}");
        assert!(e.static_rows >= 1, "{p} has no series names");
    }
    assert_eq!(s.entity("plots/torques").unwrap().temporal_rows, frames);
    assert_eq!(s.entity("plots/contacts").unwrap().temporal_rows, frames);
    assert_eq!(s.entity("world/velocity").unwrap().temporal_rows, frames);
    // Episode starts (and ends or cuts) are events.
    assert!(s.entity("events").expect("events").temporal_rows >= 4);
    // The layout travels with the recording.
    assert!(
        s.application_ids.contains(viz::PLAY_APP_ID),
        "{:?}",
        s.application_ids
    );
    assert!(
        s.blueprint_chunks > 0 && s.blueprint_activations == 1,
        "{} {}",
        s.blueprint_chunks,
        s.blueprint_activations
    );
    verify_with_rerun_cli(&path);
}

#[test]
fn an_episode_is_sent_in_whole_batches_of_steps() {
    // The reset frame rides with the first batch: 30 steps at 10 steps per batch are
    // three chunks per entity, not three and a one-frame remainder sent after the
    // last step (which costs a chunk per entity when the recording closes).
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("batches.rrd");
    let cfg = small_cfg(CriticKind::Iqn);
    let opts = PlayOptions {
        episodes: 1,
        max_steps: Some(30),
        flush_steps: 10,
        ..PlayOptions::default()
    };
    let (report, s) = record_play(&cfg, &opts, &path);
    assert_eq!(report.policy_steps, 30, "the robot fell: {report:?}");
    for p in ["world/robot/trunk", "plots/torques", "world/velocity"] {
        assert_eq!(
            s.entity(p).unwrap().temporal_chunk_rows,
            [11, 10, 10],
            "{p}"
        );
    }
}

#[test]
fn rough_terrain_is_logged_as_mesh_chunks_near_the_robot() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("rough.rrd");
    let cfg = rough_cfg();
    let opts = PlayOptions {
        episodes: 1,
        max_steps: Some(5),
        terrain_level: 2,
        ..PlayOptions::default()
    };
    let (_, s) = record_play(&cfg, &opts, &path);
    let chunks: Vec<&String> = s
        .entities
        .keys()
        .filter(|k| k.starts_with("/world/terrain/chunk_"))
        .collect();
    assert!(
        !chunks.is_empty(),
        "no terrain chunks: {:?}",
        s.entities.keys().collect::<Vec<_>>()
    );
    for c in &chunks {
        let e = &s.entities[*c];
        assert!(
            e.static_rows >= 1 && e.components.iter().any(|c| c.starts_with("Mesh3D")),
            "{c}: {e:?}"
        );
    }
    assert!(
        s.entity("world/ground").is_none(),
        "a rough scene has no flat quad"
    );
}

#[test]
fn scalar_critic_logs_the_value_without_a_distribution() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("scalar.rrd");
    let cfg = small_cfg(CriticKind::Scalar);
    let opts = PlayOptions {
        episodes: 1,
        max_steps: Some(5),
        ..PlayOptions::default()
    };
    let (report, s) = record_play(&cfg, &opts, &path);
    assert!(s.entity("value/quantiles").is_none());
    assert_eq!(
        s.entity("value/stats").unwrap().temporal_rows,
        (report.episodes[0].steps as u64 + 1).div_ceil(VALUE_EVERY_FRAMES as u64)
    );
}

#[test]
fn value_probe_matches_the_learner() {
    let cfg = small_cfg(CriticKind::Iqn);
    let l = learner(&cfg);
    let probe = ValueProbe::new(&l, 10);
    assert_eq!(probe.taus().len(), 10);
    assert_eq!(probe.label(), "CVaR_0.5");
    let obs: Vec<f32> = (0..OBS_DIM)
        .map(|i| ((i * 37 % 11) as f32 - 5.0) * 0.1)
        .collect();
    let r = probe.read(&l, &obs);
    let want_q = l.value_quantiles(&obs, probe.taus());
    assert_eq!(r.quantiles.len(), 10);
    for (a, b) in r.quantiles.iter().zip(&want_q) {
        assert!((a - b).abs() < 1e-5, "{a} vs {b}");
    }
    assert!((r.distorted - l.distorted_value(&obs)[0]).abs() < 1e-5);
    assert!((r.iqr - l.iqr(&obs)[0]).abs() < 1e-5);
    let mean = want_q.iter().sum::<f32>() / 10.0;
    assert!((r.mean - mean).abs() < 1e-5);
}

#[test]
fn training_recording_has_metrics_per_iteration_and_evaluation_episodes() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("train.rrd");
    let cfg = small_cfg(CriticKind::Iqn);
    let opts = TrainRecordingOptions {
        eval_every: 1,
        eval_steps: 10,
    };
    let mut recorder =
        TrainRecorder::open(&RerunTarget::Save(path.clone()), "test run", &cfg, opts)
            .expect("recorder");
    let stop = Arc::new(AtomicBool::new(false));
    let summary = rall::runner::train(cfg, &dir.path().join("run"), false, stop, &mut recorder)
        .expect("train");
    recorder.finish().expect("finish");
    assert_eq!(summary.iterations_done, 2);
    let s = viz::summarize_rrd(&path).expect("read back");
    assert!(s.application_ids.contains(viz::TRAIN_APP_ID));
    for p in [
        "train/loss/policy",
        "train/loss/value",
        "train/learning_rate",
        "train/std",
        "train/steps_per_s",
    ] {
        let e = s.entity(p).unwrap_or_else(|| panic!("no {p}"));
        assert_eq!(e.temporal_rows, 2, "{p}");
        assert!(e.timelines.contains("iteration"), "{p}: {:?}", e.timelines);
    }
    // Two evaluation episodes of 10 steps (11 frames each, unless the robot fell).
    let trunk = s.entity("world/robot/trunk").expect("trunk");
    assert!(
        trunk.temporal_rows > 2 && trunk.temporal_rows <= 22,
        "{}",
        trunk.temporal_rows
    );
    assert!(trunk.timelines.contains("iteration") && trunk.timelines.contains("sim_time"));
    assert_eq!(
        s.entity("value/quantiles").unwrap().temporal_rows,
        trunk.temporal_rows.div_ceil(VALUE_EVERY_FRAMES as u64)
    );
    assert!(s.blueprint_activations == 1);
    verify_with_rerun_cli(&path);
}

#[test]
fn blueprint_files_decode() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("play.rbl");
    viz::write_blueprint_file(&path, viz::PLAY_APP_ID, viz::play_blueprint()).expect("write");
    let s = viz::summarize_rrd(&path).expect("read back");
    assert!(s.blueprint_chunks > 0 && s.blueprint_activations == 1);
    assert!(s.application_ids.contains(viz::PLAY_APP_ID));
    assert!(s.entities.is_empty(), "a blueprint holds no recording data");
    // The 3D view's eye follows the robot (a view property in the same blueprint).
    assert!(
        s.blueprint_entities
            .iter()
            .any(|e| e.starts_with("/view/") && e.ends_with("/EyeControls3D")),
        "{:?}",
        s.blueprint_entities
    );
}

fn rall(dir: &Path) -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_rall"));
    c.current_dir(root())
        .env("RERUN_ANALYTICS", "0")
        .env("TMPDIR", dir);
    c
}

/// A config file holding only `[env]` (what `rall play --config` reads).
fn env_file(dir: &Path, name: &str, env: &rall::env::EnvConfig) -> PathBuf {
    let path = dir.join(name);
    let text = toml::to_string(&toml::Table::from_iter([(
        "env".to_string(),
        toml::Value::try_from(env).unwrap(),
    )]))
    .unwrap();
    std::fs::write(&path, text).unwrap();
    path
}

/// `rall play --checkpoint CKPT --config CONFIG --save OUT`.
fn play_saving(dir: &Path, ckpt: &Path, config: &Path, out: &Path) -> std::process::Output {
    rall(dir)
        .args(["play", "--checkpoint"])
        .arg(ckpt)
        .arg("--config")
        .arg(config)
        .arg("--save")
        .arg(out)
        .output()
        .unwrap()
}

#[test]
fn cli_play_saves_a_recording() {
    let dir = tempfile::tempdir().unwrap();
    let ckpt = checkpoint(dir.path(), &small_cfg(CriticKind::Iqn));
    let out_path = dir.path().join("out.rrd");
    let out = rall(dir.path())
        .args(["play", "--checkpoint"])
        .arg(&ckpt)
        .args(["--episodes", "1", "--steps-per-episode", "10", "--save"])
        .arg(&out_path)
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{stdout}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(stdout.contains("rerun "), "{stdout}");
    let s = viz::summarize_rrd(&out_path).unwrap();
    assert_eq!(s.entity("world/robot/trunk").unwrap().temporal_rows, 11);
}

#[test]
fn cli_play_takes_the_env_from_a_config_file() {
    let dir = tempfile::tempdir().unwrap();
    let ckpt = checkpoint(dir.path(), &small_cfg(CriticKind::Iqn));
    // A scenario: rough ground instead of the checkpoint's flat ground.
    let mut env = rough_cfg().env;
    env.episode.length_s = 0.2;
    let scenario = env_file(dir.path(), "scenario.toml", &env);
    let out_path = dir.path().join("scenario.rrd");
    let out = play_saving(dir.path(), &ckpt, &scenario, &out_path);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let s = viz::summarize_rrd(&out_path).unwrap();
    assert!(s
        .entities
        .keys()
        .any(|k| k.starts_with("/world/terrain/chunk_")));
    // 0.2 s = 10 steps: the scenario's episode length, not the checkpoint's 1 s.
    assert_eq!(s.entity("world/robot/trunk").unwrap().temporal_rows, 11);
}

#[test]
fn cli_play_whose_scene_cannot_be_built_leaves_no_recording() {
    let dir = tempfile::tempdir().unwrap();
    let ckpt = checkpoint(dir.path(), &small_cfg(CriticKind::Iqn));
    let mut env = small_cfg(CriticKind::Iqn).env;
    env.robot_mjcf = "mjcf/no-such-robot.xml".into();
    let scenario = env_file(dir.path(), "missing.toml", &env);
    let out_path = dir.path().join("missing.rrd");
    let out = play_saving(dir.path(), &ckpt, &scenario, &out_path);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(
        err.contains("no-such-robot.xml") && err.contains("nothing recorded"),
        "{err}"
    );
    assert!(!out_path.exists(), "a partial recording was left behind");
}

#[test]
fn cli_play_without_a_viewer_fails_fast_with_what_to_do() {
    let dir = tempfile::tempdir().unwrap();
    let ckpt = checkpoint(dir.path(), &small_cfg(CriticKind::Iqn));
    // --connect to a port where nothing listens.
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let t0 = std::time::Instant::now();
    let out = rall(dir.path())
        .args(["play", "--checkpoint"])
        .arg(&ckpt)
        .args(["--connect", &format!("127.0.0.1:{port}")])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(
        err.contains("nothing is listening") && err.contains("pip install rerun-sdk"),
        "{err}"
    );
    assert!(t0.elapsed().as_secs() < 20, "took {:?}", t0.elapsed());
    // --spawn with no `rerun` on PATH (unless a viewer already listens on 9876).
    if std::net::TcpStream::connect("127.0.0.1:9876").is_ok() {
        println!("skipped the --spawn check: something listens on 127.0.0.1:9876");
        return;
    }
    let empty = dir.path().join("empty-bin");
    std::fs::create_dir_all(&empty).unwrap();
    let out = rall(dir.path())
        .env("PATH", &empty)
        .args(["play", "--checkpoint"])
        .arg(&ckpt)
        .arg("--spawn")
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(
        err.contains("no `rerun` on PATH") && err.contains("pip install rerun-sdk==0.36"),
        "{err}"
    );
}

#[test]
fn cli_play_needs_exactly_one_destination() {
    let dir = tempfile::tempdir().unwrap();
    let out = rall(dir.path())
        .args(["play", "--checkpoint", "x.safetensors"])
        .output()
        .unwrap();
    assert!(!out.status.success());
    let out = rall(dir.path())
        .args([
            "play",
            "--checkpoint",
            "x.safetensors",
            "--spawn",
            "--save",
            "a.rrd",
        ])
        .output()
        .unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("cannot be used with"));
}

#[test]
fn a_named_scenario_plays_with_its_payload_and_ground() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("scenario.rrd");
    let cfg = small_cfg(CriticKind::Iqn);
    let opts = PlayOptions {
        episodes: 1,
        max_steps: Some(30),
        scenario: Some("moving_arm+rough+push".into()),
        ..PlayOptions::default()
    };
    let (report, s) = record_play(&cfg, &opts, &path);
    let frames = report.episodes[0].steps as u64 + 1;
    // the arm's links are bodies of the scene: one transform per frame each
    for link in ["z1_link02", "z1_link06"] {
        let e = s.entity(&format!("world/robot/{link}")).unwrap_or_else(|| {
            panic!(
                "no entity for {link}: {:?}",
                s.entities.keys().collect::<Vec<_>>()
            )
        });
        assert_eq!(e.temporal_rows, frames, "{link}");
    }
    // the scenario's heightfield is drawn as terrain chunks, not the flat quad
    assert!(s
        .entities
        .keys()
        .any(|k| k.starts_with("/world/terrain/chunk_")));
    assert!(s.entity("world/ground").is_none());
    let unknown = PlayOptions {
        scenario: Some("lava".into()),
        ..PlayOptions::default()
    };
    match viz::play(&learner(&cfg), &cfg.env, &unknown, None) {
        Ok(_) => panic!("an unknown scenario must be refused"),
        Err(e) => assert!(format!("{e:#}").contains("lava"), "{e:#}"),
    }
    verify_with_rerun_cli(&path);
}

#[test]
fn quantile_bars_tile_the_unit_interval() {
    let cfg = small_cfg(CriticKind::Iqn);
    let l = learner(&cfg);
    let probe = ValueProbe::new(&l, 32);
    let w = bar_widths(probe.taus());
    assert_eq!(w.len(), 32);
    // Each bar is 1/32 wide and centred on its tau: side by side over [0, 1], no overlap.
    for (tau, w) in probe.taus().iter().zip(&w) {
        assert!((w - 1.0 / 32.0).abs() < 1e-6, "{w}");
        assert!(tau - w / 2.0 >= -1e-6 && tau + w / 2.0 <= 1.0 + 1e-6);
    }
    assert!((w.iter().sum::<f32>() - 1.0).abs() < 1e-5);
    // The bars are Z_tau(s) minus their mean (rerun starts bars at 0): they sum to 0.
    let r = probe.read(&l, &vec![0.2; l.obs_dim()]);
    let bars = centred(&r.quantiles, r.mean);
    assert_eq!(bars.len(), 32);
    assert!(bars.iter().sum::<f32>().abs() < 1e-4, "{bars:?}");
}
