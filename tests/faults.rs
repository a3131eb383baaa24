//! Faults a user's training run meets, tried on the real binary: `kill -9` at
//! random moments (checkpoint writes included) 20 times in a row, SIGTERM from
//! a scheduler, a run that goes numerically wrong, a corrupted checkpoint, an
//! empty config, NaN/inf settings, more envs than memory, a shared run folder
//! with other programs' temp files, run names that leave `runs/`, and a run
//! stopped and resumed that must equal the uninterrupted one. Every time the run
//! must resume, lose at most one save interval, and leave no unreadable
//! checkpoint or inconsistent metrics file on disk.

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

/// `rall train --config cfg --run-dir run` with fault-injection variable `var` set to
/// `value`: its output and its stderr as text.
fn train_with_fault(
    cfg: &Path,
    run: &Path,
    var: &str,
    value: &str,
) -> (std::process::Output, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_rall"))
        .args(["train", "--config", cfg.to_str().unwrap(), "--run-dir"])
        .arg(run)
        .env(var, value)
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr).into_owned();
    (out, stderr)
}

#[test]
fn a_run_that_goes_numerically_wrong_stops_with_an_error() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = tiny_config_file(dir.path(), 5);
    // before any checkpoint: the error says none was written (no file named)
    let run = dir.path().join("early");
    let (out, stderr) = train_with_fault(&cfg, &run, "RALL_FAULT_NAN", "1");
    assert!(!out.status.success(), "a diverged run must fail: {stderr}");
    assert!(stderr.contains("diverged"), "{stderr}");
    assert!(stderr.contains("no checkpoint was written"), "{stderr}");
    assert!(!run.join(LATEST).exists());
    // later: it names the last good checkpoint, and nothing non-finite is saved
    let run = dir.path().join("run");
    let (out, stderr) = train_with_fault(&cfg, &run, "RALL_FAULT_NAN", "3");
    assert!(!out.status.success(), "a diverged run must fail: {stderr}");
    assert!(stderr.contains("model_000002.safetensors"), "{stderr}");
    all_checkpoints_load(&run);
    let p = load_policy(&run.join(LATEST)).unwrap();
    assert_eq!(p.progress.iteration, 2);
    for t in p.learner.state() {
        assert!(t.data.iter().all(|v| v.is_finite()), "{} holds NaN", t.name);
    }
}

fn rall_output(args: &[&str]) -> (bool, Option<i32>, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_rall"))
        .args(args)
        .output()
        .unwrap();
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    (out.status.success(), out.status.code(), text)
}

/// Offset in the file of tensor `name`'s first data byte.
fn tensor_offset(bytes: &[u8], name: &str) -> usize {
    let n = u64::from_le_bytes(bytes[..8].try_into().unwrap()) as usize;
    let header: serde_json::Value = serde_json::from_slice(&bytes[8..8 + n]).unwrap();
    8 + n + header[name]["data_offsets"][0].as_u64().unwrap() as usize
}

#[test]
fn a_corrupt_checkpoint_is_refused_by_name_and_resume_falls_back_once() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = tiny_config_file(dir.path(), 2);
    let run = dir.path().join("run");
    let (ok, _, log) = rall_output(&[
        "train",
        "--config",
        cfg.to_str().unwrap(),
        "--run-dir",
        run.to_str().unwrap(),
    ]);
    assert!(ok, "{log}");
    // the exponent byte of the first weight of actor.l0.weight
    let latest = run.join(LATEST);
    let mut bytes = std::fs::read(&latest).unwrap();
    let at = tensor_offset(&bytes, "actor.l0.weight") + 3;
    bytes[at] ^= 0x40;
    std::fs::write(&latest, &bytes).unwrap();
    let e = format!(
        "{:#}",
        load_policy(&latest)
            .err()
            .expect("a corrupt file is refused")
    );
    assert!(
        e.contains("actor.l0.weight") && e.contains("corrupt"),
        "{e}"
    );
    // a truncated numbered checkpoint too: resume passes both, once each
    let second = run.join("checkpoints/model_000002.safetensors");
    let len = std::fs::metadata(&second).unwrap().len();
    std::fs::OpenOptions::new()
        .write(true)
        .open(&second)
        .unwrap()
        .set_len(len / 2)
        .unwrap();
    let (ok, _, log) = rall_output(&[
        "train",
        "--resume",
        run.to_str().unwrap(),
        "--iterations",
        "3",
    ]);
    assert!(ok, "{log}");
    assert_eq!(log.matches("is unusable").count(), 1, "{log}");
    assert!(log.contains("model_000001.safetensors"), "{log}");
    assert!(
        run.join("checkpoints/model_000002.safetensors.corrupt")
            .exists(),
        "the truncated checkpoint is moved aside: {log}"
    );
    assert_eq!(load_policy(&latest).unwrap().progress.iteration, 3);
}

