//! `rall experiment FILE --status`: where every run stands and, for a campaign
//! trained over several sittings, how much is left at the pace runs go now.

use std::path::Path;

use anyhow::{Context, Result};

use super::spec::ExperimentSpec;
use super::stats;
use super::{run_state, RunState};
use crate::runner::metrics::metrics_columns;

/// Iterations over which a run's recent pace is measured.
pub const PACE_WINDOW: usize = 100;

/// Seconds per iteration over the last `window` iterations of `metrics.csv` at
/// `path`: the median of the iterations' wall-clock steps, so that a pause (a
/// stopped process, a machine asleep) counts as one slow iteration and does not
/// stretch the pace; `None` with fewer rows than that.
pub fn recent_s_per_iteration(path: &Path, window: usize) -> Result<Option<f64>> {
    let text = match std::fs::read_to_string(path) {
        Ok(t) => t,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
        Err(e) => return Err(e).with_context(|| format!("reading {}", path.display())),
    };
    let rows: Vec<(usize, f64)> = metrics_columns(&text, path, ["iteration", "wall_s"])?
        .into_iter()
        .filter_map(|[it, wall]| Some((it.parse().ok()?, wall.parse().ok()?)))
        .collect();
    let Some(&(last_it, _)) = rows.last() else {
        return Ok(None);
    };
    let Some(first) = rows
        .iter()
        .rposition(|(it, _)| last_it.saturating_sub(*it) >= window)
    else {
        return Ok(None);
    };
    let steps: Vec<f64> = rows[first..]
        .windows(2)
        .filter(|w| w[1].0 > w[0].0)
        .map(|w| (w[1].1 - w[0].1) / (w[1].0 - w[0].0) as f64)
        .collect();
    if steps.is_empty() {
        return Ok(None);
    }
    Ok(Some(stats::quantile(&steps, 0.5)))
}

/// Where a run stands.
#[derive(Clone, Copy, PartialEq)]
enum Stage {
    Done,
    Unfinished,
    NotStarted,
}

impl Stage {
    fn of(s: &RunState) -> Stage {
        if s.done() {
            Stage::Done
        } else if s.progress.is_some() {
            Stage::Unfinished
        } else {
            Stage::NotStarted
        }
    }

    fn name(self) -> &'static str {
        match self {
            Stage::Done => "done",
            Stage::Unfinished => "unfinished",
            Stage::NotStarted => "not started",
        }
    }
}

/// One run's line of the status.
struct RunLine {
    label: String,
    stage: Stage,
    at: usize,
    target: usize,
    dir: String,
    s_per_it: Option<f64>,
}

impl RunLine {
    fn new(label: &str, s: &RunState) -> Result<RunLine> {
        let stage = Stage::of(s);
        let s_per_it = match stage {
            Stage::Unfinished => recent_s_per_iteration(&s.dir.join("metrics.csv"), PACE_WINDOW)?,
            _ => None,
        };
        Ok(RunLine {
            label: label.to_string(),
            stage,
            at: s.progress.as_ref().map_or(0, |p| p.iteration),
            target: s.target,
            dir: s.dir.display().to_string(),
            s_per_it,
        })
    }

    /// Iterations still to train.
    fn left(&self) -> usize {
        self.target - self.at.min(self.target)
    }
}

/// The status of every run of `spec`, one line each, then what is left.
pub fn status_lines(spec: &ExperimentSpec) -> Result<Vec<String>> {
    let runs = spec
        .runs
        .iter()
        .map(|r| RunLine::new(&r.label, &run_state(spec, r)?))
        .collect::<Result<Vec<_>>>()?;
    let width = runs.iter().map(|r| r.label.len()).max().unwrap_or(0);
    let mut out: Vec<String> = runs
        .iter()
        .map(|r| {
            let pace = r.s_per_it.map_or(String::new(), |s| {
                format!(
                    "  {s:.2} s/it (median of its last {PACE_WINDOW} iterations): {:.1} h to go",
                    s * r.left() as f64 / 3600.0
                )
            });
            format!(
                "{:<width$} {:<12} {:>6} / {:<6} {}{pace}",
                r.label,
                r.stage.name(),
                r.at,
                r.target,
                r.dir
            )
        })
        .collect();
    let left: usize = runs.iter().map(RunLine::left).sum();
    let unfinished = runs.iter().filter(|r| r.stage != Stage::Done).count();
    if left > 0 {
        let mut paces: Vec<f64> = runs.iter().filter_map(|r| r.s_per_it).collect();
        paces.sort_by(f64::total_cmp);
        let line = match paces.get(paces.len() / 2) {
            Some(&s) => format!(
                "left: {left} iterations in {unfinished} runs, {:.1} run-hours at {s:.2} s/it \
                 (the median recent pace of the runs in training; one run per core)",
                s * left as f64 / 3600.0
            ),
            None => format!("left: {left} iterations in {unfinished} runs"),
        };
        out.push(line);
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_pace_is_taken_over_the_last_window_of_iterations() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("metrics.csv");
        let mut csv = String::from("iteration,wall_s,total_env_steps\n");
        // 1 s per iteration up to 150, then 3 s per iteration, with a 1,000 s pause
        // (a stopped process) before iteration 290
        let mut wall = 0.0;
        for it in 1..=300usize {
            wall += if it <= 150 { 1.0 } else { 3.0 };
            if it == 290 {
                wall += 1000.0;
            }
            csv.push_str(&format!("{it},{wall},{}\n", it * 10));
        }
        std::fs::write(&path, csv).unwrap();
        // the pause is one slow iteration of 100, not 10 s added to each
        let s = recent_s_per_iteration(&path, 100).unwrap().unwrap();
        assert!((s - 3.0).abs() < 1e-9, "{s}");
        // over 290 iterations, 140 at 1 s and 150 at 3 s: the median step is 3 s
        let s = recent_s_per_iteration(&path, 290).unwrap().unwrap();
        assert!((s - 3.0).abs() < 1e-9, "{s}");
        // the last 299 steps, 149 at 1 s and 150 at 3 s (one of them the pause)
        let s = recent_s_per_iteration(&path, 299).unwrap().unwrap();
        assert!((s - 3.0).abs() < 1e-9, "{s}");
        assert_eq!(recent_s_per_iteration(&path, 400).unwrap(), None);
        assert_eq!(
            recent_s_per_iteration(&dir.path().join("none.csv"), 100).unwrap(),
            None
        );
        std::fs::write(&path, "iteration,steps\n1,2\n").unwrap();
        let err = recent_s_per_iteration(&path, 1).unwrap_err();
        assert!(err.to_string().contains("no column wall_s"), "{err}");
    }
}
