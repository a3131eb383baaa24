//! The command-space safety map as a benchmark (`[commands]`): each listed run's
//! last checkpoint holds every command of a grid for one episode per robot
//! (`rall eval commands`: flat ground, no payload, no pushes, the checkpoint's own
//! observation noise, PD and randomisation). Per run: the share of safe cells and
//! the worst cell's fall rate (the highest over the cells); per method: their mean
//! over its seeds with a t-interval over seeds, and the worst cell of any seed.
//! Both numbers are also contrasts (`safe_share`, `worst_cell_falls`, one number
//! per seed) that `[verdicts]` may name. [`CommandMap`] is the built-in
//! [`Benchmark`] that runs it.

use anyhow::{ensure, Context, Result};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use super::benchmark::{Benchmark, BenchmarkContext, BenchmarkMetric, Evaluated};
use super::contrasts::{Contrast, CONTRAST_LEVEL};
use super::curves::Resampling;
use super::final_policy::load_final_policy;
use super::last_checkpoints::checkpoint_path;
use super::pooled::{methods_of, Method};
use super::spec::{ExperimentSpec, RunSpec};
use super::stats::{cell_seed, mean, percentile, Estimate};
use crate::eval::commands::CellResult;
use crate::eval::{
    evaluate_command_map_cached, lin_vel_score, CommandGrid, CommandMapOptions, NamedPolicy,
    RobotTracking, RolloutCache, SafetyThreshold,
};
use crate::stats::{student_t, wilson, Z_95};

/// The benchmark's name in `contrasts.csv`, and its two metrics.
pub const BENCHMARK: &str = "commands";
pub const SAFE_SHARE: &str = "safe_share";
pub const WORST_CELL_FALLS: &str = "worst_cell_falls";

/// `[commands]`: the runs to map, the grid, the robots and when a cell is safe.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CommandsSpec {
    /// Labels of the runs to map; a method's seeds pool (as in `[ttf]`).
    pub methods: Vec<String>,
    /// The grid's forward speeds (m/s); `vx` is read as well.
    #[serde(alias = "vx")]
    pub vx_mps: Vec<f64>,
    /// Lateral speeds (m/s); `vy` is read as well.
    #[serde(alias = "vy")]
    pub vy_mps: Vec<f64>,
    /// Yaw rates (rad/s); `yaw` is read as well.
    #[serde(alias = "yaw")]
    pub yaw_rate_rad_s: Vec<f64>,
    /// Robots per cell, one episode each.
    pub robots: usize,
    /// Scene and env seed, the same for every cell and run.
    #[serde(default)]
    pub seed: u64,
    /// Episode length (s); absent: each checkpoint's own.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub episode_s: Option<f64>,
    /// A safe cell's fall rate is below this (percent); default 5.
    #[serde(default = "default_max_falls_pct")]
    pub max_falls_pct: f64,
    /// ... and its linear tracking at least this; default 0.8.
    #[serde(default = "default_min_lin_tracking")]
    pub min_lin_tracking: f64,
}

fn default_max_falls_pct() -> f64 {
    100.0 * SafetyThreshold::default().max_fall_rate
}

fn default_min_lin_tracking() -> f64 {
    SafetyThreshold::default().min_lin_tracking
}

/// Refuses an axis of the grid that is empty, holds a non-finite number or a
/// value twice, naming its key.
fn check_axis(key: &str, values: &[f64]) -> Result<()> {
    ensure!(
        !values.is_empty(),
        "{key} lists no value: each axis of the command grid needs at least one"
    );
    if let Some(v) = values.iter().find(|v| !v.is_finite()) {
        anyhow::bail!("{key}: {v} is not a finite command");
    }
    let mut sorted = values.to_vec();
    sorted.sort_by(f64::total_cmp);
    if let Some(w) = sorted.windows(2).find(|w| w[0] == w[1]) {
        anyhow::bail!("{key} lists the command {} twice", w[0]);
    }
    Ok(())
}