#[test]
fn an_empty_config_is_refused_naming_the_file() {
    let dir = tempfile::tempdir().unwrap();
    let empty = dir.path().join("empty.toml");
    std::fs::write(&empty, "# nothing here\n").unwrap();
    let run = dir.path().join("run");
    let (ok, _, log) = rall_output(&[
        "train",
        "--config",
        empty.to_str().unwrap(),
        "--run-dir",
        run.to_str().unwrap(),
    ]);
    assert!(!ok);
    assert!(
        log.contains("empty.toml") && log.contains("no sections"),
        "{log}"
    );
    assert!(!run.join("metrics.csv").exists());
}

/// `toml` with `line` (`key = value`) set in `table`: the key's line replaced,
/// or added under the table header.
fn set_key(toml: &str, table: &str, line: &str) -> String {
    let key = format!("{} =", line.split(" =").next().unwrap());
    let mut out = Vec::new();
    let (mut inside, mut done) = (false, false);
    for l in toml.lines() {
        if l.starts_with('[') {
            if inside && !done {
                out.push(line.to_string());
                done = true;
            }
            inside = l == table;
        }
        if inside && l.starts_with(&key) {
            out.push(line.to_string());
            done = true;
        } else {
            out.push(l.to_string());
        }
    }
    if inside && !done {
        out.push(line.to_string());
        done = true;
    }
    assert!(done, "{table} is in the tiny config");
    out.join("\n") + "\n"
}

#[test]
fn nan_and_infinite_settings_are_refused_naming_the_key() {
    let dir = tempfile::tempdir().unwrap();
    let base = TrainConfig::from_toml_str(
        &std::fs::read_to_string(tiny_config_file(dir.path(), 2)).unwrap(),
    )
    .unwrap()
    .to_toml();
    let mut wide = TrainConfig::from_toml_str(&base).unwrap();
    wide.learner.actor_hidden = vec![100_000];
    let e = format!("{:#}", wide.validate().unwrap_err());
    assert!(e.contains("learner.actor_hidden[0]"), "{e}");
    let cases = [
        ("[env.observation]", "clip = inf", "observation.clip"),
        (
            "[env.observation.scales]",
            "lin_vel = 1e30",
            "observation.scales.lin_vel",
        ),
        (
            "[learner.ppo]",
            "learning_rate = nan",
            "learner.ppo.learning_rate",
        ),
        ("[learner.ppo]", "min_lr = -1.0", "learner.ppo.min_lr"),
        ("[learner.ppo]", "max_lr = inf", "learner.ppo.max_lr"),
        (
            "[env.reward]",
            "lin_vel_tracking = 3e38",
            "reward.lin_vel_tracking",
        ),
        ("[learner]", "num_cos = 100000", "learner.num_cos"),
        ("[runner]", "threads = 100000", "runner.threads"),
        ("[env.terrain]", "num_levels = 100000", "terrain.num_levels"),
    ];
    for (i, (table, line, key)) in cases.iter().enumerate() {
        let text = set_key(&base, table, line);
        let path = dir.path().join(format!("bad{i}.toml"));
        std::fs::write(&path, &text).unwrap();
        let run = dir.path().join(format!("run{i}"));
        let (ok, code, log) = rall_output(&[
            "train",
            "--config",
            path.to_str().unwrap(),
            "--run-dir",
            run.to_str().unwrap(),
        ]);
        assert!(!ok && code == Some(1), "{line}: {code:?} {log}");
        assert!(log.contains(key), "{line}: the error names {key}: {log}");
    }
}

