//! A run stopped at any checkpoint and resumed is the same run: every tensor of
//! its final checkpoint (and the envs' stored state) and every non-timing column
//! of `metrics.csv` equal those of the uninterrupted run, bit for bit. Single
//! process for RALL (IQN critic, rough terrain curriculum), the Baseline (scalar
//! critic) and RMA's phase 2, each resumed at two iterations; and `mpirun -np 2`.

use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

use rall::config::TrainConfig;
use rall::learn::read_checkpoint;
use rall::runner::{train, IterationObserver, LATEST};

mod common;
use common::{metrics_without_timing, tiny_method};

fn no_stop() -> Arc<AtomicBool> {
    Arc::new(AtomicBool::new(false))
}

/// A method's tiny config trained for `iterations` (RMA: phase 1), saving every one.
fn config(method: &str, iterations: usize) -> TrainConfig {
    let mut c = tiny_method(method);
    c.runner.iterations = iterations;
    c.runner.save_interval = 1;
    c.runner.threads = 2;
    if let Some(a) = &mut c.learner.adaptation {
        a.iterations = 3;
    }
    c
}

/// Named tensors as bit patterns, and named state blobs.
type State = (Vec<(String, Vec<u32>)>, Vec<(String, Vec<u8>)>);

/// Every tensor and state blob of the run's final checkpoint, bit for bit.
fn final_state(run: &Path) -> State {
    let c = read_checkpoint(&run.join(LATEST)).unwrap();
    assert!(c.verified, "a new checkpoint carries checksums");
    let tensors = c
        .tensors
        .into_iter()
        .map(|t| (t.name, t.data.iter().map(|v| v.to_bits()).collect()))
        .collect();
    (tensors, c.blobs)
}

/// Copies `from` (a finished run) to `to` as it stood when it wrote iteration
/// `at`: `latest` is that numbered checkpoint, later ones are gone (what a run
/// killed right after that save leaves; metrics rows after it are dropped on resume).
fn rewind_copy(from: &Path, to: &Path, at: usize) {
    std::fs::create_dir_all(to.join("checkpoints")).unwrap();
    for name in ["metrics.csv", "config.toml", "adaptation.csv"] {
        if from.join(name).exists() {
            std::fs::copy(from.join(name), to.join(name)).unwrap();
        }
    }
    let numbered = |it: usize| format!("checkpoints/model_{it:06}.safetensors");
    for it in 1..=at {
        std::fs::copy(from.join(numbered(it)), to.join(numbered(it))).unwrap();
    }
    std::fs::copy(from.join(numbered(at)), to.join(LATEST)).unwrap();
}

fn assert_same_run(a: &Path, b: &Path, what: &str) {
    let (ta, ba) = final_state(a);
    let (tb, bb) = final_state(b);
    let differ: Vec<&String> = ta
        .iter()
        .zip(&tb)
        .filter(|(x, y)| x != y)
        .map(|(x, _)| &x.0)
        .collect();
    assert_eq!(ta.len(), tb.len(), "{what}: tensor count");
    assert!(differ.is_empty(), "{what}: tensors differ: {differ:?}");
    assert_eq!(ba, bb, "{what}: stored learner/env state differs");
    assert_eq!(
        metrics_without_timing(a),
        metrics_without_timing(b),
        "{what}: metrics.csv differs"
    );
    let adaptation = |r: &Path| std::fs::read_to_string(r.join("adaptation.csv")).ok();
    if let (Some(x), Some(y)) = (adaptation(a), adaptation(b)) {
        let strip = |t: String| -> Vec<String> {
            // iteration, then non-timing columns (wall_s, collect_s, learn_s are 1..=4)
            t.lines()
                .map(|l| {
                    let f: Vec<&str> = l.split(',').collect();
                    [&f[..1], &f[5..]].concat().join(",")
                })
                .collect()
        };
        assert_eq!(strip(x), strip(y), "{what}: adaptation.csv differs");
    }
}

/// Trains `method` uninterrupted to the end, then again resumed from each of
/// `stops`, and compares.
fn check_method(method: &str, iterations: usize, stops: &[usize]) {
    let dir = tempfile::tempdir().unwrap();
    let whole = dir.path().join("whole");
    train(
        config(method, iterations),
        &whole,
        false,
        no_stop(),
        &mut (),
    )
    .unwrap();
    for &at in stops {
        let resumed = dir.path().join(format!("resumed-{at}"));
        rewind_copy(&whole, &resumed, at);
        let s = train(
            config(method, iterations),
            &resumed,
            true,
            no_stop(),
            &mut (),
        )
        .unwrap();
        assert!(!s.interrupted);
        assert_same_run(&whole, &resumed, &format!("{method} resumed at {at}"));
    }
}

