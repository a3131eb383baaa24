//! `rall experiment FILE`: the paper's campaign from one file. Trains what is
//! missing, resumes what is unfinished, skips what is done; then evaluates every
//! policy with the paper's protocol (tracking, table I TTF, table II platform
//! drops, race track with the IQR meta controller) and writes tables beside the
//! paper's numbers, CSV/JSON with every cell, bootstrap intervals and figures.

mod clock;
pub mod contrasts;
pub mod curve_plots;
pub mod curves;
pub mod kcheck;
mod ladder;
pub mod plots;
pub mod pooled;
pub mod results;
pub mod risk_signal;
pub mod selection;
pub mod spec;
pub mod stats;

use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;
use std::sync::Arc;

use anyhow::{bail, Context, Result};

use crate::config::TrainConfig;
use crate::env::{build_scene, EnvConfig, VecEnv};
use crate::eval::{
    evaluate_race, evaluate_tracking, tracking_env, with_randomization, ActionMode, GroundKind,
    Load, MetaConfig, NamedPolicy, PlatformOptions, RaceOptions, ScenarioParams, TtfOptions,
};
use crate::runner::policy_file::{is_actor_only, save_actor_only};
use crate::runner::{install_teacher, train, PhaseOneOnly, Progress, RunDir, TrainSummary, LATEST};
use clock::PhaseClock;
pub use clock::PhaseTime;
pub use results::{ExperimentResults, RunTracking, TrackingEstimates};
pub use spec::ExperimentSpec;
use spec::MetaSpec;

/// What to do.
#[derive(Debug, Clone)]
pub struct ExperimentOptions {
    pub train: bool,
    pub evaluate: bool,
    /// Evaluate unfinished runs at their latest checkpoint instead of refusing.
    pub allow_unfinished: bool,
}

/// A run's state on disk.
#[derive(Debug, Clone)]
pub struct RunState {
    pub dir: PathBuf,
    /// Iterations to reach (PPO + RMA's phase 2).
    pub target: usize,
    pub progress: Option<Progress>,
}

impl RunState {
    pub fn done(&self) -> bool {
        self.progress
            .as_ref()
            .is_some_and(|p| p.iteration >= self.target)
    }
}

/// The config of run `r` as the experiment trains it.
pub fn run_config(spec: &ExperimentSpec, r: &spec::RunSpec) -> Result<TrainConfig> {
    let mut cfg =
        TrainConfig::from_toml_file(&r.config).with_context(|| format!("run {:?}", r.label))?;
    cfg.runner.seed = r.seed;
    cfg.runner.iterations = r.iterations;
    cfg.runner.threads = spec.threads;
    Ok(cfg)
}

/// The iterations run `r` with config `cfg` trains to: PPO's, then RMA's phase 2.
fn target_iterations(r: &spec::RunSpec, cfg: &TrainConfig) -> usize {
    r.iterations + cfg.learner.adaptation.as_ref().map_or(0, |a| a.iterations)
}

/// The iterations run `r` trains to, from its config alone (no checkpoint read).
pub fn run_target(spec: &ExperimentSpec, r: &spec::RunSpec) -> Result<usize> {
    Ok(target_iterations(r, &run_config(spec, r)?))
}

/// Where run `r` stands (reads its newest readable checkpoint).
pub fn run_state(spec: &ExperimentSpec, r: &spec::RunSpec) -> Result<RunState> {
    let cfg = run_config(spec, r)?;
    let target = target_iterations(r, &cfg);
    let dir = spec.run_dir(r);
    let progress = match newest_checkpoint(spec, r)? {
        Some(path) => {
            let loaded = crate::runner::load_policy(&path)?;
            // what a resume would train: the stored config with this budget and last stage
            let stored = crate::runner::train::keep_runner_settings(
                loaded.config.clone(),
                &cfg,
                loaded.progress.iteration,
            )
            .with_context(|| format!("run {:?} ({})", r.label, path.display()))?;
            let changed = learning_differences(&stored, &cfg);
            if !changed.is_empty() {
                bail!(
                    "run {:?}: its checkpoint {} was trained with another config than {} now gives \
                     (differs in {}); move the run's directory away (and its shipped copy) to \
                     retrain it, or give the run a new name",
                    r.label,
                    path.display(),
                    r.config.display(),
                    changed.join(", ")
                );
            }
            Some(loaded.progress)
        }
        None => None,
    };
    Ok(RunState {
        dir,
        target,
        progress,
    })
}