#[test]
fn too_many_envs_are_refused_before_allocation() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = tiny_config_file(dir.path(), 1);
    for (envs, says) in [("100000000", "runner.num_envs"), ("1000000", "GB")] {
        let run = dir.path().join(format!("run{envs}"));
        let (ok, code, log) = rall_output(&[
            "train",
            "--config",
            cfg.to_str().unwrap(),
            "--run-dir",
            run.to_str().unwrap(),
            "--envs",
            envs,
        ]);
        assert!(
            !ok && code == Some(1),
            "--envs {envs} ends with an error, not a signal: {code:?} {log}"
        );
        assert!(
            log.contains(says) && log.contains("num_envs"),
            "--envs {envs}: {log}"
        );
    }
}

#[test]
fn a_shared_run_dir_keeps_other_programs_temp_files() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = tiny_config_file(dir.path(), 1);
    let shared = dir.path().join("shared");
    std::fs::create_dir_all(shared.join("checkpoints")).unwrap();
    for name in [
        "notes.tmp",
        "upload.safetensors.tmp",
        "checkpoints/other.tmp",
    ] {
        std::fs::write(shared.join(name), "not rall's").unwrap();
    }
    std::fs::write(shared.join("latest.safetensors.tmp"), "a killed write").unwrap();
    let train = |force: &[&str]| {
        let mut args = vec![
            "train",
            "--config",
            cfg.to_str().unwrap(),
            "--run-dir",
            shared.to_str().unwrap(),
        ];
        args.extend(force);
        rall_output(&args)
    };
    // a folder with files rall did not write takes --force
    let (ok, _, log) = train(&[]);
    assert!(
        !ok && log.contains("notes.tmp") && log.contains("--force"),
        "{log}"
    );
    let (ok, _, log) = train(&["--force"]);
    assert!(ok, "{log}");
    for name in [
        "notes.tmp",
        "upload.safetensors.tmp",
        "checkpoints/other.tmp",
    ] {
        assert!(shared.join(name).exists(), "{name} was removed");
    }
    assert!(!shared.join("latest.safetensors.tmp").exists());
    assert!(!shared.join("config.toml.tmp").exists());
}

#[test]
fn run_names_that_leave_the_runs_folder_are_refused() {
    use rall::experiment::spec::check_run_name;
    for bad in ["../escape", "a/b", "..", ".", "", "a\\b", "x..y", "-rf"] {
        assert!(check_run_name(bad).is_err(), "{bad:?} accepted");
    }
    for good in ["rall", "rma-teacher", "flat_v2.1"] {
        check_run_name(good).unwrap();
    }
}

#[test]
fn stopping_and_resuming_with_the_cli_is_the_uninterrupted_run() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = tiny_config_file(dir.path(), 3);
    let (whole, parts) = (dir.path().join("whole"), dir.path().join("parts"));
    let (ok, _, log) = rall_output(&[
        "train",
        "--config",
        cfg.to_str().unwrap(),
        "--run-dir",
        whole.to_str().unwrap(),
    ]);
    assert!(ok, "{log}");
    let (ok, _, log) = rall_output(&[
        "train",
        "--config",
        cfg.to_str().unwrap(),
        "--run-dir",
        parts.to_str().unwrap(),
        "--iterations",
        "1",
    ]);
    assert!(ok, "{log}");
    let (ok, _, log) = rall_output(&[
        "train",
        "--resume",
        parts.to_str().unwrap(),
        "--iterations",
        "3",
    ]);
    assert!(ok, "{log}");
    assert!(!log.contains("not bit-identically"), "{log}");
    let state = |r: &Path| rall::learn::read_checkpoint(&r.join(LATEST)).unwrap();
    let (a, b) = (state(&whole), state(&parts));
    for (x, y) in a.tensors.iter().zip(&b.tensors) {
        assert!(x == y, "tensor {} differs", x.name);
    }
    assert_eq!(a.blobs, b.blobs);
    let rows = |r: &Path| -> Vec<String> {
        let text = std::fs::read_to_string(r.join("metrics.csv")).unwrap();
        let head: Vec<String> = text
            .lines()
            .next()
            .unwrap()
            .split(',')
            .map(String::from)
            .collect();
        text.lines()
            .map(|l| {
                l.split(',')
                    .zip(&head)
                    .filter(|(_, h)| !h.ends_with("_s"))
                    .map(|(v, _)| v)
                    .collect::<Vec<_>>()
                    .join(",")
            })
            .collect()
    };
    assert_eq!(rows(&whole), rows(&parts));
}

