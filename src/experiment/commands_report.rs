//! The command maps in the results: `commands.csv` (every cell of every run),
//! `commands_by_method.csv`, the README's section "Commands a policy cannot
//! hold" and each method's figure, all from [`CommandsResult`] alone (so
//! `--redraw` rebuilds them): the command map's [`BenchmarkOutput`].

use std::fmt::Write as _;
use std::path::Path;

use anyhow::{bail, Result};

use super::benchmark::{BenchmarkOutput, FigureEntry};
use super::command_plots::commands_figure;
use super::commands::{CommandCell, CommandsResult, MethodCommands, SeedMean};
use crate::eval::report::csv_field;

/// `-1, -0.5, 0` (a grid axis).
fn values(v: &[f64]) -> String {
    v.iter()
        .map(|x| format!("{x}"))
        .collect::<Vec<_>>()
        .join(", ")
}

/// An optional number with 4 decimals as a CSV field (empty when absent).
fn opt4(v: Option<f64>) -> String {
    v.map_or(String::new(), |x| format!("{x:.4}"))
}

/// `83.3% [78.0, 88.6] {81.5, 85.2}`: a fraction's seed mean in percent, its
/// interval over seeds when it has one, each seed's value when there are two.
fn show_seed_mean(m: &SeedMean) -> String {
    let mut s = format!("{:.1}%", 100.0 * m.mean);
    if let (Some(lo), Some(hi)) = (m.lo, m.hi) {
        let _ = write!(s, " [{:.1}, {:.1}]", 100.0 * lo, 100.0 * hi);
    }
    if m.per_seed.len() > 1 {
        let seeds: Vec<String> = m
            .per_seed
            .iter()
            .map(|v| format!("{:.1}", 100.0 * v))
            .collect();
        let _ = write!(s, " {{{}}}", seeds.join(", "));
    }
    s
}

/// `vx +0.30, vy +0.00 m/s, yaw +0.00 rad/s: 4 of 8 robots fell (RALL seed 3)`.
fn show_worst(m: &MethodCommands) -> String {
    let c: &CommandCell = &m.worst;
    format!(
        "{}: {} of {} robots fell, linear tracking {:.2} ({})",
        c.describe_command(),
        c.falls,
        c.robots,
        c.lin_tracking.value,
        m.worst_run
    )
}

impl CommandsResult {
    /// `commands.csv`: one row per run and cell.
    pub fn cells_csv(&self) -> String {
        let mut s = String::from(
            "method,label,seed,checkpoint_iteration,vx_mps,vy_mps,yaw_rate_rad_s,commanded_in_training,robots,falls,fall_rate,fall_rate_lo,fall_rate_hi,strict_falls,lin_tracking,lin_tracking_lo,lin_tracking_hi,yaw_tracking,yaw_tracking_lo,yaw_tracking_hi,safe\n",
        );
        for r in &self.runs {
            for c in &r.cells {
                let _ = writeln!(
                    s,
                    "{},{},{},{},{},{},{},{},{},{},{},{},{},{},{}",
                    csv_field(&r.method),
                    csv_field(&r.label),
                    r.seed,
                    r.iteration.map_or(String::new(), |i| i.to_string()),
                    c.vx_mps,
                    c.vy_mps,
                    c.yaw_rate_rad_s,
                    c.commanded_in_training,
                    c.robots,
                    c.falls,
                    c.fall_rate().csv(4),
                    c.strict_falls,
                    c.lin_tracking.csv(4),
                    c.yaw_tracking.csv(4),
                    c.is_safe(&self.threshold)
                );
            }
        }
        s
    }

    /// `commands_by_method.csv`: one row per method over its seeds.
    pub fn methods_csv(&self) -> String {
        let mut s = String::from(
            "method,seeds,n_seeds,safe_share,safe_share_lo,safe_share_hi,safe_share_per_seed,worst_cell_fall_rate,worst_cell_fall_rate_lo,worst_cell_fall_rate_hi,worst_cell_fall_rate_per_seed,seeds_falling,worst_run,worst_vx_mps,worst_vy_mps,worst_yaw_rate_rad_s,worst_falls,worst_robots,worst_lin_tracking\n",
        );
        let per_seed = |v: &[f64]| {
            v.iter()
                .map(|x| format!("{x:.4}"))
                .collect::<Vec<_>>()
                .join(";")
        };
        for m in &self.methods {
            let (a, w, c) = (&m.safe_share, &m.worst_cell_falls, &m.worst);
            let _ = writeln!(
                s,
                "{},{},{},{:.4},{},{},{},{:.4},{},{},{},{},{},{},{},{},{},{},{:.4}",
                csv_field(&m.method.label),
                csv_field(&m.method.seeds.join(";")),
                m.method.seeds.len(),
                a.mean,
                opt4(a.lo),
                opt4(a.hi),
                per_seed(&a.per_seed),
                w.mean,
                opt4(w.lo),
                opt4(w.hi),
                per_seed(&w.per_seed),
                m.seeds_falling,
                csv_field(&m.worst_run),
                c.vx_mps,
                c.vy_mps,
                c.yaw_rate_rad_s,
                c.falls,
                c.robots,
                c.lin_tracking.value
            );
        }
        s
    }