/// Dotted keys in which two run configs differ, leaving out the runner keys that
/// do not change what is learned (budget, threads, logging and checkpoint cadence)
/// and the history group RMA's phase 2 adds.
pub fn learning_differences(a: &TrainConfig, b: &TrainConfig) -> Vec<String> {
    let comparable = |c: &TrainConfig| {
        let mut c = c.clone();
        c.runner.iterations = 0;
        c.runner.threads = 0;
        c.runner.save_interval = 1;
        c.runner.log_interval = 1;
        c.runner.runs_dir.clear();
        // RMA's phase 2 adds the history group itself (runner::adapt)
        if c.learner.adaptation.is_some() {
            let history = crate::env::observation::ObsGroup::History;
            c.env.observation.groups.retain(|g| *g != history);
        }
        toml::Value::try_from(c).ok()
    };
    let mut out = Vec::new();
    match (comparable(a), comparable(b)) {
        (Some(x), Some(y)) => value_differences("", &x, &y, &mut out),
        _ => out.push("(a config that cannot be written as TOML)".into()),
    }
    out
}

fn value_differences(at: &str, a: &toml::Value, b: &toml::Value, out: &mut Vec<String>) {
    match (a, b) {
        (toml::Value::Table(x), toml::Value::Table(y)) => {
            let mut keys: Vec<&String> = x.keys().chain(y.keys()).collect();
            keys.sort();
            keys.dedup();
            for k in keys {
                let key = if at.is_empty() {
                    k.clone()
                } else {
                    format!("{at}.{k}")
                };
                match (x.get(k), y.get(k)) {
                    (Some(u), Some(v)) => value_differences(&key, u, v, out),
                    _ => out.push(key),
                }
            }
        }
        _ if a != b => out.push(at.to_string()),
        _ => {}
    }
}

/// Files of a run that travel with its checkpoint.
const SHIPPED_FILES: [&str; 6] = [
    "config.toml",
    "metrics.csv",
    "adaptation.csv",
    selection::TEACHER_SELECTION_CSV,
    selection::SELECTION_CSV,
    selection::SELECTED,
];

/// Copies `from` to `to` through a temp file and a rename.
fn copy_atomic(from: &Path, to: &Path) -> Result<()> {
    let tmp = to.with_extension("copy.tmp");
    std::fs::copy(from, &tmp)
        .with_context(|| format!("copying {} to {}", from.display(), tmp.display()))?;
    std::fs::rename(&tmp, to).with_context(|| format!("writing {}", to.display()))
}

/// Writes `text` to `path` through a temp file and a rename.
fn write_atomic(path: &Path, text: &str) -> Result<()> {
    crate::fsio::write_atomic(path, text.as_bytes())
}

/// Whether a run directory holds checkpoints of its own (else its shipped copy
/// stands in for it).
fn has_checkpoints(rd: &RunDir) -> bool {
    rd.latest().exists() || rd.root.join("checkpoints").exists()
}