#[test]
fn the_shipped_policies_without_checksums_still_load() {
    fn walk(dir: &Path, out: &mut Vec<PathBuf>) {
        for e in std::fs::read_dir(dir).into_iter().flatten().flatten() {
            let p = e.path();
            if p.is_dir() {
                walk(&p, out);
            } else if p.extension().is_some_and(|x| x == "safetensors") {
                out.push(p);
            }
        }
    }
    let mut files = Vec::new();
    walk(
        &Path::new(env!("CARGO_MANIFEST_DIR")).join("policies"),
        &mut files,
    );
    assert!(!files.is_empty(), "policies/ holds checkpoints");
    let mut without_checksums = 0;
    for f in &files {
        // Every shipped file loads: the old ones unverified and never resumed
        // as exact, the newer ones verified against their checksum.
        let c = rall::learn::read_checkpoint(f).unwrap_or_else(|e| panic!("{e:#}"));
        let p = load_policy(f).unwrap_or_else(|e| panic!("{}: {e:#}", f.display()));
        if !c.verified {
            without_checksums += 1;
            assert!(
                !p.exact,
                "{}: an old checkpoint resumes, not exactly",
                f.display()
            );
        } else if f.file_name().is_some_and(|n| n == LATEST) {
            // A shipped latest is the run's exact state, or, once the run has
            // finished, its actor alone: an evaluation copy that never resumes.
            assert!(
                p.exact != p.actor_only,
                "{}: a shipped latest resumes exactly or is an actor-only evaluation copy",
                f.display()
            );
        }
    }
    assert!(
        without_checksums > 0,
        "policies/ still holds checkpoints written before checksums"
    );
}

/// A checkpoint as rall wrote it before checksums and exact state: f32 tensors
/// and metadata only.
fn write_old_format(path: &Path, c: &rall::learn::Checkpoint) {
    use safetensors::tensor::{Dtype, TensorView};
    let bytes: Vec<Vec<u8>> = c
        .tensors
        .iter()
        .map(|t| t.data.iter().flat_map(|v| v.to_le_bytes()).collect())
        .collect();
    let views: Vec<(String, TensorView)> = c
        .tensors
        .iter()
        .zip(&bytes)
        .map(|(t, b)| {
            let v = TensorView::new(Dtype::F32, t.shape.clone(), b).unwrap();
            (t.name.clone(), v)
        })
        .collect();
    let buf = safetensors::serialize(views, Some(c.metadata.clone())).unwrap();
    std::fs::write(path, buf).unwrap();
}

#[test]
fn a_checkpoint_from_before_checksums_resumes_with_one_note_each() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = tiny_config_file(dir.path(), 2);
    let run = dir.path().join("run");
    let (ok, _, log) = rall_output(&[
        "train",
        "--config",
        cfg.to_str().unwrap(),
        "--run-dir",
        run.to_str().unwrap(),
    ]);
    assert!(ok, "{log}");
    let latest = run.join(LATEST);
    let c = rall::learn::read_checkpoint(&latest).unwrap();
    write_old_format(&latest, &c);
    let (ok, _, log) = rall_output(&[
        "train",
        "--resume",
        run.to_str().unwrap(),
        "--iterations",
        "3",
    ]);
    assert!(ok, "{log}");
    assert_eq!(log.matches("has no checksums").count(), 1, "{log}");
    assert_eq!(log.matches("not bit-identically").count(), 1, "{log}");
    let p = load_policy(&latest).unwrap();
    assert!(p.exact && p.progress.iteration == 3);
}