/// The command map as a benchmark of `rall experiment` (section `[commands]`).
pub struct CommandMap;

impl Benchmark for CommandMap {
    type Section = CommandsSpec;
    type Output = CommandsResult;

    fn name(&self) -> &'static str {
        BENCHMARK
    }

    fn stage(&self) -> &'static str {
        "command-space maps"
    }

    fn validate(&self, section: &CommandsSpec, spec: &ExperimentSpec) -> Result<()> {
        section.validate(spec)
    }

    fn evaluate(
        &self,
        section: &CommandsSpec,
        cx: &BenchmarkContext,
    ) -> Result<Evaluated<CommandsResult>> {
        let (output, contrasts) =
            evaluate_commands(cx.spec, section, cx.available, cx.threads, cx.cache)?;
        Ok(Evaluated { output, contrasts })
    }

    /// The safe share, and the worst cell's fall rate (lower is safer).
    fn metrics(&self) -> Vec<BenchmarkMetric> {
        vec![
            BenchmarkMetric {
                name: SAFE_SHARE,
                title: "command map safe share",
                contrast_title: "command map: safe share",
                decimals: 3,
                lower_is_safer: false,
            },
            BenchmarkMetric {
                name: WORST_CELL_FALLS,
                title: "command map worst cell's fall rate",
                contrast_title: "command map: worst cell's fall rate",
                decimals: 3,
                lower_is_safer: true,
            },
        ]
    }

    fn compares(&self, section: &CommandsSpec, spec: &ExperimentSpec, label: &str) -> bool {
        section.maps_method_of(spec, label)
    }
}

impl CommandsSpec {
    /// The experiment's `[commands]` section (`None` without one); one that does
    /// not parse is refused, naming the key.
    pub fn of(spec: &ExperimentSpec) -> Result<Option<CommandsSpec>> {
        super::benchmark::section(spec, BENCHMARK)
            .map(|v| CommandsSpec::deserialize(v.clone()).context("[commands]"))
            .transpose()
    }

    /// Every method is a run label (none twice), the grid has a cell, the robots,
    /// the episode length and the threshold are usable; each refusal names its key.
    pub fn validate(&self, spec: &ExperimentSpec) -> Result<()> {
        ensure!(!self.methods.is_empty(), "commands.methods lists no run");
        for (i, m) in self.methods.iter().enumerate() {
            if spec.run(m).is_none() {
                let known: Vec<&str> = spec.runs.iter().map(|r| r.label.as_str()).collect();
                anyhow::bail!(
                    "commands.methods names {m:?}, which is not the label of any [[run]] ({})",
                    known.join(", ")
                );
            }
            ensure!(
                !self.methods[..i].contains(m),
                "commands.methods lists {m:?} twice"
            );
        }
        self.grid()?;
        ensure!(
            self.robots > 0,
            "commands.robots = 0: each cell needs at least 1 robot"
        );
        if let Some(s) = self.episode_s {
            ensure!(
                s.is_finite() && s > 0.0,
                "commands.episode_s = {s}: the episode length must be a positive number of seconds"
            );
        }
        self.threshold()?;
        Ok(())
    }

    /// The grid of `vx_mps` x `vy_mps` x `yaw_rate_rad_s`.
    pub fn grid(&self) -> Result<CommandGrid> {
        check_axis("commands.vx_mps", &self.vx_mps)?;
        check_axis("commands.vy_mps", &self.vy_mps)?;
        check_axis("commands.yaw_rate_rad_s", &self.yaw_rate_rad_s)?;
        CommandGrid::new(
            self.vx_mps.clone(),
            self.vy_mps.clone(),
            self.yaw_rate_rad_s.clone(),
        )
        .context("[commands] grid")
    }