/// Copies the files that travel with a checkpoint from run directory `run` to its
/// shipped copy `dst`, and removes those the run does not have: a run trained anew
/// under an old run's name must not ship the old run's `adaptation.csv`.
fn ship_files(run: &Path, dst: &Path) -> Result<()> {
    for f in SHIPPED_FILES {
        if run.join(f).exists() {
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
            // finished and its final policy chosen: evaluation reads `selected` (whole,
            // critic included) and the headline checkpoints, never resumes it
            save_actor_only(&ckpt, &dst.join(LATEST))?;
        } else {
            copy_atomic(&ckpt, &dst.join(LATEST))?;
        }
        ship_files(&rd.root, &dst)?;
        // kept whether or not `[checkpoints]` is on yet, so that it can be turned on later
        let keep = spec.checkpoints.clone().unwrap_or(spec::CheckpointsSpec {
            last: 5,
            every: 100,
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
    Ok(())
}

/// Actor-only copies of run `r`'s headline checkpoints (`c`) that its run
/// directory holds, into `dst/checkpoints/`: what evaluating them needs.
fn ship_headline_checkpoints(
    spec: &ExperimentSpec,
    c: &spec::CheckpointsSpec,
    r: &spec::RunSpec,
    rd: &RunDir,
    dst: &Path,
) -> Result<()> {
    let target = run_target(spec, r)?;
    let Ok(iterations) = kcheck::headline_iterations(c, target) else {
        return Ok(());
    };
    for it in iterations {
        let name = format!("model_{it:06}.safetensors");
        let src = rd.root.join("checkpoints").join(&name);
        if src.exists() {
            save_actor_only(&src, &dst.join("checkpoints").join(&name))?;
        }
    }
    Ok(())
}

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
fn validation<'a>(
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
fn selected_in(
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
fn choose_final_policy(spec: &ExperimentSpec, r: &spec::RunSpec, threads: usize) -> Result<()> {
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
fn warn_unchosen_teachers(spec: &ExperimentSpec, runs: &[(spec::RunSpec, RunState)]) -> Result<()> {
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
fn load_final_policy(spec: &ExperimentSpec, label: &str) -> Result<(NamedPolicy, Option<usize>)> {
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
fn load_run(spec: &ExperimentSpec, label: &str) -> Result<NamedPolicy> {
    load_final_policy(spec, label).map(|(p, _)| p)
}

fn load_runs(spec: &ExperimentSpec, labels: &[String]) -> Result<Vec<NamedPolicy>> {
    labels.iter().map(|l| load_run(spec, l)).collect()
}

fn seeds(first: u64, n: usize) -> Vec<u64> {
    (first..first + n as u64).collect()
}

fn parse_load(s: &str) -> Result<Load> {
    Load::PAYLOADS
        .into_iter()
        .find(|l| l.name() == s)
        .with_context(|| format!("ttf.loads: unknown load {s:?} (ball, frozen_arm, moving_arm)"))
}

/// The meta controller's threshold by the experiment's rule: a quantile of the
/// risky critic's IQR over robots walking one episode on flat ground.
pub fn calibrate_threshold(m: &MetaSpec, risky: &NamedPolicy, threads: usize) -> Result<f32> {
    let critic = risky.critic()?.config().critic;
    anyhow::ensure!(
        critic.has_quantiles(),
        "meta.risky = {:?} has a {critic} critic: the meta controller needs the IQR of a value distribution (a critic with quantiles, such as IQN)",
        m.risky
    );
    let cfg = tracking_env(&risky.env);
    let scene = build_scene(&cfg, m.calibration_seed)?;
    let n = m.calibration_robots.max(1);
    let mut venv = VecEnv::new(
        Arc::new(cfg.clone()),
        &scene.model,
        scene.terrain.clone(),
        n,
        threads,
        m.calibration_seed,
    )?;
    let mut obs = venv.batch().obs.clone();
    let mut iqrs = Vec::new();
    for _ in 0..cfg.max_episode_steps() {
        let critic = risky.critic()?;
        iqrs.extend(critic.iqr(&obs).iter().map(|&v| v as f64));
        let actions = critic.act_mean(&obs);
        obs.copy_from_slice(&venv.step(&actions).obs);
    }
    let t = stats::quantile(&iqrs, m.threshold_quantile);
    anyhow::ensure!(
        t.is_finite(),
        "meta.risky = {:?}: its critic's IQR is {t}",
        m.risky
    );
    Ok(t as f32)
}

/// The runs to evaluate with their states; an unfinished one is refused unless
/// `opts.allow_unfinished`.
fn runs_to_evaluate(
    spec: &ExperimentSpec,
    opts: &ExperimentOptions,
) -> Result<Vec<(spec::RunSpec, RunState)>> {
    let mut runs = Vec::new();
    for r in &spec.runs {
        let state = run_state(spec, r)?;
        if !state.done() && !opts.allow_unfinished {
            bail!(
                "run {:?} is not finished ({} of {} iterations): train it (`rall experiment FILE`) or evaluate it as it is with --allow-unfinished",
                r.label,
                state.progress.as_ref().map_or(0, |p| p.iteration),
                state.target
            );
        }
        runs.push((r.clone(), state));
    }
    Ok(runs)
}

/// Labels of the runs with a checkpoint (with --allow-unfinished, the others are left out).
fn runs_with_checkpoints(
    spec: &ExperimentSpec,
    runs: &[(spec::RunSpec, RunState)],
) -> Result<Vec<String>> {
    let mut available = Vec::new();
    for (r, _) in runs {
        if newest_checkpoint(spec, r)?.is_some() {
            available.push(r.label.clone());
        } else {
            eprintln!("  {} has no checkpoint yet: left out", r.label);
        }
    }
    Ok(available)
}

/// Every available run's final policy tracked under its own randomisation and
/// each common one.
fn track_all(
    spec: &ExperimentSpec,
    runs: &[(spec::RunSpec, RunState)],
    available: &[String],
    threads: usize,
) -> Result<Vec<RunTracking>> {
    let common = spec
        .tracking
        .randomization_from
        .iter()
        .map(|path| Ok(TrainConfig::from_toml_file(path)?.env.randomization))
        .collect::<Result<Vec<_>>>()?;
    let policies = runs
        .iter()
        .filter(|(r, _)| available.contains(&r.label))
        .map(|(r, _)| load_final_policy(spec, &r.label))
        .collect::<Result<Vec<_>>>()?;
    // One job per (run, environment), not per run: the jobs are many and small,
    // so the cores stay busy to the end of the stage. A common randomisation
    // equal to the run's own is the same evaluation: run once, reported twice.
    let mut jobs: Vec<(usize, EnvConfig)> = Vec::new();
    let mut reports_of_run = Vec::new();
    for (i, (p, _)) in policies.iter().enumerate() {
        let own = tracking_env(&p.env);
        let mut slots = Vec::new();
        for env in std::iter::once(own.clone())
            .chain(common.iter().map(|c| with_randomization(own.clone(), c)))
        {
            let existing = jobs.iter().position(|(j, e)| *j == i && *e == env);
            slots.push(existing.unwrap_or_else(|| {
                jobs.push((i, env));
                jobs.len() - 1
            }));
        }
        reports_of_run.push(slots);
    }
    let reports = crate::eval::jobs::run_jobs(&jobs, threads, |(i, env), threads| {
        evaluate_tracking(
            &policies[*i].0.policy,
            env,
            spec.tracking.episodes,
            threads,
            spec.tracking.seed,
            ActionMode::Mean,
        )
    })?;
    Ok(policies
        .iter()
        .zip(reports_of_run)
        .map(|((p, policy_iteration), slots)| RunTracking {
            label: p.name.clone(),
            own: reports[slots[0]].clone(),
            common: slots[1..].iter().map(|&k| reports[k].clone()).collect(),
            policy_iteration: *policy_iteration,
        })
        .collect())
}

fn ttf_options(spec: &ExperimentSpec, threads: usize) -> Result<TtfOptions> {
    Ok(TtfOptions {
        seeds: seeds(spec.ttf.first_seed, spec.ttf.seeds),
        repeats: spec.ttf.repeats,
        threads,
        loads: spec
            .ttf
            .loads
            .iter()
            .map(|l| parse_load(l))
            .collect::<Result<_>>()?,
        terrains: vec![GroundKind::Flat, GroundKind::Rough],
        pushes: vec![false, true],
        params: ScenarioParams::default(),
    })
}

fn platform_options(spec: &ExperimentSpec, threads: usize) -> PlatformOptions {
    PlatformOptions {
        heights_m: spec.platform.heights_m.clone(),
        seeds: seeds(spec.platform.first_seed, spec.platform.seeds),
        repeats: spec.platform.repeats,
        threads,
        settle_s: 2.0,
        load: Load::None,
        params: ScenarioParams::default(),
    }
}

fn race_options(spec: &ExperimentSpec, threads: usize) -> RaceOptions {
    RaceOptions {
        agents: spec.race.agents,
        episodes: spec.race.episodes,
        threads,
        seed: spec.race.seed,
        course_seed: spec.race.course_seed,
        params: ScenarioParams::default(),
    }
}

/// Each meta controller whose two runs exist, its threshold fixed by the rule.
fn meta_configs(
    spec: &ExperimentSpec,
    available: &[String],
    threads: usize,
) -> Result<Vec<MetaConfig>> {
    let mut metas = Vec::new();
    for m in &spec.meta {
        if !(available.contains(&m.risky) && available.contains(&m.safe)) {
            eprintln!(
                "  {} left out: {} or {} has no checkpoint",
                m.label, m.risky, m.safe
            );
            continue;
        }
        let risky = load_run(spec, &m.risky)?;
        let threshold = calibrate_threshold(m, &risky, threads)?;
        eprintln!(
            "  {}: threshold {threshold:.4} = quantile {} of {}'s IQR on flat ground",
            m.label, m.threshold_quantile, m.risky
        );
        metas.push(MetaConfig {
            name: m.label.clone(),
            risky: m.risky.clone(),
            safe: m.safe.clone(),
            threshold,
            hysteresis: threshold * m.hysteresis_fraction,
            min_safe_steps: m.min_safe_steps,
        });
    }
    Ok(metas)
}

/// The race's runs: its methods, then the meta controllers' runs not among them.
fn race_runs(methods: Vec<String>, metas: &[MetaConfig]) -> Vec<String> {
    let mut labels = methods;
    for m in metas {
        for l in [&m.risky, &m.safe] {
            if !labels.contains(l) {
                labels.push(l.clone());
            }
        }
    }
    labels
}

/// Runs every evaluation of the experiment on the runs' latest checkpoints.
pub fn evaluate_all(spec: &ExperimentSpec, opts: &ExperimentOptions) -> Result<ExperimentResults> {
    let threads = crate::config::worker_threads(spec.threads);
    let stages = if spec.curves.is_some() { 6 } else { 5 };
    let mut clock = PhaseClock::new(stages);
    let runs = runs_to_evaluate(spec, opts)?;
    let available = runs_with_checkpoints(spec, &runs)?;
    let have = |labels: &[String]| -> Vec<String> {
        let mut out = labels.to_vec();
        out.retain(|l| available.contains(l));
        out
    };
    if spec.selection.is_some() {
        eprintln!("[eval 0/{stages}] choosing each finished run's final policy ([selection])");
        choose_final_policies(spec, threads)?;
        warn_unchosen_teachers(spec, &runs)?;
    }
    clock.next("velocity tracking of every policy");
    let tracking = track_all(spec, &runs, &available, threads)?;

    clock.next("table I: time to fall");
    let ttf_opts = ttf_options(spec, threads)?;
    let ttf_methods = have(&spec.ttf.methods);
    let mut spread = Vec::new();
    let ttf = if ttf_methods.is_empty() {
        None
    } else {
        let (report, s) = kcheck::evaluate_ttf_runs(spec, &ttf_methods, &ttf_opts, |c| {
            eprintln!(
                "  {:<10} {:<6} push {:<5} {:<14} TTF {:.3}",
                c.load.name(),
                c.terrain,
                c.push,
                c.policy,
                c.ttf
            )
        })?;
        spread.extend(s);
        Some(report)
    };

    clock.next("table II: platform drops");
    let platform_opts = platform_options(spec, threads);
    let platform_methods = have(&spec.platform.methods);
    let platform = if platform_methods.is_empty() {
        None
    } else {
        let (report, s) =
            kcheck::evaluate_platform_runs(spec, &platform_methods, &platform_opts, |c| {
                eprintln!(
                    "  {:.2} m {:<14} success {:.1}%",
                    c.height_m, c.policy, c.success_pct
                )
            })?;
        spread.extend(s);
        Some(report)
    };

    clock.next("meta controller thresholds (rule of the experiment file)");
    let metas = meta_configs(spec, &available, threads)?;

    clock.next("race track");
    let race_labels = race_runs(have(&spec.race.methods), &metas);
    let race_opts = race_options(spec, threads);
    let race = if race_labels.is_empty() {
        None
    } else {
        let policies = load_runs(spec, &race_labels)?;
        Some(evaluate_race(&policies, &metas, &race_opts, |r| {
            eprintln!(
                "  {:<14} returns q0.25 {:.3} q0.5 {:.3} q0.75 {:.3}",
                r.name, r.q25, r.q50, r.q75
            )
        })?)
    };
    let reports = ladder::RungReports {
        ttf: ttf.as_ref(),
        platform: platform.as_ref(),
        race: race.as_ref(),
    };
    let tables = ladder::TableRuns {
        ttf: (&ttf_opts, ttf_methods),
        platform: (&platform_opts, platform_methods),
        race: (&race_opts, race_labels),
        metas: &metas,
    };
    let (curves, contrasts) = match &spec.curves {
        Some(c) => {
            clock.next("robustness curves over the severity ladder");
            ladder::evaluate_curves(spec, c, &reports, &tables, &mut clock)?
        }
        None => (
            Vec::new(),
            ladder::rung_contrasts(spec, 0, &reports, &tables),
        ),
    };
    let (whole, phases) = clock.finish();
    let mut results = ExperimentResults::new(spec, runs, tracking, ttf, platform, race);
    results.evaluation_time = Some(whole);
    results.phases = phases;
    results.set_curves(spec, curves)?;
    results.contrasts = contrasts;
    results.preface = spec.preface_text()?;
    results.checkpoint_spread = spread;
    if let Some(rs) = &spec.risk_signal {
        results.risk_signal = risk_signal::risk_rows(spec, rs)?;
    }
    Ok(results)
}

/// Trains (if asked), evaluates (if asked) and writes the results.
pub fn run_experiment(
    spec: &ExperimentSpec,
    opts: &ExperimentOptions,
    stop: Arc<AtomicBool>,
) -> Result<()> {
    if opts.train {
        train_all(spec, stop)?;
    }
    if opts.evaluate {
        let results = evaluate_all(spec, opts)?;
        results.write(&spec.results_dir)?;
        eprintln!("results in {}", spec.results_dir.display());
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

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
        assert!(!dst.join("adaptation.copy.tmp").exists());
    }
}