#[test]
fn rall_resumed_at_two_iterations_is_the_uninterrupted_run() {
    check_method("rall", 4, &[1, 3]);
}

#[test]
fn baseline_resumed_at_two_iterations_is_the_uninterrupted_run() {
    check_method("baseline", 4, &[2, 3]);
}

#[test]
fn rma_resumed_in_phase_two_and_at_its_start_is_the_uninterrupted_run() {
    // phase 1: iterations 1-2; phase 2: 3-5
    check_method("rma", 2, &[2, 4]);
}

/// Stops the run (as Ctrl-C does) once it has logged iteration `at`.
struct StopAt {
    at: usize,
    stop: Arc<AtomicBool>,
}

impl IterationObserver for StopAt {
    fn on_iteration(
        &mut self,
        row: &rall::runner::metrics::IterationRow,
        _: &rall::learn::Learner,
    ) -> anyhow::Result<()> {
        if row.iteration == self.at {
            self.stop.store(true, Ordering::SeqCst);
        }
        Ok(())
    }
}

#[test]
fn a_run_interrupted_by_a_signal_resumes_as_the_same_run() {
    let dir = tempfile::tempdir().unwrap();
    let whole = dir.path().join("whole");
    train(config("rall", 4), &whole, false, no_stop(), &mut ()).unwrap();
    let stopped = dir.path().join("stopped");
    let stop = no_stop();
    let mut observer = StopAt {
        at: 2,
        stop: stop.clone(),
    };
    let mut cfg = config("rall", 4);
    cfg.runner.save_interval = 100;
    let s = train(cfg.clone(), &stopped, false, stop, &mut observer).unwrap();
    assert!(s.interrupted && s.iterations_done == 2);
    train(cfg, &stopped, true, no_stop(), &mut ()).unwrap();
    assert_same_run(&whole, &stopped, "rall interrupted at 2");
}

#[cfg(feature = "mpi")]
fn mpirun_train(args: &[&str]) -> Option<std::process::Output> {
    let out = std::process::Command::new("mpirun")
        .args([
            "-np",
            "2",
            "--oversubscribe",
            env!("CARGO_BIN_EXE_rall"),
            "train",
        ])
        .args(args)
        .env("OMPI_ALLOW_RUN_AS_ROOT", "1")
        .env("OMPI_ALLOW_RUN_AS_ROOT_CONFIRM", "1")
        .env("OMPI_MCA_btl_tcp_if_include", "lo")
        .env("OMPI_MCA_oob_tcp_if_include", "lo")
        .output();
    match out {
        Ok(o) => Some(o),
        Err(e) => {
            println!("skipped: mpirun is not available ({e}); install openmpi-bin");
            None
        }
    }
}

#[cfg(feature = "mpi")]
#[test]
fn two_ranks_resumed_at_two_checkpoints_are_the_uninterrupted_job() {
    let dir = tempfile::tempdir().unwrap();
    let mut cfg = config("rall", 3);
    cfg.runner.threads = 1;
    let cfg_path = dir.path().join("tiny.toml");
    std::fs::write(&cfg_path, cfg.to_toml()).unwrap();
    let whole = dir.path().join("whole");
    let c = cfg_path.to_str().unwrap();
    let Some(o) = mpirun_train(&["--config", c, "--run-dir", whole.to_str().unwrap()]) else {
        return;
    };
    let log = |o: &std::process::Output| String::from_utf8_lossy(&o.stderr).to_string();
    assert!(o.status.success(), "{}", log(&o));
    for at in [1, 2] {
        let resumed = dir.path().join(format!("resumed-{at}"));
        rewind_copy(&whole, &resumed, at);
        let o = mpirun_train(&["--resume", resumed.to_str().unwrap()]).unwrap();
        assert!(o.status.success(), "{}", log(&o));
        assert!(!log(&o).contains("not bit-identically"), "{}", log(&o));
        assert_same_run(&whole, &resumed, &format!("two ranks resumed at {at}"));
    }
}
