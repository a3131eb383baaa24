//! Robustness curves: one number per policy (or method) and severity rung, with a
//! 95% percentile bootstrap over robots, for each benchmark:
//! - `ttf`: Time to Fall averaged over the table's cells (loads x terrain x push),
//!   each cell weighted equally (robots resampled within their cell);
//! - `platform`: success rate pooled over the rung's heights;
//! - `race`: the returns' 0.25 quantile (the worst case the paper's figure reads).

use serde::{Deserialize, Serialize};

use super::stats::{bootstrap_strata, cell_seed, mean, quantile, Estimate};
use crate::eval::{PlatformReport, RaceReport, TtfReport};

/// One point of a robustness curve.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct CurvePoint {
    pub benchmark: &'static str,
    pub metric: &'static str,
    pub policy: String,
    pub severity: usize,
    pub estimate: Estimate,
    /// Robots (or race episodes) behind the point.
    pub units: usize,
}

/// The benchmark and metric names a results file may hold, as the `&'static str`
/// the code compares them with.
const NAMES: [&str; 6] = [
    "ttf",
    "strict_ttf",
    "platform",
    "success_pct",
    "race",
    "return_q25",
];

/// One of [`NAMES`] (read from a results file written by rall); anything else is refused.
pub fn static_name(name: &str) -> Result<&'static str, String> {
    NAMES.into_iter().find(|n| *n == name).ok_or_else(|| {
        format!(
            "unknown benchmark or metric {name:?} (known: {})",
            NAMES.join(", ")
        )
    })
}

/// [`CurvePoint`] as a results file holds it.
#[derive(Deserialize)]
struct CurvePointFile {
    benchmark: String,
    metric: String,
    policy: String,
    severity: usize,
    estimate: Estimate,
    units: usize,
}

impl<'de> Deserialize<'de> for CurvePoint {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<CurvePoint, D::Error> {
        let f = CurvePointFile::deserialize(d)?;
        let name = |n: &str| static_name(n).map_err(serde::de::Error::custom);
        Ok(CurvePoint {
            benchmark: name(&f.benchmark)?,
            metric: name(&f.metric)?,
            policy: f.policy,
            severity: f.severity,
            estimate: f.estimate,
            units: f.units,
        })
    }
}

/// Bootstrap settings.
#[derive(Debug, Clone, Copy)]
pub struct Resampling {
    pub resamples: usize,
    pub level: f64,
    pub seed: u64,
}

impl Default for Resampling {
    fn default() -> Self {
        Resampling {
            resamples: 1000,
            level: 0.95,
            seed: 0,
        }
    }
}

/// Mean over strata of each stratum's mean.
pub(super) fn mean_of_means(strata: &[Vec<f64>]) -> f64 {
    mean(&strata.iter().map(|s| mean(s)).collect::<Vec<_>>())
}

/// The robots' survived fractions of the runs `policies` in every cell of
/// `report`, a stratum per run and cell; `strict` takes the strict fall definition.
pub(super) fn ttf_strata(report: &TtfReport, policies: &[String], strict: bool) -> Vec<Vec<f64>> {
    report
        .cells
        .iter()
        .filter(|c| policies.contains(&c.policy))
        .map(|c| {
            let steps = if strict {
                &c.strict_steps_per_robot
            } else {
                &c.steps_per_robot
            };
            let full = c.episode_steps.max(1) as f64;
            steps.iter().map(|&s| s as f64 / full).collect()
        })
        .collect()
}

/// The robots' platform successes (0 or 100) of the runs `policies`, a stratum
/// per run and height.
pub(super) fn platform_strata(report: &PlatformReport, policies: &[String]) -> Vec<Vec<f64>> {
    report
        .cells
        .iter()
        .filter(|c| policies.contains(&c.policy))
        .map(|c| {
            c.success_per_robot
                .iter()
                .map(|&s| if s { 100.0 } else { 0.0 })
                .collect()
        })
        .collect()
}

/// The race returns of the rows `policies`, a stratum per row.
pub(super) fn race_strata(report: &RaceReport, policies: &[String]) -> Vec<Vec<f64>> {
    report
        .rows
        .iter()
        .filter(|row| policies.contains(&row.name))
        .map(|row| row.returns.clone())
        .collect()
}

