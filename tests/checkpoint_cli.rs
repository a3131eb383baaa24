//! `rall checkpoint info | actor-only | evaluation-only` on run states the tests
//! train themselves (the shipped runs are finished, so they ship no run state).

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use rall::learn::CriticKind;

mod common;
use common::tiny_config;

fn rall(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_rall"))
        .args(args)
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .output()
        .expect("running rall")
}

fn stdout(o: &Output) -> String {
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    String::from_utf8_lossy(&o.stdout).into_owned()
}

/// The stderr of a `rall` call that must fail.
fn refused(args: &[&str]) -> String {
    let o = rall(args);
    assert!(!o.status.success(), "rall {args:?} succeeded");
    String::from_utf8_lossy(&o.stderr).into_owned()
}

/// A full run state (IQN critic, seed `seed`): a tiny run of two iterations
/// trained into `dir/run-<seed>`; returns its `latest.safetensors`.
fn run_state(dir: &Path, seed: u64) -> PathBuf {
    let mut c = tiny_config(CriticKind::Iqn);
    c.runner.iterations = 2;
    c.runner.threads = 1;
    c.runner.seed = seed;
    let cfg = dir.join(format!("tiny-{seed}.toml"));
    std::fs::write(&cfg, c.to_toml()).unwrap();
    let run = dir.join(format!("run-{seed}"));
    stdout(&rall(&[
        "train",
        "--config",
        cfg.to_str().unwrap(),
        "--run-dir",
        run.to_str().unwrap(),
    ]));
    run.join("latest.safetensors")
}

/// `rall checkpoint KIND` (actor-only or evaluation-only) from `src` to `out`.
fn cut(kind: &str, src: &Path, out: &Path) -> Output {
    rall(&[
        "checkpoint",
        kind,
        "--checkpoint",
        src.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ])
}

/// Tensors whose name `keep` accepts, by name.
fn tensors(s: &[rall::learn::NamedTensor], keep: impl Fn(&str) -> bool) -> Vec<(String, Vec<f32>)> {
    s.iter()
        .filter(|t| keep(&t.name))
        .map(|t| (t.name.clone(), t.data.clone()))
        .collect()
}

#[test]
fn info_tells_a_run_state_from_an_actor_only_copy() {
    let dir = tempfile_dir("actor-only");
    let state = run_state(&dir, 1);
    let copy = dir.join("actor.safetensors");
    let out = stdout(&rall(&["checkpoint", "info", state.to_str().unwrap()]));
    assert!(out.contains("iteration 2"), "{out}");
    assert!(out.contains("iqn critic"), "{out}");
    assert!(out.contains("checksums verified"), "{out}");
    assert!(out.contains("resumes bit for bit"), "{out}");

    let out = stdout(&cut("actor-only", &state, &copy));
    assert!(
        out.contains("actor only: evaluates, never resumes"),
        "{out}"
    );
    let full = std::fs::metadata(&state).unwrap().len();
    let small = std::fs::metadata(&copy).unwrap().len();
    assert!(small * 4 < full, "actor-only {small} B against {full} B");

    // the copy acts exactly like the run state it was cut from
    let a = rall::runner::load_policy(&state).unwrap();
    let b = rall::runner::load_policy(&copy).unwrap();
    assert!(b.actor_only && !a.actor_only);
    let actor = |n: &str| n.starts_with("actor.");
    assert_eq!(
        tensors(&a.learner.state(), actor),
        tensors(&b.learner.state(), actor)
    );
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn an_evaluation_file_keeps_every_trained_tensor_and_never_resumes() {
    let dir = tempfile_dir("evaluation-only");
    let state = run_state(&dir, 1);
    let eval = dir.join("eval.safetensors");
    let out = stdout(&cut("evaluation-only", &state, &eval));
    assert!(out.contains("evaluation only"), "{out}");
    assert!(out.contains("never resumes"), "{out}");
    let full = std::fs::metadata(&state).unwrap().len();
    let small = std::fs::metadata(&eval).unwrap().len();
    assert!(
        small * 2 < full,
        "evaluation file {small} B against {full} B"
    );

    // actor, critic and normaliser bit for bit; only the optimiser state is fresh
    let a = rall::runner::load_policy(&state).unwrap();
    let b = rall::runner::load_policy(&eval).unwrap();
    assert!(b.evaluation_only && !b.actor_only && !b.resumable() && a.resumable());
    let trained = |n: &str| !n.starts_with("adam.") && !n.starts_with("adapt_adam.");
    let kept = tensors(&b.learner.state(), trained);
    assert_eq!(tensors(&a.learner.state(), trained), kept);
    assert!(kept.iter().any(|(n, _)| n.starts_with("critic.")));
    assert_eq!(a.progress.iteration, b.progress.iteration);
    assert_eq!(a.config.to_toml(), b.config.to_toml());

    // a run folder holding it as latest is refused, naming the file and why
    let run = dir.join("resume");
    std::fs::create_dir_all(&run).unwrap();
    std::fs::copy(&eval, run.join("latest.safetensors")).unwrap();
    let err = refused(&["train", "--resume", run.to_str().unwrap()]);
    assert!(
        err.contains("evaluation file") && err.contains("cannot be resumed"),
        "{err}"
    );

    // an actor-only copy has no trained critic to keep
    let actor = dir.join("actor.safetensors");
    stdout(&cut("actor-only", &state, &actor));
    let err =
        String::from_utf8_lossy(&cut("evaluation-only", &actor, &dir.join("x.safetensors")).stderr)
            .into_owned();
    assert!(err.contains("holds the actor alone"), "{err}");
    // nor does it overwrite a run state
    let err = String::from_utf8_lossy(&cut("evaluation-only", &eval, &state).stderr).into_owned();
    assert!(err.contains("full checkpoint"), "{err}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn bad_input_is_named() {
    let err = refused(&["checkpoint", "info", "no/such/file.safetensors"]);
    assert!(err.contains("no/such/file.safetensors"), "{err}");

    let dir = tempfile_dir("full");
    let state = run_state(&dir, 1);
    let o = cut("actor-only", &state, &state);
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("is the checkpoint itself"), "{err}");

    // nor any other file that still resumes a run
    let other = dir.join("latest.safetensors");
    std::fs::copy(&state, &other).unwrap();
    let before = std::fs::read(&other).unwrap();
    let o = cut("actor-only", &state, &other);
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("already holds a full checkpoint"), "{err}");
    assert_eq!(std::fs::read(&other).unwrap(), before);
    let _ = std::fs::remove_dir_all(&dir);
}