    /// The episode length of every run (`20.0 s`), or `each checkpoint's own`
    /// when they differ.
    fn episode_text(&self) -> String {
        let first = self.runs.first().map_or(0.0, |r| r.episode_s);
        if self.runs.iter().all(|r| (r.episode_s - first).abs() < 1e-9) {
            format!("{first:.1} s")
        } else {
            "each checkpoint's own length".into()
        }
    }

    /// Which checkpoint each run's map is of: the most common choice for
    /// "every other run", each other choice with its runs.
    fn checkpoints_text(&self) -> String {
        let mut groups: Vec<(&str, Vec<&str>)> = Vec::new();
        for r in &self.runs {
            match groups.iter_mut().find(|(c, _)| *c == r.checkpoint) {
                Some((_, labels)) => labels.push(&r.label),
                None => groups.push((&r.checkpoint, vec![&r.label])),
            }
        }
        let most = (0..groups.len()).max_by_key(|&k| (groups[k].1.len(), usize::MAX - k));
        let mut parts = Vec::new();
        for (k, (what, labels)) in groups.iter().enumerate() {
            if Some(k) == most {
                let who = if groups.len() == 1 {
                    "every run"
                } else {
                    "every other run"
                };
                parts.push(format!("{who}: {what}"));
            } else {
                parts.push(format!("{}: {what}", labels.join(", ")));
            }
        }
        parts.join("; ")
    }
}

/// What each method's figure shows, as the README lists it.
const FIGURE_SHOWS: &str = "a method's command map: fall rate per command (vx across, yaw rate up, a panel per vy), mean over its seeds, with the seeds in which each cell is safe";

impl BenchmarkOutput for CommandsResult {
    fn csv_files(&self) -> Vec<(String, String)> {
        vec![
            ("commands.csv".into(), self.cells_csv()),
            ("commands_by_method.csv".into(), self.methods_csv()),
        ]
    }

    /// One map per method, `figures/commands_<method>.svg`.
    fn figures(&self) -> Vec<FigureEntry> {
        self.methods
            .iter()
            .map(|m| FigureEntry {
                file: m.figure.clone(),
                shows: FIGURE_SHOWS.into(),
            })
            .collect()
    }

    fn draw(&self, file: &str, path: &Path) -> Result<()> {
        match self.methods.iter().find(|m| m.figure == file) {
            Some(m) => commands_figure(self, m, path),
            None => bail!("no method's command map is drawn as {file:?}"),
        }
    }

    /// The README's section, on its first page: per method the safe share, the
    /// worst cell and its fall rate.
    fn markdown(&self, s: &mut String) {
        let _ = writeln!(s, "## Commands a policy cannot hold\n");
        let g = &self.grid;
        let _ = writeln!(
            s,
            "Each run's command map: its robots hold every command of a {} x {} x {} grid (vx {} m/s, vy {} m/s, yaw rate {} rad/s; {} cells) for one {} episode, {} robots per cell, on {}, no pushes, each checkpoint with its own observation noise, PD and randomisation, seed {}. A cell is safe when {}. Per method, over its seeds: the share of safe cells and the worst cell's fall rate (the highest over the cells), each the mean over seeds with a 95% t-interval over seeds (none for one seed) and each seed's value in braces; how many seeds fall somewhere (a cell at or above the fall threshold); and the worst cell of any seed. A method that is robust on average can still fall at one command: that is what this table shows.\n",
            g.vx_mps.len(),
            g.vy_mps.len(),
            g.yaw_rate_rad_s.len(),
            values(&g.vx_mps),
            values(&g.vy_mps),
            values(&g.yaw_rate_rad_s),
            g.len(),
            self.episode_text(),
            self.robots,
            self.conditions,
            self.seed,
            self.threshold.describe()
        );
        if self.methods.is_empty() {
            let _ = writeln!(s, "No run of `[commands]` has a checkpoint yet.\n");
            return;
        }
        let _ = writeln!(
            s,
            "| Method | safe share | worst cell's fall rate | seeds falling somewhere | worst cell of any seed |"
        );
        let _ = writeln!(s, "|---|---:|---:|---:|---|");
        for m in &self.methods {
            let _ = writeln!(
                s,
                "| {} | {} | {} | {} of {} | {} |",
                m.method.display(),
                show_seed_mean(&m.safe_share),
                show_seed_mean(&m.worst_cell_falls),
                m.seeds_falling,
                m.safe_share.per_seed.len(),
                show_worst(m)
            );
        }
        let _ = writeln!(
            s,
            "\nCheckpoints mapped: {}. `commands.csv` lists every cell of every run, `commands_by_method.csv` this table; `figures/commands_<method>.svg` draws each method's map.\n",
            self.checkpoints_text()
        );
    }
}
