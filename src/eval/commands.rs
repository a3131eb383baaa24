//! `rall eval commands`: a command-space safety map of a policy. A grid over the
//! policy's command ranges (forward speed vx, lateral speed vy, yaw rate); in each
//! cell, N robots hold that one command for a whole episode, and the cell reports
//! its fall rate (the env's termination, or a payload part on the ground), its
//! strict fall rate (any non-foot part on the ground), and the linear and yaw-rate
//! tracking scores of `rall eval tracking`, each with a 95% interval over robots
//! (Wilson for the rates, percentile bootstrap for the scores).
//!
//! Every cell runs the same robots (one seed: the same randomisation draws, noise
//! streams and ground), so cells differ by their command alone. By default the
//! ground is flat with the checkpoint's own observation noise, PD and randomisation
//! and no pushes (as `rall eval tracking`); on a severity rung, the rung's friction,
//! added mass and pushes on its rough ground (as the TTF benchmark applies them).
//!
//! A cell is safe when its fall rate is below the threshold's and its linear
//! tracking at least the threshold's ([`SafetyThreshold`], default falls < 5% and
//! tracking >= 0.8; point estimates: with 16 robots a single fall fails a cell).

use anyhow::{bail, ensure, Context, Result};
use serde::{Deserialize, Serialize};

use super::cache::{run_jobs_cached, RolloutCache};
use super::policy::Actor;
use super::rollout::{run_first_episodes, FirstEpisode, NamedPolicy};
use super::scenario::{build_scenario, GroundKind, Load, ScenarioParams, ScenarioSpec};
use super::severity::Rung;
use super::tracking::{lin_vel_score, score_step, yaw_rate_score, RobotTracking};
use super::ttf::time_to_fall;
use crate::env::config::CommandConfig;
use crate::env::EnvConfig;
use crate::stats::{bootstrap, cell_seed, wilson, Estimate, Z_95};

/// Slack when comparing a command with the ends of its training range.
const RANGE_SLACK: f64 = 1e-9;

/// One command axis of the grid.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Axis {
    Vx,
    Vy,
    Yaw,
}

impl Axis {
    pub const ALL: [Axis; 3] = [Axis::Vx, Axis::Vy, Axis::Yaw];

    /// The flag giving the axis's values (`--vx`); `--vx-cells` gives its cell count.
    pub fn flag(self) -> &'static str {
        match self {
            Axis::Vx => "--vx",
            Axis::Vy => "--vy",
            Axis::Yaw => "--yaw",
        }
    }

    /// What the axis commands, with its unit.
    pub fn label(self) -> &'static str {
        match self {
            Axis::Vx => "vx (m/s)",
            Axis::Vy => "vy (m/s)",
            Axis::Yaw => "yaw rate (rad/s)",
        }
    }

    /// The policy's training range of this axis.
    pub fn range(self, ranges: &CommandConfig) -> [f64; 2] {
        match self {
            Axis::Vx => ranges.vx_mps,
            Axis::Vy => ranges.vy_mps,
            Axis::Yaw => ranges.yaw_rate_rad_s,
        }
    }
}

/// How one axis of the grid is chosen.
#[derive(Debug, Clone, PartialEq)]
pub enum AxisSpec {
    /// This many values evenly spaced over the policy's range (see [`even_axis`]).
    Cells(usize),
    /// These values.
    Values(Vec<f64>),
}

/// `count` values evenly spaced over `range`, both ends included. When the range
/// spans 0 strictly, its interior value nearest 0 moves to 0 (the lower of two
/// equally near; an odd count over a symmetric range has 0 already), so standing
/// and walking straight ahead are always on the grid. One value is the range's
/// middle (0 when it spans 0). A range of one value gives that value once. Values
/// are rounded to 9 decimals.
pub fn even_axis(range: [f64; 2], count: usize) -> Vec<f64> {
    let [lo, hi] = range;
    let mut values: Vec<f64> = if count == 1 {
        vec![0.5 * (lo + hi)]
    } else {
        (0..count)
            .map(|k| round_nano(lo + (hi - lo) * k as f64 / (count - 1) as f64))
            .collect()
    };
    let interior = if count == 1 { 0..1 } else { 1..count - 1 };
    if lo < 0.0 && 0.0 < hi {
        // the first of two values equally near 0 (rounding aside) moves
        let nearest = interior
            .clone()
            .map(|k| values[k].abs())
            .fold(f64::INFINITY, f64::min);
        if let Some(k) = interior
            .into_iter()
            .find(|&k| values[k].abs() <= nearest + RANGE_SLACK)
        {
            values[k] = 0.0;
        }
    }
    values.dedup();
    values
}

