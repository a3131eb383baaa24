//! Method against method (`[contrasts]`): for each named pair, benchmark and rung,
//! the difference of the two methods' pooled numbers (the robustness curves'), with
//! two intervals that answer different questions:
//! - over robots: each seed's robots resampled within their cells, the trained
//!   seeds kept as they are; it says whether these policies differ, not whether
//!   the methods would with other seeds;
//! - over seeds and robots: each method's seeds resampled with replacement, then
//!   robots within each drawn seed (a two-level bootstrap); it carries the
//!   seed-to-seed spread of training. With three seeds it is coarse and somewhat
//!   narrow (a bootstrap over n units underestimates their spread by (n-1)/n), so
//!   every seed's own number and the count of seed pairs in which the first method
//!   is ahead are reported beside it.
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
    /// The same difference with its interval over seeds and robots.
    pub over_seeds: Estimate,
    /// Each seed's own number, in the experiment file's order.
    pub first_seeds: Vec<f64>,
    pub second_seeds: Vec<f64>,
}

impl Contrast {
    /// Seed pairs (one of each method) in which the first method is ahead, and all pairs.
    pub fn pairs_ahead(&self) -> (usize, usize) {
        let ahead = self
            .first_seeds
            .iter()
            .map(|a| self.second_seeds.iter().filter(|&&b| *a > b).count())
            .sum();
        (ahead, self.first_seeds.len() * self.second_seeds.len())
    }

