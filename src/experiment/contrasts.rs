//! Method against method (`[contrasts]`): for each named pair, benchmark and rung,
//! the difference of the two methods' pooled numbers (the robustness curves'), judged
//! at two levels that answer different questions:
//! - over seeds, the verdict: each seed's number (its robots' statistic) is one unit,
//!   and Welch's t-test on those numbers (with the exact permutation test over seed
//!   labels beside it) says whether the methods would differ with other seeds. Its
//!   false-positive rate holds at 3 seeds and more (`tests/verdict_null.rs`); every
//!   contrast here is exploratory, unadjusted for the others (`[verdicts]` holds the
//!   pre-registered primary and the Holm-adjusted families);
//! - over robots, a description: each seed's robots resampled within their cells, the
//!   trained seeds kept as they are; it says whether these trained policies differ,
//!   never whether the methods do.
//!
//! Higher is more robust on every benchmark (TTF, platform success, race return
//! q0.25), so a positive difference favours the first method.

use std::fmt::Write as _;

use anyhow::{bail, Result};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use super::curves::{
    mean_of_means, platform_strata, q25_pooled, race_strata, ttf_strata, Resampling,
};
use super::pooled::{methods_of, Method};
use super::spec::ExperimentSpec;
use super::stats::{cell_seed, percentile, Estimate};
use crate::eval::report::csv_field;
use crate::eval::{PlatformReport, RaceReport, TtfReport};
use crate::stats::seed_test::{permutation_p, welch, Verdict, Welch};

/// `[contrasts]`: the pairs of methods to compare, each `[first, second]` by the
/// label of a run (or meta controller) of the method; the first minus the second.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ContrastsSpec {
    pub pairs: Vec<[String; 2]>,
}

impl ContrastsSpec {
    /// Every name is a run or meta label of `spec`, and no pair compares a method
    /// with itself.
    pub fn validate(&self, spec: &ExperimentSpec) -> Result<()> {
        if self.pairs.is_empty() {
            bail!("contrasts.pairs lists no pair");
        }
        let known = |l: &str| spec.run(l).is_some() || spec.meta.iter().any(|m| m.label == l);
        for [a, b] in &self.pairs {
            for name in [a, b] {
                if !known(name) {
                    bail!(
                        "contrasts.pairs names {name:?}, which is not the label of any [[run]] or [[meta]]"
                    );
                }
            }
            if method_key(spec, a) == method_key(spec, b) {
                bail!("contrasts.pairs compares {a:?} with {b:?}, runs of the same method");
            }
        }
        Ok(())
    }
}

/// What makes runs one method (as `methods_of` groups them): a run's name, or a
/// meta controller's pair of run names.
fn method_key(spec: &ExperimentSpec, label: &str) -> String {
    let all: Vec<String> = spec
        .runs
        .iter()
        .map(|r| r.label.clone())
        .chain(spec.meta.iter().map(|m| m.label.clone()))
        .collect();
    methods_of(spec, &all)
        .into_iter()
        .find(|m| m.seeds.iter().any(|s| s == label))
        .map_or(label.to_string(), |m| m.label)
}

/// One pair on one benchmark metric at one rung.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Contrast {
    pub benchmark: String,
    pub metric: String,
    pub severity: usize,
    /// The two methods (their first seed's label), first minus second.
    pub first: String,
    pub second: String,
    /// The difference with its interval over robots (seeds as trained).
    pub over_robots: Estimate,
    /// Each seed's own number, in the experiment file's order.
    pub first_seeds: Vec<f64>,
    pub second_seeds: Vec<f64>,
    /// The run label of each number in `first_seeds` and `second_seeds` (empty in
    /// results written before labels were kept: then the method's seeds in file order).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub first_labels: Vec<String>,
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub second_labels: Vec<String>,
}

/// The level of every contrast's seed-level interval (95%), its test's alpha 0.05.
pub const CONTRAST_LEVEL: f64 = 0.95;

/// +1 for a metric on which higher is more robust (every benchmark's but one),
/// -1 for a benchmark's metric on which lower is safer (the command map's
/// worst-cell fall rate): a method is ahead on it with a negative difference.
pub fn safer_sign(metric: &str) -> f64 {
    if super::benchmark::metric(metric).is_some_and(|(_, m)| m.lower_is_safer) {
        -1.0
    } else {
        1.0
    }
}

