//! Shipping runs with the repository: `--ship` copies each run's files and the
//! checkpoints evaluation needs to the experiment's `shipped_dir` (a finished,
//! chosen run as actor-only copies and its final policy as an evaluation file,
//! without optimiser state), rewrites the enclosing `MANIFEST`, and a fresh clone
//! restores unfinished runs into `runs/` (finished ones are read where they are).

use std::path::Path;

use anyhow::{Context, Result};

use super::final_policy::selected_in;
use super::spec::{self, ExperimentSpec};
use super::{last_checkpoints, selection};
use super::{run_state, run_target};
use crate::fsio::copy_atomic;
use crate::runner::checkpoint_kinds::{is_actor_only, save_actor_only, save_evaluation_only};
use crate::runner::manifest;
use crate::runner::{RunDir, LATEST};

/// Files of a run that travel with its checkpoint.
pub(super) const SHIPPED_FILES: [&str; 6] = [
    "config.toml",
    "metrics.csv",
    "adaptation.csv",
    selection::TEACHER_SELECTION_CSV,
    selection::SELECTION_CSV,
    selection::SELECTED,
];

/// Whether a run directory holds checkpoints of its own (else its shipped copy
/// stands in for it).
pub(super) fn has_checkpoints(rd: &RunDir) -> bool {
    rd.latest().exists() || rd.root.join("checkpoints").exists()
}

/// Copies the files that travel with a checkpoint from run directory `run` to its
/// shipped copy `dst`, and removes those the run does not have: a run trained anew
/// under an old run's name must not ship the old run's `adaptation.csv`.
pub(super) fn ship_files(run: &Path, dst: &Path) -> Result<()> {
    for f in SHIPPED_FILES {
        if f == selection::SELECTED && run.join(f).exists() {
            // evaluation reads its actor, critic and normaliser, never its optimiser
            save_evaluation_only(&run.join(f), &dst.join(f))?;
        } else if run.join(f).exists() {
            copy_atomic(&run.join(f), &dst.join(f))?;
        } else if dst.join(f).exists() {
            std::fs::remove_file(dst.join(f))
                .with_context(|| format!("removing the stale {}", dst.join(f).display()))?;
        }
    }
    Ok(())
}

/// Whether checkpoint `path` holds the actor alone (unreadable: no).
fn holds_actor_only(path: &Path) -> bool {
    crate::learn::read_checkpoint(path).is_ok_and(|c| is_actor_only(&c.metadata))
}

/// A run absent from `runs_dir` starts from its shipped checkpoint, if any.
/// Returns whether it was restored.
pub fn restore_shipped(spec: &ExperimentSpec, r: &spec::RunSpec) -> Result<bool> {
    let Some(src) = spec.shipped_copy(r) else {
        return Ok(false);
    };
    let dst = spec.run_dir(r);
    if has_checkpoints(&RunDir { root: dst.clone() })
        || !src.join(LATEST).exists()
        || holds_actor_only(&src.join(LATEST))
    {
        // a finished run shipped for evaluation is read where it is
        return Ok(false);
    }
    std::fs::create_dir_all(&dst).with_context(|| format!("creating {}", dst.display()))?;
    for f in SHIPPED_FILES.iter().copied().chain([LATEST]) {
        if src.join(f).exists() {
            copy_atomic(&src.join(f), &dst.join(f))?;
        }
    }
    Ok(true)
}

/// Copies every run's newest readable checkpoint (as `latest.safetensors`) with
/// its config and metrics into its shipped copy (`shipped_dir`, or the run's own
/// `shipped` folder), with a README saying how it was made.
pub fn ship_all(spec: &ExperimentSpec, file: &Path) -> Result<()> {
    for r in &spec.runs {
        let rd = RunDir {
            root: spec.run_dir(r),
        };
        let Ok((ckpt, loaded)) = rd.resume_point() else {
            continue;
        };
        let state = run_state(spec, r)?;
        let dst = spec.shipped_copy(r).with_context(|| {
            format!("run {:?}: the experiment file sets no shipped_dir", r.label)
        })?;
        std::fs::create_dir_all(&dst).with_context(|| format!("creating {}", dst.display()))?;
        if loaded.progress.iteration >= state.target && selected_in(spec, r, &state).is_some() {
            // finished and its final policy chosen: evaluation reads `selected` (actor,
            // critic and normaliser) and the headline checkpoints, never resumes it
            save_actor_only(&ckpt, &dst.join(LATEST))?;
        } else {
            copy_atomic(&ckpt, &dst.join(LATEST))?;
        }
        ship_files(&rd.root, &dst)?;
        // kept whether or not `[checkpoints]` is on yet, so that it can be turned on later
        let keep = spec.checkpoints.clone().unwrap_or(spec::CheckpointsSpec {
            last: 5,
            every: 100,
            milestones: Vec::new(),
        });
        ship_headline_checkpoints(spec, &keep, r, &rd, &dst)?;
        let p = &loaded.progress;
        let chosen = match selected_in(spec, r, &state) {
            Some((_, it)) => format!(
                "\n\nIts final policy is `{}`, the checkpoint of iteration {it}, chosen by the experiment's `[selection]` rule (`{}` lists every candidate).",
                selection::SELECTED,
                selection::SELECTION_CSV
            ),
            None => String::new(),
        };
        let teacher = spec
            .selection
            .as_ref()
            .and_then(|sel| selection::stored_teacher(&rd.root, sel, r.iterations))
            .map(|it| {
                format!(
                    " Its phase 2 trained on the teacher of iteration {it}, chosen by the same rule (`{}`).",
                    selection::TEACHER_SELECTION_CSV
                )
            })
            .unwrap_or_default();
        let chosen = chosen + &teacher;
        let text = format!(
            "# {label}\n\n`{config}`, seed {seed}: iteration {it} of {target}{unfinished}, {steps:.1} M env steps, {h:.2} h of training.{chosen}\n\nMade by `rall experiment {file}` (run `{name}`); {next}.\n",
            label = r.label,
            config = r.config.display(),
            seed = r.seed,
            it = p.iteration,
            target = state.target,
            unfinished = if p.iteration < state.target { " (unfinished)" } else { "" },
            steps = p.total_env_steps as f64 / 1e6,
            h = p.wall_s / 3600.0,
            file = file.display(),
            name = spec.run_dir_name(r),
            next = if p.iteration < state.target {
                format!("`rall experiment {}` resumes it from here", file.display())
            } else {
                format!("`rall experiment {} --eval-only` evaluates it from here", file.display())
            },
        );
        crate::fsio::write_atomic(&dst.join("README.md"), text.as_bytes())?;
        eprintln!(
            "shipped {} (iteration {}) to {}",
            r.label,
            p.iteration,
            dst.display()
        );
    }
    if let Some(dir) = spec.shipped_dir.as_deref() {
        refresh_manifest(dir)?;
    }
    Ok(())
}