    /// `ahead`, `behind` (the interval over seeds and robots excludes 0) or `level`.
    pub fn verdict(&self) -> &'static str {
        if self.over_seeds.lo > 0.0 {
            "ahead"
        } else if self.over_seeds.hi < 0.0 {
            "behind"
        } else {
            "level"
        }
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

/// Method `m`'s strata per seed (`strata(seed label)`), seeds without any left out.
fn by_seed(m: &Method, strata: impl Fn(&String) -> Vec<Vec<f64>>) -> BySeed {
    m.seeds
        .iter()
        .map(strata)
        .filter(|s| s.iter().any(|c| !c.is_empty()))
        .collect()
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
    let (ua, ub) = (by_seed(ma, &m.strata), by_seed(mb, &m.strata));
    if ua.is_empty() || ub.is_empty() {
        return None;
    }
    let stat = m.stat;
    let name = format!(
        "contrast/{benchmark}/{metric}/{}/{}/{severity}",
        ma.label, mb.label
    );
    let (over_robots, over_seeds) = intervals(&ua, &ub, stat, r, &name);
    Some(Contrast {
        benchmark: benchmark.into(),
        metric: metric.into(),
        severity,
        first: ma.label.clone(),
        second: mb.label.clone(),
        over_robots,
        over_seeds,
        first_seeds: ua.iter().map(|s| stat(s)).collect(),
        second_seeds: ub.iter().map(|s| stat(s)).collect(),
    })
}

/// The difference `stat(a) - stat(b)` with its interval over robots (seeds as
/// they are) and over seeds and robots, each bootstrap seeded by `name`.
fn intervals(
    a: &BySeed,
    b: &BySeed,
    stat: Statistic,
    r: Resampling,
    name: &str,
) -> (Estimate, Estimate) {
    let value = stat(&a.concat()) - stat(&b.concat());
    let interval = |resample_seeds: bool, what: &str| {
        let mut rng = ChaCha8Rng::seed_from_u64(cell_seed(r.seed, &format!("{name}/{what}")));
        let mut diffs: Vec<f64> = (0..r.resamples)
            .map(|_| {
                let sa = resample(a, resample_seeds, &mut rng);
                let sb = resample(b, resample_seeds, &mut rng);
                stat(&sa) - stat(&sb)
            })
            .collect();
        diffs.sort_by(f64::total_cmp);
        let alpha = (1.0 - r.level) / 2.0;
        Estimate {
            value,
            lo: percentile(&diffs, alpha),
            hi: percentile(&diffs, 1.0 - alpha),
        }
    };
    (interval(false, "robots"), interval(true, "seeds"))
}

/// One bootstrap draw of a method's strata: its seeds as they are or drawn with
/// replacement (`resample_seeds`), then every stratum's units drawn with replacement.
fn resample(seeds: &BySeed, resample_seeds: bool, rng: &mut ChaCha8Rng) -> Vec<Vec<f64>> {
    let n = seeds.len();
    let mut out = Vec::new();
    for k in 0..n {
        let seed = if resample_seeds {
            &seeds[rng.gen_range(0..n)]
        } else {
            &seeds[k]
        };
        for stratum in seed {
            let m = stratum.len();
            out.push((0..m).map(|_| stratum[rng.gen_range(0..m)]).collect());
        }
    }
    out
}

/// `contrasts.csv`: a row per pair, metric and rung.
pub fn contrasts_csv(rows: &[Contrast]) -> String {
    let mut s = String::from(
        "first,second,benchmark,metric,severity,difference,robots_lo,robots_hi,seeds_lo,seeds_hi,first_seeds,second_seeds,seed_pairs_ahead,seed_pairs,verdict\n",
    );
    let list = |v: &[f64]| {
        v.iter()
            .map(|x| format!("{x:.4}"))
            .collect::<Vec<_>>()
            .join(";")
    };
    for c in rows {
        let (ahead, pairs) = c.pairs_ahead();
        let _ = writeln!(
            s,
            "{},{},{},{},{},{:.4},{:.4},{:.4},{:.4},{:.4},{},{},{ahead},{pairs},{}",
            csv_field(&c.first),
            csv_field(&c.second),
            c.benchmark,
            c.metric,
            c.severity,
            c.over_robots.value,
            c.over_robots.lo,
            c.over_robots.hi,
            c.over_seeds.lo,
            c.over_seeds.hi,
            list(&c.first_seeds),
            list(&c.second_seeds),
            c.verdict()
        );
    }
    s
}

/// The metrics in the order the results show them: (metric, title, decimals).
const METRICS: [(&str, &str, usize); 4] = [
    ("ttf", "TTF", 3),
    ("strict_ttf", "strict TTF", 3),
    ("success_pct", "platform success (points)", 1),
    ("return_q25", "race return q0.25", 1),
];

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
    let _ = writeln!(s, "## Method against method\n");
    let _ = writeln!(s, "Each pair's difference, first minus second (higher is more robust on every benchmark), on every rung: the difference of the two methods' numbers in the robustness curves, with a 95% interval over robots (each seed's robots resampled within their cells; whether these trained policies differ) and one over seeds and robots (each method's seeds drawn with replacement, then robots within each drawn seed; whether the methods would differ with other seeds; with three seeds it is coarse and a little narrow), every seed's own number, and in how many seed pairs the first method is ahead. A method is called ahead or behind on a rung only when the interval over seeds and robots excludes 0.\n");
    for &(a, b) in &pairs {
        let these: Vec<&Contrast> = rows
            .iter()
            .filter(|c| c.first == a && c.second == b)
            .collect();
        let _ = writeln!(s, "**{a} against {b}.**");
        for (metric, title, _) in METRICS {
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
            "| benchmark | rung | difference [over robots] | [over seeds and robots] | {a}: seeds | {b}: seeds | seed pairs ahead |"
        );
        let _ = writeln!(s, "|---|---:|---:|---:|---|---|---:|");
        for (metric, title, d) in METRICS {
            for c in these.iter().filter(|c| c.metric == metric) {
                let list = |v: &[f64]| {
                    v.iter()
                        .map(|x| format!("{x:.d$}"))
                        .collect::<Vec<_>>()
                        .join(", ")
                };
                let (ahead, n) = c.pairs_ahead();
                let _ = writeln!(
                    s,
                    "| {title} | {} | {:+.d$} [{:+.d$}, {:+.d$}] | [{:+.d$}, {:+.d$}] | {} | {} | {ahead} / {n} |",
                    c.severity,
                    c.over_robots.value,
                    c.over_robots.lo,
                    c.over_robots.hi,
                    c.over_seeds.lo,
                    c.over_seeds.hi,
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
    fn resampling_seeds_draws_whole_seeds_and_keeps_their_count() {
        let s = seeds(&[&[1.0; 5], &[2.0; 5], &[3.0; 5]]);
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        let mut saw_repeat = false;
        for _ in 0..50 {
            let d = resample(&s, true, &mut rng);
            assert_eq!(d.len(), 3);
            // a drawn seed keeps its own units: every stratum is constant
            for st in &d {
                assert!(st.iter().all(|&x| x == st[0]));
            }
            let firsts: Vec<f64> = d.iter().map(|st| st[0]).collect();
            saw_repeat |= firsts[0] == firsts[1] || firsts[1] == firsts[2];
        }
        assert!(saw_repeat, "seeds are drawn with replacement");
        // without seed resampling each seed stays in place
        let d = resample(&s, false, &mut rng);
        assert_eq!(d, s.concat());
    }

    /// Robots around `centre`, spread +-0.05.
    fn robots(centre: f64) -> Vec<f64> {
        (0..20).map(|i| centre + 0.005 * i as f64 - 0.05).collect()
    }

    #[test]
    fn seeds_that_disagree_widen_the_interval_over_seeds_only() {
        // A's seeds at 0.9, 0.5, 0.7 (mean 0.7); B's three at 0.6: A is ahead on
        // these robots, but one of A's seeds is behind every B seed
        let a: BySeed = [0.9, 0.5, 0.7].iter().map(|&c| vec![robots(c)]).collect();
        let b: BySeed = [0.6, 0.6, 0.6].iter().map(|&c| vec![robots(c)]).collect();
        let r = Resampling::default();
        let (robots_iv, seeds_iv) = intervals(&a, &b, mean_of_means, r, "t");
        assert!((robots_iv.value - 0.1).abs() < 1e-9, "{robots_iv:?}");
        assert_eq!(robots_iv.value, seeds_iv.value);
        assert!(robots_iv.lo > 0.05 && robots_iv.hi < 0.15, "{robots_iv:?}");
        assert!(seeds_iv.lo < 0.0 && seeds_iv.hi > 0.15, "{seeds_iv:?}");
        // reproducible, and another cell's name draws differently
        assert_eq!(
            intervals(&a, &b, mean_of_means, r, "t"),
            (robots_iv, seeds_iv)
        );
        assert_ne!(intervals(&a, &b, mean_of_means, r, "u").1, seeds_iv);
        // seeds that agree: the interval over seeds excludes 0 too
        let a2: BySeed = [0.7, 0.7, 0.7].iter().map(|&c| vec![robots(c)]).collect();
        let (_, agree) = intervals(&a2, &b, mean_of_means, r, "t");
        assert!(agree.lo > 0.05, "{agree:?}");
    }

    #[test]
    fn pairs_count_the_seeds_and_the_verdict_reads_the_seed_interval() {
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
            over_seeds: Estimate {
                value: 0.1,
                lo: -0.02,
                hi: 0.2,
            },
            first_seeds: vec![0.5, 0.7, 0.6],
            second_seeds: vec![0.55, 0.45, 0.5],
        };
        assert_eq!(c.pairs_ahead(), (7, 9));
        assert_eq!(c.verdict(), "level");
    }
}
