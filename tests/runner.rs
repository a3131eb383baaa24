//! The runner: configs, checkpoints, resume, tracking evaluation.

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;
use std::sync::Arc;

use rall::config::TrainConfig;
use rall::env::terrain::TerrainKind;
use rall::env::OBS_DIM;
use rall::eval::{evaluate_tracking, tracking_env, ActionMode};
use rall::learn::{load_checkpoint, save_checkpoint, CriticKind};
use rall::runner::{load_policy, train, LATEST};

mod common;
use common::tiny_config;

fn no_stop() -> Arc<AtomicBool> {
    Arc::new(AtomicBool::new(false))
}

/// A 2-iteration run in a temp dir: (the dir guard, the run directory).
fn trained_run(critic: CriticKind) -> (tempfile::TempDir, PathBuf) {
    let dir = tempfile::tempdir().unwrap();
    let run = dir.path().join("run");
    train(tiny_config(critic), &run, false, no_stop(), &mut ()).unwrap();
    (dir, run)
}

/// A scalar-critic run of `iterations`, a checkpoint every `save_interval`.
fn scalar_run(iterations: usize, save_interval: usize) -> (tempfile::TempDir, PathBuf) {
    let dir = tempfile::tempdir().unwrap();
    let run = dir.path().join("run");
    let mut cfg = tiny_config(CriticKind::Scalar);
    cfg.runner.iterations = iterations;
    cfg.runner.save_interval = save_interval;
    train(cfg, &run, false, no_stop(), &mut ()).unwrap();
    (dir, run)
}

fn metric_rows(dir: &Path) -> Vec<Vec<String>> {
    let text = std::fs::read_to_string(dir.join("metrics.csv")).unwrap();
    text.lines()
        .skip(1)
        .map(|l| l.split(',').map(String::from).collect())
        .collect()
}

#[test]
fn training_writes_metrics_and_checkpoints_and_resume_continues() {
    for critic in [CriticKind::Iqn, CriticKind::Scalar] {
        let dir = tempfile::tempdir().unwrap();
        let run = dir.path().join("run");
        let s = train(tiny_config(critic), &run, false, no_stop(), &mut ()).unwrap();
        assert_eq!(s.iterations_done, 2);
        assert!(
            run.join(LATEST).exists() && run.join("checkpoints/model_000002.safetensors").exists()
        );
        let rows = metric_rows(&run);
        assert_eq!(rows.len(), 2);
        assert_eq!(rows[1][0], "2");
        assert_eq!(rows[1][2], (2 * 8 * 8).to_string(), "total env steps");

        let before = load_policy(&run.join(LATEST)).unwrap();
        assert_eq!(before.progress.iteration, 2);
        let lr_before = before.learner.learning_rate();

        // resume to iteration 3: continues at 3, with the stored lr as its start
        let mut more = tiny_config(critic);
        more.runner.iterations = 3;
        let s = train(more, &run, true, no_stop(), &mut ()).unwrap();
        assert_eq!(s.iterations_done, 3);
        let rows = metric_rows(&run);
        assert_eq!(rows.len(), 3, "metrics appended, not overwritten");
        assert_eq!(rows[2][0], "3");
        assert_eq!(rows[2][2], (3 * 8 * 8).to_string());
        let after = load_policy(&run.join(LATEST)).unwrap();
        assert_eq!(after.progress.iteration, 3);
        assert!(
            after.progress.rng_word_pos > before.progress.rng_word_pos,
            "action RNG continued"
        );
        assert!(lr_before > 0.0 && after.learner.learning_rate() > 0.0);
    }
}

#[test]
fn a_saved_policy_loads_with_identical_outputs() {
    let (_dir, run) = trained_run(CriticKind::Iqn);
    let a = load_policy(&run.join(LATEST)).unwrap();
    let b = load_policy(&run.join("checkpoints/model_000002.safetensors")).unwrap();
    let obs: Vec<f32> = (0..4 * OBS_DIM)
        .map(|i| ((i * 37) % 17) as f32 / 17.0 - 0.5)
        .collect();
    assert_eq!(a.learner.act_mean(&obs), b.learner.act_mean(&obs));
    assert_eq!(
        a.learner.value_quantiles(&obs, &[0.1, 0.5, 0.9]),
        b.learner.value_quantiles(&obs, &[0.1, 0.5, 0.9])
    );
    assert_eq!(a.config, b.config);
}

