//! `rall train` under `mpirun -np 2` on this machine, as CI runs it
//! (`.ci/run` installs Open MPI; as root it needs OMPI_ALLOW_RUN_AS_ROOT, set
//! here). Built without the `mpi` feature, these tests are not compiled.
#![cfg(feature = "mpi")]

use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::time::{Duration, Instant};

use rall::learn::CriticKind;
use rall::runner::{load_policy, LATEST};

mod common;
use common::tiny_config;

const RALL: &str = env!("CARGO_BIN_EXE_rall");

/// `mpirun -np 2` (Open MPI: oversubscribing allowed, root allowed) of `rall args`.
fn mpirun(args: &[&str], envs: &[(&str, &str)]) -> Command {
    let mut c = Command::new("mpirun");
    c.args(["-np", "2", "--oversubscribe", RALL])
        .args(args)
        .env("OMPI_ALLOW_RUN_AS_ROOT", "1")
        .env("OMPI_ALLOW_RUN_AS_ROOT_CONFIRM", "1")
        // loopback only: a test host's other interfaces may be unroutable
        .env("OMPI_MCA_btl_tcp_if_include", "lo")
        .env("OMPI_MCA_oob_tcp_if_include", "lo");
    for (k, v) in envs {
        c.env(k, v);
    }
    c
}

fn run(mut c: Command) -> Output {
    c.output()
        .expect("running mpirun (install Open MPI: apt-get install openmpi-bin libopenmpi-dev)")
}

fn text(o: &Output) -> String {
    format!(
        "{}\n{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    )
}

/// The tiny config (2 x 8 envs, small networks) written as a file for the CLI.
fn tiny_config_file(dir: &Path) -> PathBuf {
    let mut cfg = tiny_config(CriticKind::Iqn);
    cfg.runner.threads = 1;
    let path = dir.join("tiny.toml");
    std::fs::write(&path, cfg.to_toml()).unwrap();
    path
}

fn metric_rows(run: &Path) -> (Vec<String>, Vec<Vec<String>>) {
    let text = std::fs::read_to_string(run.join("metrics.csv")).unwrap();
    let mut lines = text.lines();
    let head = lines.next().unwrap().split(',').map(String::from).collect();
    let rows = lines
        .map(|l| l.split(',').map(String::from).collect())
        .collect();
    (head, rows)
}

fn column(head: &[String], name: &str) -> usize {
    head.iter().position(|h| h == name).unwrap()
}

#[test]
fn two_ranks_train_one_policy_that_evaluates_and_resumes() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = tiny_config_file(dir.path());
    let run_dir = dir.path().join("run");
    let (cfg_s, run_s) = (cfg.to_str().unwrap(), run_dir.to_str().unwrap());
    let first = run(mpirun(
        &[
            "train",
            "--config",
            cfg_s,
            "--run-dir",
            run_s,
            "--iterations",
            "3",
        ],
        &[],
    ));
    let log = text(&first);
    assert!(first.status.success(), "{log}");
    assert!(log.contains("on each of 2 ranks"), "{log}");
    // rank 0 alone writes: one metrics file, one row per iteration, steps of both ranks
    let (head, rows) = metric_rows(&run_dir);
    assert_eq!(rows.len(), 3, "{rows:?}");
    let (steps, ranks) = (column(&head, "total_env_steps"), column(&head, "ranks"));
    for (k, row) in rows.iter().enumerate() {
        assert_eq!(row[0], (k + 1).to_string());
        assert_eq!(
            row[steps],
            ((k + 1) * 2 * 8 * 8).to_string(),
            "sum over ranks"
        );
        assert_eq!(row[ranks], "2");
    }
    // the ranks compared their whole learner state at every checkpoint (save
    // interval 1): the run finishing means they were bit-identical each time
    let ckpt = load_policy(&run_dir.join(LATEST)).unwrap();
    assert_eq!(ckpt.progress.iteration, 3);
    assert_eq!(ckpt.progress.total_env_steps, 3 * 2 * 8 * 8);

    // evaluation reads it like any other checkpoint
    let eval = Command::new(RALL)
        .args(["eval", "tracking", "--checkpoint"])
        .arg(run_dir.join(LATEST))
        .args(["--episodes", "2", "--threads", "1"])
        .output()
        .unwrap();
    assert!(eval.status.success(), "{}", text(&eval));

    // resume under MPI: the iteration count and the learning rate continue
    let lr = format!("lr {:.2e}", ckpt.learner.learning_rate());
    let second = run(mpirun(
        &["train", "--resume", run_s, "--iterations", "5"],
        &[],
    ));
    let log = text(&second);
    assert!(second.status.success(), "{log}");
    assert!(
        log.contains("at iteration 3") && log.contains(&lr),
        "{lr}: {log}"
    );
    let (_, rows) = metric_rows(&run_dir);
    let its: Vec<&str> = rows.iter().map(|r| r[0].as_str()).collect();
    assert_eq!(its, ["1", "2", "3", "4", "5"]);
    let end = load_policy(&run_dir.join(LATEST)).unwrap();
    assert_eq!(end.progress.total_env_steps, 5 * 2 * 8 * 8);
}

