//! The experiment's numbers: every cell with its bootstrap interval, the
//! paper's number beside it, written as Markdown, CSV, JSON and figures.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use serde::{Deserialize, Serialize};

use super::clock::PhaseTime;
use super::contrasts::{contrasts_csv, contrasts_markdown, Contrast};
use super::curves::{curve_csv, curve_markdown, CurvePoint};
use super::kcheck::CheckpointSpread;
use super::pooled::{show_with_seeds, MethodTables};
use super::spec::{common_ground_name, ExperimentSpec, RunSpec};
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
    /// With `[contrasts]`: each pair of methods on every benchmark and rung.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub contrasts: Vec<Contrast>,
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
            contrasts: Vec::new(),
            preface: None,
            evaluation_time: None,
            phases: Vec::new(),
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

    fn spread_markdown(&self, s: &mut String) {
        if self.checkpoint_spread.is_empty() {
            return;
        }
        let _ = writeln!(s, "## From checkpoint to checkpoint\n");
        let _ = writeln!(s, "Every run's number in tables I and II is the mean over its last checkpoints (below, newest first), each judged on its share of the robots; this is how much a single checkpoint would have moved it. The race and the tracking judge each run's `[selection]` policy (a secondary view).\n");
        let _ = writeln!(
            s,
            "| benchmark | run | checkpoints | per checkpoint | min - max |"
        );
        let _ = writeln!(s, "|---|---|---|---|---|");
        for c in &self.checkpoint_spread {
            let digits = if c.benchmark == "ttf" { 3 } else { 1 };
            let its: Vec<String> = c.iterations.iter().map(|i| i.to_string()).collect();
            let vals: Vec<String> = c.values.iter().map(|v| format!("{v:.digits$}")).collect();
            let _ = writeln!(
                s,
                "| {} | {} | {} | {} | {:.digits$} - {:.digits$} |",
                c.benchmark,
                c.run,
                its.join(", "),
                vals.join(", "),
                c.min(),
                c.max()
            );
        }
        let _ = writeln!(s);
    }

    fn curves_markdown(&self, s: &mut String) {
        let Some(ladder) = &self.ladder else { return };
        if self.curves.is_empty() {
            return;
        }
        let mut rungs: Vec<usize> = self.curves.iter().map(|p| p.severity).collect();
        rungs.sort_unstable();
        rungs.dedup();
        let _ = writeln!(
            s,
            "## Robustness curves
"
        );
        let _ = writeln!(s, "Each method (seeds pooled with equal weight) on every rung of the severity ladder; rung 0 is the paper's protocol (the tables below), each higher rung harder on every axis. 95% bootstrap over robots in brackets; `figures/curve_<benchmark>.svg` draws them, `curves.csv` lists them.
");
        let _ = writeln!(s, "{}", ladder.markdown(&rungs));
        for (metric, title, digits) in [
            ("ttf", "Time to Fall, mean over table I's cells", 3),
            ("strict_ttf", "Time to Fall, strict fall definition", 3),
            (
                "success_pct",
                "Platform success (%), the rung's heights pooled",
                1,
            ),
            ("return_q25", "Race return, 0.25 quantile", 1),
        ] {
            let these: Vec<CurvePoint> = self
                .curves
                .iter()
                .filter(|p| p.metric == metric)
                .cloned()
                .collect();
            if !these.is_empty() {
                let _ = writeln!(s, "### {title}\n\n{}", curve_markdown(&these, digits));
            }
        }
        let _ = writeln!(s, "{}\n", crate::eval::FALL_DEFINITION);
    }

    /// Methods in table order (first appearance).
    fn methods_of<'a>(names: impl Iterator<Item = &'a String>) -> Vec<String> {
        let mut out: Vec<String> = Vec::new();
        for n in names {
            if !out.contains(n) {
                out.push(n.clone());
            }
        }
        out
    }

    pub fn markdown(&self) -> String {
        let mut s = String::new();
        let _ = writeln!(s, "# Results: {}\n", self.name);
        if let Some(p) = &self.preface {
            let _ = writeln!(s, "{}\n", p.trim_end());
        }
        let _ = writeln!(
            s,
            "Every number: ours with its {} in brackets; the paper's beside it where it gives one.\n",
            self.confidence
        );
        contrasts_markdown(&self.contrasts, &mut s);
        self.runs_markdown(&mut s);
        self.common_ground_markdown(&mut s);

        self.curves_markdown(&mut s);
        self.spread_markdown(&mut s);
        super::risk_signal::risk_markdown(&self.risk_signal, &mut s);
        self.methods_markdown(&mut s);
        self.per_run_markdown(&mut s);
        let _ = writeln!(s, "\n## Figures\n");
        for (f, what) in plots_list() {
            let _ = writeln!(s, "- [{f}](figures/{f}): {what}");
        }
        s
    }

    /// The training runs: budget, progress and tracking of each.
    fn runs_markdown(&self, s: &mut String) {
        let _ = writeln!(s, "## Training runs\n");
        let _ = writeln!(
            s,
            "| Method | iterations | env steps | wall clock (h) | terrain level | lin tracking | yaw tracking | falls |"
        );
        let _ = writeln!(s, "|---|---:|---:|---:|---:|---:|---:|---:|");
        for r in &self.runs {
            let unfinished = if r.iterations_done == 0 {
                " (not started)"
            } else if r.iterations_done < r.iterations_target {
                " (unfinished)"
            } else {
                ""
            };
            let chosen = r
                .policy_iteration
                .map_or(String::new(), |it| format!(", policy of {it}"));
            let [lin, yaw, falls] = r
                .tracking
                .map_or_else(|| ["-".to_string(), "-".into(), "-".into()], |t| t.cells());
            let _ = writeln!(
                s,
                "| {} | {} / {}{unfinished}{chosen} | {:.1} M | {:.2} | {} | {lin} | {yaw} | {falls} |",
                r.label,
                r.iterations_done,
                r.iterations_target,
                r.env_steps as f64 / 1e6,
                r.wall_clock_h,
                r.terrain_level.map_or("-".into(), |l| format!("{l:.2}")),
            );
        }
        let _ = writeln!(s, "\nTracking: `rall eval tracking` protocol ({} episodes, mean actions, flat ground, each policy under its own training randomisation); targets: linear >= 0.8, yaw >= 0.7, falls < 5%.",
            self.runs.first().map_or(0, |r| r.tracking_episodes));
        let _ = writeln!(s);
    }

    /// Every run on its own: tables I and II, the race and the meta controllers.
    fn per_run_markdown(&self, s: &mut String) {
        let _ = writeln!(s, "## Per training run\n");
        let _ = writeln!(
            s,
            "Every run on its own (the tables above pool these by method).\n"
        );
        let loads = Self::methods_of(self.ttf.iter().map(|r| &r.load));
        let methods = Self::methods_of(self.ttf.iter().map(|r| &r.method));
        write_ttf_table(
            s,
            &loads,
            &methods,
            |_, m| Some(m.to_string()),
            |l, m, (t, p)| {
                let c = self
                    .ttf
                    .iter()
                    .find(|r| r.load == l && r.method == m && r.terrain == t && r.push == p)?;
                let paper = c
                    .paper
                    .map_or(String::new(), |p| format!(" (paper {p:.3})"));
                Some(format!("{}{paper}", c.ttf.show(3)))
            },
        );
        let _ = writeln!(s, "\n### Table II: walking off a platform (success %)\n");
        let _ = writeln!(s, "| Height | Method | ours | paper | robots |");
        let _ = writeln!(s, "|---:|---|---:|---:|---:|");
        for r in &self.platform {
            let _ = writeln!(
                s,
                "| {:.2} m | {} | {} | {} | {} |",
                r.height_m,
                r.method,
                r.success_pct.show(1),
                r.paper.map_or("-".into(), |p| format!("{p:.1}")),
                r.robots
            );
        }
        let _ = writeln!(s, "\n### Race track: return quantiles\n");
        let _ = writeln!(
            s,
            "| Method | q0.25 (worst case) | q0.5 | q0.75 (best case) | mean | falls | episodes |"
        );
        let _ = writeln!(s, "|---|---:|---:|---:|---:|---:|---:|");
        for r in &self.race {
            let _ = writeln!(
                s,
                "| {} | {} | {} | {} | {:.2} | {:.1}% | {} |",
                r.method,
                r.q25.show(2),
                r.q50.show(2),
                r.q75.show(2),
                r.mean_return,
                100.0 * r.fall_fraction,
                r.episodes
            );
        }
        for m in &self.meta {
            let _ = writeln!(
                s,
                "\nMeta controller {}: {} (risk neutral) / {} (risk averse); {}: {:.4}. On the race it acted with {} for {:.1}% of robot-steps, {:.2} switches per episode.",
                m.label,
                m.risky,
                m.safe,
                m.rule,
                m.threshold,
                m.safe,
                100.0 * m.safe_fraction,
                m.switches_per_episode
            );
        }
        let _ = writeln!(s, "\nThe paper gives the race only as a figure (fig. 4, right): the meta controller has the highest return at all three quantiles.");
    }

    /// The paper's TTF for `method` at `load` and column `k`.
    fn paper_ttf(&self, method: &str, load: &str, (t, p): (&str, bool)) -> Option<f64> {
        self.ttf
            .iter()
            .find(|r| r.method == method && r.load == load && r.terrain == t && r.push == p)
            .and_then(|r| r.paper)
    }

    /// The three tables with one row per method (seeds pooled, each seed in braces).
    fn methods_markdown(&self, s: &mut String) {
        let m = &self.methods;
        if m.ttf.is_empty() && m.platform.is_empty() && m.race.is_empty() {
            return;
        }
        let _ = writeln!(s, "## Each method over its training seeds\n");
        let _ = writeln!(s, "Runs that differ only in their training seed are one method here. Its number weights every seed equally (the mean of the seeds' means; the race: quantiles of the seeds' returns pooled) with a 95% bootstrap that resamples robots within each seed; each seed's own value follows in braces, because with two seeds the spread between them is the honest measure of what another seed would do, and no interval over robots covers it.\n");
        let loads = Self::methods_of(m.ttf.iter().map(|r| &r.load));
        let labels = Self::methods_of(m.ttf.iter().map(|r| &r.method.label));
        write_ttf_table(
            s,
            &loads,
            &labels,
            |l, label| {
                m.ttf
                    .iter()
                    .find(|r| r.load == l && r.method.label == label)
                    .map(|r| r.method.display())
            },
            |l, label, (t, p)| {
                let c = m.ttf.iter().find(|r| {
                    r.load == l && r.method.label == label && r.terrain == t && r.push == p
                })?;
                let paper = self
                    .paper_ttf(label, l, (t, p))
                    .map_or(String::new(), |p| format!(" (paper {p:.3})"));
                Some(format!(
                    "{}{paper}",
                    show_with_seeds(&c.ttf, &c.per_seed, 3)
                ))
            },
        );
        let _ = writeln!(s, "\n### Table II: walking off a platform (success %)\n");
        let _ = writeln!(s, "| Height | Method | ours | paper | robots |");
        let _ = writeln!(s, "|---:|---|---:|---:|---:|");
        for r in &m.platform {
            let paper = self
                .platform
                .iter()
                .find(|p| p.method == r.method.label && p.height_m == r.height_m)
                .and_then(|p| p.paper);
            let _ = writeln!(
                s,
                "| {:.2} m | {} | {} | {} | {} |",
                r.height_m,
                r.method.display(),
                show_with_seeds(&r.success_pct, &r.per_seed, 1),
                paper.map_or("-".into(), |p| format!("{p:.1}")),
                r.robots
            );
        }
        let _ = writeln!(s, "\n### Race track: return quantiles\n");
        let _ = writeln!(
            s,
            "| Method | q0.25 (worst case) | q0.5 | q0.75 (best case) | falls | episodes |"
        );
        let _ = writeln!(s, "|---|---:|---:|---:|---:|---:|");
        for r in &m.race {
            let q = |k: usize, e: &Estimate| {
                let seeds: Vec<f64> = r.per_seed.iter().map(|q| q[k]).collect();
                show_with_seeds(e, &seeds, 2)
            };
            let _ = writeln!(
                s,
                "| {} | {} | {} | {} | {:.1}% | {} |",
                r.method.display(),
                q(0, &r.q25),
                q(1, &r.q50),
                q(2, &r.q75),
                100.0 * r.fall_fraction,
                r.episodes
            );
        }
        let _ = writeln!(s);
    }

    /// Tracking with every policy on the same ground: one column per common
    /// randomisation, beside each policy's own.
    fn common_ground_markdown(&self, s: &mut String) {
        if self.common_randomization.is_empty() {
            return;
        }
        let _ = writeln!(s, "### Tracking on common ground: lin / yaw / falls\n");
        let _ = write!(s, "| Method | own randomisation |");
        for c in &self.common_randomization {
            let _ = write!(s, " `{c}`'s |");
        }
        let _ = writeln!(
            s,
            "\n|---|---:|{}",
            "---:|".repeat(self.common_randomization.len())
        );
        let show = |t: Option<&TrackingEstimates>| t.map_or("-".into(), |t| t.cells().join(" / "));
        for r in &self.runs {
            let _ = write!(s, "| {} | {} |", r.label, show(r.tracking.as_ref()));
            for k in 0..self.common_randomization.len() {
                let _ = write!(s, " {} |", show(r.common_tracking.get(k)));
            }
            let _ = writeln!(s);
        }
        let _ = writeln!(s, "\nThe same episodes (commands, noise, starts) with friction, added mass, motor strength, PD factors and centre of mass drawn from each config's `[env.randomization]` for every policy (`rall eval tracking --randomization-from CONFIG`, pushes off), so that all methods walk on the same ground; the targets above apply to the own column.\n");
    }

    fn csv_files(&self) -> Vec<(&'static str, String)> {
        let mut files = vec![
            ("runs.csv", self.runs_csv()),
            ("ttf_by_method.csv", self.ttf_by_method_csv()),
            ("platform_by_method.csv", self.platform_by_method_csv()),
            ("race_by_method.csv", self.race_by_method_csv()),
            ("ttf.csv", self.ttf_csv()),
            ("platform.csv", self.platform_csv()),
            ("race.csv", self.race_csv()),
        ];
        if !self.curves.is_empty() {
            files.push(("curves.csv", curve_csv(&self.curves)));
        }
        if !self.contrasts.is_empty() {
            files.push(("contrasts.csv", contrasts_csv(&self.contrasts)));
        }
        if !self.checkpoint_spread.is_empty() {
            files.push(("checkpoints.csv", self.checkpoints_csv()));
        }
        if !self.risk_signal.is_empty() {
            files.push((
                "risk_signal.csv",
                super::risk_signal::risk_csv(&self.risk_signal),
            ));
        }
        files
    }

    /// `runs.csv`: one row per run, its own and its common-ground tracking.
    fn runs_csv(&self) -> String {
        let tracking_columns = |prefix: &str| {
            ["lin_tracking", "yaw_tracking", "fall_rate"]
                .iter()
                .flat_map(|f| {
                    [
                        format!("{prefix}{f}"),
                        format!("{prefix}{f}_lo"),
                        format!("{prefix}{f}_hi"),
                    ]
                })
                .collect::<Vec<_>>()
                .join(",")
        };
        let mut runs = format!(
            "method,config,seed,iterations_done,iterations_target,env_steps,wall_clock_h,terrain_level,{}",
            tracking_columns("")
        );
        // one group of columns per common randomisation, named after its config file
        for c in &self.common_randomization {
            let _ = write!(
                runs,
                ",{}",
                tracking_columns(&format!("on_{}_", common_ground_name(Path::new(c))))
            );
        }
        runs.push('\n');
        let none = ",".repeat(8);
        for r in &self.runs {
            let own = r.tracking.map_or(none.clone(), |t| t.csv());
            let common: String = (0..self.common_randomization.len())
                .map(|k| {
                    format!(
                        ",{}",
                        r.common_tracking.get(k).map_or(none.clone(), |t| t.csv())
                    )
                })
                .collect();
            let _ = writeln!(
                runs,
                "{},{},{},{},{},{},{:.4},{},{own}{common}",
                csv_field(&r.label),
                csv_field(&r.config),
                r.seed,
                r.iterations_done,
                r.iterations_target,
                r.env_steps,
                r.wall_clock_h,
                opt(r.terrain_level),
            );
        }
        runs
    }

    /// `ttf.csv`: time to fall per cell.
    fn ttf_csv(&self) -> String {
        let mut ttf = String::from("method,load,terrain,push,ttf,ttf_lo,ttf_hi,robots,paper\n");
        for r in &self.ttf {
            let _ = writeln!(
                ttf,
                "{},{},{},{},{},{},{}",
                csv_field(&r.method),
                r.load,
                r.terrain,
                r.push,
                r.ttf.csv(4),
                r.robots,
                opt(r.paper)
            );
        }
        ttf
    }

    /// `platform.csv`: platform success per cell.
    fn platform_csv(&self) -> String {
        let mut platform =
            String::from("method,height_m,success_pct,success_lo,success_hi,robots,paper\n");
        for r in &self.platform {
            let _ = writeln!(
                platform,
                "{},{},{},{},{}",
                csv_field(&r.method),
                r.height_m,
                r.success_pct.csv(2),
                r.robots,
                opt(r.paper)
            );
        }
        platform
    }

    /// `race.csv`: race-track return quantiles per policy.
    fn race_csv(&self) -> String {
        let mut race = String::from("method,q25,q25_lo,q25_hi,q50,q50_lo,q50_hi,q75,q75_lo,q75_hi,mean_return,fall_fraction,episodes\n");
        for r in &self.race {
            let _ = writeln!(
                race,
                "{},{},{},{},{:.4},{:.4},{}",
                csv_field(&r.method),
                r.q25.csv(4),
                r.q50.csv(4),
                r.q75.csv(4),
                r.mean_return,
                r.fall_fraction,
                r.episodes
            );
        }
        race
    }

    /// `ttf_by_method.csv`: time to fall pooled over each method's seeds.
    fn ttf_by_method_csv(&self) -> String {
        let mut ttf_m =
            String::from("method,seeds,load,terrain,push,ttf,ttf_lo,ttf_hi,per_seed,robots\n");
        for r in &self.methods.ttf {
            let _ = writeln!(
                ttf_m,
                "{},{},{},{},{},{},{},{}",
                csv_field(&r.method.label),
                seeds(&r.method),
                r.load,
                r.terrain,
                r.push,
                r.ttf.csv(4),
                per_seed(&r.per_seed, 4),
                r.robots
            );
        }
        ttf_m
    }

    /// `platform_by_method.csv`: platform success pooled over seeds.
    fn platform_by_method_csv(&self) -> String {
        let mut platform_m = String::from(
            "method,seeds,height_m,success_pct,success_lo,success_hi,per_seed,robots\n",
        );
        for r in &self.methods.platform {
            let _ = writeln!(
                platform_m,
                "{},{},{},{},{},{}",
                csv_field(&r.method.label),
                seeds(&r.method),
                r.height_m,
                r.success_pct.csv(2),
                per_seed(&r.per_seed, 2),
                r.robots
            );
        }
        platform_m
    }

    /// `race_by_method.csv`: race quantiles pooled over seeds.
    fn race_by_method_csv(&self) -> String {
        let mut race_m = String::from("method,seeds,q25,q25_lo,q25_hi,q50,q50_lo,q50_hi,q75,q75_lo,q75_hi,per_seed_q25,per_seed_q50,per_seed_q75,fall_fraction,episodes\n");
        for r in &self.methods.race {
            let col = |k: usize| per_seed(&r.per_seed.iter().map(|q| q[k]).collect::<Vec<_>>(), 4);
            let _ = writeln!(
                race_m,
                "{},{},{},{},{},{},{},{},{:.4},{}",
                csv_field(&r.method.label),
                seeds(&r.method),
                r.q25.csv(4),
                r.q50.csv(4),
                r.q75.csv(4),
                col(0),
                col(1),
                col(2),
                r.fall_fraction,
                r.episodes
            );
        }
        race_m
    }

    /// `checkpoints.csv`: each benchmark's value at every kept checkpoint.
    fn checkpoints_csv(&self) -> String {
        let mut csv = String::from("benchmark,run,iteration,value\n");
        for c in &self.checkpoint_spread {
            for (it, v) in c.iterations.iter().zip(&c.values) {
                csv.push_str(&format!(
                    "{},{},{it},{v:.4}\n",
                    c.benchmark,
                    csv_field(&c.run)
                ));
            }
        }
        csv
    }

    /// Writes README.md, the CSVs, results.json and figures/ into `dir`: first all
    /// into a fresh folder beside it, then each file into place by a rename, so a
    /// failure while writing leaves what `dir` held untouched.
    pub fn write(&self, dir: &Path) -> Result<()> {
        let staging = fresh_staging(dir)?;
        self.write_into(&staging)?;
        move_staged(&staging, dir, &["", "figures"])?;
        Ok(())
    }

    /// Writes the README, the CSV tables and the figures of the results already in
    /// `dir` again from its `results.json` with the current code, `preface` opening
    /// the README, without evaluating anything: they are written into a staging
    /// folder, then renamed over the old ones. `results.json` and
    /// `evaluation_time.txt` stay as they are. Returns the files written.
    pub fn redraw(dir: &Path, preface: Option<String>) -> Result<Vec<PathBuf>> {
        let json = dir.join("results.json");
        let text = std::fs::read_to_string(&json).with_context(|| {
            format!(
                "reading {} (written by `rall experiment`; evaluate first)",
                json.display()
            )
        })?;
        let mut results: ExperimentResults = serde_json::from_str(&text)
            .with_context(|| format!("{} is not a results file of this version", json.display()))?;
        results.preface = preface;
        let staging = fresh_staging(dir)?;
        results.write_derived(&staging)?;
        move_staged(&staging, dir, &["", "figures"])
    }

    /// The whole evaluation's time, then each phase's: wall-clock minutes and
    /// processor minutes of every thread.
    fn evaluation_time_text(&self) -> String {
        let mut text = self
            .evaluation_time
            .as_ref()
            .map_or("not measured".into(), PhaseTime::show);
        text.push('\n');
        for p in &self.phases {
            text.push_str(&format!("  {}: {}\n", p.phase, p.show()));
        }
        text
    }

    /// What `results.json` determines, into `dir`: README.md, the CSV tables and
    /// the figures.
    fn write_derived(&self, dir: &Path) -> Result<()> {
        std::fs::create_dir_all(dir.join("figures"))
            .with_context(|| format!("creating {}", dir.display()))?;
        write_file(dir, "README.md", &self.markdown())?;
        for (name, text) in self.csv_files() {
            write_file(dir, name, &text)?;
        }
        super::plots::write_all(self, &dir.join("figures"))
    }

    fn write_into(&self, dir: &Path) -> Result<()> {
        self.write_derived(dir)?;
        write_file(dir, "results.json", &serde_json::to_string_pretty(self)?)?;
        write_file(dir, "evaluation_time.txt", &self.evaluation_time_text())
    }
}

