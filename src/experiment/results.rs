//! The experiment's numbers: every cell with its bootstrap interval, the
//! paper's number beside it, written as Markdown, CSV, JSON and figures.

mod csv_tables;
mod readme;
mod write;

use std::fmt::Write as _;

use anyhow::Result;
use serde::{Deserialize, Serialize};

use super::clock::PhaseTime;
use super::contrasts::Contrast;
use super::curves::CurvePoint;
use super::last_checkpoints::CheckpointSpread;
use super::pooled::MethodTables;
use super::spec::{ExperimentSpec, RunSpec};
use super::stats::{bootstrap, cell_seed, mean, quantile, Estimate};
use super::RunState;
use crate::eval::race::IqrBin;
use crate::eval::report::csv_field;
use crate::eval::{
    fall_rate, lin_vel_score, yaw_rate_score, Ladder, PlatformReport, RaceReport, RobotTracking,
    TrackingReport, TtfReport,
};

/// One training run: budget, what it reached, how it tracks commands.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct RunRow {
    pub label: String,
    pub config: String,
    pub seed: u64,
    pub dir: String,
    pub iterations_done: usize,
    pub iterations_target: usize,
    pub env_steps: u64,
    pub wall_clock_h: f64,
    /// Mean terrain-curriculum level over the envs at the checkpoint (rough ground).
    pub terrain_level: Option<f64>,
    /// Under the run's own training randomisation (`None`: not evaluated).
    pub tracking: Option<TrackingEstimates>,
    pub tracking_episodes: usize,
    /// The iteration of the evaluated policy when `[selection]` chose it (else the last).
    pub policy_iteration: Option<usize>,
    /// The same under each of the experiment's common randomisations
    /// (`tracking.randomization_from`, in its order).
    pub common_tracking: Vec<TrackingEstimates>,
}

/// The tracking figures with bootstrap intervals over robots.
#[derive(Debug, Clone, Copy, Serialize, Deserialize)]
pub struct TrackingEstimates {
    pub lin: Estimate,
    pub yaw: Estimate,
    pub falls: Estimate,
}

impl TrackingEstimates {
    /// Percentile bootstrap over `t`'s robots; `seed_of("lin" | "yaw" | "falls")` seeds
    /// each figure's resampling.
    pub fn new(
        t: &TrackingReport,
        resamples: usize,
        level: f64,
        seed_of: impl Fn(&str) -> u64,
    ) -> Self {
        let ci = |what: &str, stat: fn(&[RobotTracking]) -> f64| {
            bootstrap(&t.robots, stat, resamples, level, seed_of(what))
        };
        TrackingEstimates {
            lin: ci("lin", lin_vel_score),
            yaw: ci("yaw", yaw_rate_score),
            falls: ci("falls", fall_rate),
        }
    }

    /// The tracking targets: linear >= 0.8, yaw >= 0.7, falls < 5%.
    pub fn meets_targets(&self) -> bool {
        self.lin.value >= 0.8 && self.yaw.value >= 0.7 && self.falls.value < 0.05
    }

    /// `lin / yaw / falls` with their intervals.
    fn cells(&self) -> [String; 3] {
        [
            self.lin.show(3),
            self.yaw.show(3),
            self.falls.show_percent(),
        ]
    }

    /// Nine CSV fields: each figure, its low and high end.
    pub fn csv(&self) -> String {
        [self.lin, self.yaw, self.falls].map(|e| e.csv(4)).join(",")
    }
}