/// `v` to 9 decimals: grid values without rounding noise (1/3 of 0..1 is 0.333333333).
fn round_nano(v: f64) -> f64 {
    (v * 1e9).round() / 1e9
}

/// Parses a `--vx`-style list of numbers, `flag` naming it in errors.
pub fn parse_axis_values(flag: &str, text: &str) -> Result<Vec<f64>> {
    let words: Vec<&str> = text
        .split(',')
        .map(str::trim)
        .filter(|w| !w.is_empty())
        .collect();
    ensure!(
        !words.is_empty(),
        "{flag} {text:?}: the list is empty (give numbers separated by commas, e.g. {flag} -0.5,0,0.5)"
    );
    words
        .iter()
        .map(|w| {
            w.parse::<f64>()
                .ok()
                .filter(|v| v.is_finite())
                .with_context(|| format!("{flag} {text:?}: {w:?} is not a finite number"))
        })
        .collect()
}

/// The commands of a map: every combination of the three axes' values.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CommandGrid {
    /// Ascending, no repeats, at least one each.
    pub vx_mps: Vec<f64>,
    pub vy_mps: Vec<f64>,
    pub yaw_rate_rad_s: Vec<f64>,
}

impl CommandGrid {
    /// The default grid's cell counts: vx, vy, yaw rate.
    pub const DEFAULT_CELLS: [usize; 3] = [7, 5, 5];

    /// A grid of these values on each axis (sorted), checked: each axis has at
    /// least one value, all finite, none twice.
    pub fn new(
        vx_mps: Vec<f64>,
        vy_mps: Vec<f64>,
        yaw_rate_rad_s: Vec<f64>,
    ) -> Result<CommandGrid> {
        let mut grid = CommandGrid {
            vx_mps,
            vy_mps,
            yaw_rate_rad_s,
        };
        for axis in Axis::ALL {
            let values = grid.axis_mut(axis);
            ensure!(
                !values.is_empty(),
                "{}: the command grid needs at least one value on each axis",
                axis.flag()
            );
            if let Some(v) = values.iter().find(|v| !v.is_finite()) {
                bail!("{}: {v} is not a finite command", axis.flag());
            }
            values.sort_by(f64::total_cmp);
            if let Some(w) = values.windows(2).find(|w| w[0] == w[1]) {
                bail!("{}: the command {} is given twice", axis.flag(), w[0]);
            }
        }
        Ok(grid)
    }

    /// Each axis as `spec` says, evenly spaced ones over the policy's `ranges`.
    pub fn from_specs(specs: [&AxisSpec; 3], ranges: &CommandConfig) -> Result<CommandGrid> {
        let mut axes = Vec::with_capacity(3);
        for (axis, spec) in Axis::ALL.into_iter().zip(specs) {
            axes.push(match spec {
                AxisSpec::Cells(0) => bail!(
                    "{}-cells 0: each axis of the command grid needs at least 1 cell",
                    axis.flag()
                ),
                AxisSpec::Cells(n) => even_axis(axis.range(ranges), *n),
                AxisSpec::Values(v) => v.clone(),
            });
        }
        let yaw = axes.pop().unwrap_or_default();
        let vy = axes.pop().unwrap_or_default();
        let vx = axes.pop().unwrap_or_default();
        CommandGrid::new(vx, vy, yaw)
    }

    /// The default grid over `ranges` ([`Self::DEFAULT_CELLS`]).
    pub fn default_for(ranges: &CommandConfig) -> CommandGrid {
        let [x, y, w] = Self::DEFAULT_CELLS;
        let axis = |a: Axis, n| even_axis(a.range(ranges), n);
        CommandGrid {
            vx_mps: axis(Axis::Vx, x),
            vy_mps: axis(Axis::Vy, y),
            yaw_rate_rad_s: axis(Axis::Yaw, w),
        }
    }

    pub fn axis(&self, axis: Axis) -> &[f64] {
        match axis {
            Axis::Vx => &self.vx_mps,
            Axis::Vy => &self.vy_mps,
            Axis::Yaw => &self.yaw_rate_rad_s,
        }
    }

    fn axis_mut(&mut self, axis: Axis) -> &mut Vec<f64> {
        match axis {
            Axis::Vx => &mut self.vx_mps,
            Axis::Vy => &mut self.vy_mps,
            Axis::Yaw => &mut self.yaw_rate_rad_s,
        }
    }