/// Rewrites the manifest of the folder that holds `shipped` (the nearest
/// ancestor with a `MANIFEST`), so that what was shipped is listed with its hash.
fn refresh_manifest(shipped: &Path) -> Result<()> {
    let mut dir = Some(shipped);
    while let Some(d) = dir {
        if d.join(manifest::MANIFEST).exists() {
            let m = manifest::write(d)?;
            eprintln!(
                "rewrote {} ({} files)",
                d.join(manifest::MANIFEST).display(),
                m.len()
            );
            return Ok(());
        }
        dir = d.parent().filter(|p| !p.as_os_str().is_empty());
    }
    Ok(())
}

/// Actor-only copies of run `r`'s headline checkpoints and milestones (`c`) that
/// its run directory holds, into `dst/checkpoints/`: what evaluating them needs.
fn ship_headline_checkpoints(
    spec: &ExperimentSpec,
    c: &spec::CheckpointsSpec,
    r: &spec::RunSpec,
    rd: &RunDir,
    dst: &Path,
) -> Result<()> {
    let target = run_target(spec, r)?;
    for it in shipped_iterations(c, target) {
        let name = format!("model_{it:06}.safetensors");
        let src = rd.root.join("checkpoints").join(&name);
        if src.exists() {
            save_actor_only(&src, &dst.join("checkpoints").join(&name))?;
        }
    }
    Ok(())
}

/// The iterations whose checkpoints a run of `target` iterations ships: its
/// headline checkpoints, then its milestones before the target.
fn shipped_iterations(c: &spec::CheckpointsSpec, target: usize) -> Vec<usize> {
    let mut its = last_checkpoints::headline_iterations(c, target).unwrap_or_default();
    for &m in &c.milestones {
        if m > 0 && m < target && !its.contains(&m) {
            its.push(m);
        }
    }
    its
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn milestones_ship_beside_the_headline_checkpoints() {
        let c = spec::CheckpointsSpec {
            last: 2,
            every: 100,
            milestones: vec![1500, 3000, 4500, 9000, 0],
        };
        assert_eq!(shipped_iterations(&c, 4500), vec![4500, 4400, 1500, 3000]);
        let none = spec::CheckpointsSpec {
            milestones: Vec::new(),
            ..c
        };
        assert_eq!(shipped_iterations(&none, 4500), vec![4500, 4400]);
    }

    #[test]
    fn shipping_removes_files_the_run_no_longer_has() {
        let dir = tempfile::tempdir().unwrap();
        let (run, dst) = (dir.path().join("run"), dir.path().join("shipped"));
        std::fs::create_dir_all(&run).unwrap();
        std::fs::create_dir_all(&dst).unwrap();
        // the shipped copy of an older run of the same name, with a phase-2 log
        for f in SHIPPED_FILES {
            std::fs::write(dst.join(f), "old").unwrap();
        }
        // the new run has not reached phase 2
        std::fs::write(run.join("config.toml"), "new config").unwrap();
        std::fs::write(run.join("metrics.csv"), "new metrics").unwrap();
        ship_files(&run, &dst).unwrap();
        let read = |f: &str| std::fs::read_to_string(dst.join(f)).unwrap();
        assert_eq!(read("config.toml"), "new config");
        assert_eq!(read("metrics.csv"), "new metrics");
        assert!(!dst.join("adaptation.csv").exists());
        assert!(!dst.join("adaptation.csv.tmp").exists());
    }
}