/// One run's tracking: under its own training randomisation, and under each common one.
#[derive(Debug, Clone)]
pub struct RunTracking {
    pub label: String,
    pub own: TrackingReport,
    pub common: Vec<TrackingReport>,
    /// The iteration of the policy tracked, when `[selection]` chose it.
    pub policy_iteration: Option<usize>,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct TtfRow {
    pub method: String,
    pub load: String,
    pub terrain: String,
    pub push: bool,
    pub ttf: Estimate,
    pub robots: usize,
    pub paper: Option<f64>,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct PlatformRow {
    pub method: String,
    pub height_m: f64,
    pub success_pct: Estimate,
    pub robots: usize,
    pub paper: Option<f64>,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct RaceRow {
    pub method: String,
    pub q25: Estimate,
    pub q50: Estimate,
    pub q75: Estimate,
    pub mean_return: f64,
    pub fall_fraction: f64,
    pub episodes: usize,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct MetaSummary {
    pub label: String,
    pub risky: String,
    pub safe: String,
    pub rule: String,
    pub threshold: f32,
    pub safe_fraction: f64,
    pub switches_per_episode: f64,
    pub iqr_by_x: Vec<IqrBin>,
}

/// Everything the experiment measured.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct ExperimentResults {
    pub name: String,
    pub confidence: String,
    pub runs: Vec<RunRow>,
    /// The run configs whose randomisation every policy was also tracked under.
    pub common_randomization: Vec<String>,
    pub ttf: Vec<TtfRow>,
    pub platform: Vec<PlatformRow>,
    pub race: Vec<RaceRow>,
    /// One per meta controller (`[[meta]]`).
    pub meta: Vec<MetaSummary>,
    /// The three tables again, one row per method over its seeds.
    pub methods: MethodTables,
    /// Robustness curves (`[curves]`): a point per method, benchmark and rung.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub curves: Vec<CurvePoint>,
    /// The ladder behind the curves.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ladder: Option<Ladder>,
    /// With `[checkpoints]`: each run's number at each of its last K checkpoints.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub checkpoint_spread: Vec<CheckpointSpread>,
    /// The paper's number at rung 0 of each curve that has one: (benchmark, method, value).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub curve_paper: Vec<(String, String, f64)>,
    /// With `[risk_signal]`: each run's risk terms over its last training iterations.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub risk_signal: Vec<super::risk_signal::RiskTermRow>,
    /// With `[critic_tail]`: each run's critic before falls and elsewhere.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub critic_tail: Option<super::critic_tail::CriticTail>,
    /// Each benchmark's output with its section (`[commands]`: each listed run's
    /// command-space map, and each method's), one entry per benchmark by its name.
    #[serde(flatten)]
    pub benchmarks: super::benchmark::BenchmarkOutputs,
    /// With `[contrasts]`: each pair of methods on every benchmark and rung.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub contrasts: Vec<Contrast>,
    /// With `[verdicts]`: the pre-registered primary and the families, tested on
    /// `contrasts` (computed from them each time the results are written, never
    /// stored in `results.json`).
    #[serde(skip)]
    pub verdicts: Option<super::verdicts::VerdictsResult>,
    /// The experiment's `preface` file, opening the README (read from the file
    /// each time the README is written, never stored in `results.json`).
    #[serde(skip)]
    pub preface: Option<String>,
    /// Not part of the tables (they are reproducible to the byte; this is not).
    #[serde(skip)]
    pub evaluation_time: Option<PhaseTime>,
    /// Where the evaluation's time went, stage by stage, in order.
    #[serde(skip)]
    pub phases: Vec<PhaseTime>,
    /// How many rollouts ran and how many came from the rollout cache.
    #[serde(skip)]
    pub rollouts: Option<crate::eval::CacheUse>,
}

const TTF_COLUMNS: [(&str, bool); 4] = [
    ("flat", false),
    ("flat", true),
    ("random", false),
    ("random", true),
];

impl ExperimentResults {
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        spec: &ExperimentSpec,
        runs: Vec<(RunSpec, RunState)>,
        tracking: Vec<RunTracking>,
        ttf: Option<TtfReport>,
        platform: Option<PlatformReport>,
        race: Option<RaceReport>,
    ) -> ExperimentResults {
        let b = &spec.bootstrap;
        let methods = MethodTables::new(spec, ttf.as_ref(), platform.as_ref(), race.as_ref());
        let (race_rows, meta) = race_rows(spec, race.as_ref());
        ExperimentResults {
            name: spec.name.clone(),
            confidence: format!(
                "{:.0}% percentile bootstrap over robots (race: over agents), {} resamples, seed {}",
                100.0 * b.level,
                b.resamples,
                b.seed
            ),
            runs: run_rows(spec, &runs, &tracking),
            common_randomization: spec
                .tracking
                .randomization_from
                .iter()
                .map(|p| p.display().to_string())
                .collect(),
            ttf: ttf_rows(spec, ttf.as_ref()),
            platform: platform_rows(spec, platform.as_ref()),
            race: race_rows,
            meta,
            methods,
            curves: Vec::new(),
            ladder: None,
            curve_paper: Vec::new(),
            checkpoint_spread: Vec::new(),
            risk_signal: Vec::new(),
            critic_tail: None,
            benchmarks: Default::default(),
            contrasts: Vec::new(),
            verdicts: None,
            preface: None,
            evaluation_time: None,
            phases: Vec::new(),
            rollouts: None,
        }
    }

    /// Adds the robustness curves of `spec`'s `[curves]` (none without it).
    pub fn set_curves(&mut self, spec: &ExperimentSpec, points: Vec<CurvePoint>) -> Result<()> {
        self.ladder = match &spec.curves {
            Some(c) => Some(c.ladder()?),
            None => None,
        };
        self.curve_paper = Vec::new();
        for p in points.iter().filter(|p| p.severity == 0) {
            let known = self
                .curve_paper
                .iter()
                .any(|(b, m, _)| b == p.benchmark && *m == p.policy);
            if let Some(v) = paper_curve_value(spec, p.benchmark, &p.policy).filter(|_| !known) {
                self.curve_paper
                    .push((p.benchmark.to_string(), p.policy.clone(), v));
            }
        }
        self.curves = points;
        Ok(())
    }
}

/// The paper's number of `method` at rung 0 of `benchmark`'s curve: table I's
/// mean over its twelve cells, table II's mean over its heights.
fn paper_curve_value(spec: &ExperimentSpec, benchmark: &str, method: &str) -> Option<f64> {
    let values: Vec<f64> = match benchmark {
        "ttf" => spec
            .paper
            .ttf
            .iter()
            .filter(|r| r.method == method)
            .flat_map(|r| r.ttf)
            .collect(),
        "platform" => spec
            .paper
            .platform
            .iter()
            .filter(|r| r.method == method)
            .map(|r| r.success_pct)
            .collect(),
        _ => Vec::new(),
    };
    (!values.is_empty()).then(|| mean(&values))
}

/// Table I in Markdown under its heading: a row per load x method, named by
/// `row(load, method)` (no row when it gives none), `cell(load, method, column)` in the
/// columns of [`TTF_COLUMNS`] ("-" where it gives none).
fn write_ttf_table(
    s: &mut String,
    loads: &[String],
    methods: &[String],
    row: impl Fn(&str, &str) -> Option<String>,
    cell: impl Fn(&str, &str, (&str, bool)) -> Option<String>,
) {
    let _ = writeln!(s, "### Table I: Time to Fall\n");
    let _ = writeln!(
        s,
        "| Load | Method | Flat, no push | Flat, push | Random, no push | Random, push |"
    );
    let _ = writeln!(s, "|---|---|---:|---:|---:|---:|");
    for l in loads {
        for m in methods {
            let Some(name) = row(l, m) else { continue };
            let mut line = format!("| {l} | {name} |");
            for col in TTF_COLUMNS {
                let text = cell(l, m, col).unwrap_or_else(|| "-".into());
                let _ = write!(line, " {text} |");
            }
            let _ = writeln!(s, "{line}");
        }
    }
}

/// The bootstrap interval of `stat` over `units`, seeded by the cell's name.
fn cell_estimate(
    spec: &ExperimentSpec,
    cell: String,
    units: &[f64],
    stat: &dyn Fn(&[f64]) -> f64,
) -> Estimate {
    let b = &spec.bootstrap;
    bootstrap(units, stat, b.resamples, b.level, cell_seed(b.seed, &cell))
}

/// One row per run: its budget and progress, and its tracking estimates.
fn run_rows(
    spec: &ExperimentSpec,
    runs: &[(RunSpec, RunState)],
    tracking: &[RunTracking],
) -> Vec<RunRow> {
    let b = &spec.bootstrap;
    runs.iter()
        .map(|(r, s)| {
            let p = s.progress.clone().unwrap_or_default();
            let found = tracking.iter().find(|t| t.label == r.label);
            // one seed for both: the same robots give the same interval
            let cell = format!("tracking/{}", r.label);
            let estimates = |t: &TrackingReport| {
                TrackingEstimates::new(t, b.resamples, b.level, |what| {
                    cell_seed(b.seed, &format!("{cell}/{what}"))
                })
            };
            RunRow {
                label: r.label.clone(),
                config: r.config.display().to_string(),
                seed: r.seed,
                dir: s.dir.display().to_string(),
                iterations_done: p.iteration,
                iterations_target: s.target,
                env_steps: p.total_env_steps,
                wall_clock_h: p.wall_s / 3600.0,
                terrain_level: p
                    .terrain_levels
                    .as_ref()
                    .map(|l| l.iter().sum::<usize>() as f64 / l.len().max(1) as f64),
                tracking: found.map(|t| estimates(&t.own)),
                policy_iteration: found.and_then(|t| t.policy_iteration),
                tracking_episodes: found.map_or(0, |t| t.own.episodes),
                common_tracking: found
                    .map(|t| t.common.iter().map(estimates).collect())
                    .unwrap_or_default(),
            }
        })
        .collect()
}

/// Time to fall per cell (fraction of the episode), with the paper's number.
fn ttf_rows(spec: &ExperimentSpec, ttf: Option<&TtfReport>) -> Vec<TtfRow> {
    ttf.iter()
        .flat_map(|t| &t.cells)
        .map(|c| {
            let steps: Vec<f64> = c.steps_per_robot.iter().map(|&s| s as f64).collect();
            let len = c.episode_steps.max(1) as f64;
            let col = TTF_COLUMNS
                .iter()
                .position(|&(t, p)| t == c.terrain && p == c.push);
            let paper = spec
                .paper
                .ttf
                .iter()
                .find(|row| row.load == c.load.name() && row.method == c.policy)
                .zip(col)
                .map(|(row, k)| row.ttf[k]);
            let cell = format!(
                "ttf/{}/{}/{}/{}",
                c.policy,
                c.load.name(),
                c.terrain,
                c.push
            );
            TtfRow {
                method: c.policy.clone(),
                load: c.load.name().to_string(),
                terrain: c.terrain.clone(),
                push: c.push,
                ttf: cell_estimate(spec, cell, &steps, &|v| mean(v) / len),
                robots: c.robots,
                paper,
            }
        })
        .collect()
}

/// Platform success rate per cell (percent), with the paper's number.
fn platform_rows(spec: &ExperimentSpec, platform: Option<&PlatformReport>) -> Vec<PlatformRow> {
    platform
        .iter()
        .flat_map(|p| &p.cells)
        .map(|c| {
            let ok: Vec<f64> = c
                .success_per_robot
                .iter()
                .map(|&s| if s { 100.0 } else { 0.0 })
                .collect();
            let cell = format!("platform/{}/{}", c.policy, c.height_m);
            PlatformRow {
                method: c.policy.clone(),
                height_m: c.height_m,
                success_pct: cell_estimate(spec, cell, &ok, &mean),
                robots: c.robots,
                paper: spec
                    .paper
                    .platform
                    .iter()
                    .find(|p| (p.height_m - c.height_m).abs() < 1e-6 && p.method == c.policy)
                    .map(|p| p.success_pct),
            }
        })
        .collect()
}

/// Race-track return quantiles per policy (agents are the bootstrap units),
/// and a summary of each meta controller.
fn race_rows(spec: &ExperimentSpec, race: Option<&RaceReport>) -> (Vec<RaceRow>, Vec<MetaSummary>) {
    let b = &spec.bootstrap;
    let per_agent = race.map_or(1, |r| r.options.episodes.max(1));
    let mut meta = Vec::new();
    let mut race_rows = Vec::new();
    for r in race.iter().flat_map(|r| &r.rows) {
        // agents are the bootstrap units: each keeps its episodes together
        let agents: Vec<Vec<f64>> = r.returns.chunks(per_agent).map(|c| c.to_vec()).collect();
        let q = |q: f64| {
            move |a: &[Vec<f64>]| quantile(&a.iter().flatten().copied().collect::<Vec<_>>(), q)
        };
        let est = |stat: &dyn Fn(&[Vec<f64>]) -> f64, quantile: &str| {
            let seed = cell_seed(b.seed, &format!("race/{}/{quantile}", r.name));
            bootstrap(&agents, stat, b.resamples, b.level, seed)
        };
        race_rows.push(RaceRow {
            method: r.name.clone(),
            q25: est(&q(0.25), "q25"),
            q50: est(&q(0.5), "q50"),
            q75: est(&q(0.75), "q75"),
            mean_return: r.mean_return,
            fall_fraction: r.fall_fraction,
            episodes: r.episodes,
        });
        if let (Some(m), Some(ms)) = (&r.meta, spec.meta.iter().find(|m| m.label == r.name)) {
            meta.push(MetaSummary {
                label: r.name.clone(),
                risky: m.config.risky.clone(),
                safe: m.config.safe.clone(),
                rule: format!(
                    "threshold = quantile {} of {}'s critic IQR over {} robots x one episode on flat ground (random commands); back below {:.0}% of it after at least {} steps",
                    ms.threshold_quantile,
                    ms.risky,
                    ms.calibration_robots,
                    100.0 * (1.0 - ms.hysteresis_fraction),
                    ms.min_safe_steps
                ),
                threshold: m.config.threshold,
                safe_fraction: m.safe_fraction,
                switches_per_episode: m.switches_per_episode,
                iqr_by_x: m.iqr_by_x.clone(),
            });
        }
    }
    (race_rows, meta)
}

/// An optional number as a CSV field (empty when absent).
fn opt(v: Option<f64>) -> String {
    v.map_or(String::new(), |v| format!("{v}"))
}

/// A pooled method's seeds as one CSV field.
fn seeds(m: &super::pooled::Method) -> String {
    csv_field(&m.seeds.join(";"))
}

/// Per-seed values joined by `;` with `d` decimals.
fn per_seed(v: &[f64], d: usize) -> String {
    v.iter()
        .map(|x| format!("{x:.d$}", d = d))
        .collect::<Vec<_>>()
        .join(";")
}
