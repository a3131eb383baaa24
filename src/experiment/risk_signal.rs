//! What each run's risk penalties marked (`[risk_signal]`): over the last
//! `window` training iterations of its `metrics.csv`, per risk term, how often
//! the threshold was crossed, how often the Bernoulli penalty fired, and how many
//! of those firings came within 1 s before a fall. A signal that marks danger
//! fires rarely and mostly before falls; one that punishes ordinary gait does not.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use serde::{Deserialize, Serialize};

use super::spec::{ExperimentSpec, RunSpec};
use crate::runner::RunDir;

/// `[risk_signal]`: the training iterations summarised (the newest `window`).
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RiskSignalSpec {
    pub window: usize,
}

/// One risk term of one run over the window.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct RiskTermRow {
    pub run: String,
    pub term: String,
    pub first_iteration: usize,
    pub last_iteration: usize,
    pub robot_steps: u64,
    pub crossings: f64,
    pub firings: f64,
    pub firings_before_fall: f64,
}

impl RiskTermRow {
    /// Robot-steps past the threshold, per 1,000.
    pub fn crossings_per_1k_steps(&self) -> f64 {
        1000.0 * self.crossings / self.robot_steps.max(1) as f64
    }

    pub fn firings_per_iteration(&self) -> f64 {
        self.firings / (self.last_iteration + 1 - self.first_iteration) as f64
    }

    /// The share of firings within 1 s before a fall (`None` without firings).
    pub fn share_before_fall(&self) -> Option<f64> {
        (self.firings > 0.0).then(|| self.firings_before_fall / self.firings)
    }
}

/// The run's `metrics.csv`: in its run directory, else in its shipped copy.
fn metrics_path(spec: &ExperimentSpec, r: &RunSpec) -> Option<PathBuf> {
    let local = RunDir {
        root: spec.run_dir(r),
    }
    .metrics();
    if local.exists() {
        return Some(local);
    }
    let shipped = spec.shipped_copy(r)?.join("metrics.csv");
    shipped.exists().then_some(shipped)
}

/// Every risk term of every run with a `metrics.csv` (a run without one, or
/// without risk terms, has no rows).
pub fn risk_rows(spec: &ExperimentSpec, s: &RiskSignalSpec) -> Result<Vec<RiskTermRow>> {
    let mut rows = Vec::new();
    for r in &spec.runs {
        if let Some(path) = metrics_path(spec, r) {
            rows.extend(
                run_rows(&r.label, &path, s.window)
                    .with_context(|| format!("run {:?}: {}", r.label, path.display()))?,
            );
        }
    }
    Ok(rows)
}

/// The rows of one run from its metrics file.
fn run_rows(label: &str, path: &Path, window: usize) -> Result<Vec<RiskTermRow>> {
    let text = std::fs::read_to_string(path).context("reading")?;
    let mut lines = text.lines();
    let header: Vec<&str> = lines.next().context("empty file")?.split(',').collect();
    let column = |name: &str| header.iter().position(|h| *h == name);
    let (Some(it_col), Some(steps_col)) = (column("iteration"), column("total_env_steps")) else {
        bail!("no iteration or total_env_steps column");
    };
    let rows = parse_rows(lines, &header, &[it_col, steps_col])?;
    if rows.len() < 2 {
        return Ok(Vec::new());
    }
    let first = rows.len().saturating_sub(window).max(1);
    let recent = &rows[first..];
    let value = |row: &[Option<f64>], col: usize| {
        row[col].expect("a required field, checked by parse_rows")
    };
    // a column added to metrics.csv after the run started is empty in its older rows:
    // a term whose window holds such a row is left out, not summed as zero
    let sum = |col: usize| -> Option<f64> { recent.iter().map(|v| v[col]).sum() };
    let robot_steps = (value(&rows[rows.len() - 1], steps_col) - value(&rows[first - 1], steps_col))
        .max(0.0) as u64;
    let mut out = Vec::new();
    for h in &header {
        let Some(term) = h.strip_prefix("risk_fired_before_fall_") else {
            continue;
        };
        let (Some(crossed), Some(fired), Some(before)) = (
            column(&format!("risk_exceeded_{term}")),
            column(&format!("risk_fired_{term}")),
            column(h),
        ) else {
            continue;
        };
        let (Some(crossings), Some(firings), Some(firings_before_fall)) =
            (sum(crossed), sum(fired), sum(before))
        else {
            continue;
        };
        out.push(RiskTermRow {
            run: label.to_string(),
            term: term.to_string(),
            first_iteration: value(&recent[0], it_col) as usize,
            last_iteration: value(&recent[recent.len() - 1], it_col) as usize,
            robot_steps,
            crossings,
            firings,
            firings_before_fall,
        });
    }
    Ok(out)
}

/// The data rows of a metrics file: an empty field is `None` (a column the run did
/// not log yet); a row of another width, a field that is not a number or an empty
/// field in a `required` column is refused, naming its line.
fn parse_rows<'a>(
    lines: impl Iterator<Item = &'a str>,
    header: &[&str],
    required: &[usize],
) -> Result<Vec<Vec<Option<f64>>>> {
    let width = header.len();
    lines
        .enumerate()
        .filter(|(_, l)| !l.trim().is_empty())
        .map(|(i, l)| {
            let line = i + 2;
            let fields: Vec<&str> = l.split(',').collect();
            if fields.len() != width {
                bail!(
                    "line {line} has {} fields, the header {width}",
                    fields.len()
                );
            }
            fields
                .iter()
                .enumerate()
                .map(|(c, v)| match v.trim() {
                    "" if required.contains(&c) => bail!("line {line}: no {}", header[c]),
                    "" => Ok(None),
                    v => v.parse().map(Some).with_context(|| {
                        format!("line {line}, column {}: {v:?} is not a number", c + 1)
                    }),
                })
                .collect()
        })
        .collect()
}