impl Contrast {
    /// Seed pairs (one of each method) in which the first method is ahead (safer
    /// by [`safer_sign`]), and all pairs.
    pub fn pairs_ahead(&self) -> (usize, usize) {
        let sign = safer_sign(&self.metric);
        let ahead = self
            .first_seeds
            .iter()
            .map(|a| {
                self.second_seeds
                    .iter()
                    .filter(|&&b| sign * *a > sign * b)
                    .count()
            })
            .sum();
        (ahead, self.first_seeds.len() * self.second_seeds.len())
    }

    /// Welch's test on the seeds' numbers (`None` under two seeds on either side).
    pub fn welch(&self) -> Option<Welch> {
        welch(&self.first_seeds, &self.second_seeds, CONTRAST_LEVEL)
    }

    /// The exact permutation test over seed labels.
    pub fn permutation_p(&self) -> Option<f64> {
        permutation_p(&self.first_seeds, &self.second_seeds)
    }

    /// `ahead`, `behind` (Welch's interval over seeds excludes 0, the first safer
    /// or less safe by [`safer_sign`]) or `level` (also with too few seeds to test).
    pub fn verdict(&self) -> &'static str {
        let sign = safer_sign(&self.metric);
        self.welch()
            .map_or(Verdict::Level, |w| {
                Verdict::from_p(sign * w.difference, w.p, 1.0 - CONTRAST_LEVEL)
            })
            .as_str()
    }
}

/// One method's units on one metric: per seed, its strata (cells) of robots.
type BySeed = Vec<Vec<Vec<f64>>>;

/// A metric's statistic over strata (the curve's: mean of cell means, or the
/// pooled return quantile).
type Statistic = fn(&[Vec<f64>]) -> f64;

/// Every pair of `spec`'s `[contrasts]` on every benchmark both methods ran at
/// rung `severity` (`reports`: the rung's TTF, platform and race reports; `labels`:
/// each table's evaluated runs and meta controllers).
pub fn contrasts_at(
    spec: &ExperimentSpec,
    severity: usize,
    ttf: Option<(&TtfReport, &[String])>,
    platform: Option<(&PlatformReport, &[String])>,
    race: Option<(&RaceReport, &[String])>,
    r: Resampling,
) -> Vec<Contrast> {
    let Some(c) = &spec.contrasts else {
        return Vec::new();
    };
    // every metric this rung has: its methods, a seed's strata and its statistic
    let mut metrics: Vec<Metric> = Vec::new();
    if let Some((rep, labels)) = ttf {
        for (metric, strict) in [("ttf", false), ("strict_ttf", true)] {
            metrics.push(Metric {
                name: ("ttf", metric),
                methods: methods_of(spec, labels),
                strata: Box::new(move |s| ttf_strata(rep, std::slice::from_ref(s), strict)),
                stat: mean_of_means,
            });
        }
    }
    if let Some((rep, labels)) = platform {
        metrics.push(Metric {
            name: ("platform", "success_pct"),
            methods: methods_of(spec, labels),
            strata: Box::new(move |s| platform_strata(rep, std::slice::from_ref(s))),
            stat: mean_of_means,
        });
    }
    if let Some((rep, labels)) = race {
        metrics.push(Metric {
            name: ("race", "return_q25"),
            methods: methods_of(spec, labels),
            strata: Box::new(move |s| race_strata(rep, std::slice::from_ref(s))),
            stat: q25_pooled,
        });
    }
    let mut out = Vec::new();
    for [a, b] in &c.pairs {
        for m in &metrics {
            out.extend(contrast(m, severity, (a, b), r));
        }
    }
    out
}

/// One run's strata of robots on a metric, by its label.
type RunStrata<'a> = Box<dyn Fn(&String) -> Vec<Vec<f64>> + 'a>;

/// One benchmark metric at one rung: the methods that ran it, one seed's strata
/// (by run label) and the curve's statistic.
struct Metric<'a> {
    name: (&'static str, &'static str),
    methods: Vec<Method>,
    strata: RunStrata<'a>,
    stat: Statistic,
}

/// Method `m`'s strata per seed (`strata(seed label)`) with the seed's label, seeds
/// without any left out.
fn by_seed(m: &Method, strata: impl Fn(&String) -> Vec<Vec<f64>>) -> (BySeed, Vec<String>) {
    m.seeds
        .iter()
        .map(|l| (strata(l), l.clone()))
        .filter(|(s, _)| s.iter().any(|c| !c.is_empty()))
        .unzip()
}