#[test]
fn mismatched_or_corrupt_checkpoints_are_refused_with_the_cause() {
    let (dir, run) = trained_run(CriticKind::Iqn);
    let good = run.join(LATEST);
    let (tensors, meta) = load_checkpoint(&good).unwrap();

    let rewrite = |name: &str, edit: &dyn Fn(&mut HashMap<String, String>)| {
        let mut m = meta.clone();
        edit(&mut m);
        let p = dir.path().join(name);
        save_checkpoint(&p, &tensors, &m).unwrap();
        load_policy(&p)
            .err()
            .map(|e| format!("{e:#}"))
            .expect("refused")
    };
    let e = rewrite("layout.safetensors", &|m| {
        m.insert(
            "obs_layout".into(),
            "base_lin_vel_body:3,height_scan:187".into(),
        );
    });
    assert!(e.contains("observation layout mismatch"), "{e}");
    let e = rewrite("version.safetensors", &|m| {
        m.insert("format_version".into(), "99".into());
    });
    assert!(e.contains("format 99"), "{e}");
    // the config says 64-wide networks but the tensors are 32-wide
    let e = rewrite("shapes.safetensors", &|m| {
        let cfg = m["config_toml"].replace(
            "actor_hidden = [\n    32,\n    32,\n]",
            "actor_hidden = [\n    64,\n    32,\n]",
        );
        assert_ne!(cfg, m["config_toml"], "test edits the config");
        m.insert("config_toml".into(), cfg);
    });
    assert!(e.contains("shape"), "{e}");

    let bytes = std::fs::read(&good).unwrap();
    let truncated = dir.path().join("truncated.safetensors");
    std::fs::write(&truncated, &bytes[..bytes.len() / 2]).unwrap();
    let e = format!("{:#}", load_policy(&truncated).err().unwrap());
    assert!(e.contains("truncated.safetensors"), "{e}");
    let e = format!(
        "{:#}",
        load_policy(&dir.path().join("missing.safetensors"))
            .err()
            .unwrap()
    );
    assert!(e.contains("missing.safetensors"), "{e}");
}

#[test]
fn configs_in_the_repo_parse_and_bad_values_name_their_key() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("configs");
    let mut n = 0;
    for entry in std::fs::read_dir(&dir).unwrap() {
        let p = entry.unwrap().path();
        if p.extension().is_some_and(|e| e == "toml") {
            TrainConfig::from_toml_file(&p).unwrap_or_else(|e| panic!("{}: {e:#}", p.display()));
            n += 1;
        }
    }
    assert!(
        n >= 11,
        "expected every method in terrain and flat variants, found {n} configs"
    );
    let err = |text: &str| format!("{:#}", TrainConfig::from_toml_str(text).unwrap_err());
    let e = err("[env.risk]\nprobability = -0.1\n");
    assert!(e.contains("risk.probability"), "{e}");
    let e = err("[env.terrain]\nkind = \"lava\"\n");
    assert!(e.contains("lava") && e.contains("kind"), "{e}");
    let e = err("[env.control]\ntorque_limits_nm = [44.0, 55.0]\n");
    assert!(e.contains("torque_limits_nm"), "{e}");
    let e = err("[env.reward]\nlin_vel_trackin = 5.0\n");
    assert!(e.contains("lin_vel_trackin"), "{e}");
    let e = err("[learner]\ncvar_etta = 0.5\n");
    assert!(e.contains("cvar_etta"), "{e}");
    let e = err("[learner.ppo]\nclip = 0.2\n");
    assert!(e.contains("clip"), "{e}");
    let e = err("[learner]\ncvar_eta = 1.5\n");
    assert!(e.contains("eta"), "{e}");
    let e = err("[runner]\nnum_envs = 0\n");
    assert!(e.contains("num_envs"), "{e}");
    let e = err("[env.commands]\nvx_mps = [1.0, -1.0]\n");
    assert!(e.contains("commands.vx_mps"), "{e}");
    // contradictory pairs are refused naming both keys
    let e = err("[learner]\ncvar_eta = 0.5\ndistortion = { kind = \"wang\", lambda = -0.75 }\n");
    assert!(e.contains("cvar_eta") && e.contains("distortion"), "{e}");
    let e = err("[learner]\ncritic = \"scalar\"\ncvar_eta = 0.5\n");
    assert!(e.contains("scalar") && e.contains("cvar_eta"), "{e}");
    let e = err("[learner]\ncritic = \"scalar\"\ndistortion = { kind = \"cvar\", eta = 0.5 }\n");
    assert!(e.contains("scalar") && e.contains("distortion"), "{e}");
}