#[test]
fn a_rank_whose_parameters_diverge_stops_the_job_naming_it() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = tiny_config_file(dir.path());
    let run_dir = dir.path().join("run");
    let out = run(mpirun(
        &[
            "train",
            "--config",
            cfg.to_str().unwrap(),
            "--run-dir",
            run_dir.to_str().unwrap(),
            "--iterations",
            "4",
        ],
        // rank 1 nudges one weight after iteration 2's update
        &[("RALL_FAULT_PERTURB", "1:2")],
    ));
    let log = text(&out);
    assert!(!out.status.success(), "{log}");
    assert!(
        log.contains("diverged at iteration 2") && log.contains("rank(s) [1] differ from rank 0"),
        "{log}"
    );
    // the checkpoint of the diverged iteration was not written
    assert!(run_dir
        .join("checkpoints/model_000001.safetensors")
        .exists());
    assert!(!run_dir
        .join("checkpoints/model_000002.safetensors")
        .exists());
}

/// The pid of the `rall` process that is rank `rank` of a job whose command
/// line mentions `marker`.
fn rank_pid(marker: &str, rank: usize) -> Option<u32> {
    for e in std::fs::read_dir("/proc").ok()?.flatten() {
        let Ok(pid) = e.file_name().to_string_lossy().parse::<u32>() else {
            continue;
        };
        let cmd = std::fs::read(format!("/proc/{pid}/cmdline")).unwrap_or_default();
        let cmd = String::from_utf8_lossy(&cmd);
        if !cmd.starts_with(RALL) || !cmd.contains(marker) {
            continue;
        }
        let env = std::fs::read(format!("/proc/{pid}/environ")).unwrap_or_default();
        let want = format!("OMPI_COMM_WORLD_RANK={rank}");
        if env.split(|b| *b == 0).any(|kv| kv == want.as_bytes()) {
            return Some(pid);
        }
    }
    None
}