/// The 0.25 quantile of every stratum's values pooled.
pub(super) fn q25_pooled(strata: &[Vec<f64>]) -> f64 {
    quantile(&strata.concat(), 0.25)
}

/// TTF of the runs `policies` (a method's seeds, pooled as `label`) over every
/// cell of `report` (robots' survived fraction; every run and cell weighted
/// equally); `strict` takes the strict fall definition.
pub fn ttf_point(
    report: &TtfReport,
    policies: &[String],
    label: &str,
    severity: usize,
    strict: bool,
    r: Resampling,
) -> Option<CurvePoint> {
    let strata = ttf_strata(report, policies, strict);
    let metric = if strict { "strict_ttf" } else { "ttf" };
    point(("ttf", metric), label, severity, &strata, mean_of_means, r)
}

/// The point of `label` at `severity` from its robots `strata` and `statistic`,
/// with a bootstrap seeded by the point's own name.
fn point(
    (benchmark, metric): (&'static str, &'static str),
    label: &str,
    severity: usize,
    strata: &[Vec<f64>],
    statistic: impl Fn(&[Vec<f64>]) -> f64,
    r: Resampling,
) -> Option<CurvePoint> {
    if strata.is_empty() {
        return None;
    }
    let name = format!("curve/{benchmark}/{metric}/{label}/{severity}");
    Some(CurvePoint {
        benchmark,
        metric,
        policy: label.to_string(),
        severity,
        units: strata.iter().map(Vec::len).sum(),
        estimate: bootstrap_strata(
            strata,
            statistic,
            r.resamples,
            r.level,
            cell_seed(r.seed, &name),
        ),
    })
}

/// Success (%) of the runs `policies` pooled over the heights of `report`
/// (every run and height weighted equally).
pub fn platform_point(
    report: &PlatformReport,
    policies: &[String],
    label: &str,
    severity: usize,
    r: Resampling,
) -> Option<CurvePoint> {
    let strata = platform_strata(report, policies);
    point(
        ("platform", "success_pct"),
        label,
        severity,
        &strata,
        mean_of_means,
        r,
    )
}

/// The 0.25 quantile of the returns of the race rows `policies` pooled (as the
/// race table pools a method's seeds), resampled within each row.
pub fn race_point(
    report: &RaceReport,
    policies: &[String],
    label: &str,
    severity: usize,
    r: Resampling,
) -> Option<CurvePoint> {
    let strata = race_strata(report, policies);
    point(
        ("race", "return_q25"),
        label,
        severity,
        &strata,
        q25_pooled,
        r,
    )
}

/// `benchmark,metric,policy,severity,value,lo,hi,units` rows.
pub fn curve_csv(points: &[CurvePoint]) -> String {
    let mut s = String::from("benchmark,metric,policy,severity,value,lo,hi,units\n");
    for p in points {
        s.push_str(&format!(
            "{},{},{},{},{},{}\n",
            p.benchmark,
            p.metric,
            p.policy,
            p.severity,
            p.estimate.csv(4),
            p.units
        ));
    }
    s
}

/// A markdown table: a row per policy, a column per rung.
pub fn curve_markdown(points: &[CurvePoint], digits: usize) -> String {
    let mut rungs: Vec<usize> = points.iter().map(|p| p.severity).collect();
    rungs.sort_unstable();
    rungs.dedup();
    let mut policies: Vec<&str> = Vec::new();
    for p in points {
        if !policies.contains(&p.policy.as_str()) {
            policies.push(&p.policy);
        }
    }
    let mut s = String::from("| policy |");
    for r in &rungs {
        s.push_str(&format!(" rung {r} |"));
    }
    s.push_str("\n|---|");
    s.push_str(&"---:|".repeat(rungs.len()));
    s.push('\n');
    for name in policies {
        s.push_str(&format!("| {name} |"));
        for r in &rungs {
            match points.iter().find(|p| p.policy == name && p.severity == *r) {
                Some(p) => s.push_str(&format!(" {} |", p.estimate.show(digits))),
                None => s.push_str(" - |"),
            }
        }
        s.push('\n');
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cells_weigh_equally_whatever_their_size() {
        let strata = vec![vec![1.0, 1.0, 1.0, 1.0], vec![0.0]];
        assert_eq!(mean_of_means(&strata), 0.5);
    }
}