#[test]
fn the_risk_setting_is_the_one_the_actor_follows() {
    use rall::learn::Distortion;
    let cfg = |text: &str| TrainConfig::from_toml_str(text).unwrap().learner;
    assert_eq!(cfg("").distortion(), Distortion::Cvar { eta: 0.5 });
    assert_eq!(
        cfg("[learner]\ncvar_eta = 1.0\n").distortion(),
        Distortion::Cvar { eta: 1.0 }
    );
    let wang = cfg("[learner]\ndistortion = { kind = \"wang\", lambda = -0.75 }\n");
    assert_eq!(wang.distortion(), Distortion::Wang { lambda: -0.75 });
    assert_eq!(wang.risk_label(), "wang-0.75");
    let scalar = cfg("[learner]\ncritic = \"scalar\"\n");
    assert_eq!(scalar.distortion(), Distortion::Cvar { eta: 1.0 });
    assert_eq!(scalar.risk_label(), "scalar");
}

#[test]
fn tracking_evaluation_of_an_untrained_policy_gives_bounded_scores() {
    let (_dir, run) = trained_run(CriticKind::Scalar);
    let p = load_policy(&run.join(LATEST)).unwrap();
    let env = tracking_env(&p.config.env);
    let r = evaluate_tracking(&p.learner, &env, 4, 2, 1, ActionMode::Mean).unwrap();
    assert_eq!(r.episodes, 4);
    assert!((0.0..=1.0).contains(&r.lin_vel_score) && (0.0..=1.0).contains(&r.yaw_rate_score));
    assert!((0.0..=1.0).contains(&r.fall_rate));
    assert!(r.mean_episode_length_steps > 0.0 && r.mean_episode_length_steps <= 25.0);
}

/// Every fall of a tracking evaluation has a record of how it happened: with a
/// tilt limit of 0.02 rad robots "fall" within a few steps; each record carries
/// the last attitude (still within that limit), its command and a full CSV row.
#[test]
fn tracking_evaluation_records_how_each_robot_fell() {
    use rall::eval::{evaluate_tracking_with_falls, FallRecord};
    let (_dir, run) = trained_run(CriticKind::Scalar);
    let p = load_policy(&run.join(LATEST)).unwrap();
    let mut env = tracking_env(&p.config.env);
    env.episode.max_tilt_rad = 0.02;
    let (r, falls) =
        evaluate_tracking_with_falls(&p.learner, &env, 6, 2, 3, ActionMode::Mean).unwrap();
    let fell = (r.fall_rate * r.episodes as f64).round() as usize;
    assert!(fell > 0, "{r:?}");
    assert_eq!(falls.len(), fell, "one record per fall");
    let columns = FallRecord::CSV_HEADER.split(',').count();
    for f in &falls {
        assert!(f.env_index < 6 && f.steps >= 1, "{f:?}");
        // the last step before the end was still within the tilt limit
        assert!(
            f.roll_rad.abs() <= 0.02 && f.pitch_rad.abs() <= 0.02,
            "{f:?}"
        );
        assert!(f.steps_at_torque_limit <= f.steps.min(25), "{f:?}");
        assert!(f.command.iter().all(|c| c.is_finite()));
        assert_eq!(f.csv_row().split(',').count(), columns, "{}", f.csv_row());
    }
    // the same evaluation without the records gives the same report
    assert_eq!(
        evaluate_tracking(&p.learner, &env, 6, 2, 3, ActionMode::Mean).unwrap(),
        r
    );
    // commands resampled every 5 steps: a robot that falls later than that fell on a
    // command it had followed for at most 5 steps, with the one before it recorded
    env.commands.resample_interval_s = 0.1;
    env.episode.max_tilt_rad = 0.05;
    let (_, falls) =
        evaluate_tracking_with_falls(&p.learner, &env, 12, 2, 5, ActionMode::Mean).unwrap();
    assert!(falls.iter().any(|f| f.steps > 5), "{falls:?}");
    for f in &falls {
        assert!(f.steps_since_command_change <= f.steps, "{f:?}");
        if f.steps > 5 {
            assert!(f.previous_command.is_some(), "{f:?}");
            assert!((1..=5).contains(&f.steps_since_command_change), "{f:?}");
        } else {
            assert_eq!(
                (f.previous_command, f.steps_since_command_change),
                (None, f.steps)
            );
        }
        assert_eq!(f.csv_row().split(',').count(), columns, "{}", f.csv_row());
    }
}

