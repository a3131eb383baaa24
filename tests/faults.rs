//! Faults a user's training run meets, tried on the real binary: `kill -9` at
//! random moments (checkpoint writes included) 20 times in a row, SIGTERM from
//! a scheduler, and a run that goes numerically wrong. Every time the run must
//! resume, lose at most one save interval, and leave no unreadable checkpoint
//! or inconsistent metrics file on disk.

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use rall::config::TrainConfig;
use rall::learn::CriticKind;
use rall::runner::{load_policy, LATEST};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

mod common;
use common::tiny_config;

/// The tests' tiny run config (IQN, one thread) written to `dir/tiny.toml`.
fn tiny_config_file(dir: &Path, iterations: usize) -> PathBuf {
    let mut c = tiny_config(CriticKind::Iqn);
    c.runner.iterations = iterations;
    c.runner.log_interval = 1;
    c.runner.threads = 1;
    let path = dir.join("tiny.toml");
    std::fs::write(&path, c.to_toml()).unwrap();
    path
}

fn rall(args: &[&str]) -> Child {
    Command::new(env!("CARGO_BIN_EXE_rall"))
        .args(args)
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap()
}

/// Iterations in metrics.csv, checking every row is complete and wall time never goes back.
fn metric_iterations(run: &Path) -> Vec<usize> {
    let text = std::fs::read_to_string(run.join("metrics.csv")).unwrap_or_default();
    let mut lines = text.lines();
    let Some(header) = lines.next() else {
        return vec![];
    };
    let width = header.split(',').count();
    let mut out = Vec::new();
    let mut last_wall = 0.0f64;
    for (i, line) in lines.enumerate() {
        let fields: Vec<&str> = line.split(',').collect();
        // the last line may be cut by the kill (it is dropped on resume)
        if fields.len() != width {
            assert_eq!(
                i + 2,
                text.lines().count(),
                "a cut row that is not the last"
            );
            continue;
        }
        out.push(fields[0].parse().unwrap());
        let wall: f64 = fields[1].parse().unwrap();
        assert!(wall >= last_wall, "wall time went back: {line}");
        last_wall = wall;
    }
    out
}

/// Every checkpoint on disk loads (no corrupt file is ever left behind).
fn all_checkpoints_load(run: &Path) -> usize {
    let mut n = 0;
    let latest = run.join(LATEST);
    if latest.exists() {
        load_policy(&latest).unwrap_or_else(|e| panic!("{}: {e:#}", latest.display()));
        n += 1;
    }
    if let Ok(entries) = std::fs::read_dir(run.join("checkpoints")) {
        for e in entries.flatten() {
            let p = e.path();
            if p.extension().is_some_and(|x| x == "safetensors") {
                load_policy(&p).unwrap_or_else(|e| panic!("{}: {e:#}", p.display()));
                n += 1;
            }
        }
    }
    n
}