/// Writes `text` to `dir/name`, naming the file on failure.
fn write_file(dir: &Path, name: &str, text: &str) -> Result<()> {
    let path = dir.join(name);
    std::fs::write(&path, text).with_context(|| format!("writing {}", path.display()))
}

/// An empty staging folder beside results folder `dir` (`.<name>.rall-tmp`).
fn fresh_staging(dir: &Path) -> Result<PathBuf> {
    let name = dir
        .file_name()
        .map_or("results".into(), |n| n.to_string_lossy().into_owned());
    let staging = dir.with_file_name(format!(".{name}.rall-tmp"));
    if staging.exists() {
        std::fs::remove_dir_all(&staging)
            .with_context(|| format!("removing {}", staging.display()))?;
    }
    Ok(staging)
}

/// Renames every file of `staging`'s subfolders `subs` ("" is the folder itself)
/// into the same subfolders of `dir`, then removes `staging`; returns the files'
/// new paths, sorted.
fn move_staged(staging: &Path, dir: &Path, subs: &[&str]) -> Result<Vec<PathBuf>> {
    let mut moved = Vec::new();
    for sub in subs {
        std::fs::create_dir_all(dir.join(sub))
            .with_context(|| format!("creating {}", dir.join(sub).display()))?;
        for entry in std::fs::read_dir(staging.join(sub))? {
            let path = entry?.path();
            if path.is_file() {
                let to = dir.join(sub).join(path.file_name().expect("a file name"));
                std::fs::rename(&path, &to)
                    .with_context(|| format!("moving {} to {}", path.display(), to.display()))?;
                moved.push(to);
            }
        }
    }
    std::fs::remove_dir_all(staging).with_context(|| format!("removing {}", staging.display()))?;
    moved.sort();
    Ok(moved)
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

/// The figures [`super::plots::write_all`] draws.
pub fn plots_list() -> [(&'static str, &'static str); 4] {
    [
        ("ttf.svg", "TTF per cell and method, seeds pooled, with intervals and a dot per seed (table I)"),
        ("platform.svg", "platform success per height and method, seeds pooled, a dot per seed (table II)"),
        ("race.svg", "race return quantiles per method (seeds pooled, a dot per seed) and the meta controller"),
        ("race_iqr.svg", "the risk-neutral critic's IQR and the meta controller's use of the safe policy along the race track (the paper's fig. 4, left)"),
    ]
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