#[test]
fn fall_directions_follow_the_larger_tilt() {
    use rall::env::EpisodeEnd;
    use rall::eval::FallRecord;
    let fall = |roll_rad: f64, pitch_rad: f64| FallRecord {
        env_index: 0,
        steps: 10,
        end: EpisodeEnd::Tilt,
        command: [0.5, 0.0, 0.0],
        roll_rad,
        pitch_rad,
        base_lin_vel_body_mps: [0.0; 3],
        foot_contact: [true, true, false, false],
        steps_at_torque_limit: 3,
        steps_since_command_change: 10,
        previous_command: None,
        draw: rall::env::EpisodeDraw {
            friction: Some(0.8),
            added_base_mass_kg: 1.0,
            motor_strength: [0.95; 12],
            kp_factor: 1.05,
            ..Default::default()
        },
    };
    assert_eq!(fall(0.1, 0.7).direction(), "nose down");
    assert_eq!(fall(0.1, -0.7).direction(), "nose up");
    assert_eq!(fall(1.1, 0.3).direction(), "right side down");
    assert_eq!(fall(-1.1, 0.3).direction(), "left side down");
    assert!(fall(0.1, 0.7)
        .csv_row()
        .starts_with("0,10,Tilt,nose down,0.500,"));
    // the draws close the row, in the header's order
    assert!(fall(0.1, 0.7)
        .csv_row()
        .ends_with(",0.800,1.000,0.950,0.950,1.050,1.000,0.0000,0.0000,0.0000"));
}

/// A run killed after its checkpoint at iteration 2 but before the next (the
/// metrics already hold iteration 3 and half a row, `latest` is broken, a temp
/// file is left): the resume starts from the newest readable checkpoint, cuts
/// the metrics back to it, and removes the temp file.
#[test]
fn resume_after_a_crash_continues_from_the_newest_readable_checkpoint() {
    let (_dir, run) = scalar_run(3, tiny_config(CriticKind::Scalar).runner.save_interval);
    // simulate the crash: checkpoint 3 and latest lost, a cut row, a temp file
    std::fs::remove_file(run.join("checkpoints/model_000003.safetensors")).unwrap();
    std::fs::write(run.join(LATEST), b"garbage").unwrap();
    std::fs::write(
        run.join("checkpoints/model_000004.safetensors.tmp"),
        b"half",
    )
    .unwrap();
    let mut csv = std::fs::read_to_string(run.join("metrics.csv")).unwrap();
    csv.push_str("4,1.0,2");
    std::fs::write(run.join("metrics.csv"), csv).unwrap();

    let mut more = tiny_config(CriticKind::Scalar);
    more.runner.iterations = 4;
    let s = train(more, &run, true, no_stop(), &mut ()).unwrap();
    assert_eq!(s.iterations_done, 4);
    let rows = metric_rows(&run);
    let iterations: Vec<&str> = rows.iter().map(|r| r[0].as_str()).collect();
    assert_eq!(iterations, ["1", "2", "3", "4"], "one row per iteration");
    let width = rows[0].len();
    assert!(rows.iter().all(|r| r.len() == width), "no glued rows");
    let wall: Vec<f64> = rows.iter().map(|r| r[1].parse().unwrap()).collect();
    assert!(
        wall.windows(2).all(|w| w[1] >= w[0]),
        "wall time never goes back: {wall:?}"
    );
    assert!(!run
        .join("checkpoints/model_000004.safetensors.tmp")
        .exists());
    assert_eq!(
        load_policy(&run.join(LATEST)).unwrap().progress.iteration,
        4
    );
}