    /// When a cell is safe.
    pub fn threshold(&self) -> Result<SafetyThreshold> {
        let p = self.max_falls_pct;
        ensure!(
            p.is_finite() && (0.0..=100.0).contains(&p),
            "commands.max_falls_pct = {p}: must be a percentage in [0, 100]"
        );
        let t = self.min_lin_tracking;
        ensure!(
            t.is_finite() && (0.0..=1.0).contains(&t),
            "commands.min_lin_tracking = {t}: must be a tracking score in [0, 1]"
        );
        SafetyThreshold::new(p, t)
    }

    /// How every cell runs: flat ground, no payload, no pushes (the defaults),
    /// `resamples` for the tracking intervals.
    pub fn options(&self, resamples: usize) -> CommandMapOptions {
        CommandMapOptions {
            robots: self.robots,
            seed: self.seed,
            episode_length_s: self.episode_s,
            resamples,
            ..CommandMapOptions::default()
        }
    }

    /// Whether some run of `label`'s method (runs of the same `name`) is mapped.
    pub fn maps_method_of(&self, spec: &ExperimentSpec, label: &str) -> bool {
        let name = |l: &str| spec.run(l).map(|r| r.name.clone());
        let wanted = name(label);
        wanted.is_some() && self.methods.iter().any(|m| name(m) == wanted)
    }
}

/// One cell of one run's map as the results keep it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CommandCell {
    pub vx_mps: f64,
    pub vy_mps: f64,
    pub yaw_rate_rad_s: f64,
    /// Whether training could have given this command.
    pub commanded_in_training: bool,
    pub robots: usize,
    /// Robots whose episode ended before the time-out.
    pub falls: usize,
    /// Robots with any non-foot part on the ground before the time-out.
    pub strict_falls: usize,
    /// 95% bootstrap over robots.
    pub lin_tracking: Estimate,
    pub yaw_tracking: Estimate,
}

impl CommandCell {
    fn of(c: &CellResult) -> CommandCell {
        CommandCell {
            vx_mps: c.vx_mps,
            vy_mps: c.vy_mps,
            yaw_rate_rad_s: c.yaw_rate_rad_s,
            commanded_in_training: c.commanded_in_training,
            robots: c.robots,
            falls: c.falls,
            strict_falls: c.strict_falls,
            lin_tracking: c.lin_tracking,
            yaw_tracking: c.yaw_tracking,
        }
    }

    pub fn command(&self) -> [f64; 3] {
        [self.vx_mps, self.vy_mps, self.yaw_rate_rad_s]
    }

    /// The fall rate with its 95% Wilson interval (as `rall eval commands` gives it).
    pub fn fall_rate(&self) -> Estimate {
        wilson(self.falls, self.robots, Z_95)
    }

    /// Fall rate below the threshold's and linear tracking at least its.
    pub fn is_safe(&self, t: &SafetyThreshold) -> bool {
        self.fall_rate().value < t.max_fall_rate && self.lin_tracking.value >= t.min_lin_tracking
    }

    /// `vx +0.30, vy +0.00 m/s, yaw +0.00 rad/s`.
    pub fn describe_command(&self) -> String {
        format!(
            "vx {:+.2}, vy {:+.2} m/s, yaw {:+.2} rad/s",
            self.vx_mps, self.vy_mps, self.yaw_rate_rad_s
        )
    }
}

/// The cell that falls most, ties broken by the lowest linear tracking, then the
/// first (the rule of `rall eval commands`); `None` for no cell.
pub fn worst_of<'a>(cells: impl IntoIterator<Item = &'a CommandCell>) -> Option<&'a CommandCell> {
    cells.into_iter().reduce(|worst, c| {
        let by_falls = c.fall_rate().value.total_cmp(&worst.fall_rate().value);
        let by_tracking = worst.lin_tracking.value.total_cmp(&c.lin_tracking.value);
        if by_falls.then(by_tracking).is_gt() {
            c
        } else {
            worst
        }
    })
}

/// One run's map.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RunCommands {
    pub label: String,
    /// Its method (the method's first seed's label).
    pub method: String,
    pub seed: u64,
    /// Which checkpoint was mapped, in words.
    pub checkpoint: String,
    /// Its iteration, when known.
    pub iteration: Option<usize>,
    /// Episode length (s).
    pub episode_s: f64,
    /// In grid order (vx slowest, yaw rate fastest).
    pub cells: Vec<CommandCell>,
}