/// Waits up to `limit` for `child` to exit; `None` if it is still running.
fn wait_for(child: &mut Child, limit: Duration) -> Option<std::process::ExitStatus> {
    let start = Instant::now();
    while start.elapsed() < limit {
        if let Some(status) = child.try_wait().unwrap() {
            return Some(status);
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    None
}

/// Sends SIGTERM to `child` and waits for it.
fn terminate(child: &mut Child) {
    let _ = Command::new("kill")
        .args(["-TERM", &child.id().to_string()])
        .status();
    if wait_for(child, Duration::from_secs(60)).is_none() {
        let _ = child.kill();
        let _ = child.wait();
    }
}

#[test]
fn two_trainings_started_together_in_one_run_dir_do_not_both_train() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = tiny_config_file(dir.path(), 100_000);
    let run = dir.path().join("run");
    let train = |delay_ms: &str| {
        Command::new(env!("CARGO_BIN_EXE_rall"))
            .args(["train", "--config", cfg.to_str().unwrap(), "--run-dir"])
            .arg(&run)
            .args(["--save-interval", "100000"])
            .env("RALL_FAULT_LOCK_DELAY_MS", delay_ms)
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap()
    };
    // the first stops for 4 s in the middle of taking the lock; the second
    // starts meanwhile and takes it at once
    let mut first = train("4000");
    std::thread::sleep(Duration::from_millis(1500));
    let mut second = train("0");
    let first_status = wait_for(&mut first, Duration::from_secs(60));
    let second_running = second.try_wait().unwrap().is_none();
    terminate(&mut second);
    let Some(first_status) = first_status else {
        terminate(&mut first);
        panic!("both trainings ran in one run directory");
    };
    let mut err = String::new();
    std::io::Read::read_to_string(&mut first.stderr.take().unwrap(), &mut err).unwrap();
    assert!(!first_status.success(), "{err}");
    assert!(
        err.contains(&format!("is being trained by process {}", second.id())),
        "the first is refused naming the second: {err}"
    );
    assert!(second_running, "the second trained on");
    assert!(!run.join("train.lock").exists(), "the lock is released");
}

#[test]
fn a_full_disk_during_the_metrics_append_leaves_whole_rows_and_names_the_path() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = tiny_config_file(dir.path(), 3);
    let run = dir.path().join("run");
    // appends to metrics.csv: the header, row 1, then row 2 meets a full disk
    let (out, stderr) = train_with_fault(&cfg, &run, "RALL_FAULT_DISK_FULL", "metrics.csv:3");
    assert!(
        !out.status.success(),
        "a failed append stops the run: {stderr}"
    );
    let metrics = run.join("metrics.csv");
    assert!(
        stderr.contains(&metrics.display().to_string()) && stderr.contains("No space left"),
        "the error names the file's full path and the cause: {stderr}"
    );
    let text = std::fs::read_to_string(&metrics).unwrap();
    assert!(text.ends_with('\n'), "no half row: {text:?}");
    assert_eq!(metric_iterations(&run), [1]);
    // the run resumes from its last checkpoint with one row per iteration
    let (ok, _, log) = rall_output(&["train", "--resume", run.to_str().unwrap()]);
    assert!(ok, "{log}");
    assert_eq!(metric_iterations(&run), [1, 2, 3]);
}

/// Copies the folder `from` to `to`, files and subfolders.
fn copy_folder(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap().flatten() {
        let target = to.join(e.file_name());
        if e.file_type().unwrap().is_dir() {
            copy_folder(&e.path(), &target);
        } else {
            std::fs::copy(e.path(), &target).unwrap();
        }
    }
}

/// Rewrites checkpoint `path` without its run identity, as rall wrote it
/// before identities existed (checksums kept).
fn drop_identity(path: &Path) {
    let mut c = rall::learn::read_checkpoint(path).unwrap();
    c.metadata.retain(|k, _| !k.starts_with("run_"));
    rall::learn::save_checkpoint_with(path, &c.tensors, &c.blobs, &c.metadata).unwrap();
}

