//! `rall checkpoint`: what a checkpoint file holds, and its actor-only copy.

use std::path::{Path, PathBuf};

use anyhow::{bail, Result};
use clap::{Args, Subcommand};

use crate::learn::read_checkpoint;
use crate::runner::load_policy;
use crate::runner::policy_file::{is_actor_only, save_actor_only};

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
    }
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
    if read_checkpoint(out).is_ok_and(|c| !is_actor_only(&c.metadata)) {
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
        (true, _, _) => "actor only: evaluates, never resumes",
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
