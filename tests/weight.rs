//! The repository's weight cannot creep back: every tracked file over 2 MB is a
//! shipped binary listed in `policies/MANIFEST`, the tracked tree stays under its
//! ceiling, and `rall checkpoint verify policies` finds every listed file as listed.

use std::path::{Path, PathBuf};
use std::process::Command;

use rall::runner::manifest;

/// A tracked file larger than this must be listed in the manifest.
const LISTED_ABOVE_BYTES: u64 = 2_000_000;

/// Ceiling of the tracked tree (every file `git ls-files` lists). A ratchet: lowered
/// as the shipped runs are slimmed (the goal is 100 MB), never raised without a
/// reason in the commit that raises it.
const TREE_CEILING_BYTES: u64 = 420_000_000;

fn repo() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// Tracked files with their sizes, or `None` outside a git checkout (a source
/// tarball has no history to guard).
fn tracked_files() -> Option<Vec<(String, u64)>> {
    let out = Command::new("git")
        .args(["ls-files", "-z"])
        .current_dir(repo())
        .output()
        .ok()?;
    if !out.status.success() {
        return None;
    }
    let text = String::from_utf8(out.stdout).expect("paths are UTF-8");
    let files = text
        .split('\0')
        .filter(|p| !p.is_empty())
        .filter_map(|p| {
            // a file deleted in the work tree but not yet in the index is not weight
            let len = std::fs::metadata(repo().join(p)).ok()?.len();
            Some((p.to_string(), len))
        })
        .collect();
    Some(files)
}

#[test]
fn every_large_tracked_file_is_in_the_manifest_and_the_tree_is_under_its_ceiling() {
    let Some(files) = tracked_files() else {
        eprintln!("not a git checkout: nothing to check");
        return;
    };
    let listed = manifest::read(&repo().join("policies")).unwrap();
    let unlisted: Vec<String> = files
        .iter()
        .filter(|(_, len)| *len > LISTED_ABOVE_BYTES)
        .filter(|(p, _)| {
            p.strip_prefix("policies/")
                .is_none_or(|rel| !listed.contains_key(rel))
        })
        .map(|(p, len)| format!("{p} ({:.1} MB)", *len as f64 / 1e6))
        .collect();
    assert!(
        unlisted.is_empty(),
        "tracked files over {:.0} MB that policies/MANIFEST does not list (ship weights under \
         policies/ and run `rall checkpoint manifest policies`): {unlisted:?}",
        LISTED_ABOVE_BYTES as f64 / 1e6
    );
    let total: u64 = files.iter().map(|(_, len)| len).sum();
    assert!(
        total <= TREE_CEILING_BYTES,
        "the tracked tree is {:.1} MB, over its ceiling of {:.1} MB",
        total as f64 / 1e6,
        TREE_CEILING_BYTES as f64 / 1e6
    );
}

fn rall(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_rall"))
        .args(args)
        .current_dir(repo())
        .output()
        .unwrap()
}

#[test]
fn the_shipped_policies_match_their_manifest() {
    let out = rall(&["checkpoint", "verify", "policies"]);
    let text =
        String::from_utf8_lossy(&out.stdout).to_string() + &String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{text}");
    assert!(text.contains("match the manifest"), "{text}");
}

fn copy(from: &Path, to: &Path) {
    std::fs::create_dir_all(to.parent().unwrap()).unwrap();
    std::fs::copy(from, to).unwrap();
}

#[test]
fn a_changed_missing_or_unlisted_binary_is_named() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let src = repo().join("policies/time-to-walk.safetensors");
    copy(&src, &d.join("a/one.safetensors"));
    copy(&src, &d.join("two.safetensors"));
    let d_s = d.to_str().unwrap();
    let out = rall(&["checkpoint", "manifest", d_s]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let ok = rall(&["checkpoint", "verify", d_s]);
    assert!(
        ok.status.success(),
        "{}",
        String::from_utf8_lossy(&ok.stderr)
    );

    // one byte changed in a tensor, one file gone, one added
    let one = d.join("a/one.safetensors");
    let mut bytes = std::fs::read(&one).unwrap();
    let last = bytes.len() - 1;
    bytes[last] ^= 1;
    std::fs::write(&one, bytes).unwrap();
    std::fs::remove_file(d.join("two.safetensors")).unwrap();
    copy(&src, &d.join("three.safetensors"));
    let bad = rall(&["checkpoint", "verify", d_s]);
    let err = String::from_utf8_lossy(&bad.stderr).to_string();
    assert!(!bad.status.success(), "a tampered folder verified: {err}");
    for (file, what) in [
        ("one.safetensors", "manifest lists"),
        ("two.safetensors", "missing"),
        ("three.safetensors", "does not list"),
    ] {
        assert!(
            err.lines().any(|l| l.contains(file) && l.contains(what)),
            "{file}: expected a line saying {what:?} in {err}"
        );
    }
}

#[test]
fn a_folder_without_a_manifest_is_refused_with_the_command_that_writes_one() {
    let dir = tempfile::tempdir().unwrap();
    let out = rall(&["checkpoint", "verify", dir.path().to_str().unwrap()]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(
        err.contains("MANIFEST") && err.contains("rall checkpoint manifest"),
        "{err}"
    );
}