/// The contrast of methods `a` and `b` (labels of one of their runs) on metric
/// `m`; `None` when either did not run it.
fn contrast(
    m: &Metric,
    severity: usize,
    (a, b): (&String, &String),
    r: Resampling,
) -> Option<Contrast> {
    let (benchmark, metric) = m.name;
    let find = |l: &String| m.methods.iter().find(|x| x.seeds.contains(l));
    let (ma, mb) = (find(a)?, find(b)?);
    let ((ua, la), (ub, lb)) = (by_seed(ma, &m.strata), by_seed(mb, &m.strata));
    if ua.is_empty() || ub.is_empty() {
        return None;
    }
    let stat = m.stat;
    let name = format!(
        "contrast/{benchmark}/{metric}/{}/{}/{severity}",
        ma.label, mb.label
    );
    let over_robots = over_robots(&ua, &ub, stat, r, &name);
    Some(Contrast {
        benchmark: benchmark.into(),
        metric: metric.into(),
        severity,
        first: ma.label.clone(),
        second: mb.label.clone(),
        over_robots,
        first_seeds: ua.iter().map(|s| stat(s)).collect(),
        second_seeds: ub.iter().map(|s| stat(s)).collect(),
        first_labels: la,
        second_labels: lb,
    })
}

/// The difference `stat(a) - stat(b)` with its percentile bootstrap interval over
/// robots: every stratum's robots drawn with replacement, the seeds kept as they are
/// (seeded by `name`, so the same data give the same interval).
fn over_robots(a: &BySeed, b: &BySeed, stat: Statistic, r: Resampling, name: &str) -> Estimate {
    let value = stat(&a.concat()) - stat(&b.concat());
    let mut rng = ChaCha8Rng::seed_from_u64(cell_seed(r.seed, &format!("{name}/robots")));
    let mut diffs: Vec<f64> = (0..r.resamples)
        .map(|_| stat(&resample_robots(a, &mut rng)) - stat(&resample_robots(b, &mut rng)))
        .collect();
    diffs.sort_by(f64::total_cmp);
    let alpha = (1.0 - r.level) / 2.0;
    Estimate {
        value,
        lo: percentile(&diffs, alpha),
        hi: percentile(&diffs, 1.0 - alpha),
    }
}

/// One bootstrap draw of a method's strata: every seed as it is, every stratum's
/// units drawn with replacement.
fn resample_robots(seeds: &BySeed, rng: &mut ChaCha8Rng) -> Vec<Vec<f64>> {
    seeds
        .iter()
        .flatten()
        .map(|stratum| {
            let m = stratum.len();
            (0..m).map(|_| stratum[rng.gen_range(0..m)]).collect()
        })
        .collect()
}

/// `contrasts.csv`: a row per pair, metric and rung.
pub fn contrasts_csv(rows: &[Contrast]) -> String {
    let mut s = String::from(
        "first,second,benchmark,metric,severity,difference,robots_lo,robots_hi,seed_mean_difference,welch_lo,welch_hi,welch_df,welch_p,permutation_p,first_seeds,second_seeds,seed_pairs_ahead,seed_pairs,verdict\n",
    );
    let list = |v: &[f64]| {
        v.iter()
            .map(|x| format!("{x:.4}"))
            .collect::<Vec<_>>()
            .join(";")
    };
    for c in rows {
        let (ahead, pairs) = c.pairs_ahead();
        let welch = c.welch().map_or(",,,,".into(), |w| {
            format!(
                "{:.4},{:.4},{:.4},{:.2},{:.4}",
                w.difference, w.lo, w.hi, w.df, w.p
            )
        });
        let perm = c
            .permutation_p()
            .map_or(String::new(), |p| format!("{p:.4}"));
        let _ = writeln!(
            s,
            "{},{},{},{},{},{:.4},{:.4},{:.4},{welch},{perm},{},{},{ahead},{pairs},{}",
            csv_field(&c.first),
            csv_field(&c.second),
            c.benchmark,
            c.metric,
            c.severity,
            c.over_robots.value,
            c.over_robots.lo,
            c.over_robots.hi,
            list(&c.first_seeds),
            list(&c.second_seeds),
            c.verdict()
        );
    }
    s
}