#[test]
fn kill_9_at_random_moments_never_corrupts_and_the_run_resumes() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = tiny_config_file(dir.path(), 100_000);
    let run = dir.path().join("run");
    let run_s = run.to_str().unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(9);
    let mut done_before = 0usize;
    for kill in 0..20 {
        let mut child = if kill == 0 {
            rall(&[
                "train",
                "--config",
                cfg.to_str().unwrap(),
                "--run-dir",
                run_s,
            ])
        } else {
            rall(&["train", "--resume", run_s])
        };
        // die at a random moment: start-up, mid-iteration or mid-save
        let start = Instant::now();
        let wait = Duration::from_millis(rng.gen_range(150..900));
        while start.elapsed() < wait {
            if let Ok(Some(status)) = child.try_wait() {
                let mut err = String::new();
                if let Some(mut e) = child.stderr.take() {
                    let _ = std::io::Read::read_to_string(&mut e, &mut err);
                }
                panic!("run {kill} exited early: {status:?}: {err}");
            }
            std::thread::sleep(Duration::from_millis(10));
        }
        child.kill().unwrap(); // SIGKILL
        child.wait().unwrap();

        let saved = all_checkpoints_load(&run);
        let its = metric_iterations(&run);
        if saved == 0 {
            continue; // killed before the first save: nothing to resume yet
        }
        let resumed_at = rall::runner::RunDir { root: run.clone() }
            .resume_point()
            .unwrap()
            .1
            .progress
            .iteration;
        // at most one save interval (1 iteration) of metrics is beyond the checkpoint
        let last = its.last().copied().unwrap_or(0);
        assert!(
            last <= resumed_at + 1,
            "kill {kill}: metrics at {last}, checkpoint at {resumed_at}"
        );
        assert!(
            resumed_at >= done_before,
            "kill {kill}: went back from {done_before} to {resumed_at}"
        );
        done_before = resumed_at;
    }
    // a last clean resume finishes a few more iterations with consistent metrics
    let target = (done_before + 2).to_string();
    let out = Command::new(env!("CARGO_BIN_EXE_rall"))
        .args(["train", "--resume", run_s, "--iterations", &target])
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let its = metric_iterations(&run);
    let want: Vec<usize> = (1..=done_before + 2).collect();
    assert_eq!(its, want, "one row per iteration, in order");
    all_checkpoints_load(&run);
    let leftovers: Vec<_> = std::fs::read_dir(run.join("checkpoints"))
        .unwrap()
        .flatten()
        .filter(|e| e.path().extension().is_some_and(|x| x == "tmp"))
        .collect();
    assert!(leftovers.is_empty(), "temp files left: {leftovers:?}");
    assert!(
        done_before >= 3,
        "the 20 runs made progress ({done_before} iterations)"
    );
}

#[test]
fn sigterm_writes_a_checkpoint_and_exits_cleanly() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = tiny_config_file(dir.path(), 100_000);
    let run = dir.path().join("run");
    let child = rall(&[
        "train",
        "--config",
        cfg.to_str().unwrap(),
        "--run-dir",
        run.to_str().unwrap(),
        "--save-interval",
        "100000",
    ]);
    // wait for the first metrics row, then terminate as a scheduler would
    let start = Instant::now();
    while metric_iterations(&run).is_empty() {
        assert!(
            start.elapsed() < Duration::from_secs(60),
            "no iteration within 60 s"
        );
        std::thread::sleep(Duration::from_millis(20));
    }
    let status = Command::new("kill")
        .args(["-TERM", &child.id().to_string()])
        .status()
        .unwrap();
    assert!(status.success());
    let out = child.wait_with_output().unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "exit {:?}: {stderr}", out.status);
    let p = load_policy(&run.join(LATEST)).unwrap();
    assert!(p.progress.iteration >= 1);
    assert_eq!(
        metric_iterations(&run).last().copied(),
        Some(p.progress.iteration)
    );
}

#[test]
fn a_run_that_goes_numerically_wrong_stops_with_an_error() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = tiny_config_file(dir.path(), 5);
    // rewards scaled to overflow: the losses become non-finite at once
    let text = std::fs::read_to_string(&cfg).unwrap();
    let mut c = TrainConfig::from_toml_str(&text).unwrap();
    c.env.reward.lin_vel_tracking = 3e38;
    c.env.reward.feet_air_time = 3e38;
    std::fs::write(&cfg, c.to_toml()).unwrap();
    let run = dir.path().join("run");
    let out = Command::new(env!("CARGO_BIN_EXE_rall"))
        .args(["train", "--config", cfg.to_str().unwrap(), "--run-dir"])
        .arg(&run)
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "a diverged run must fail: {stderr}");
    assert!(stderr.contains("diverged"), "{stderr}");
    // nothing non-finite was saved
    all_checkpoints_load(&run);
    if run.join(LATEST).exists() {
        let p = load_policy(&run.join(LATEST)).unwrap();
        for t in p.learner.state() {
            assert!(t.data.iter().all(|v| v.is_finite()), "{} holds NaN", t.name);
        }
    }
}