impl RunCommands {
    /// Safe cells / cells (0 without cells).
    pub fn safe_share(&self, t: &SafetyThreshold) -> f64 {
        let safe = self.cells.iter().filter(|c| c.is_safe(t)).count();
        safe as f64 / self.cells.len().max(1) as f64
    }

    pub fn worst_cell(&self) -> Option<&CommandCell> {
        worst_of(&self.cells)
    }

    /// The worst cell's fall rate (0 without cells).
    pub fn worst_cell_falls(&self) -> f64 {
        self.worst_cell().map_or(0.0, |c| c.fall_rate().value)
    }
}

/// A method's mean over its seeds, with a t-interval over seeds (none with one
/// seed) and each seed's value.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SeedMean {
    pub mean: f64,
    pub lo: Option<f64>,
    pub hi: Option<f64>,
    pub per_seed: Vec<f64>,
}

impl SeedMean {
    /// The mean of `per_seed` and Student's t-interval at `level` (n - 1 degrees
    /// of freedom: Welch's interval of one method), clipped to [0, 1] as both
    /// metrics are fractions; no interval under two seeds.
    pub fn of(per_seed: Vec<f64>, level: f64) -> SeedMean {
        let n = per_seed.len();
        let m = mean(&per_seed);
        let (lo, hi) = if n >= 2 {
            let var = per_seed.iter().map(|x| (x - m).powi(2)).sum::<f64>() / (n - 1) as f64;
            let half =
                student_t::quantile(0.5 + level / 2.0, (n - 1) as f64) * (var / n as f64).sqrt();
            (Some((m - half).max(0.0)), Some((m + half).min(1.0)))
        } else {
            (None, None)
        };
        SeedMean {
            mean: m,
            lo,
            hi,
            per_seed,
        }
    }
}

/// One method over its seeds.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MethodCommands {
    pub method: Method,
    /// Its figure's file name in `figures/`.
    pub figure: String,
    pub safe_share: SeedMean,
    pub worst_cell_falls: SeedMean,
    /// Seeds with some cell whose fall rate reaches the threshold's.
    pub seeds_falling: usize,
    /// The worst cell over every seed's cells, and the run it is of.
    pub worst_run: String,
    pub worst: CommandCell,
}

/// Everything `[commands]` measured.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CommandsResult {
    pub grid: CommandGrid,
    pub robots: usize,
    pub seed: u64,
    pub threshold: SafetyThreshold,
    /// Where the robots walk (`flat ground, no payload`).
    pub conditions: String,
    pub runs: Vec<RunCommands>,
    pub methods: Vec<MethodCommands>,
}

/// The checkpoint `[commands]` maps of run `r`: its last headline checkpoint
/// (`checkpoints/model_<target>.safetensors`, in its run directory or shipped
/// copy), else its final policy; with which it is in words and its iteration.
fn map_policy(spec: &ExperimentSpec, r: &RunSpec) -> Result<(NamedPolicy, String, Option<usize>)> {
    let target = super::run_target(spec, r)?;
    if let Ok(path) = checkpoint_path(spec, r, target) {
        let what = format!("iteration {target} (its last checkpoint)");
        return Ok((NamedPolicy::load(&r.label, &path)?, what, Some(target)));
    }
    let (policy, chosen) = load_final_policy(spec, &r.label)?;
    let what = match chosen {
        Some(it) => format!(
            "iteration {it} (its final policy, the [selection] choice: no checkpoint of iteration {target})"
        ),
        None => format!("its newest checkpoint (no checkpoint of iteration {target})"),
    };
    Ok((policy, what, chosen))
}