/// Rough-ground checkpoints carry the curriculum; resuming keeps it going.
/// A run killed after its first metrics row but before its first checkpoint
/// has nothing to resume from: `--resume` starts it again from its
/// config.toml (and a run with neither is refused with the reason).
#[test]
fn resume_of_a_run_stopped_before_its_first_checkpoint_starts_it_again() {
    let dir = tempfile::tempdir().unwrap();
    let run = dir.path().join("run");
    let mut cfg = tiny_config(CriticKind::Scalar);
    cfg.runner.iterations = 2;
    train(cfg.clone(), &run, false, no_stop(), &mut ()).unwrap();
    std::fs::remove_file(run.join(LATEST)).unwrap();
    std::fs::remove_dir_all(run.join("checkpoints")).unwrap();
    // resuming passes a config with other runner settings only
    let mut more = TrainConfig::default();
    more.runner.iterations = 3;
    let s = train(more, &run, true, no_stop(), &mut ()).unwrap();
    assert_eq!(s.iterations_done, 3);
    let its: Vec<String> = metric_rows(&run)
        .into_iter()
        .map(|r| r[0].clone())
        .collect();
    assert_eq!(its, ["1", "2", "3"], "old rows replaced");
    let stored = load_policy(&run.join(LATEST)).unwrap().config;
    assert_eq!(
        stored.runner.num_envs, cfg.runner.num_envs,
        "its own config"
    );

    let empty = dir.path().join("empty");
    std::fs::create_dir_all(&empty).unwrap();
    let e = train(TrainConfig::default(), &empty, true, no_stop(), &mut ())
        .err()
        .unwrap();
    assert!(format!("{e:#}").contains("no readable checkpoint"), "{e:#}");
}

/// `rall eval falls`: every logged state is either before a fall or elsewhere,
/// and no more states precede falls than `window` per fall.
#[test]
fn the_states_before_falls_are_counted_once_each() {
    let (_dir, run) = trained_run(CriticKind::Iqn);
    let p = load_policy(&run.join(LATEST)).unwrap();
    // a robot that barely tilts "falls": falls happen within the test
    let mut cfg = p.config.clone();
    cfg.env.episode.max_tilt_rad = 0.02;
    cfg.env.episode.length_s = 5.0;
    let (robots, steps, window) = (6, 80, 5);
    let r = rall::eval::critic_before_falls(&p.learner, &cfg, None, (robots, steps, window), 2, 3)
        .unwrap();
    assert_eq!(r.before_fall.states + r.elsewhere.states, robots * steps);
    assert!(r.falls > 0, "{r:?}");
    assert!(r.before_fall.states > 0 && r.before_fall.states <= r.falls * window);
    assert!(r.elsewhere.iqr.is_finite() && r.before_fall.iqr.is_finite());
}

#[test]
fn rough_checkpoints_store_every_envs_terrain_level() {
    let dir = tempfile::tempdir().unwrap();
    let run = dir.path().join("run");
    let mut cfg = tiny_config(CriticKind::Scalar);
    cfg.env.terrain.kind = TerrainKind::Rough;
    train(cfg.clone(), &run, false, no_stop(), &mut ()).unwrap();
    let p = load_policy(&run.join(LATEST)).unwrap();
    let levels = p.progress.terrain_levels.expect("levels stored");
    assert_eq!(levels.len(), 8);
    cfg.runner.iterations = 3;
    train(cfg, &run, true, no_stop(), &mut ()).unwrap();
    let after = load_policy(&run.join(LATEST)).unwrap().progress;
    assert_eq!(after.iteration, 3);
    let moved = after
        .terrain_levels
        .unwrap()
        .iter()
        .zip(&levels)
        .all(|(a, b)| a.abs_diff(*b) <= 1);
    assert!(moved, "one iteration moves each level by at most one");
    // flat runs store none
    let (_d, flat) = trained_run(CriticKind::Scalar);
    assert!(load_policy(&flat.join(LATEST))
        .unwrap()
        .progress
        .terrain_levels
        .is_none());
}