/// `risk_signal.csv`.
pub fn risk_csv(rows: &[RiskTermRow]) -> String {
    let mut s = String::from(
        "run,term,first_iteration,last_iteration,robot_steps,crossings,crossings_per_1k_steps,firings,firings_per_iteration,firings_before_fall,share_before_fall\n",
    );
    for r in rows {
        let _ = writeln!(
            s,
            "{},{},{},{},{},{},{:.4},{},{:.4},{},{}",
            r.run,
            r.term,
            r.first_iteration,
            r.last_iteration,
            r.robot_steps,
            r.crossings,
            r.crossings_per_1k_steps(),
            r.firings,
            r.firings_per_iteration(),
            r.firings_before_fall,
            r.share_before_fall()
                .map_or(String::new(), |v| format!("{v:.4}"))
        );
    }
    s
}

/// The section of the results' README: one row per run (all terms), then the terms.
pub fn risk_markdown(rows: &[RiskTermRow], s: &mut String) {
    if rows.is_empty() {
        return;
    }
    let _ = writeln!(s, "\n## What the risk penalties marked\n");
    let _ = writeln!(
        s,
        "Training iterations {}-{} of each run (`metrics.csv`): threshold crossings per 1,000 robot-steps, penalties fired, and the share of firings within 1 s before a fall (`risk_signal.csv` has every term).\n",
        rows[0].first_iteration, rows[0].last_iteration
    );
    let _ = writeln!(
        s,
        "| Run | term | crossings / 1k steps | firings / iteration | before a fall |"
    );
    let _ = writeln!(s, "|---|---|---:|---:|---:|");
    let mut runs: Vec<&str> = rows.iter().map(|r| r.run.as_str()).collect();
    runs.dedup();
    for run in runs {
        let of_run: Vec<&RiskTermRow> = rows.iter().filter(|r| r.run == run).collect();
        let all = RiskTermRow {
            term: "all".into(),
            crossings: of_run.iter().map(|r| r.crossings).sum(),
            firings: of_run.iter().map(|r| r.firings).sum(),
            firings_before_fall: of_run.iter().map(|r| r.firings_before_fall).sum(),
            ..of_run[0].clone()
        };
        for r in of_run.into_iter().chain([&all]) {
            let _ = writeln!(
                s,
                "| {} | {} | {:.2} | {:.3} | {} |",
                r.run,
                r.term,
                r.crossings_per_1k_steps(),
                r.firings_per_iteration(),
                r.share_before_fall()
                    .map_or("-".into(), |v| format!("{:.1}%", 100.0 * v))
            );
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_window_sums_the_newest_iterations_and_shares_firings_before_falls() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("metrics.csv");
        let mut text = String::from(
            "iteration,total_env_steps,risk_exceeded_base_pitch,risk_fired_base_pitch,risk_fired_before_fall_base_pitch\n",
        );
        for it in 1..=10 {
            let _ = writeln!(text, "{it},{},{},{},{}", it * 100, it, it % 2, it % 4 / 3);
        }
        std::fs::write(&path, text).unwrap();
        let rows = run_rows("r", &path, 4).unwrap();
        assert_eq!(rows.len(), 1);
        let r = &rows[0];
        assert_eq!((r.first_iteration, r.last_iteration), (7, 10));
        assert_eq!(r.robot_steps, 400);
        assert_eq!(r.crossings, (7 + 8 + 9 + 10) as f64);
        assert_eq!(r.firings, 2.0); // iterations 7 and 9
        assert_eq!(r.firings_before_fall, 1.0); // iteration 7
        assert_eq!(r.share_before_fall(), Some(0.5));
        assert!((r.crossings_per_1k_steps() - 85.0).abs() < 1e-12);
    }

    #[test]
    fn damaged_metrics_are_refused_naming_the_line_and_unlogged_terms_left_out() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("metrics.csv");
        let head = "iteration,total_env_steps,risk_exceeded_roll,risk_fired_roll,risk_fired_before_fall_roll\n";
        std::fs::write(&path, format!("{head}1,10,1,0,0\n2,20,1,x,0\n")).unwrap();
        let e = format!("{:#}", run_rows("r", &path, 5).unwrap_err());
        assert!(e.contains("line 3") && e.contains("\"x\""), "{e}");
        std::fs::write(&path, format!("{head}1,10,1,0,0\n2,20,1\n")).unwrap();
        let e = format!("{:#}", run_rows("r", &path, 5).unwrap_err());
        assert!(e.contains("line 3") && e.contains("3 fields"), "{e}");
        std::fs::write(&path, format!("{head}1,10,1,0,0\n2,,1,0,0\n")).unwrap();
        let e = format!("{:#}", run_rows("r", &path, 5).unwrap_err());
        assert!(
            e.contains("line 3") && e.contains("no total_env_steps"),
            "{e}"
        );
        // the before-a-fall column was added mid-run: empty in the older rows
        std::fs::write(&path, format!("{head}1,10,1,0,\n2,20,1,0,\n3,30,1,1,1\n")).unwrap();
        assert!(run_rows("r", &path, 5).unwrap().is_empty());
        assert_eq!(run_rows("r", &path, 1).unwrap()[0].firings_before_fall, 1.0);
    }

    #[test]
    fn a_run_without_risk_terms_has_no_rows() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("metrics.csv");
        std::fs::write(&path, "iteration,total_env_steps\n1,10\n2,20\n").unwrap();
        assert!(run_rows("r", &path, 10).unwrap().is_empty());
    }
}
