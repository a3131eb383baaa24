//! A run's checkpoints as evaluation reads them: its newest, its final policy
//! (`[selection]`'s choice, else the newest) and loading them by label.

use std::path::PathBuf;

use anyhow::{Context, Result};

use super::selection;
use super::ship::has_checkpoints;
use super::spec::{self, ExperimentSpec};
use super::training::validation;
use super::{run_config, run_state, RunState};
use crate::eval::NamedPolicy;
use crate::runner::RunDir;

/// The newest readable checkpoint of run `r`: in its run directory, else its
/// shipped copy (its `latest`, or for a finished run shipped as its numbered
/// actor-only checkpoints alone, the newest of those); `None` when it has none.
pub fn newest_checkpoint(spec: &ExperimentSpec, r: &spec::RunSpec) -> Result<Option<PathBuf>> {
    let rd = RunDir {
        root: spec.run_dir(r),
    };
    if has_checkpoints(&rd) {
        return Ok(Some(rd.resume_point()?.0));
    }
    let Some(root) = spec.shipped_copy(r) else {
        return Ok(None);
    };
    let copy = RunDir { root };
    if copy.latest().exists() {
        return Ok(Some(copy.latest()));
    }
    Ok(copy.checkpoints_by_iteration().pop().map(|(_, path)| path))
}

/// The chosen final policy of finished run `r` under `[selection]` (its file and
/// iteration): in its run directory, else in its shipped copy; `None` without
/// `[selection]`, for an unfinished run, or when it has not been chosen yet
/// ([`choose_final_policies`]).
pub(super) fn selected_in(
    spec: &ExperimentSpec,
    r: &spec::RunSpec,
    state: &RunState,
) -> Option<(PathBuf, usize)> {
    let sel = spec.selection.as_ref()?;
    if !state.done() {
        return None;
    }
    selection::stored(&choices_dir(spec, r, state)?, sel, state.target)
}

/// Where run `r`'s stored choices are read: its run directory, or its shipped copy
/// when the run directory has no checkpoints (as for [`newest_checkpoint`]): a run
/// trained anew must not get an old choice. `None` when neither exists.
fn choices_dir(spec: &ExperimentSpec, r: &spec::RunSpec, state: &RunState) -> Option<PathBuf> {
    if has_checkpoints(&RunDir {
        root: state.dir.clone(),
    }) {
        return Some(state.dir.clone());
    }
    spec.shipped_copy(r)
}

/// The file of run `r`'s chosen final policy ([`selected_in`]).
pub fn selected_checkpoint(spec: &ExperimentSpec, r: &spec::RunSpec) -> Result<Option<PathBuf>> {
    if spec.selection.is_none() {
        return Ok(None);
    }
    Ok(selected_in(spec, r, &run_state(spec, r)?).map(|(path, _)| path))
}

/// The final policy of every finished run by the experiment's `[selection]` rule:
/// reuses a stored choice made under the same rule, else tracks each candidate
/// checkpoint on the validation episodes and stores the choice in the run directory.
pub fn choose_final_policies(spec: &ExperimentSpec, threads: usize) -> Result<()> {
    for r in &spec.runs {
        choose_final_policy(spec, r, threads)?;
    }
    Ok(())
}

/// [`choose_final_policies`] for run `r` alone (nothing to do when it is not
/// finished, has its choice already, or the experiment has no `[selection]`).
pub(super) fn choose_final_policy(
    spec: &ExperimentSpec,
    r: &spec::RunSpec,
    threads: usize,
) -> Result<()> {
    let Some(sel) = &spec.selection else {
        return Ok(());
    };
    let state = run_state(spec, r)?;
    if !state.done() || selected_in(spec, r, &state).is_some() {
        return Ok(());
    }
    let chosen = selection::select(
        &state.dir,
        sel,
        state.target,
        validation(sel, &r.label, threads),
    )
    .with_context(|| format!("run {:?}", r.label))?;
    eprintln!(
        "  {}: final policy = iteration {} ({:.1}% falls on validation)",
        r.label,
        chosen.iteration,
        100.0 * chosen.fall_rate
    );
    Ok(())
}

/// Names every finished RMA run whose teacher `[selection]` did not choose (a run
/// trained before the rule reached teachers): its student learnt from phase 1's
/// last checkpoint, whatever it fell.
pub(super) fn warn_unchosen_teachers(
    spec: &ExperimentSpec,
    runs: &[(spec::RunSpec, RunState)],
) -> Result<()> {
    let Some(sel) = &spec.selection else {
        return Ok(());
    };
    for (r, state) in runs {
        if !state.done() || run_config(spec, r)?.learner.adaptation.is_none() {
            continue;
        }
        let dir = choices_dir(spec, r, state).unwrap_or_else(|| state.dir.clone());
        if selection::stored_teacher(&dir, sel, r.iterations).is_none() {
            eprintln!(
                "  warning: {}: its teacher was not chosen by [selection] (no {} in {}): phase 2 trained on phase 1's last checkpoint",
                r.label,
                selection::TEACHER_SELECTION_CSV,
                dir.display()
            );
        }
    }
    Ok(())
}

/// The final policy of the run labelled `label`: the chosen one under
/// `[selection]` (with its iteration), else the latest.
pub(super) fn load_final_policy(
    spec: &ExperimentSpec,
    label: &str,
) -> Result<(NamedPolicy, Option<usize>)> {
    let r = spec
        .run(label)
        .with_context(|| format!("no run labelled {label:?}"))?;
    let chosen = match spec.selection {
        Some(_) => selected_in(spec, r, &run_state(spec, r)?),
        None => None,
    };
    let (path, iteration) = match chosen {
        Some((path, it)) => (path, Some(it)),
        None => (
            newest_checkpoint(spec, r)?
                .with_context(|| format!("run {label:?} has no checkpoint yet: train it first"))?,
            None,
        ),
    };
    Ok((NamedPolicy::load(label, &path)?, iteration))
}

/// [`load_final_policy`] without the iteration.
pub(super) fn load_run(spec: &ExperimentSpec, label: &str) -> Result<NamedPolicy> {
    load_final_policy(spec, label).map(|(p, _)| p)
}

pub(super) fn load_runs(spec: &ExperimentSpec, labels: &[String]) -> Result<Vec<NamedPolicy>> {
    labels.iter().map(|l| load_run(spec, l)).collect()
}