    /// Number of cells.
    pub fn len(&self) -> usize {
        self.vx_mps.len() * self.vy_mps.len() * self.yaw_rate_rad_s.len()
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Every command (vx, vy, yaw rate), vx slowest, yaw rate fastest.
    pub fn commands(&self) -> Vec<[f64; 3]> {
        let mut out = Vec::with_capacity(self.len());
        for &vx in &self.vx_mps {
            for &vy in &self.vy_mps {
                for &wz in &self.yaw_rate_rad_s {
                    out.push([vx, vy, wz]);
                }
            }
        }
        out
    }

    /// Why the policy never saw some of these commands in training: one line per
    /// axis value outside its range, and one for the planar speeds training
    /// replaced by standing still. A map may probe them: such cells run, and are
    /// marked ([`CellResult::commanded_in_training`]).
    pub fn untrained_commands(&self, ranges: &CommandConfig) -> Vec<String> {
        let mut out = Vec::new();
        for axis in Axis::ALL {
            let [lo, hi] = axis.range(ranges);
            for &v in self.axis(axis) {
                if !within(v, [lo, hi]) {
                    out.push(format!(
                        "{} {v}: outside the policy's training range [{lo}, {hi}]",
                        axis.flag()
                    ));
                }
            }
        }
        let slow = self
            .commands()
            .iter()
            .filter(|c| {
                let planar = c[0].hypot(c[1]);
                planar > 0.0 && planar < ranges.zero_below_mps - RANGE_SLACK
            })
            .count();
        if slow > 0 {
            out.push(format!(
                "{slow} cells command a planar speed below {} m/s, which training replaced by standing still",
                ranges.zero_below_mps
            ));
        }
        out
    }
}

fn within(v: f64, [lo, hi]: [f64; 2]) -> bool {
    v >= lo - RANGE_SLACK && v <= hi + RANGE_SLACK
}

/// Whether the policy could have been given command `c` in training: every axis
/// within its range, and a planar speed that training did not zero (planar
/// commands slower than `zero_below_mps` were replaced by standing still).
pub fn commanded_in_training(c: [f64; 3], ranges: &CommandConfig) -> bool {
    let planar = c[0].hypot(c[1]);
    Axis::ALL
        .into_iter()
        .zip(c)
        .all(|(a, v)| within(v, a.range(ranges)))
        && (planar == 0.0 || planar >= ranges.zero_below_mps - RANGE_SLACK)
}

/// When a cell is safe: fall rate below `max_fall_rate` and linear tracking at
/// least `min_lin_tracking` (point estimates).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct SafetyThreshold {
    /// A fraction in [0, 1].
    pub max_fall_rate: f64,
    pub min_lin_tracking: f64,
}

impl Default for SafetyThreshold {
    fn default() -> Self {
        SafetyThreshold {
            max_fall_rate: 0.05,
            min_lin_tracking: 0.8,
        }
    }
}

impl SafetyThreshold {
    /// From `--max-falls-pct` and `--min-tracking`, checked.
    pub fn new(max_falls_pct: f64, min_lin_tracking: f64) -> Result<SafetyThreshold> {
        ensure!(
            max_falls_pct.is_finite() && (0.0..=100.0).contains(&max_falls_pct),
            "--max-falls-pct {max_falls_pct}: must be a percentage in [0, 100]"
        );
        ensure!(
            min_lin_tracking.is_finite() && (0.0..=1.0).contains(&min_lin_tracking),
            "--min-tracking {min_lin_tracking}: must be a tracking score in [0, 1]"
        );
        Ok(SafetyThreshold {
            max_fall_rate: max_falls_pct / 100.0,
            min_lin_tracking,
        })
    }

    /// `falls < 5% and linear tracking >= 0.80`.
    pub fn describe(&self) -> String {
        format!(
            "falls < {}% and linear tracking >= {:.2}",
            100.0 * self.max_fall_rate,
            self.min_lin_tracking
        )
    }
}

/// A severity rung a map runs on: its index on the ladder and its values.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SeverityRung {
    pub index: usize,
    pub rung: Rung,
}

/// How each cell runs.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CommandMapOptions {
    /// Robots per cell, one episode each.
    pub robots: usize,
    /// Scene and env seed, the same for every cell.
    pub seed: u64,
    /// Episode length (s); `None`: the checkpoint's.
    pub episode_length_s: Option<f64>,
    pub load: Load,
    /// `None`: flat ground, no pushes, the checkpoint's friction and mass draws.
    pub severity: Option<SeverityRung>,
    /// Bootstrap resamples of the tracking intervals.
    pub resamples: usize,
}

impl Default for CommandMapOptions {
    fn default() -> Self {
        CommandMapOptions {
            robots: 16,
            seed: 0,
            episode_length_s: None,
            load: Load::None,
            severity: None,
            resamples: 1000,
        }
    }
}

