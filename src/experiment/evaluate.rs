//! Evaluating an experiment: tracking, table I (TTF), table II (platform), the
//! race with the meta controllers, the robustness curves and each benchmark with
//! a section, stage by stage with the time each took.

use std::sync::Arc;

use anyhow::{bail, Context, Result};

use super::benchmark::{self, BenchmarkContext};
use super::clock::PhaseClock;
use super::final_policy::{
    choose_final_policies, load_final_policy, load_run, load_runs, newest_checkpoint,
    warn_unchosen_teachers,
};
use super::results::{ExperimentResults, RunTracking};
use super::spec::{self, ExperimentSpec, MetaSpec};
use super::{critic_tail, ladder, last_checkpoints, risk_signal, stats};
use super::{run_state, ExperimentOptions, RunState};
use crate::config::TrainConfig;
use crate::env::{build_scene, EnvConfig, VecEnv};
use crate::eval::cache::run_jobs_cached;
use crate::eval::race::evaluate_race_cached;
use crate::eval::{
    evaluate_tracking, tracking_env, with_randomization, ActionMode, GroundKind, Load, MetaConfig,
    NamedPolicy, PlatformOptions, RaceOptions, RaceReport, RolloutCache, ScenarioParams,
    TtfOptions,
};

pub(super) fn seeds(first: u64, n: usize) -> Vec<u64> {
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
    cache: &RolloutCache,
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
    let (episodes, seed) = (spec.tracking.episodes, spec.tracking.seed);
    let key = |(i, env): &(usize, EnvConfig)| {
        let p = &policies[*i].0;
        let own = p.rollout_key()?;
        Some(format!(
            "tracking, mean action\n{own}\nevaluated in {env:?}\nepisodes {episodes} seed {seed}"
        ))
    };
    let reports = run_jobs_cached(&jobs, threads, cache, key, |(i, env), threads| {
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

/// The experiment's rollout cache: `<runs_dir>/rollout-cache`, unless the
/// options turn it off.
fn rollout_cache(spec: &ExperimentSpec, opts: &ExperimentOptions) -> RolloutCache {
    if opts.fresh_rollouts {
        RolloutCache::none()
    } else {
        RolloutCache::at(spec.runs_dir.join("rollout-cache"))
    }
}

/// Runs every evaluation of the experiment on the runs' latest checkpoints.
pub fn evaluate_all(spec: &ExperimentSpec, opts: &ExperimentOptions) -> Result<ExperimentResults> {
    let threads = crate::config::worker_threads(spec.threads);
    let stages = 5
        + spec.curves.is_some() as usize
        + spec.critic_tail.is_some() as usize
        + benchmark::stage_count(spec);
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
    let cache = rollout_cache(spec, opts);
    let tracking = track_all(spec, &runs, &available, threads, &cache)?;

    clock.next("table I: time to fall");
    let ttf_opts = ttf_options(spec, threads)?;
    let ttf_methods = have(&spec.ttf.methods);
    let mut spread = Vec::new();
    let ttf = if ttf_methods.is_empty() {
        None
    } else {
        let (report, s) =
            last_checkpoints::evaluate_ttf_runs(spec, &ttf_methods, &ttf_opts, &cache, |c| {
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
        let (report, s) = last_checkpoints::evaluate_platform_runs(
            spec,
            &platform_methods,
            &platform_opts,
            &cache,
            |c| {
                eprintln!(
                    "  {:.2} m {:<14} success {:.1}%",
                    c.height_m, c.policy, c.success_pct
                )
            },
        )?;
        spread.extend(s);
        Some(report)
    };

    clock.next("meta controller thresholds (rule of the experiment file)");
    let metas = meta_configs(spec, &available, threads)?;

    clock.next("race track");
    let race_labels = race_runs(have(&spec.race.methods), &metas);
    let race_opts = race_options(spec, threads);
    let race = run_race(spec, &race_labels, &metas, &race_opts, &cache)?;
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
        cache: &cache,
    };
    let (curves, mut contrasts) = match &spec.curves {
        Some(c) => {
            clock.next("robustness curves over the severity ladder");
            ladder::evaluate_curves(spec, c, &reports, &tables, &mut clock)?
        }
        None => (
            Vec::new(),
            ladder::rung_contrasts(spec, 0, &reports, &tables),
        ),
    };
    let critic_tail = critics_before_falls(spec, &available, threads, &cache, &mut clock)?;
    let cx = BenchmarkContext {
        spec,
        available: &available,
        threads,
        cache: &cache,
    };
    let (outputs, more) = benchmark::evaluate_benchmarks(&cx, &mut clock)?;
    let (whole, phases) = clock.finish();
    let cache_use = cache.usage();
    if let Some(dir) = cache.dir() {
        eprintln!("  {} ({})", cache_use.show(), dir.display());
    }
    let mut results = ExperimentResults::new(spec, runs, tracking, ttf, platform, race);
    results.evaluation_time = Some(whole);
    results.phases = phases;
    results.rollouts = cache.dir().map(|_| cache_use);
    results.set_curves(spec, curves)?;
    contrasts.extend(more);
    results.benchmarks = outputs;
    results.verdicts = super::verdicts::VerdictsResult::of(spec, &contrasts);
    results.contrasts = contrasts;
    finish_results(spec, &mut results, critic_tail, spread)?;
    Ok(results)
}

/// The race of runs `labels` and meta controllers `metas` (none without runs).
fn run_race(
    spec: &ExperimentSpec,
    labels: &[String],
    metas: &[MetaConfig],
    opts: &RaceOptions,
    cache: &RolloutCache,
) -> Result<Option<RaceReport>> {
    if labels.is_empty() {
        return Ok(None);
    }
    let policies = load_runs(spec, labels)?;
    let report = evaluate_race_cached(&policies, metas, opts, cache, |r| {
        eprintln!(
            "  {:<14} returns q0.25 {:.3} q0.5 {:.3} q0.75 {:.3}",
            r.name, r.q25, r.q50, r.q75
        )
    })?;
    Ok(Some(report))
}

/// The stage of `[critic_tail]` (none without it).
fn critics_before_falls(
    spec: &ExperimentSpec,
    available: &[String],
    threads: usize,
    cache: &RolloutCache,
    clock: &mut PhaseClock,
) -> Result<Option<critic_tail::CriticTail>> {
    let Some(s) = &spec.critic_tail else {
        return Ok(None);
    };
    clock.next("the critics before falls");
    Ok(Some(critic_tail::evaluate_critic_tail(
        spec, s, available, threads, cache,
    )?))
}

/// The results' parts that need no rollout: the critics' table, the checkpoint
/// spread, the preface and the risk signal.
fn finish_results(
    spec: &ExperimentSpec,
    results: &mut ExperimentResults,
    critic_tail: Option<critic_tail::CriticTail>,
    spread: Vec<last_checkpoints::CheckpointSpread>,
) -> Result<()> {
    results.critic_tail = critic_tail;
    results.preface = spec.preface_text()?;
    results.checkpoint_spread = spread;
    if let Some(rs) = &spec.risk_signal {
        results.risk_signal = risk_signal::risk_rows(spec, rs)?;
    }
    Ok(())
}