#[test]
fn an_action_std_reset_applies_once_and_a_resumed_run_adds_it_identically() {
    let dir = tempfile::tempdir().unwrap();
    let with_reset = |iterations: usize| {
        let mut c = tiny_config(CriticKind::Iqn);
        c.runner.iterations = iterations;
        c.runner.action_std_reset = Some(rall::config::ActionStdReset {
            after_iteration: 2,
            action_std: 0.3,
        });
        c
    };
    let std_at = |run: &Path, it: usize| -> Vec<f32> {
        let p = run.join(format!("checkpoints/model_{it:06}.safetensors"));
        let l = load_policy(&p).unwrap().learner;
        l.actor_critic()
            .actor
            .log_std()
            .iter()
            .map(|l| l.exp())
            .collect()
    };
    // configured from the start (resumed at 2, as a resume rebuilds the envs):
    // iterations 1-2 at the initial std, 3-4 from 0.3
    let whole = dir.path().join("whole");
    train(with_reset(2), &whole, false, no_stop(), &mut ()).unwrap();
    train(with_reset(4), &whole, true, no_stop(), &mut ()).unwrap();
    assert!(std_at(&whole, 2).iter().all(|s| (s - 1.0).abs() < 0.05));
    for it in [3, 4] {
        let s = std_at(&whole, it);
        assert!(
            s.iter().all(|s| (s - 0.3).abs() < 0.03),
            "iteration {it}: {s:?}"
        );
    }
    // a run started without the stage gets it on resume at iteration 2: the same weights
    let added = dir.path().join("added");
    train(
        tiny_config(CriticKind::Iqn),
        &added,
        false,
        no_stop(),
        &mut (),
    )
    .unwrap();
    train(with_reset(4), &added, true, no_stop(), &mut ()).unwrap();
    let weights = |run: &Path| load_checkpoint(&run.join(LATEST)).unwrap().0;
    let (a, b) = (weights(&whole), weights(&added));
    assert_eq!(a.len(), b.len());
    for (x, y) in a.iter().zip(&b) {
        assert_eq!((&x.name, &x.data), (&y.name, &y.data));
    }
    let stored = load_policy(&added.join(LATEST)).unwrap().config;
    assert_eq!(
        stored.runner.action_std_reset,
        with_reset(4).runner.action_std_reset
    );
    // ... but not to a run already past it
    let past = dir.path().join("past");
    let mut three = tiny_config(CriticKind::Iqn);
    three.runner.iterations = 3;
    train(three, &past, false, no_stop(), &mut ()).unwrap();
    let err = train(with_reset(4), &past, true, no_stop(), &mut ()).unwrap_err();
    assert!(
        format!("{err:#}").contains("before the checkpoint's iteration 3"),
        "{err:#}"
    );
}

/// `rall eval tracking --run-dir`: one line and one CSV row per numbered
/// checkpoint, oldest first, each figure inside its interval; the row of a
/// checkpoint equals `--checkpoint` on that file.
#[test]
fn tracking_curve_over_a_runs_checkpoints() {
    let (dir, run) = scalar_run(4, 1);
    let rall = |args: &[&str]| {
        let out = std::process::Command::new(env!("CARGO_BIN_EXE_rall"))
            .args(["eval", "tracking", "--episodes", "3", "--threads", "1"])
            .args(args)
            .output()
            .unwrap();
        let text = String::from_utf8_lossy(&out.stdout).to_string()
            + &String::from_utf8_lossy(&out.stderr);
        (out.status.success(), text)
    };
    let csv = dir.path().join("curve.csv");
    let run_s = run.to_str().unwrap();
    let (ok, log) = rall(&[
        "--run-dir",
        run_s,
        "--every",
        "2",
        "--curve-csv",
        csv.to_str().unwrap(),
    ]);
    assert!(ok, "{log}");
    let text = std::fs::read_to_string(&csv).unwrap();
    let rows: Vec<Vec<f64>> = text
        .lines()
        .skip(1)
        .map(|l| l.split(',').map(|x| x.parse().unwrap()).collect())
        .collect();
    assert_eq!(
        rows.iter().map(|r| r[0]).collect::<Vec<_>>(),
        [2.0, 4.0],
        "{text}"
    );
    for r in &rows {
        for k in [3, 6, 9] {
            assert!(r[k + 1] <= r[k] && r[k] <= r[k + 2], "{r:?}");
        }
    }
    let (ok, one) = rall(&[
        "--checkpoint",
        run.join("checkpoints/model_000004.safetensors")
            .to_str()
            .unwrap(),
    ]);
    assert!(ok, "{one}");
    // the CSV keeps 4 decimals and the log 3, both rounded from the same score:
    // within half a unit of each's last digit (re-rounding the CSV's value to 3
    // decimals would round twice)
    let printed: f64 = one
        .lines()
        .find_map(|l| l.strip_prefix("lin-vel tracking"))
        .and_then(|l| l.split_whitespace().next())
        .and_then(|x| x.parse().ok())
        .unwrap_or_else(|| panic!("no lin-vel tracking line: {one}"));
    assert!(
        (printed - rows[1][3]).abs() <= 0.0005 + 0.00005 + 1e-9,
        "{}: {one}",
        rows[1][3]
    );
    // bad input: a directory without checkpoints, and both sources at once
    let (ok, log) = rall(&["--run-dir", dir.path().to_str().unwrap()]);
    assert!(!ok && log.contains("has no checkpoints"), "{log}");
    let (ok, _) = rall(&["--run-dir", run_s, "--checkpoint", "x.safetensors"]);
    assert!(!ok);
}
