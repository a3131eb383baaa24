//! `rall checkpoint info | actor-only` on the shipped files.

use std::path::Path;
use std::process::{Command, Output};

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

/// `rall checkpoint actor-only` from the shipped run state to `out`.
fn actor_only_to(out: &str) -> Output {
    rall(&[
        "checkpoint",
        "actor-only",
        "--checkpoint",
        RUN_STATE,
        "--out",
        out,
    ])
}

const RUN_STATE: &str = "policies/paper/baseline-s1/latest.safetensors";

#[test]
fn info_tells_a_run_state_from_an_actor_only_copy() {
    let dir = tempfile_dir("actor-only");
    let copy = dir.join("actor.safetensors");
    let out = stdout(&rall(&["checkpoint", "info", RUN_STATE]));
    assert!(out.contains("iteration 4500"), "{out}");
    assert!(out.contains("scalar critic"), "{out}");
    assert!(out.contains("checksums verified"), "{out}");
    assert!(out.contains("resumes bit for bit"), "{out}");

    let out = stdout(&actor_only_to(copy.to_str().unwrap()));
    assert!(
        out.contains("actor only: evaluates, never resumes"),
        "{out}"
    );
    let full = std::fs::metadata(Path::new(env!("CARGO_MANIFEST_DIR")).join(RUN_STATE))
        .unwrap()
        .len();
    let small = std::fs::metadata(&copy).unwrap().len();
    assert!(small * 4 < full, "actor-only {small} B against {full} B");

    // the copy acts exactly like the run state it was cut from
    let a =
        rall::runner::load_policy(&Path::new(env!("CARGO_MANIFEST_DIR")).join(RUN_STATE)).unwrap();
    let b = rall::runner::load_policy(&copy).unwrap();
    assert!(b.actor_only && !a.actor_only);
    let names = |s: &[rall::learn::NamedTensor]| -> Vec<(String, Vec<f32>)> {
        s.iter()
            .filter(|t| t.name.starts_with("actor."))
            .map(|t| (t.name.clone(), t.data.clone()))
            .collect()
    };
    assert_eq!(names(&a.learner.state()), names(&b.learner.state()));
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn bad_input_is_named() {
    let err = refused(&["checkpoint", "info", "no/such/file.safetensors"]);
    assert!(err.contains("no/such/file.safetensors"), "{err}");

    let o = actor_only_to(RUN_STATE);
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("is the checkpoint itself"), "{err}");

    // nor any other file that still resumes a run
    let dir = tempfile_dir("full");
    let other = dir.join("latest.safetensors");
    std::fs::copy(
        Path::new(env!("CARGO_MANIFEST_DIR")).join(RUN_STATE),
        &other,
    )
    .unwrap();
    let before = std::fs::read(&other).unwrap();
    let o = actor_only_to(other.to_str().unwrap());
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
    let copy = dir.join("actor.safetensors");
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join(RUN_STATE);
    rall::runner::policy_file::save_actor_only(&src, &copy).unwrap();
    let first = std::fs::read(&copy).unwrap();
    // several tries: a rewrite would order the metadata afresh each time
    for _ in 0..4 {
        rall::runner::policy_file::save_actor_only(&src, &copy).unwrap();
        assert!(
            std::fs::read(&copy).unwrap() == first,
            "the copy was rewritten"
        );
    }
    // a different source does replace it
    let other =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("policies/paper/baseline-s2/latest.safetensors");
    rall::runner::policy_file::save_actor_only(&other, &copy).unwrap();
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
    strip_checksums(
        &Path::new(env!("CARGO_MANIFEST_DIR")).join(RUN_STATE),
        &stripped,
    );
    let out = stdout(&rall(&["checkpoint", "info", stripped.to_str().unwrap()]));
    assert!(out.contains("unverified"), "{out}");
    assert!(!out.contains("bit for bit"), "{out}");
    let _ = std::fs::remove_dir_all(&dir);
}