/// A fresh folder of this test process for one test.
fn tempfile_dir(test: &str) -> std::path::PathBuf {
    let d = std::env::temp_dir().join(format!("rall-checkpoint-cli-{}-{test}", std::process::id()));
    std::fs::create_dir_all(&d).unwrap();
    d
}

#[test]
fn cutting_the_same_actor_twice_leaves_the_file_alone() {
    let dir = tempfile_dir("actor-only-twice");
    let src = run_state(&dir, 1);
    let other = run_state(&dir, 2);
    let copy = dir.join("actor.safetensors");
    rall::runner::checkpoint_kinds::save_actor_only(&src, &copy).unwrap();
    let first = std::fs::read(&copy).unwrap();
    // several tries: a rewrite would order the metadata afresh each time
    for _ in 0..4 {
        rall::runner::checkpoint_kinds::save_actor_only(&src, &copy).unwrap();
        assert!(
            std::fs::read(&copy).unwrap() == first,
            "the copy was rewritten"
        );
    }
    // a different source does replace it
    rall::runner::checkpoint_kinds::save_actor_only(&other, &copy).unwrap();
    let b = rall::runner::load_policy(&copy).unwrap();
    assert_eq!(b.config.runner.seed, 2);
    let _ = std::fs::remove_dir_all(&dir);
}

/// `src`'s tensors, byte tensors and metadata written to `out` without checksums.
fn strip_checksums(src: &Path, out: &Path) {
    use safetensors::tensor::{Dtype, TensorView};
    let c = rall::learn::read_checkpoint(src).unwrap();
    let floats: Vec<Vec<u8>> = c
        .tensors
        .iter()
        .map(|t| t.data.iter().flat_map(|v| v.to_le_bytes()).collect())
        .collect();
    let mut views: Vec<(String, TensorView)> = c
        .tensors
        .iter()
        .zip(&floats)
        .map(|(t, b)| {
            let v = TensorView::new(Dtype::F32, t.shape.clone(), b).unwrap();
            (t.name.clone(), v)
        })
        .collect();
    for (name, bytes) in &c.blobs {
        let v = TensorView::new(Dtype::U8, vec![bytes.len()], bytes).unwrap();
        views.push((name.clone(), v));
    }
    let buf = safetensors::serialize(views, Some(c.metadata.clone())).unwrap();
    std::fs::write(out, buf).unwrap();
}

#[test]
fn info_calls_a_run_state_without_checksums_unverified() {
    let dir = tempfile_dir("stripped");
    let stripped = dir.join("stripped.safetensors");
    strip_checksums(&run_state(&dir, 1), &stripped);
    let out = stdout(&rall(&["checkpoint", "info", stripped.to_str().unwrap()]));
    assert!(out.contains("unverified"), "{out}");
    assert!(!out.contains("bit for bit"), "{out}");
    let _ = std::fs::remove_dir_all(&dir);
}