#[test]
fn another_runs_checkpoint_is_refused_naming_both_runs() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = tiny_config_file(dir.path(), 2);
    let (f, x) = (dir.path().join("f"), dir.path().join("x"));
    for (run, seed) in [(&f, "2"), (&x, "1")] {
        let (ok, _, log) = rall_output(&[
            "train",
            "--config",
            cfg.to_str().unwrap(),
            "--run-dir",
            run.to_str().unwrap(),
            "--seed",
            seed,
        ]);
        assert!(ok, "{log}");
    }
    let id = |p: &Path| load_policy(p).unwrap().progress.identity.unwrap();
    let (f_id, x_id) = (id(&f.join(LATEST)), id(&x.join(LATEST)));
    assert_ne!(f_id.run_id, x_id.run_id);
    assert_eq!((f_id.seed, x_id.seed), (2, 1));
    // `checkpoint info` shows the identity
    let (ok, _, info) = rall_output(&["checkpoint", "info", x.join(LATEST).to_str().unwrap()]);
    assert!(ok && info.contains(&x_id.describe()), "{info}");

    // F's checkpoint put in X's place is refused, naming both runs; X is untouched
    let before = |r: &Path| {
        ["config.toml", "metrics.csv", "identity.toml"]
            .map(|n| std::fs::read_to_string(r.join(n)).unwrap())
    };
    let x_before = before(&x);
    let x_latest = std::fs::read(x.join(LATEST)).unwrap();
    std::fs::copy(
        f.join("checkpoints/model_000002.safetensors"),
        x.join(LATEST),
    )
    .unwrap();
    let (ok, _, log) = rall_output(&[
        "train",
        "--resume",
        x.to_str().unwrap(),
        "--iterations",
        "3",
    ]);
    assert!(!ok, "another run's checkpoint was resumed: {log}");
    assert!(
        log.contains(&f_id.describe()) && log.contains(&x_id.describe()),
        "the error names both runs: {log}"
    );
    assert_eq!(before(&x), x_before, "the refused resume wrote into X");

    // a run folder copied elsewhere resumes as the same run
    std::fs::write(x.join(LATEST), &x_latest).unwrap();
    let y = dir.path().join("y");
    copy_folder(&x, &y);
    let (ok, _, log) = rall_output(&[
        "train",
        "--resume",
        y.to_str().unwrap(),
        "--iterations",
        "3",
    ]);
    assert!(ok, "{log}");
    assert_eq!(id(&y.join(LATEST)), x_id);

    // a checkpoint written before identities (and a folder without identity.toml)
    // resumes, and `checkpoint info` says the identity is not recorded
    drop_identity(&x.join(LATEST));
    let (ok, _, info) = rall_output(&["checkpoint", "info", x.join(LATEST).to_str().unwrap()]);
    assert!(ok && info.contains("identity not recorded"), "{info}");
    let (ok, _, log) = rall_output(&[
        "train",
        "--resume",
        x.to_str().unwrap(),
        "--iterations",
        "3",
    ]);
    assert!(ok, "{log}");
    let old = dir.path().join("old");
    copy_folder(&f, &old);
    drop_identity(&old.join(LATEST));
    std::fs::remove_file(old.join("identity.toml")).unwrap();
    let (ok, _, log) = rall_output(&[
        "train",
        "--resume",
        old.to_str().unwrap(),
        "--iterations",
        "3",
    ]);
    assert!(ok, "{log}");
    assert_eq!(
        load_policy(&old.join(LATEST)).unwrap().progress.iteration,
        3
    );
}

