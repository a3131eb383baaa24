//! Training an experiment's runs: each run that is not done, in file order,
//! resumed where it stopped; RMA's two phases; each finished run's final policy
//! chosen while the checkpoints its rule needs still exist.

use std::path::Path;
use std::sync::atomic::AtomicBool;
use std::sync::Arc;

use anyhow::{bail, Context, Result};

use super::final_policy::{choose_final_policy, selected_in};
use super::selection;
use super::ship::{has_checkpoints, restore_shipped};
use super::spec::{self, ExperimentSpec};
use super::{run_config, run_state};
use crate::config::TrainConfig;
use crate::eval::{evaluate_tracking, tracking_env, ActionMode, NamedPolicy};
use crate::runner::{install_teacher, train, PhaseOneOnly, RunDir, TrainSummary};

/// Trains every run that is not done, in file order; stops (resumably) on a signal.
pub fn train_all(spec: &ExperimentSpec, stop: Arc<AtomicBool>) -> Result<()> {
    let n = spec.runs.len();
    for (k, r) in spec.runs.iter().enumerate() {
        if restore_shipped(spec, r)? {
            eprintln!("{}: starting from its shipped checkpoint", r.label);
        }
        let state = run_state(spec, r)?;
        let head = format!("[run {}/{n}] {} ({})", k + 1, r.label, state.dir.display());
        if state.done() {
            eprintln!("{head}: done ({} iterations), skipped", state.target);
            choose_while_the_window_exists(spec, r)?;
            continue;
        }
        let cfg = run_config(spec, r)?;
        let resume = state.progress.is_some();
        if resume
            && !has_checkpoints(&RunDir {
                root: state.dir.clone(),
            })
        {
            bail!(
                "{head}: its budget is {} iterations, but it was shipped finished at {} as an \
                 evaluation copy (actor only), which cannot be trained further: continue it where its \
                 full training state is (the run directory it was trained in), or train it anew \
                 under a new name",
                state.target,
                state.progress.as_ref().map_or(0, |p| p.iteration)
            );
        }
        match &state.progress {
            Some(p) => {
                let per_it = p.wall_s / p.iteration.max(1) as f64;
                let left = state.target.saturating_sub(p.iteration);
                eprintln!(
                    "{head}: resuming at iteration {} of {}; about {:.0} min left at its pace so far",
                    p.iteration,
                    state.target,
                    left as f64 * per_it / 60.0
                );
            }
            None => eprintln!("{head}: starting ({} iterations)", state.target),
        }
        let summary = match &spec.selection {
            Some(sel) if cfg.learner.adaptation.is_some() => {
                let at = state.progress.as_ref().map(|p| p.iteration);
                train_rma(spec, r, sel, cfg, at, stop.clone())
            }
            _ => train(cfg, &state.dir, resume, stop.clone(), &mut ()),
        }
        .with_context(|| format!("training run {:?}", r.label))?;
        if summary.interrupted {
            bail!(
                "interrupted during run {:?} at iteration {}; the same command continues it",
                r.label,
                summary.iterations_done
            );
        }
        choose_while_the_window_exists(spec, r)?;
    }
    Ok(())
}

/// RMA under `[selection]`, from its stored iteration (`None`: nothing to resume):
/// phase 1, then its teacher chosen by the same rule among phase 1's last
/// checkpoints and installed, then phase 2 on that teacher. A run stopped at the
/// end of phase 1 chooses (or reuses its stored choice) and installs again:
/// installing the same teacher twice changes nothing.
fn train_rma(
    spec: &ExperimentSpec,
    r: &spec::RunSpec,
    sel: &selection::SelectionSpec,
    cfg: TrainConfig,
    stored_at: Option<usize>,
    stop: Arc<AtomicBool>,
) -> Result<TrainSummary> {
    let dir = spec.run_dir(r);
    let phase1_end = cfg.runner.iterations;
    let mut at = stored_at.unwrap_or(0);
    if at < phase1_end {
        let s = train(
            cfg.clone(),
            &dir,
            stored_at.is_some(),
            stop.clone(),
            &mut PhaseOneOnly(&mut ()),
        )?;
        if s.interrupted {
            return Ok(s);
        }
        at = s.iterations_done;
    }
    if at == phase1_end {
        let rd = RunDir { root: dir.clone() };
        let chosen = match selection::stored_teacher(&dir, sel, phase1_end) {
            Some(it) => it,
            None => {
                eprintln!(
                    "  {}: choosing its teacher ([selection] over phase 1's checkpoints)",
                    r.label
                );
                let threads = crate::config::worker_threads(spec.threads);
                let c = selection::select_as(
                    &dir,
                    sel,
                    phase1_end,
                    selection::Choice::Teacher,
                    validation(sel, &r.label, threads),
                )?;
                c.iteration
            }
        };
        let file = selection::checkpoint_of(&dir, chosen, phase1_end, selection::Choice::Teacher)
            .with_context(|| {
            format!(
                "{}: the chosen teacher's checkpoint (iteration {chosen}) is gone",
                dir.display()
            )
        })?;
        install_teacher(&rd, &file)?;
        eprintln!(
            "  {}: phase 2 trains on the teacher of iteration {chosen}",
            r.label
        );
    }
    train(cfg, &dir, true, stop, &mut ())
}

/// A candidate's validation: `[selection]`'s tracking episodes (own randomisation,
/// mean actions) of the checkpoint at a path.
pub(super) fn validation<'a>(
    sel: &'a selection::SelectionSpec,
    label: &'a str,
    threads: usize,
) -> impl FnMut(&Path) -> Result<selection::Candidate> + 'a {
    move |path| {
        let p = NamedPolicy::load(label, path)?;
        let t = evaluate_tracking(
            &p.policy,
            &tracking_env(&p.env),
            sel.episodes,
            threads,
            sel.seed,
            ActionMode::Mean,
        )?;
        Ok(selection::Candidate {
            iteration: 0,
            fall_rate: t.fall_rate,
            lin_vel_score: t.lin_vel_score,
            yaw_rate_score: t.yaw_rate_score,
        })
    }
}

/// A finished run's final policy is chosen as soon as training ends: the
/// candidates are checkpoints of the run directory, which is not shipped, so a
/// later checkout (a fresh clone) may no longer have them. A run whose window is
/// gone is left to the evaluation, which refuses it naming the missing checkpoint.
fn choose_while_the_window_exists(spec: &ExperimentSpec, r: &spec::RunSpec) -> Result<()> {
    let Some(sel) = &spec.selection else {
        return Ok(());
    };
    let state = run_state(spec, r)?;
    if !state.done() || selected_in(spec, r, &state).is_some() {
        return Ok(());
    }
    let rd = RunDir {
        root: state.dir.clone(),
    };
    let window_complete = sel
        .candidates(state.target)
        .iter()
        .all(|&it| rd.checkpoint(it).exists() || it == state.target);
    if !window_complete {
        eprintln!(
            "  {}: its final policy cannot be chosen: the run directory lacks checkpoints of iterations {}-{} ([selection]); the evaluation will refuse it",
            r.label,
            sel.candidates(state.target)[0],
            state.target
        );
        return Ok(());
    }
    eprintln!("  {}: choosing its final policy ([selection])", r.label);
    choose_final_policy(spec, r, crate::config::worker_threads(spec.threads))
}