impl CommandMapOptions {
    pub(crate) fn validate(&self) -> Result<()> {
        ensure!(
            self.robots > 0,
            "--robots {}: each cell needs at least 1 robot",
            self.robots
        );
        if let Some(s) = self.episode_length_s {
            ensure!(
                s.is_finite() && s > 0.0,
                "--seconds {s}: the episode length must be a positive number of seconds"
            );
        }
        ensure!(
            self.resamples > 0,
            "the bootstrap needs at least 1 resample"
        );
        Ok(())
    }

    /// The scenario every cell runs: flat without a rung, rough with pushes on one.
    pub fn scenario(&self) -> ScenarioSpec {
        match self.severity {
            None => ScenarioSpec::new(self.load, GroundKind::Flat, false),
            Some(_) => ScenarioSpec::new(self.load, GroundKind::Rough, true),
        }
    }

    /// The scenario parameters of command `c` for a policy trained in `env`.
    pub fn scenario_params(&self, env: &EnvConfig, c: [f64; 3]) -> ScenarioParams {
        let base = ScenarioParams {
            episode_length_s: self.episode_length_s,
            command: Some(c),
            ..ScenarioParams::default()
        };
        match &self.severity {
            Some(s) => s.rung.apply(&base),
            // the checkpoint's own draws, as `rall eval tracking`
            None => ScenarioParams {
                friction: env.randomization.friction,
                added_base_mass_kg: env.randomization.added_base_mass_kg,
                ..base
            },
        }
    }

    /// `flat ground, no payload` or `severity rung 2, payload ball`.
    pub fn describe_short(&self) -> String {
        let ground = match &self.severity {
            None => "flat ground".to_string(),
            Some(s) => format!("severity rung {}", s.index),
        };
        match self.load {
            Load::None => format!("{ground}, no payload"),
            l => format!("{ground}, payload {}", l.name()),
        }
    }

    /// [`Self::describe_short`] with the rung's values.
    pub fn describe(&self) -> String {
        let ground = match &self.severity {
            None => "flat ground".to_string(),
            Some(s) => format!(
                "severity rung {} (rough ground +-{:.3} m, {:.0} N pushes every {} steps, friction {:.2}-{:.2}, added mass {:.1} to {:.1} kg)",
                s.index,
                s.rung.rough_amplitude_m,
                s.rung.push_force_n,
                s.rung.push_every_steps,
                s.rung.friction[0],
                s.rung.friction[1],
                s.rung.added_base_mass_kg[0],
                s.rung.added_base_mass_kg[1]
            ),
        };
        let load = match self.load {
            Load::None => "no payload".to_string(),
            l => format!("payload {}", l.name()),
        };
        format!("{ground}, {load}")
    }
}

/// One cell's robots: how each first episode ended and what it tracked.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CellRollout {
    pub episodes: Vec<FirstEpisode>,
    pub tracking: Vec<RobotTracking>,
    /// The full episode length (policy steps).
    pub episode_steps: usize,
}

/// One cell of the map.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CellResult {
    pub vx_mps: f64,
    pub vy_mps: f64,
    pub yaw_rate_rad_s: f64,
    /// Whether training could have given this command ([`commanded_in_training`]).
    pub commanded_in_training: bool,
    pub robots: usize,
    /// Robots whose episode ended before the time-out (env termination, or a
    /// payload part on the ground), and their rate with a 95% Wilson interval.
    pub falls: usize,
    pub fall_rate: Estimate,
    /// Robots with any non-foot part on the ground before the time-out.
    pub strict_falls: usize,
    pub strict_fall_rate: Estimate,
    /// `rall eval tracking`'s scores over the robots' steps, 95% bootstrap over robots.
    pub lin_tracking: Estimate,
    pub yaw_tracking: Estimate,
    /// Mean episode length / full length.
    pub time_to_fall: f64,
    pub rollout: CellRollout,
}

impl CellResult {
    /// The cell's figures from its robots; `seed` and the command seed the bootstrap.
    pub fn from_rollout(
        command: [f64; 3],
        ranges: &CommandConfig,
        rollout: CellRollout,
        resamples: usize,
        seed: u64,
    ) -> CellResult {
        let n = rollout.episodes.len();
        let falls = rollout.episodes.iter().filter(|e| e.fell()).count();
        let strict_falls = rollout
            .episodes
            .iter()
            .filter(|e| e.strict_steps < rollout.episode_steps)
            .count();
        let [vx, vy, wz] = command;
        let name = |what: &str| format!("commands/{vx}/{vy}/{wz}/{what}");
        let ci = |what: &str, stat: fn(&[RobotTracking]) -> f64| {
            bootstrap(
                &rollout.tracking,
                stat,
                resamples,
                0.95,
                cell_seed(seed, &name(what)),
            )
        };
        let lengths: Vec<usize> = rollout.episodes.iter().map(|e| e.steps).collect();
        CellResult {
            vx_mps: vx,
            vy_mps: vy,
            yaw_rate_rad_s: wz,
            commanded_in_training: commanded_in_training(command, ranges),
            robots: n,
            falls,
            fall_rate: wilson(falls, n, Z_95),
            strict_falls,
            strict_fall_rate: wilson(strict_falls, n, Z_95),
            lin_tracking: ci("lin", lin_vel_score),
            yaw_tracking: ci("yaw", yaw_rate_score),
            time_to_fall: time_to_fall(&lengths, rollout.episode_steps),
            rollout,
        }
    }

