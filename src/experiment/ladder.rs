//! The experiment's robustness curves: every table's methods on every rung of
//! the severity ladder (`[curves]`). Rung 0 reads the tables' own evaluations;
//! each higher rung runs the benchmarks again with that rung's perturbations,
//! on as many robots as `[curves]` gives.

use anyhow::Result;

use super::clock::PhaseClock;
use super::contrasts::{contrasts_at, Contrast};
use super::curves::{platform_point, race_point, ttf_point, CurvePoint, Resampling};
use super::evaluate::seeds;
use super::final_policy::load_runs;
use super::last_checkpoints::{evaluate_platform_runs, evaluate_ttf_runs};
use super::pooled::methods_of;
use super::spec::{CurvesSpec, ExperimentSpec};
use crate::eval::race::evaluate_race_cached;
use crate::eval::{
    MetaConfig, PlatformOptions, PlatformReport, RaceOptions, RaceReport, RolloutCache, TtfOptions,
    TtfReport,
};

/// The three benchmarks' reports at one rung.
pub(super) struct RungReports<'a> {
    pub ttf: Option<&'a TtfReport>,
    pub platform: Option<&'a PlatformReport>,
    pub race: Option<&'a RaceReport>,
}

/// The evaluations the tables ran (rung 0), which the higher rungs repeat.
pub(super) struct TableRuns<'a> {
    pub ttf: (&'a TtfOptions, Vec<String>),
    pub platform: (&'a PlatformOptions, Vec<String>),
    pub race: (&'a RaceOptions, Vec<String>),
    pub metas: &'a [MetaConfig],
    /// Where finished rollouts are kept, so an evaluation resumes.
    pub cache: &'a RolloutCache,
}

/// The experiment's bootstrap settings.
fn resampling(spec: &ExperimentSpec) -> Resampling {
    let b = &spec.bootstrap;
    Resampling {
        resamples: b.resamples,
        level: b.level,
        seed: b.seed,
    }
}

/// The race's evaluated runs and meta controllers.
fn race_names(labels: &TableRuns) -> Vec<String> {
    let mut names = labels.race.1.clone();
    names.extend(labels.metas.iter().map(|m| m.name.clone()));
    names
}

/// Every `[contrasts]` pair at rung `severity` from `reports`.
pub(super) fn rung_contrasts(
    spec: &ExperimentSpec,
    severity: usize,
    reports: &RungReports,
    labels: &TableRuns,
) -> Vec<Contrast> {
    let race = race_names(labels);
    contrasts_at(
        spec,
        severity,
        reports.ttf.map(|r| (r, labels.ttf.1.as_slice())),
        reports.platform.map(|r| (r, labels.platform.1.as_slice())),
        reports.race.map(|r| (r, race.as_slice())),
        resampling(spec),
    )
}

/// Every method's points at rung `severity` from `reports`.
fn points_at(
    spec: &ExperimentSpec,
    severity: usize,
    reports: &RungReports,
    labels: &TableRuns,
) -> Vec<CurvePoint> {
    let r = resampling(spec);
    let mut out = Vec::new();
    if let Some(rep) = reports.ttf {
        for m in methods_of(spec, &labels.ttf.1) {
            out.extend(ttf_point(rep, &m.seeds, &m.label, severity, false, r));
            out.extend(ttf_point(rep, &m.seeds, &m.label, severity, true, r));
        }
    }
    if let Some(rep) = reports.platform {
        for m in methods_of(spec, &labels.platform.1) {
            out.extend(platform_point(rep, &m.seeds, &m.label, severity, r));
        }
    }
    if let Some(rep) = reports.race {
        for m in methods_of(spec, &race_names(labels)) {
            out.extend(race_point(rep, &m.seeds, &m.label, severity, r));
        }
    }
    out
}

/// One rung above 0: the tables' evaluations with the rung's perturbations (each
/// benchmark's minutes listed on `clock`): its points and contrasts.
fn evaluate_rung(
    spec: &ExperimentSpec,
    c: &CurvesSpec,
    severity: usize,
    tables: &TableRuns,
    clock: &mut PhaseClock,
) -> Result<(Vec<CurvePoint>, Vec<Contrast>)> {
    let ladder = c.ladder()?;
    let rung = ladder.rung(severity)?;
    let what = |benchmark: &str| format!("curves, rung {severity}, {benchmark}");
    let ttf = clock.time(what("time to fall"), || -> Result<_> {
        if tables.ttf.1.is_empty() {
            return Ok(None);
        }
        let opts = TtfOptions {
            seeds: seeds(spec.ttf.first_seed, c.ttf_seeds),
            repeats: c.ttf_repeats,
            params: rung.apply(&tables.ttf.0.params),
            ..tables.ttf.0.clone()
        };
        Ok(Some(
            evaluate_ttf_runs(spec, &tables.ttf.1, &opts, tables.cache, |_| {})?.0,
        ))
    })?;
    let platform = clock.time(what("platform"), || -> Result<_> {
        if tables.platform.1.is_empty() {
            return Ok(None);
        }
        let opts = PlatformOptions {
            heights_m: rung.platform_heights_m.clone(),
            seeds: seeds(spec.platform.first_seed, c.platform_seeds),
            repeats: c.platform_repeats,
            params: rung.apply(&tables.platform.0.params),
            ..tables.platform.0.clone()
        };
        Ok(Some(
            evaluate_platform_runs(spec, &tables.platform.1, &opts, tables.cache, |_| {})?.0,
        ))
    })?;
    let race = clock.time(what("race"), || -> Result<_> {
        if tables.race.1.is_empty() {
            return Ok(None);
        }
        let opts = RaceOptions {
            agents: c.race_agents,
            episodes: c.race_episodes,
            params: rung.apply_race(&tables.race.0.params),
            ..tables.race.0.clone()
        };
        let policies = load_runs(spec, &tables.race.1)?;
        Ok(Some(evaluate_race_cached(
            &policies,
            tables.metas,
            &opts,
            tables.cache,
            |_| {},
        )?))
    })?;
    let reports = RungReports {
        ttf: ttf.as_ref(),
        platform: platform.as_ref(),
        race: race.as_ref(),
    };
    Ok((
        points_at(spec, severity, &reports, tables),
        rung_contrasts(spec, severity, &reports, tables),
    ))
}

/// Every rung of `c`: rung 0 from the tables' `reports`, the others evaluated
/// (each benchmark's minutes listed on `clock`); the points and the contrasts.
pub(super) fn evaluate_curves(
    spec: &ExperimentSpec,
    c: &CurvesSpec,
    reports: &RungReports,
    tables: &TableRuns,
    clock: &mut PhaseClock,
) -> Result<(Vec<CurvePoint>, Vec<Contrast>)> {
    let mut points = Vec::new();
    let mut contrasts = Vec::new();
    for &s in &c.severity {
        eprintln!("  severity rung {s}");
        let (at, differences) = if s == 0 {
            (
                points_at(spec, 0, reports, tables),
                rung_contrasts(spec, 0, reports, tables),
            )
        } else {
            evaluate_rung(spec, c, s, tables, clock)?
        };
        contrasts.extend(differences);
        for p in &at {
            eprintln!(
                "    {:<8} {:<11} {:<22} {}",
                p.benchmark,
                p.metric,
                p.policy,
                p.estimate.show(3)
            );
        }
        points.extend(at);
    }
    Ok((points, contrasts))
}
