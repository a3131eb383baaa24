//! `rall checkpoint`: what a checkpoint file holds, its slim copies (actor-only,
//! evaluation-only), and the manifest of shipped weights.

use std::path::{Path, PathBuf};

use anyhow::{bail, Result};
use clap::{Args, Subcommand};

use crate::learn::read_checkpoint;
use crate::runner::checkpoint_kinds::{is_run_state, save_actor_only, save_evaluation_only};
use crate::runner::load_policy;
use crate::runner::manifest;

#[derive(Debug, Args)]
pub struct CheckpointArgs {
    #[command(subcommand)]
    pub command: CheckpointCommand,
}

#[derive(Debug, Subcommand)]
pub enum CheckpointCommand {
    /// Print each file's iteration, env steps, method, run identity (id, seed,
    /// config hash), size, whether its checksums verify, and whether it resumes
    /// bit for bit, resumes inexactly or only acts.
    Info {
        #[arg(required = true)]
        files: Vec<PathBuf>,
    },
    /// Write the acting part of a checkpoint (actor, observation normaliser,
    /// config and progress; about a sixth of the size): enough to evaluate,
    /// never to resume.
    ActorOnly {
        /// The checkpoint to read.
        #[arg(long)]
        checkpoint: PathBuf,
        /// The file to write (written atomically).
        #[arg(long)]
        out: PathBuf,
    },
    /// Write what evaluation reads of a checkpoint (actor, critic, observation
    /// normaliser, config and progress; no optimiser moments or environment state,
    /// about a third of a PPO run state): every benchmark and critic analysis gives
    /// the same numbers as on the full file; it never resumes.
    EvaluationOnly {
        /// The checkpoint to read (a full one: it must hold the trained critic).
        #[arg(long)]
        checkpoint: PathBuf,
        /// The file to write (written atomically).
        #[arg(long)]
        out: PathBuf,
    },
    /// Write DIR/MANIFEST: the SHA-256 and size of every binary (.safetensors,
    /// .onnx) under DIR.
    Manifest { dir: PathBuf },
    /// Check every binary under DIR against DIR/MANIFEST (size and SHA-256; a
    /// missing, changed or unlisted file is named) and every listed checkpoint's
    /// tensor checksums; exit 1 when anything differs.
    Verify { dir: PathBuf },
}

pub fn run(args: &CheckpointArgs) -> Result<()> {
    match &args.command {
        CheckpointCommand::Info { files } => {
            for f in files {
                println!("{}", describe(f)?);
            }
            Ok(())
        }
        CheckpointCommand::ActorOnly { checkpoint, out } => {
            refuse_to_replace_a_run_state(checkpoint, out)?;
            save_actor_only(checkpoint, out)?;
            println!("{}", describe(out)?);
            Ok(())
        }
        CheckpointCommand::EvaluationOnly { checkpoint, out } => {
            refuse_to_replace_a_run_state(checkpoint, out)?;
            save_evaluation_only(checkpoint, out)?;
            println!("{}", describe(out)?);
            Ok(())
        }
        CheckpointCommand::Manifest { dir } => {
            let m = manifest::write(dir)?;
            let total: u64 = m.values().map(|e| e.size_bytes).sum();
            println!(
                "wrote {}: {} files, {:.1} MB",
                dir.join(manifest::MANIFEST).display(),
                m.len(),
                total as f64 / 1e6
            );
            Ok(())
        }
        CheckpointCommand::Verify { dir } => verify(dir),
    }
}

/// `rall checkpoint verify DIR`: the manifest's sizes and hashes, then each listed
/// checkpoint's own tensor checksums.
fn verify(dir: &Path) -> Result<()> {
    let (listed, mut problems) = manifest::check(dir)?;
    let mut lines: Vec<String> = problems.drain(..).map(|p| p.describe(dir)).collect();
    let mut unverified = 0;
    for rel in listed.keys().filter(|r| r.ends_with(".safetensors")) {
        let path = manifest::full_path(dir, rel);
        match read_checkpoint(&path) {
            Ok(c) if !c.verified => unverified += 1,
            Ok(_) => {}
            Err(e) if path.exists() => lines.push(format!("{}: {e:#}", path.display())),
            Err(_) => {} // already named as missing
        }
    }
    let total: u64 = listed.values().map(|e| e.size_bytes).sum();
    if !lines.is_empty() {
        for l in &lines {
            eprintln!("{l}");
        }
        bail!(
            "{} differs from {} in {} places (listed above)",
            dir.display(),
            dir.join(manifest::MANIFEST).display(),
            lines.len()
        );
    }
    println!(
        "{} files ({:.1} MB) match the manifest {}; {} checkpoints carry no tensor checksums of their own (written before checksums existed)",
        listed.len(),
        total as f64 / 1e6,
        dir.join(manifest::MANIFEST).display(),
        unverified
    );
    Ok(())
}

/// An actor-only copy never overwrites the checkpoint it is cut from, nor any
/// other file that still resumes a run.
fn refuse_to_replace_a_run_state(checkpoint: &Path, out: &Path) -> Result<()> {
    if !out.exists() {
        return Ok(());
    }
    if std::fs::canonicalize(out)? == std::fs::canonicalize(checkpoint)? {
        bail!(
            "--out {} is the checkpoint itself: an actor-only copy cannot replace the file it is read from",
            out.display()
        );
    }
    if read_checkpoint(out).is_ok_and(|c| is_run_state(&c.metadata)) {
        bail!(
            "--out {} already holds a full checkpoint (it resumes a run); remove it first or write elsewhere",
            out.display()
        );
    }
    Ok(())
}

/// One line about checkpoint `path`.
fn describe(path: &Path) -> Result<String> {
    let verified = read_checkpoint(path)?.verified;
    let p = load_policy(path)?;
    let bytes = std::fs::metadata(path)?.len();
    let contents = match (p.actor_only, p.exact, verified) {
        (true, _, _) => "actor only: evaluates, never resumes (no trained critic)",
        _ if p.evaluation_only => {
            "evaluation only: evaluates and analyses the critic, never resumes (no optimiser or environment state)"
        }
        (false, true, true) => "full: resumes bit for bit",
        (false, true, false) => {
            "full: resumes, unverified (without checksums nothing shows the state is intact)"
        }
        (false, false, _) => "full: resumes, not bit for bit (no runner state)",
    };
    let learner = &p.config.learner;
    let critic = format!("{:?}", learner.critic).to_lowercase();
    let method = match learner.risk_label() {
        label if label == critic => format!("{critic} critic"),
        label => format!("{critic} critic ({label})"),
    };
    let identity = match &p.progress.identity {
        Some(id) => id.describe(),
        None => "run identity not recorded (older file)".into(),
    };
    Ok(format!(
        "{}: iteration {}, {:.1} M env steps, {method}, {identity}, {:.1} MB, {}, {contents}",
        path.display(),
        p.progress.iteration,
        p.progress.total_env_steps as f64 / 1e6,
        bytes as f64 / 1e6,
        if verified {
            "checksums verified"
        } else {
            "no checksums: unverified"
        },
    ))
}