/// A file name for each method's figure: `commands_<label>.svg`, the label in
/// lower case with every run of other characters than [a-z0-9] as one `-`, made
/// unique by a number.
fn figure_names(methods: &[Method]) -> Vec<String> {
    let mut out: Vec<String> = Vec::new();
    for m in methods {
        let mut slug = String::new();
        for c in m.label.chars().map(|c| c.to_ascii_lowercase()) {
            if c.is_ascii_alphanumeric() {
                slug.push(c);
            } else if !slug.is_empty() && !slug.ends_with('-') {
                slug.push('-');
            }
        }
        let slug = slug.trim_end_matches('-');
        let slug = if slug.is_empty() { "method" } else { slug };
        let mut name = format!("commands_{slug}.svg");
        let mut k = 2;
        while out.contains(&name) {
            name = format!("commands_{slug}-{k}.svg");
            k += 1;
        }
        out.push(name);
    }
    out
}

/// Each mapped run's robots, per cell (kept for the contrasts' bootstrap).
type RunRobots = Vec<Vec<RobotTracking>>;

/// Maps every run of `cs.methods` that has a checkpoint (`available`), one run
/// after the other, its cells on `threads` workers through `cache`; returns the
/// results and the contrasts of `[contrasts]`' pairs on the two metrics.
pub(super) fn evaluate_commands(
    spec: &ExperimentSpec,
    cs: &CommandsSpec,
    available: &[String],
    threads: usize,
    cache: &RolloutCache,
) -> Result<(CommandsResult, Vec<Contrast>)> {
    let grid = cs.grid()?;
    let threshold = cs.threshold()?;
    let options = cs.options(spec.bootstrap.resamples);
    let labels: Vec<String> = cs
        .methods
        .iter()
        .filter(|l| available.contains(l))
        .cloned()
        .collect();
    let methods = methods_of(spec, &labels);
    let mut runs = Vec::new();
    let mut robots: Vec<RunRobots> = Vec::new();
    for label in &labels {
        let r = spec
            .run(label)
            .with_context(|| format!("no run labelled {label:?}"))?;
        let (policy, checkpoint, iteration) = map_policy(spec, r)?;
        for w in grid.untrained_commands(&policy.env.commands) {
            eprintln!("  note: {label}: {w}; its cells run");
        }
        let map = evaluate_command_map_cached(&policy, &grid, &options, threads, cache)
            .with_context(|| format!("[commands]: run {label:?}"))?;
        let method = methods
            .iter()
            .find(|m| m.seeds.contains(label))
            .map_or(label.clone(), |m| m.label.clone());
        let run = RunCommands {
            label: label.clone(),
            method,
            seed: r.seed,
            checkpoint,
            iteration,
            episode_s: map.episode_steps as f64 * policy.env.control.policy_dt_s(),
            cells: map.cells.iter().map(CommandCell::of).collect(),
        };
        eprintln!(
            "  {:<24} safe share {:.1}%, worst cell {:.1}% falls",
            label,
            100.0 * run.safe_share(&threshold),
            100.0 * run.worst_cell_falls()
        );
        robots.push(map.cells.into_iter().map(|c| c.rollout.tracking).collect());
        runs.push(run);
    }
    let rows = method_rows(&methods, &runs, &threshold);
    let r = Resampling {
        resamples: spec.bootstrap.resamples,
        level: spec.bootstrap.level,
        seed: spec.bootstrap.seed,
    };
    let contrasts = command_contrasts(spec, &methods, (&runs, &robots), &threshold, r);
    let result = CommandsResult {
        grid,
        robots: cs.robots,
        seed: cs.seed,
        threshold,
        conditions: options.describe_short(),
        runs,
        methods: rows,
    };
    Ok((result, contrasts))
}