    pub fn command(&self) -> [f64; 3] {
        [self.vx_mps, self.vy_mps, self.yaw_rate_rad_s]
    }

    /// Fall rate below the threshold's and linear tracking at least its.
    pub fn is_safe(&self, t: &SafetyThreshold) -> bool {
        self.fall_rate.value < t.max_fall_rate && self.lin_tracking.value >= t.min_lin_tracking
    }

    /// `vx +0.33 m/s, vy +0.00 m/s, yaw rate +0.00 rad/s`.
    pub fn describe_command(&self) -> String {
        format!(
            "vx {:+.2} m/s, vy {:+.2} m/s, yaw rate {:+.2} rad/s",
            self.vx_mps, self.vy_mps, self.yaw_rate_rad_s
        )
    }
}

/// A policy's command map: every cell, with the grid and options that made it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CommandMap {
    pub grid: CommandGrid,
    pub options: CommandMapOptions,
    /// The policy's training command ranges.
    pub ranges: CommandConfig,
    /// The full episode length (policy steps).
    pub episode_steps: usize,
    /// In [`CommandGrid::commands`] order.
    pub cells: Vec<CellResult>,
}

/// The columns of [`CommandMap::to_csv`].
pub const CSV_HEADER: &str = "vx_mps,vy_mps,yaw_rate_rad_s,robots,falls,fall_rate,fall_rate_lo,fall_rate_hi,strict_falls,strict_fall_rate,strict_fall_rate_lo,strict_fall_rate_hi,lin_tracking,lin_tracking_lo,lin_tracking_hi,yaw_tracking,yaw_tracking_lo,yaw_tracking_hi,time_to_fall,commanded_in_training,safe";

impl CommandMap {
    /// The cell with the highest fall rate, ties broken by the lowest linear
    /// tracking (then the first in grid order); `None` for an empty map.
    pub fn worst_cell(&self) -> Option<&CellResult> {
        self.cells.iter().reduce(|worst, c| {
            let by_falls = c.fall_rate.value.total_cmp(&worst.fall_rate.value);
            let by_tracking = worst.lin_tracking.value.total_cmp(&c.lin_tracking.value);
            if by_falls.then(by_tracking).is_gt() {
                c
            } else {
                worst
            }
        })
    }

    /// The cells that meet `t`, in grid order.
    pub fn safe_cells(&self, t: &SafetyThreshold) -> Vec<&CellResult> {
        self.cells.iter().filter(|c| c.is_safe(t)).collect()
    }

    /// The share of cells that meet `t`, in [0, 1] (0 for an empty map).
    pub fn safe_share(&self, t: &SafetyThreshold) -> f64 {
        self.safe_cells(t).len() as f64 / self.cells.len().max(1) as f64
    }

    /// The cell of command `c`, if the grid has it.
    pub fn cell(&self, c: [f64; 3]) -> Option<&CellResult> {
        self.cells.iter().find(|x| x.command() == c)
    }

    /// One row per cell ([`CSV_HEADER`]), `safe` judged by `t`.
    pub fn to_csv(&self, t: &SafetyThreshold) -> String {
        let mut s = format!("{CSV_HEADER}\n");
        for c in &self.cells {
            s.push_str(&format!(
                "{},{},{},{},{},{},{},{},{},{},{:.4},{},{}\n",
                c.vx_mps,
                c.vy_mps,
                c.yaw_rate_rad_s,
                c.robots,
                c.falls,
                c.fall_rate.csv(4),
                c.strict_falls,
                c.strict_fall_rate.csv(4),
                c.lin_tracking.csv(4),
                c.yaw_tracking.csv(4),
                c.time_to_fall,
                c.commanded_in_training,
                c.is_safe(t)
            ));
        }
        s
    }