#[test]
fn a_rank_that_dies_ends_the_job_and_the_run_resumes() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = tiny_config_file(dir.path());
    let run_dir = dir.path().join("run");
    let run_s = run_dir.to_str().unwrap();
    let mut job = mpirun(
        &[
            "train",
            "--config",
            cfg.to_str().unwrap(),
            "--run-dir",
            run_s,
            "--iterations",
            "100000",
        ],
        &[],
    )
    .stdout(Stdio::null())
    .stderr(Stdio::null())
    .spawn()
    .unwrap();
    // wait for a checkpoint, then kill rank 1 the hard way
    let t0 = Instant::now();
    while !run_dir
        .join("checkpoints/model_000002.safetensors")
        .exists()
    {
        assert!(t0.elapsed() < Duration::from_secs(120), "no checkpoint");
        std::thread::sleep(Duration::from_millis(50));
    }
    let pid = rank_pid(run_s, 1).expect("rank 1's process");
    Command::new("kill")
        .args(["-9", &pid.to_string()])
        .status()
        .unwrap();
    // the launcher ends the whole job
    let t1 = Instant::now();
    let status = loop {
        if let Some(s) = job.try_wait().unwrap() {
            break s;
        }
        if t1.elapsed() > Duration::from_secs(60) {
            let _ = job.kill();
            panic!("the job outlived its dead rank by 60 s");
        }
        std::thread::sleep(Duration::from_millis(50));
    };
    assert!(!status.success());
    // the launcher has ended rank 0; on a loaded machine it may take a moment to exit
    let t2 = Instant::now();
    while rank_pid(run_s, 0).is_some() && t2.elapsed() < Duration::from_secs(20) {
        std::thread::sleep(Duration::from_millis(100));
    }
    assert!(
        rank_pid(run_s, 0).is_none(),
        "rank 0 still running 20 s after the job"
    );
    // and the run resumes from its last checkpoint
    let done = load_policy(&run_dir.join(LATEST))
        .unwrap()
        .progress
        .iteration;
    let target = (done + 2).to_string();
    let again = run(mpirun(
        &["train", "--resume", run_s, "--iterations", &target],
        &[],
    ));
    let log = text(&again);
    assert!(again.status.success(), "{log}");
    assert!(log.contains(&format!("at iteration {done}")), "{log}");
    let (_, rows) = metric_rows(&run_dir);
    let its: Vec<usize> = rows.iter().map(|r| r[0].parse().unwrap()).collect();
    assert_eq!(its, (1..=done + 2).collect::<Vec<_>>());
}

/// Iterations of the complete rows of `run`'s metrics.csv (none before it exists).
fn finished_iterations(run: &Path) -> Vec<usize> {
    let text = std::fs::read_to_string(run.join("metrics.csv")).unwrap_or_default();
    let complete = text.rsplit_once('\n').map_or("", |(c, _)| c);
    complete
        .lines()
        .skip(1)
        .filter_map(|l| l.split(',').next()?.parse().ok())
        .collect()
}

#[test]
fn sigusr1_to_mpirun_writes_a_checkpoint_and_the_job_exits_0() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = tiny_config_file(dir.path());
    let run_dir = dir.path().join("run");
    let run_s = run_dir.to_str().unwrap();
    let mut job = mpirun(
        &[
            "train",
            "--config",
            cfg.to_str().unwrap(),
            "--run-dir",
            run_s,
            "--iterations",
            "100000",
            "--save-interval",
            "100000",
        ],
        &[],
    )
    .stdout(Stdio::null())
    .stderr(Stdio::piped())
    .spawn()
    .unwrap();
    let t0 = Instant::now();
    while finished_iterations(&run_dir).len() < 2 {
        assert!(t0.elapsed() < Duration::from_secs(120), "no iterations");
        std::thread::sleep(Duration::from_millis(50));
    }
    // what a scheduler asked to signal the job step sends (Slurm's --signal=USR1@T):
    // mpirun forwards it to every rank
    Command::new("kill")
        .args(["-USR1", &job.id().to_string()])
        .status()
        .unwrap();
    let t1 = Instant::now();
    let status = loop {
        if let Some(s) = job.try_wait().unwrap() {
            break s;
        }
        if t1.elapsed() > Duration::from_secs(60) {
            let _ = job.kill();
            panic!("the job did not stop within 60 s of SIGUSR1");
        }
        std::thread::sleep(Duration::from_millis(50));
    };
    let mut err = String::new();
    std::io::Read::read_to_string(&mut job.stderr.take().unwrap(), &mut err).unwrap();
    assert!(status.success(), "exit {status:?}: {err}");
    // the checkpoint holds the last iteration logged, and the run resumes from it
    let done = load_policy(&run_dir.join(LATEST))
        .unwrap()
        .progress
        .iteration;
    assert_eq!(finished_iterations(&run_dir).last(), Some(&done));
    let target = (done + 1).to_string();
    let again = run(mpirun(
        &["train", "--resume", run_s, "--iterations", &target],
        &[],
    ));
    assert!(again.status.success(), "{}", text(&again));
    assert_eq!(
        finished_iterations(&run_dir),
        (1..=done + 1).collect::<Vec<_>>()
    );
}