/// Each method's row: its seeds' safe shares and worst-cell fall rates, their
/// means, and the worst cell over all its seeds.
pub fn method_rows(
    methods: &[Method],
    runs: &[RunCommands],
    t: &SafetyThreshold,
) -> Vec<MethodCommands> {
    let figures = figure_names(methods);
    let mut out = Vec::new();
    for (m, figure) in methods.iter().zip(figures) {
        let seeds: Vec<&RunCommands> = m
            .seeds
            .iter()
            .filter_map(|l| runs.iter().find(|r| &r.label == l))
            .collect();
        let worst_falls: Vec<f64> = seeds.iter().map(|r| r.worst_cell_falls()).collect();
        let worst = seeds
            .iter()
            .filter_map(|r| Some((r.label.clone(), r.worst_cell()?)))
            .reduce(|a, b| {
                // the same rule over the seeds' worst cells, the first seed on a tie
                match worst_of([a.1, b.1]) {
                    Some(w) if std::ptr::eq(w, b.1) => b,
                    _ => a,
                }
            });
        let Some((worst_run, worst)) = worst else {
            continue;
        };
        out.push(MethodCommands {
            method: m.clone(),
            figure,
            safe_share: SeedMean::of(
                seeds.iter().map(|r| r.safe_share(t)).collect(),
                CONTRAST_LEVEL,
            ),
            seeds_falling: worst_falls
                .iter()
                .filter(|&&f| f >= t.max_fall_rate)
                .count(),
            worst_cell_falls: SeedMean::of(worst_falls, CONTRAST_LEVEL),
            worst_run,
            worst: worst.clone(),
        });
    }
    out
}

/// A seed's cells of robots: the safe share of its cells.
fn robots_safe_share(cells: &[Vec<RobotTracking>], t: &SafetyThreshold) -> f64 {
    let safe = cells
        .iter()
        .filter(|robots| {
            let falls = robots.iter().filter(|r| r.fell).count();
            (falls as f64 / robots.len().max(1) as f64) < t.max_fall_rate
                && lin_vel_score(robots) >= t.min_lin_tracking
        })
        .count();
    safe as f64 / cells.len().max(1) as f64
}

/// A seed's cells of robots: the highest fall rate of a cell.
fn robots_worst_falls(cells: &[Vec<RobotTracking>]) -> f64 {
    cells
        .iter()
        .map(|robots| robots.iter().filter(|r| r.fell).count() as f64 / robots.len().max(1) as f64)
        .fold(0.0, f64::max)
}

/// The seeds of one method: each its cells of robots.
type Seeds<'a> = Vec<&'a RunRobots>;

/// A seed's number from its cells of robots.
type CellStat<'a> = &'a dyn Fn(&[Vec<RobotTracking>]) -> f64;

/// The difference of the two methods' seed means of `stat`, with its percentile
/// bootstrap over robots: every cell's robots of every seed drawn with
/// replacement, the seeds kept as they are (seeded by `name`).
fn over_robots((a, b): (&Seeds, &Seeds), stat: CellStat, r: Resampling, name: &str) -> Estimate {
    let seed_mean = |seeds: &[Vec<Vec<RobotTracking>>]| {
        mean(&seeds.iter().map(|s| stat(s)).collect::<Vec<_>>())
    };
    let as_is = |s: &Seeds| s.iter().map(|x| (*x).clone()).collect::<Vec<_>>();
    let value = seed_mean(&as_is(a)) - seed_mean(&as_is(b));
    let mut rng = ChaCha8Rng::seed_from_u64(cell_seed(r.seed, &format!("{name}/robots")));
    let mut draw = |seeds: &Seeds| -> Vec<Vec<Vec<RobotTracking>>> {
        seeds
            .iter()
            .map(|cells| {
                cells
                    .iter()
                    .map(|robots| {
                        let n = robots.len();
                        (0..n).map(|_| robots[rng.gen_range(0..n)]).collect()
                    })
                    .collect()
            })
            .collect()
    };
    let mut diffs: Vec<f64> = (0..r.resamples)
        .map(|_| {
            let (da, db) = (draw(a), draw(b));
            seed_mean(&da) - seed_mean(&db)
        })
        .collect();
    diffs.sort_by(f64::total_cmp);
    let alpha = (1.0 - r.level) / 2.0;
    Estimate {
        value,
        lo: percentile(&diffs, alpha),
        hi: percentile(&diffs, 1.0 - alpha),
    }
}