/// The ladder's metrics in the order the results show them: (metric, title, decimals).
const RUNG_METRICS: [(&str, &str, usize); 4] = [
    ("ttf", "TTF", 3),
    ("strict_ttf", "strict TTF", 3),
    ("success_pct", "platform success (points)", 1),
    ("return_q25", "race return q0.25", 1),
];

/// Every metric in the order the results show them: the ladder's, then each
/// benchmark's (`super::benchmark`).
fn table_metrics() -> Vec<(&'static str, &'static str, usize)> {
    let mut out = RUNG_METRICS.to_vec();
    let of_benchmarks = super::benchmark::metrics().into_iter();
    out.extend(of_benchmarks.map(|(_, m)| (m.name, m.contrast_title, m.decimals)));
    out
}

/// Whether contrast `c` is on a benchmark's metric, which has no rung.
fn without_rung(c: &Contrast) -> bool {
    super::benchmark::metric(&c.metric).is_some()
}

/// `rungs 0, 2` / `rung 3` / `none`.
fn rung_list(rungs: &[usize]) -> String {
    match rungs {
        [] => "none".into(),
        [one] => format!("rung {one}"),
        many => format!(
            "rungs {}",
            many.iter()
                .map(|r| r.to_string())
                .collect::<Vec<_>>()
                .join(", ")
        ),
    }
}