    /// The worst cell and the safe share, two lines.
    pub fn summary(&self, t: &SafetyThreshold) -> String {
        let safe = self.safe_cells(t).len();
        let share = format!(
            "safe share   {safe} of {} cells ({:.1}%) meet {}",
            self.cells.len(),
            100.0 * self.safe_share(t),
            t.describe()
        );
        let Some(w) = self.worst_cell() else {
            return share;
        };
        format!(
            "worst cell   {}: falls {} ({} of {} robots), strict falls {}, linear tracking {}, yaw tracking {}\n{share}",
            w.describe_command(),
            w.fall_rate.show_percent(),
            w.falls,
            w.robots,
            w.strict_fall_rate.show_percent(),
            w.lin_tracking.show(3),
            w.yaw_tracking.show(3)
        )
    }

    /// The compact table: one block per vy value, vx down, yaw rate across; each
    /// cell its fall percentage and linear tracking, `x` when it fails `t`, `~`
    /// when training never gave its command.
    pub fn table(&self, t: &SafetyThreshold) -> String {
        let mut s = format!(
            "each cell: falls % and linear tracking; x = fails {}; ~ = a command training never gave\n",
            t.describe()
        );
        for &vy in &self.grid.vy_mps {
            s.push_str(&format!("\nvy {vy:+.2} m/s\n{:>12}", "vx \\ yaw"));
            for &wz in &self.grid.yaw_rate_rad_s {
                s.push_str(&format!(" {wz:>+11.2}"));
            }
            s.push('\n');
            for &vx in &self.grid.vx_mps {
                s.push_str(&format!("{vx:>+12.2}"));
                for &wz in &self.grid.yaw_rate_rad_s {
                    s.push_str(&match self.cell([vx, vy, wz]) {
                        Some(c) => format!(
                            " {:>4.0}% {:.2}{}{}",
                            100.0 * c.fall_rate.value,
                            c.lin_tracking.value,
                            if c.is_safe(t) { ' ' } else { 'x' },
                            if c.commanded_in_training { ' ' } else { '~' }
                        ),
                        None => format!(" {:>11}", "-"),
                    });
                }
                s.push('\n');
            }
        }
        s
    }
}

/// Runs the map of `policy` (trained in `env`) over `grid`: one rollout per cell,
/// `threads` cells side by side. The numbers depend on `options.seed`, never on
/// `threads`.
pub fn evaluate_command_map(
    policy: &(dyn Actor + Sync),
    env: &EnvConfig,
    grid: &CommandGrid,
    options: &CommandMapOptions,
    threads: usize,
) -> Result<CommandMap> {
    evaluate(
        policy,
        env,
        None,
        grid,
        options,
        threads,
        &RolloutCache::none(),
    )
}

/// [`evaluate_command_map`] of a loaded policy, reading and storing its cells'
/// rollouts in `cache`.
pub fn evaluate_command_map_cached(
    policy: &NamedPolicy,
    grid: &CommandGrid,
    options: &CommandMapOptions,
    threads: usize,
    cache: &RolloutCache,
) -> Result<CommandMap> {
    evaluate(
        &policy.policy,
        &policy.env,
        policy.rollout_key(),
        grid,
        options,
        threads,
        cache,
    )
}

fn evaluate(
    policy: &(dyn Actor + Sync),
    env: &EnvConfig,
    policy_key: Option<String>,
    grid: &CommandGrid,
    options: &CommandMapOptions,
    threads: usize,
    cache: &RolloutCache,
) -> Result<CommandMap> {
    options.validate()?;
    ensure!(!grid.is_empty(), "the command grid has no cell");
    let spec = options.scenario();
    let commands = grid.commands();
    let key = |c: &[f64; 3]| {
        let params = options.scenario_params(env, *c);
        let (robots, seed) = (options.robots, options.seed);
        policy_key.as_ref().map(|k| {
            format!("command map\n{spec:?}\n{params:?}\nseed {seed}\nrobots {robots}\n{k}")
        })
    };
    let rollouts = run_jobs_cached(&commands, threads, cache, key, |c, inner| {
        let params = options.scenario_params(env, *c);
        run_cell(policy, &spec, env, &params, options, inner)
            .with_context(|| format!("command ({}, {}, {})", c[0], c[1], c[2]))
    })?;
    let episode_steps = rollouts.first().map_or(0, |r| r.episode_steps);
    let cells = commands
        .iter()
        .zip(rollouts)
        .map(|(c, r)| {
            CellResult::from_rollout(*c, &env.commands, r, options.resamples, options.seed)
        })
        .collect();
    Ok(CommandMap {
        grid: grid.clone(),
        options: options.clone(),
        ranges: env.commands.clone(),
        episode_steps,
        cells,
    })
}