/// Every pair of `[contrasts]` whose two methods were both mapped, on the safe
/// share and on the worst cell's fall rate (rung 0: the map has no rung).
fn command_contrasts(
    spec: &ExperimentSpec,
    methods: &[Method],
    (runs, robots): (&[RunCommands], &[RunRobots]),
    t: &SafetyThreshold,
    r: Resampling,
) -> Vec<Contrast> {
    let Some(c) = &spec.contrasts else {
        return Vec::new();
    };
    let seeds_of = |m: &Method| -> (Seeds, Vec<String>) {
        m.seeds
            .iter()
            .filter_map(|l| {
                let k = runs.iter().position(|x| &x.label == l)?;
                Some((&robots[k], l.clone()))
            })
            .unzip()
    };
    let safe = |cells: &[Vec<RobotTracking>]| robots_safe_share(cells, t);
    let metrics: [(&str, CellStat); 2] =
        [(SAFE_SHARE, &safe), (WORST_CELL_FALLS, &robots_worst_falls)];
    let mut out = Vec::new();
    for [a, b] in &c.pairs {
        let find = |l: &String| methods.iter().find(|m| m.seeds.contains(l));
        let (Some(ma), Some(mb)) = (find(a), find(b)) else {
            continue;
        };
        let ((sa, la), (sb, lb)) = (seeds_of(ma), seeds_of(mb));
        if sa.is_empty() || sb.is_empty() {
            continue;
        }
        for (metric, stat) in metrics {
            let name = format!("contrast/{BENCHMARK}/{metric}/{}/{}/0", ma.label, mb.label);
            out.push(Contrast {
                benchmark: BENCHMARK.into(),
                metric: metric.into(),
                severity: 0,
                first: ma.label.clone(),
                second: mb.label.clone(),
                over_robots: over_robots((&sa, &sb), stat, r, &name),
                first_seeds: sa.iter().map(|s| stat(s)).collect(),
                second_seeds: sb.iter().map(|s| stat(s)).collect(),
                first_labels: la.clone(),
                second_labels: lb.clone(),
            });
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn est(v: f64) -> Estimate {
        Estimate {
            value: v,
            lo: v,
            hi: v,
        }
    }

    fn cell(vx: f64, falls: usize, lin: f64) -> CommandCell {
        CommandCell {
            vx_mps: vx,
            vy_mps: 0.0,
            yaw_rate_rad_s: 0.0,
            commanded_in_training: true,
            robots: 8,
            falls,
            strict_falls: falls,
            lin_tracking: est(lin),
            yaw_tracking: est(0.9),
        }
    }

    fn run(label: &str, cells: Vec<CommandCell>) -> RunCommands {
        RunCommands {
            label: label.into(),
            method: "A".into(),
            seed: 1,
            checkpoint: "iteration 2 (its last checkpoint)".into(),
            iteration: Some(2),
            episode_s: 20.0,
            cells,
        }
    }

    #[test]
    fn a_run_reports_its_safe_share_and_its_worst_cell() {
        let t = SafetyThreshold::default();
        let r = run(
            "A",
            vec![
                cell(0.0, 0, 0.9),
                cell(0.3, 2, 0.9),
                cell(1.0, 2, 0.5),
                cell(0.5, 0, 0.7),
            ],
        );
        assert_eq!(r.safe_share(&t), 0.25);
        // two cells fall 2 of 8: the one tracking worse is the worst
        assert_eq!(r.worst_cell().unwrap().vx_mps, 1.0);
        assert_eq!(r.worst_cell_falls(), 0.25);
        assert_eq!(run("B", vec![]).worst_cell(), None);
    }

    #[test]
    fn methods_pool_their_seeds_with_a_t_interval_and_one_seed_has_none() {
        let t = SafetyThreshold::default();
        let methods = vec![
            Method {
                label: "A".into(),
                seeds: vec!["A".into(), "A seed 2".into(), "A seed 3".into()],
            },
            Method {
                label: "B + c".into(),
                seeds: vec!["B + c".into()],
            },
        ];
        let runs = vec![
            run("A", vec![cell(0.0, 0, 0.9), cell(0.3, 1, 0.9)]),
            run("A seed 2", vec![cell(0.0, 0, 0.9), cell(0.3, 4, 0.9)]),
            run("A seed 3", vec![cell(0.0, 0, 0.9), cell(0.3, 0, 0.9)]),
            run("B + c", vec![cell(0.0, 0, 0.9), cell(0.3, 0, 0.9)]),
        ];
        let rows = method_rows(&methods, &runs, &t);
        let a = &rows[0];
        assert_eq!(a.safe_share.per_seed, vec![0.5, 0.5, 1.0]);
        assert!((a.safe_share.mean - 2.0 / 3.0).abs() < 1e-12);
        // t(0.975, 2) = 4.303, sd 0.2887 / sqrt(3): half-width 0.717, clipped to [0, 1]
        assert_eq!(a.safe_share.lo, Some(0.0));
        assert_eq!(a.safe_share.hi, Some(1.0));
        assert_eq!(a.worst_cell_falls.per_seed, vec![0.125, 0.5, 0.0]);
        let (lo, hi) = (
            a.worst_cell_falls.lo.unwrap(),
            a.worst_cell_falls.hi.unwrap(),
        );
        let half = 4.302_652_7 * (0.067_708_333_f64 / 3.0).sqrt();
        assert!((hi - (0.208_333_333 + half).min(1.0)).abs() < 1e-6, "{hi}");
        assert_eq!(lo, 0.0);
        assert_eq!(a.seeds_falling, 2);
        assert_eq!((a.worst_run.as_str(), a.worst.falls), ("A seed 2", 4));
        assert_eq!(a.figure, "commands_a.svg");
        let b = &rows[1];
        assert_eq!((b.safe_share.mean, b.safe_share.lo), (1.0, None));
        assert_eq!(b.figure, "commands_b-c.svg");
    }

    #[test]
    fn figure_names_are_plain_and_unique() {
        let m = |l: &str| Method {
            label: l.into(),
            seeds: vec![l.into()],
        };
        assert_eq!(
            figure_names(&[m("RALL eta=1"), m("RALL eta 1"), m("++")]),
            [
                "commands_rall-eta-1.svg",
                "commands_rall-eta-1-2.svg",
                "commands_method.svg"
            ]
        );
    }

    fn robot(fell: bool, lin: f64) -> RobotTracking {
        RobotTracking {
            lin_score_sum: lin * 10.0,
            yaw_score_sum: 9.0,
            scored_steps: 10,
            fell,
        }
    }

    #[test]
    fn the_robot_level_statistics_match_the_cells() {
        let t = SafetyThreshold::default();
        let cells = vec![
            vec![robot(false, 0.9); 4],
            vec![
                robot(true, 0.9),
                robot(false, 0.9),
                robot(false, 0.9),
                robot(false, 0.9),
            ],
            vec![robot(false, 0.5); 4],
        ];
        assert!((robots_safe_share(&cells, &t) - 1.0 / 3.0).abs() < 1e-12);
        assert_eq!(robots_worst_falls(&cells), 0.25);
        // a difference over robots: the same robots give the same interval
        let other = vec![vec![robot(false, 0.9); 4]; 3];
        let (a, b) = (vec![&cells], vec![&other]);
        let r = Resampling {
            resamples: 200,
            level: 0.95,
            seed: 1,
        };
        let e = over_robots((&a, &b), &robots_worst_falls, r, "t");
        assert_eq!(e.value, 0.25);
        assert!(e.lo <= e.value && e.value <= e.hi, "{e:?}");
        assert_eq!(over_robots((&a, &b), &robots_worst_falls, r, "t"), e);
    }
}