#[test]
fn a_system_directory_or_a_link_to_one_is_refused_as_run_dir() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = tiny_config_file(dir.path(), 1);
    let link = dir.path().join("runs");
    std::os::unix::fs::symlink("/proc", &link).unwrap();
    for run_dir in [link.clone(), link.join("new-run"), PathBuf::from("/proc")] {
        for force in [false, true] {
            let mut args = vec![
                "train",
                "--config",
                cfg.to_str().unwrap(),
                "--run-dir",
                run_dir.to_str().unwrap(),
            ];
            if force {
                args.push("--force");
            }
            let (ok, code, log) = rall_output(&args);
            assert!(!ok && code == Some(1), "{args:?}: {log}");
            assert!(log.contains("system directory"), "{args:?}: {log}");
        }
    }
    // someone else's folder: refused, naming a file of theirs
    let theirs = dir.path().join("theirs");
    std::fs::create_dir_all(&theirs).unwrap();
    std::fs::write(theirs.join("passwd"), "not rall's").unwrap();
    let (ok, _, log) = rall_output(&[
        "train",
        "--config",
        cfg.to_str().unwrap(),
        "--run-dir",
        theirs.to_str().unwrap(),
    ]);
    assert!(!ok && log.contains("passwd"), "{log}");
    assert!(!theirs.join("config.toml").exists() && !theirs.join("train.lock").exists());
}

#[test]
fn settings_that_would_train_nothing_are_refused_naming_the_key() {
    let dir = tempfile::tempdir().unwrap();
    let cfg_path = tiny_config_file(dir.path(), 2);
    let base = TrainConfig::from_toml_str(&std::fs::read_to_string(&cfg_path).unwrap())
        .unwrap()
        .to_toml();
    let cases = [
        // the weights would never change
        (
            "[learner.ppo]",
            "learning_rate = 0.0",
            "learner.ppo.learning_rate",
        ),
        // the adaptive rate could reach 0 and stay there
        ("[learner.ppo]", "min_lr = 0.0", "learner.ppo.min_lr"),
        ("[runner]", "iterations = 0", "runner.iterations"),
        // an episode of 5e12 physics steps
        (
            "[env.control]",
            "physics_dt_s = 1e-12",
            "control.physics_dt_s",
        ),
        // heights rounded to 1e30 m: every tile flat
        (
            "[env.terrain]",
            "vertical_scale_m = 1e30",
            "terrain.vertical_scale_m",
        ),
        // an episode shorter than one policy step
        ("[env.episode]", "length_s = 0.001", "episode.length_s"),
    ];
    for (i, (table, line, key)) in cases.iter().enumerate() {
        let path = dir.path().join(format!("nothing{i}.toml"));
        std::fs::write(&path, set_key(&base, table, line)).unwrap();
        let run = dir.path().join(format!("run{i}"));
        let (ok, code, log) = rall_output(&[
            "train",
            "--config",
            path.to_str().unwrap(),
            "--run-dir",
            run.to_str().unwrap(),
        ]);
        assert!(!ok && code == Some(1), "{line}: {code:?} {log}");
        assert!(log.contains(key), "{line}: the error names {key}: {log}");
        assert!(!run.exists(), "{line}: nothing is written");
    }
    // a discount of 0 is a legitimate (myopic) experiment: accepted
    let myopic = set_key(&base, "[learner.ppo]", "gamma = 0.0");
    TrainConfig::from_toml_str(&myopic).unwrap();

    // --iterations 0, new or resumed, is refused; so is a resume with nothing left
    let run = dir.path().join("run");
    let cfg_s = cfg_path.to_str().unwrap();
    let run_s = run.to_str().unwrap();
    let (ok, _, log) = rall_output(&[
        "train",
        "--config",
        cfg_s,
        "--run-dir",
        run_s,
        "--iterations",
        "0",
    ]);
    assert!(!ok && log.contains("runner.iterations"), "{log}");
    assert!(!run.join(LATEST).exists());
    let (ok, _, log) = rall_output(&["train", "--config", cfg_s, "--run-dir", run_s]);
    assert!(ok, "{log}");
    for target in ["0", "1", "2"] {
        let (ok, _, log) = rall_output(&["train", "--resume", run_s, "--iterations", target]);
        assert!(!ok, "--iterations {target} on a run at 2: {log}");
        assert!(
            log.contains("runner.iterations") || log.contains("nothing to train"),
            "--iterations {target}: {log}"
        );
    }
    assert_eq!(metric_iterations(&run), [1, 2]);
}