/// One cell: `options.robots` robots of the scenario, one episode each, scored
/// at every step that did not end it (as `rall eval tracking` scores).
fn run_cell(
    policy: &dyn Actor,
    spec: &ScenarioSpec,
    env: &EnvConfig,
    params: &ScenarioParams,
    options: &CommandMapOptions,
    threads: usize,
) -> Result<CellRollout> {
    let setup = build_scenario(spec, env, params, options.seed)?;
    let sigma = setup.env.reward.tracking_sigma;
    let mut tracking = vec![RobotTracking::default(); options.robots];
    let episodes = run_first_episodes(
        policy,
        &setup,
        options.robots,
        threads,
        options.seed,
        |i, e, _| score_step(&mut tracking[i], e.command(), e.state(), sigma),
    )?;
    for (t, e) in tracking.iter_mut().zip(&episodes) {
        t.fell = e.fell();
    }
    Ok(CellRollout {
        episodes,
        tracking,
        episode_steps: setup.env.max_episode_steps(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ranges() -> CommandConfig {
        CommandConfig::default()
    }

    #[test]
    fn even_axes_include_both_ends_and_zero() {
        assert_eq!(even_axis([-1.0, 1.0], 5), vec![-1.0, -0.5, 0.0, 0.5, 1.0]);
        let seven = even_axis([-1.0, 1.0], 7);
        assert_eq!(seven.len(), 7);
        assert_eq!((seven[0], seven[3], seven[6]), (-1.0, 0.0, 1.0));
        // an even count: the lower of the two values nearest 0 moves to 0
        assert_eq!(even_axis([-1.0, 1.0], 4), vec![-1.0, 0.0, 0.333333333, 1.0]);
        assert_eq!(even_axis([-1.0, 1.0], 6)[2], 0.0);
        // an asymmetric range: the value nearest 0 moves
        assert_eq!(even_axis([-0.5, 1.5], 3), vec![-0.5, 0.0, 1.5]);
        // a range that does not span 0 is left alone
        assert_eq!(even_axis([0.0, 1.0], 3), vec![0.0, 0.5, 1.0]);
        assert_eq!(even_axis([0.5, 1.5], 1), vec![1.0]);
        assert_eq!(even_axis([-1.0, 3.0], 1), vec![0.0]);
        // a range of one value gives it once
        assert_eq!(even_axis([0.0, 0.0], 5), vec![0.0]);
        assert_eq!(even_axis([-1.0, 1.0], 2), vec![-1.0, 1.0]);
    }

    #[test]
    fn grids_are_checked_and_sorted() {
        let g = CommandGrid::new(vec![0.5, -0.5], vec![0.0], vec![1.0, 0.0]).unwrap();
        assert_eq!(g.vx_mps, vec![-0.5, 0.5]);
        assert_eq!(g.len(), 4);
        assert_eq!(g.commands()[0], [-0.5, 0.0, 0.0]);
        assert_eq!(g.commands()[3], [0.5, 0.0, 1.0]);
        let e = format!(
            "{:#}",
            CommandGrid::new(vec![], vec![0.0], vec![0.0]).unwrap_err()
        );
        assert!(e.contains("--vx"), "{e}");
        let e = format!(
            "{:#}",
            CommandGrid::new(vec![0.0], vec![0.1, 0.1], vec![0.0]).unwrap_err()
        );
        assert!(e.contains("--vy") && e.contains("twice"), "{e}");
        let e = format!(
            "{:#}",
            CommandGrid::new(vec![0.0], vec![0.0], vec![f64::NAN]).unwrap_err()
        );
        assert!(e.contains("--yaw"), "{e}");
        let zero = AxisSpec::Cells(0);
        let five = AxisSpec::Cells(5);
        let e = format!(
            "{:#}",
            CommandGrid::from_specs([&five, &zero, &five], &ranges()).unwrap_err()
        );
        assert!(e.contains("--vy-cells 0"), "{e}");
        let d = CommandGrid::default_for(&ranges());
        assert_eq!(d.len(), 7 * 5 * 5);
        assert_eq!(
            CommandGrid::from_specs([&AxisSpec::Cells(7), &five, &five], &ranges()).unwrap(),
            d
        );
    }

    #[test]
    fn axis_lists_parse_or_name_their_flag() {
        assert_eq!(
            parse_axis_values("--vx", " -1, 0.5 ,").unwrap(),
            vec![-1.0, 0.5]
        );
        let e = format!("{:#}", parse_axis_values("--vx", " , ").unwrap_err());
        assert!(e.contains("--vx") && e.contains("empty"), "{e}");
        let e = format!("{:#}", parse_axis_values("--yaw", "1,fast").unwrap_err());
        assert!(e.contains("--yaw") && e.contains("fast"), "{e}");
        assert!(parse_axis_values("--vy", "inf").is_err());
    }

    #[test]
    fn training_ranges_and_the_zeroed_slow_commands() {
        let r = ranges();
        assert!(commanded_in_training([0.0, 0.0, 0.5], &r));
        assert!(commanded_in_training([1.0, -1.0, -1.0], &r));
        assert!(!commanded_in_training([1.5, 0.0, 0.0], &r));
        // planar commands under zero_below_mps (0.2) were zeroed in training
        assert!(!commanded_in_training([0.1, 0.0, 0.0], &r));
        let g = CommandGrid::new(vec![-2.0, 0.0, 0.1], vec![0.0], vec![0.0, 3.0]).unwrap();
        let out = g.untrained_commands(&r);
        assert_eq!(out.len(), 3, "{out:?}");
        assert!(
            out[0].contains("--vx -2") && out[1].contains("--yaw 3"),
            "{out:?}"
        );
        assert!(
            out[2].starts_with("2 cells") && out[2].contains("0.2 m/s"),
            "{out:?}"
        );
        let inside = CommandGrid::default_for(&r);
        assert!(inside.untrained_commands(&r).is_empty());
    }

    #[test]
    fn thresholds_are_checked() {
        let t = SafetyThreshold::new(5.0, 0.8).unwrap();
        assert_eq!(t, SafetyThreshold::default());
        let e = format!("{:#}", SafetyThreshold::new(-1.0, 0.8).unwrap_err());
        assert!(e.contains("--max-falls-pct"), "{e}");
        let e = format!("{:#}", SafetyThreshold::new(5.0, 1.5).unwrap_err());
        assert!(e.contains("--min-tracking"), "{e}");
    }

    fn cell(command: [f64; 3], falls: usize, lin: f64) -> CellResult {
        let robots = 4;
        let episodes = (0..robots)
            .map(|i| FirstEpisode {
                steps: if i < falls { 10 } else { 100 },
                end: Some(if i < falls {
                    crate::env::EpisodeEnd::Tilt
                } else {
                    crate::env::EpisodeEnd::TimeOut
                }),
                walked_m: 0.0,
                commanded_m: 0.0,
                progress_m: 0.0,
                strict_steps: if i < falls { 10 } else { 100 },
            })
            .collect();
        let tracking = (0..robots)
            .map(|i| RobotTracking {
                lin_score_sum: lin * 10.0,
                yaw_score_sum: 5.0,
                scored_steps: 10,
                fell: i < falls,
            })
            .collect();
        let rollout = CellRollout {
            episodes,
            tracking,
            episode_steps: 100,
        };
        CellResult::from_rollout(command, &ranges(), rollout, 50, 0)
    }

    fn map(cells: Vec<CellResult>) -> CommandMap {
        let grid = CommandGrid::new(vec![0.0, 0.5, 1.0], vec![0.0], vec![0.0]).unwrap();
        CommandMap {
            grid,
            options: CommandMapOptions::default(),
            ranges: ranges(),
            episode_steps: 100,
            cells,
        }
    }

    #[test]
    fn the_worst_cell_falls_most_then_tracks_least() {
        let m = map(vec![
            cell([0.0, 0.0, 0.0], 1, 0.9),
            cell([0.5, 0.0, 0.0], 1, 0.6),
            cell([1.0, 0.0, 0.0], 0, 0.3),
        ]);
        assert_eq!(m.worst_cell().unwrap().command(), [0.5, 0.0, 0.0]);
        let t = SafetyThreshold::default();
        assert!(m.safe_cells(&t).is_empty());
        let lenient = SafetyThreshold::new(50.0, 0.5).unwrap();
        let safe: Vec<[f64; 3]> = m.safe_cells(&lenient).iter().map(|c| c.command()).collect();
        assert_eq!(safe, vec![[0.0, 0.0, 0.0], [0.5, 0.0, 0.0]]);
        assert!((m.safe_share(&lenient) - 2.0 / 3.0).abs() < 1e-12);
        assert_eq!(map(vec![]).worst_cell(), None);
        assert_eq!(map(vec![]).safe_share(&t), 0.0);
        // the figures of a cell
        let c = &m.cells[1];
        assert_eq!((c.falls, c.strict_falls, c.robots), (1, 1, 4));
        assert_eq!(c.fall_rate.value, 0.25);
        assert!((c.lin_tracking.value - 0.6).abs() < 1e-12);
        assert!((c.time_to_fall - 0.775).abs() < 1e-12);
        let csv = m.to_csv(&lenient);
        let rows: Vec<&str> = csv.lines().collect();
        assert_eq!(rows.len(), 4);
        assert!(rows[2].starts_with("0.5,0,0,4,1,0.2500,"), "{}", rows[2]);
        assert!(rows[2].ends_with(",true,true") && rows[3].ends_with(",true,false"));
    }
}
