//! Robustness curves: one number per policy (or method) and severity rung, with a
//! 95% percentile bootstrap over robots, for each benchmark:
//! - `ttf`: Time to Fall averaged over the table's cells (loads x terrain x push),
//!   each cell weighted equally (robots resampled within their cell);
//! - `platform`: success rate pooled over the rung's heights;
//! - `race`: the returns' 0.25 quantile (the worst case the paper's figure reads).

use serde::{Deserialize, Serialize};

use super::pooled::show_with_seeds;
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
    /// Each training seed's own number, when the point pools a method's seeds (the
    /// spread that no interval over robots covers); empty for a single policy.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub seeds: Vec<f64>,
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
    #[serde(default)]
    seeds: Vec<f64>,
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
            seeds: f.seeds,
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
    let seeds = per_seed(policies, |p| ttf_strata(report, p, strict), mean_of_means);
    point(("ttf", metric), label, severity, &strata, mean_of_means, r)
        .map(|p| CurvePoint { seeds, ..p })
}

/// `statistic` of each of `policies` alone (a method's seeds), from `strata_of` one
/// policy; empty for a single policy, and a policy with no robots is skipped.
fn per_seed(
    policies: &[String],
    strata_of: impl Fn(&[String]) -> Vec<Vec<f64>>,
    statistic: impl Fn(&[Vec<f64>]) -> f64,
) -> Vec<f64> {
    if policies.len() < 2 {
        return Vec::new();
    }
    policies
        .iter()
        .map(|p| strata_of(std::slice::from_ref(p)))
        .filter(|s| !s.is_empty())
        .map(|s| statistic(&s))
        .collect()
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
        seeds: Vec::new(),
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
    let seeds = per_seed(policies, |p| platform_strata(report, p), mean_of_means);
    point(
        ("platform", "success_pct"),
        label,
        severity,
        &strata,
        mean_of_means,
        r,
    )
    .map(|p| CurvePoint { seeds, ..p })
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
    let seeds = per_seed(policies, |p| race_strata(report, p), q25_pooled);
    point(
        ("race", "return_q25"),
        label,
        severity,
        &strata,
        q25_pooled,
        r,
    )
    .map(|p| CurvePoint { seeds, ..p })
}

/// `benchmark,metric,policy,severity,value,lo,hi,units,seeds` rows (`seeds`: each
/// training seed's number, `;`-separated, empty for a single policy).
pub fn curve_csv(points: &[CurvePoint]) -> String {
    let mut s = String::from("benchmark,metric,policy,severity,value,lo,hi,units,seeds\n");
    for p in points {
        let seeds: Vec<String> = p.seeds.iter().map(|v| format!("{v:.4}")).collect();
        s.push_str(&format!(
            "{},{},{},{},{},{},{}\n",
            p.benchmark,
            p.metric,
            p.policy,
            p.severity,
            p.estimate.csv(4),
            p.units,
            seeds.join(";")
        ));
    }
    s
}

/// A markdown table: a row per policy, a column per rung (each seed's number in braces
/// after a method's).
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
                Some(p) => s.push_str(&format!(
                    " {} |",
                    show_with_seeds(&p.estimate, &p.seeds, digits)
                )),
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

    #[test]
    fn a_methods_point_carries_each_seeds_own_number() {
        // two seeds' robots, a stratum per (seed, cell): seed a 1.0 in both cells,
        // seed b 0.0 and 0.5
        let strata_of = |ps: &[String]| -> Vec<Vec<f64>> {
            ps.iter()
                .flat_map(|p| match p.as_str() {
                    "a" => vec![vec![1.0, 1.0], vec![1.0]],
                    _ => vec![vec![0.0], vec![0.5, 0.5]],
                })
                .collect()
        };
        let both = ["a".to_string(), "b".to_string()];
        assert_eq!(per_seed(&both, strata_of, mean_of_means), vec![1.0, 0.25]);
        assert!(per_seed(&both[..1], strata_of, mean_of_means).is_empty());
        let p = CurvePoint {
            benchmark: "ttf",
            metric: "ttf",
            policy: "M".into(),
            severity: 2,
            estimate: Estimate {
                value: 0.625,
                lo: 0.5,
                hi: 0.75,
            },
            units: 6,
            seeds: vec![1.0, 0.25],
        };
        assert!(curve_markdown(std::slice::from_ref(&p), 3)
            .contains("| M | 0.625 [0.500, 0.750] {1.000, 0.250} |"));
        assert!(curve_csv(std::slice::from_ref(&p)).ends_with(",6,1.0000;0.2500\n"));
        // a results file keeps them, and one written before them reads as no seeds
        let back: CurvePoint = serde_json::from_str(&serde_json::to_string(&p).unwrap()).unwrap();
        assert_eq!(back, p);
        let old = r#"{"benchmark":"ttf","metric":"ttf","policy":"M","severity":2,"estimate":{"value":0.6,"lo":0.5,"hi":0.7},"units":6}"#;
        assert!(serde_json::from_str::<CurvePoint>(old)
            .unwrap()
            .seeds
            .is_empty());
    }
}