/// The results' section: a verdict line per pair and metric, then a table per pair.
pub fn contrasts_markdown(rows: &[Contrast], s: &mut String) {
    if rows.is_empty() {
        return;
    }
    let mut pairs: Vec<(&str, &str)> = Vec::new();
    for c in rows {
        if !pairs.contains(&(c.first.as_str(), c.second.as_str())) {
            pairs.push((&c.first, &c.second));
        }
    }
    let metrics = table_metrics();
    let _ = writeln!(s, "## Method against method (exploratory)\n");
    let _ = writeln!(s, "Each pair's difference, first minus second (higher is more robust on every benchmark), on every rung, over every seed. The verdict is Welch's t-test on the seeds' own numbers (the seed is the unit; 95% interval, p, and the exact permutation test over seed labels beside it): a method is called ahead or behind on a rung only when Welch's interval excludes 0. These contrasts are exploratory: none is adjusted for the others, so about one in twenty true nulls is called by chance. The interval over robots (each seed's robots resampled within their cells) describes these trained policies, never the methods.\n");
    if rows
        .iter()
        .any(|c| c.benchmark == super::commands::BENCHMARK)
    {
        let _ = writeln!(s, "The command map has no rung (its rows are rung 0 in `contrasts.csv`). Its worst cell's fall rate is the one metric on which lower is safer: there a method is ahead with a negative difference, and a seed pair counts as ahead when the first seed's worst cell falls less.\n");
    }
    for &(a, b) in &pairs {
        let these: Vec<&Contrast> = rows
            .iter()
            .filter(|c| c.first == a && c.second == b)
            .collect();
        let _ = writeln!(s, "**{a} against {b}.**");
        for &(metric, title, _) in &metrics {
            let of: Vec<&&Contrast> = these.iter().filter(|c| c.metric == metric).collect();
            if of.is_empty() {
                continue;
            }
            let rungs_where = |v: &str| -> Vec<usize> {
                of.iter()
                    .filter(|c| c.verdict() == v)
                    .map(|c| c.severity)
                    .collect()
            };
            if without_rung(of[0]) {
                let _ = writeln!(s, "- {title}: {}.", of[0].verdict());
                continue;
            }
            let _ = writeln!(
                s,
                "- {title}: ahead on {}, behind on {}, level on {}.",
                rung_list(&rungs_where("ahead")),
                rung_list(&rungs_where("behind")),
                rung_list(&rungs_where("level"))
            );
        }
        let _ = writeln!(s);
        let _ = writeln!(
            s,
            "| benchmark | rung | difference [over robots] | seeds: Welch 95% | p (Welch / permutation) | {a}: seeds | {b}: seeds | seed pairs ahead |"
        );
        let _ = writeln!(s, "|---|---:|---:|---:|---|---|---|---:|");
        for &(metric, title, d) in &metrics {
            for c in these.iter().filter(|c| c.metric == metric) {
                let list = |v: &[f64]| {
                    v.iter()
                        .map(|x| format!("{x:.d$}"))
                        .collect::<Vec<_>>()
                        .join(", ")
                };
                let (ahead, n) = c.pairs_ahead();
                let (interval, p) = c.welch().map_or(("-".into(), "-".into()), |w| {
                    (
                        format!("{:+.d$} [{:+.d$}, {:+.d$}]", w.difference, w.lo, w.hi),
                        format!("{:.3}", w.p),
                    )
                });
                let perm = c.permutation_p().map_or("-".into(), |p| format!("{p:.3}"));
                let rung = if without_rung(c) {
                    "-".to_string()
                } else {
                    c.severity.to_string()
                };
                let _ = writeln!(
                    s,
                    "| {title} | {rung} | {:+.d$} [{:+.d$}, {:+.d$}] | {interval} | {p} / {perm} | {} | {} | {ahead} / {n} |",
                    c.over_robots.value,
                    c.over_robots.lo,
                    c.over_robots.hi,
                    list(&c.first_seeds),
                    list(&c.second_seeds),
                );
            }
        }
        let _ = writeln!(s);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn seeds(values: &[&[f64]]) -> BySeed {
        values.iter().map(|v| vec![v.to_vec()]).collect()
    }

    #[test]
    fn resampling_robots_keeps_every_seed_and_its_cells() {
        let s = seeds(&[&[1.0; 5], &[2.0, 3.0, 4.0], &[3.0; 2]]);
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        let d = resample_robots(&s, &mut rng);
        assert_eq!(d.len(), 3);
        assert_eq!(d[0], vec![1.0; 5]);
        assert!(d[1].len() == 3 && d[1].iter().all(|x| [2.0, 3.0, 4.0].contains(x)));
        assert_eq!(d[2], vec![3.0; 2]);
    }

    /// Robots around `centre`, spread +-0.05.
    fn robots(centre: f64) -> Vec<f64> {
        (0..20).map(|i| centre + 0.005 * i as f64 - 0.05).collect()
    }

    #[test]
    fn the_interval_over_robots_ignores_seeds_that_disagree() {
        // A's seeds at 0.9, 0.5, 0.7 (mean 0.7); B's three at 0.6: these robots
        // say A is ahead, one of A's seeds is behind every B seed
        let a: BySeed = [0.9, 0.5, 0.7].iter().map(|&c| vec![robots(c)]).collect();
        let b: BySeed = [0.6, 0.6, 0.6].iter().map(|&c| vec![robots(c)]).collect();
        let r = Resampling::default();
        let iv = over_robots(&a, &b, mean_of_means, r, "t");
        assert!((iv.value - 0.1).abs() < 1e-9, "{iv:?}");
        assert!(iv.lo > 0.05 && iv.hi < 0.15, "{iv:?}");
        // reproducible, and another cell's name draws differently
        assert_eq!(over_robots(&a, &b, mean_of_means, r, "t"), iv);
        assert_ne!(over_robots(&a, &b, mean_of_means, r, "u"), iv);
    }

    #[test]
    fn pairs_count_the_seeds_and_the_verdict_is_welch_on_seed_numbers() {
        let c = Contrast {
            benchmark: "ttf".into(),
            metric: "ttf".into(),
            severity: 1,
            first: "A".into(),
            second: "B".into(),
            over_robots: Estimate {
                value: 0.1,
                lo: 0.05,
                hi: 0.15,
            },
            first_seeds: vec![0.5, 0.7, 0.6],
            second_seeds: vec![0.55, 0.45, 0.5],
            first_labels: Vec::new(),
            second_labels: Vec::new(),
        };
        assert_eq!(c.pairs_ahead(), (7, 9));
        // Welch on (0.5, 0.7, 0.6) against (0.55, 0.45, 0.5): p about 0.2
        assert_eq!(c.verdict(), "level");
        let w = c.welch().unwrap();
        assert!(w.lo < 0.0 && w.hi > 0.1 && w.p > 0.1, "{w:?}");
        let apart = Contrast {
            first_seeds: vec![0.70, 0.72, 0.71],
            ..c.clone()
        };
        assert_eq!(apart.verdict(), "ahead");
        let behind = Contrast {
            first_seeds: vec![0.30, 0.32, 0.31],
            ..c
        };
        assert_eq!(behind.verdict(), "behind");
    }
}
