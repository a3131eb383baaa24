//! Verdicts that keep their error rate (`[verdicts]`): the primary result declared
//! before its data, its confirmation on the seeds named for it, and families of
//! secondary contrasts adjusted by Holm's step-down procedure.
//!
//! Every verdict here is a seed-level test: one number per seed (its mean over its
//! last K checkpoints and robots, the contrasts' seed numbers), Welch's t-test on
//! those numbers, the exact permutation test over seed labels beside it. Contrasts
//! outside `[verdicts]` stay exploratory (`contrasts.csv`, unadjusted).

use std::fmt::Write as _;

use anyhow::{bail, Result};
use serde::{Deserialize, Serialize};

use super::contrasts::{safer_sign, Contrast};
use super::pooled::methods_of;
use super::spec::ExperimentSpec;
use crate::stats::mean;
use crate::stats::seed_test::{holm, permutation_p, pooled_sd, seeds_for_power, welch, Verdict};

/// A metric a verdict can name: (metric, benchmark, title, decimals, seconds per
/// unit: TTF is a share of the 20 s episode).
type MetricRow = (&'static str, &'static str, &'static str, usize, Option<f64>);

/// The ladder's metrics, each on a rung.
const RUNG_METRICS: [MetricRow; 4] = [
    ("ttf", "ttf", "TTF", 3, Some(20.0)),
    ("strict_ttf", "ttf", "strict TTF", 3, Some(20.0)),
    (
        "success_pct",
        "platform",
        "platform success (points)",
        1,
        None,
    ),
    ("return_q25", "race", "race return q0.25", 1, None),
];

/// Every metric a verdict can name: the ladder's, then each benchmark's
/// (`super::benchmark`; the command map's two, `[commands]`), which have no rung.
fn metrics() -> Vec<MetricRow> {
    let mut out = RUNG_METRICS.to_vec();
    let of_benchmarks = super::benchmark::metrics().into_iter();
    out.extend(of_benchmarks.map(|(b, m)| (m.name, b, m.title, m.decimals, None)));
    out
}

/// Whether `metric` is a benchmark's (no rung), such as the command map's.
fn is_benchmark_metric(metric: &str) -> bool {
    super::benchmark::metric(metric).is_some()
}

/// `[verdicts]`: the pre-registered primary result and the families of secondary
/// contrasts, tested on the confirmatory seeds.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct VerdictsSpec {
    /// Each test's level (two-sided); also the familywise level of each family.
    /// In (0, 0.5]; default 0.05.
    #[serde(default = "default_alpha")]
    pub alpha: f64,
    /// The confirmatory seeds (the runs' `seed` numbers); empty: every seed.
    #[serde(default)]
    pub seeds: Vec<u64>,
    /// Where the hypotheses were written down before the data (shown in the results).
    #[serde(default)]
    pub preregistration: Option<std::path::PathBuf>,
    pub primary: ContrastKey,
    /// Families of secondary contrasts, each Holm-adjusted on its own (`[[verdicts.family]]`).
    #[serde(default, rename = "family")]
    pub families: Vec<Family>,
}

fn default_alpha() -> f64 {
    0.05
}

/// A named family of contrasts, adjusted together.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Family {
    pub name: String,
    pub contrasts: Vec<ContrastKey>,
}

/// One contrast: `first` minus `second` (run labels of the two methods, as in
/// `[contrasts].pairs`) on `metric` at `rung` (a rung of the ladder, or `"mean"`:
/// each seed's mean over every evaluated rung). The command map's metrics
/// (`safe_share`, `worst_cell_falls`) have no rung: leave it out (or give 0).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ContrastKey {
    pub first: String,
    pub second: String,
    pub metric: String,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub rung: Option<Rung>,
}

/// A rung, or the mean over every evaluated rung.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(untagged)]
pub enum Rung {
    One(usize),
    Named(String),
}

impl Rung {
    fn show(&self) -> String {
        match self {
            Rung::One(r) => format!("rung {r}"),
            Rung::Named(_) => "mean over rungs".into(),
        }
    }
}

impl ContrastKey {
    fn validate(&self, spec: &ExperimentSpec, at: &str) -> Result<()> {
        if is_benchmark_metric(&self.metric) {
            self.validate_benchmark_metric(spec, at)?;
        } else {
            match &self.rung {
                None => bail!(
                    "{at} gives no rung: give a rung number or \"mean\" (only a benchmark's own metrics, such as the command map's, have none)"
                ),
                Some(Rung::Named(n)) if n != "mean" => {
                    bail!("{at}.rung is {n:?}: give a rung number or \"mean\"")
                }
                _ => {}
            }
        }
        let all = metrics();
        if !all.iter().any(|m| m.0 == self.metric) {
            let known: Vec<&str> = all.iter().map(|m| m.0).collect();
            bail!(
                "{at}.metric is {:?}; known metrics: {}",
                self.metric,
                known.join(", ")
            );
        }
        let pairs = spec.contrasts.as_ref().map_or(&[][..], |c| &c.pairs[..]);
        if !pairs
            .iter()
            .any(|[a, b]| *a == self.first && *b == self.second)
        {
            bail!(
                "{at} compares {:?} with {:?}, which is not a pair of [contrasts].pairs (the verdicts test the contrasts the evaluation computes)",
                self.first,
                self.second
            );
        }
        Ok(())
    }

    /// A benchmark's metric (the command map's): no rung but 0, the benchmark's
    /// section evaluating a run of each of the two methods.
    fn validate_benchmark_metric(&self, spec: &ExperimentSpec, at: &str) -> Result<()> {
        if let Some(r) = self.rung.as_ref().filter(|r| **r != Rung::One(0)) {
            bail!(
                "{at}.rung is {}: the benchmark of {} has no severity rung; leave rung out",
                match r {
                    Rung::One(n) => n.to_string(),
                    Rung::Named(n) => format!("{n:?}"),
                },
                self.metric
            );
        }
        let labels = [self.first.as_str(), self.second.as_str()];
        super::benchmark::check_compared(spec, &self.metric, labels, at)
    }

    fn show(&self) -> String {
        let title = metrics()
            .into_iter()
            .find(|m| m.0 == self.metric)
            .map_or(self.metric.as_str(), |m| m.2);
        match &self.rung {
            Some(r) if !is_benchmark_metric(&self.metric) => {
                format!("{} - {}, {title}, {}", self.first, self.second, r.show())
            }
            _ => format!("{} - {}, {title}", self.first, self.second),
        }
    }
}

impl VerdictsSpec {
    pub fn validate(&self, spec: &ExperimentSpec) -> Result<()> {
        if !(self.alpha > 0.0 && self.alpha <= 0.5) {
            bail!("verdicts.alpha is {}; it must lie in (0, 0.5]", self.alpha);
        }
        let mut seen = self.seeds.clone();
        seen.sort_unstable();
        seen.dedup();
        if seen.len() != self.seeds.len() {
            bail!("verdicts.seeds lists a seed twice");
        }
        self.primary.validate(spec, "verdicts.primary")?;
        for (i, f) in self.families.iter().enumerate() {
            if f.contrasts.is_empty() {
                bail!("verdicts.family {:?} lists no contrast", f.name);
            }
            if self.families[..i].iter().any(|g| g.name == f.name) || f.name == "primary" {
                bail!(
                    "verdicts.family {:?}: family names must be unique and not \"primary\"",
                    f.name
                );
            }
            for (k, c) in f.contrasts.iter().enumerate() {
                c.validate(
                    spec,
                    &format!("verdicts.family {:?} contrast {}", f.name, k + 1),
                )?;
            }
        }
        Ok(())
    }

    /// `4-8`, `1, 3, 5` or `every seed`.
    fn seeds_text(&self) -> String {
        seed_list(&self.seeds)
    }
}

/// `4-8`, `1, 3, 5`, or `every seed` for none.
fn seed_list(seeds: &[u64]) -> String {
    if seeds.is_empty() {
        return "every seed".into();
    }
    let mut s = seeds.to_vec();
    s.sort_unstable();
    let consecutive = s.windows(2).all(|w| w[1] == w[0] + 1);
    if consecutive && s.len() > 2 {
        format!("{}-{}", s[0], s[s.len() - 1])
    } else {
        s.iter().map(u64::to_string).collect::<Vec<_>>().join(", ")
    }
}

/// One tested contrast.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SeedVerdict {
    /// `primary`, `primary, every seed` or a family's name.
    pub family: String,
    pub key: ContrastKey,
    /// The seed numbers behind `first_values` and `second_values`.
    pub first_seeds: Vec<u64>,
    pub second_seeds: Vec<u64>,
    pub first_values: Vec<f64>,
    pub second_values: Vec<f64>,
    /// Welch's difference of seed means and its interval at 1 - alpha (None under
    /// two seeds on either side).
    pub difference: Option<f64>,
    pub lo: Option<f64>,
    pub hi: Option<f64>,
    pub df: Option<f64>,
    pub p_welch: Option<f64>,
    pub p_permutation: Option<f64>,
    /// Holm-adjusted within its family (None for the primary).
    pub p_holm: Option<f64>,
    /// `ahead`, `behind`, `level` or `not evaluated`.
    pub verdict: String,
}

/// Every contrast of `[verdicts]` tested on `contrasts` (none without `[verdicts]`).
pub fn judge(spec: &ExperimentSpec, contrasts: &[Contrast]) -> Vec<SeedVerdict> {
    let Some(v) = &spec.verdicts else {
        return Vec::new();
    };
    let mut out = vec![test(
        spec, contrasts, &v.primary, &v.seeds, "primary", v.alpha,
    )];
    if !v.seeds.is_empty() {
        out.push(test(
            spec,
            contrasts,
            &v.primary,
            &[],
            "primary, every seed",
            v.alpha,
        ));
    }
    for f in &v.families {
        let mut rows: Vec<SeedVerdict> = f
            .contrasts
            .iter()
            .map(|k| test(spec, contrasts, k, &v.seeds, &f.name, v.alpha))
            .collect();
        let p: Vec<f64> = rows.iter().map(|r| r.p_welch.unwrap_or(f64::NAN)).collect();
        for (r, adj) in rows.iter_mut().zip(holm(&p)) {
            if adj.is_nan() {
                continue;
            }
            r.p_holm = Some(adj);
            let safer = safer_sign(&r.key.metric) * r.difference.unwrap_or(0.0);
            r.verdict = Verdict::from_p(safer, adj, v.alpha).as_str().into();
        }
        out.extend(rows);
    }
    out
}

/// The verdict of one comparison at `alpha`: Welch's two-sided test on the seed
/// numbers (ahead or behind when its 1 - alpha interval excludes 0); level with
/// fewer than two seeds on either side.
pub fn seed_verdict(first: &[f64], second: &[f64], alpha: f64) -> Verdict {
    welch(first, second, 1.0 - alpha).map_or(Verdict::Level, |w| {
        Verdict::from_p(w.difference, w.p, alpha)
    })
}

/// One contrast tested on `seeds` (empty: every seed), unadjusted.
fn test(
    spec: &ExperimentSpec,
    contrasts: &[Contrast],
    key: &ContrastKey,
    seeds: &[u64],
    family: &str,
    alpha: f64,
) -> SeedVerdict {
    let (first, second) = seed_values(spec, contrasts, key);
    let keep = |v: SeedNumbers| -> (Vec<u64>, Vec<f64>) {
        v.into_iter()
            .filter(|(s, _)| seeds.is_empty() || seeds.contains(s))
            .unzip()
    };
    let ((first_seeds, first_values), (second_seeds, second_values)) = (keep(first), keep(second));
    let w = welch(&first_values, &second_values, 1.0 - alpha);
    SeedVerdict {
        family: family.into(),
        key: key.clone(),
        difference: w.map(|w| w.difference),
        lo: w.map(|w| w.lo),
        hi: w.map(|w| w.hi),
        df: w.map(|w| w.df.min(1e9)),
        p_welch: w.map(|w| w.p),
        p_permutation: w.and(permutation_p(&first_values, &second_values)),
        p_holm: None,
        verdict: match w {
            Some(w) => Verdict::from_p(safer_sign(&key.metric) * w.difference, w.p, alpha)
                .as_str()
                .into(),
            None => "not evaluated".into(),
        },
        first_seeds,
        second_seeds,
        first_values,
        second_values,
    }
}

/// One method's (seed number, value) pairs.
type SeedNumbers = Vec<(u64, f64)>;

/// Each method's (seed number, value) on `key`: the contrast's seed numbers at its
/// rung, or each seed's mean over every rung it has (a seed missing a rung the
/// other seeds have is left out of the mean over rungs).
fn seed_values(
    spec: &ExperimentSpec,
    contrasts: &[Contrast],
    key: &ContrastKey,
) -> (SeedNumbers, SeedNumbers) {
    let rows: Vec<&Contrast> = contrasts
        .iter()
        .filter(|c| c.first == key.first && c.second == key.second && c.metric == key.metric)
        .filter(|c| match key.rung {
            Some(Rung::One(r)) => c.severity == r,
            // "mean", or the command map's one row
            _ => true,
        })
        .collect();
    let side = |first: bool| -> SeedNumbers {
        let mut per_seed: Vec<(String, Vec<f64>)> = Vec::new();
        for c in &rows {
            let (labels, values) = if first {
                (labels_of(spec, c, true), &c.first_seeds)
            } else {
                (labels_of(spec, c, false), &c.second_seeds)
            };
            for (l, v) in labels.into_iter().zip(values) {
                match per_seed.iter_mut().find(|(k, _)| *k == l) {
                    Some((_, vs)) => vs.push(*v),
                    None => per_seed.push((l, vec![*v])),
                }
            }
        }
        let rungs = rows.len();
        per_seed
            .into_iter()
            .filter(|(_, vs)| vs.len() == rungs)
            .filter_map(|(l, vs)| Some((spec.run(&l)?.seed, mean(&vs))))
            .collect()
    };
    (side(true), side(false))
}

/// The run labels of a contrast's seed numbers: stored with it, or (results written
/// before labels were kept, every seed evaluated) the method's first seeds in the
/// experiment file's order.
fn labels_of(spec: &ExperimentSpec, c: &Contrast, first: bool) -> Vec<String> {
    let (stored, n, label) = if first {
        (&c.first_labels, c.first_seeds.len(), &c.first)
    } else {
        (&c.second_labels, c.second_seeds.len(), &c.second)
    };
    if !stored.is_empty() {
        return stored.clone();
    }
    let all: Vec<String> = spec.runs.iter().map(|r| r.label.clone()).collect();
    methods_of(spec, &all)
        .into_iter()
        .find(|m| m.seeds.contains(label))
        .map(|m| m.seeds.into_iter().take(n).collect())
        .unwrap_or_default()
}

/// `verdicts.csv`: a row per tested contrast.
pub fn verdicts_csv(rows: &[SeedVerdict]) -> String {
    let mut s = String::from(
        "family,first,second,metric,rung,first_seeds,second_seeds,first_values,second_values,difference,lo,hi,df,p_welch,p_permutation,p_holm,verdict\n",
    );
    let opt = |v: Option<f64>, d: usize| v.map_or(String::new(), |x| format!("{x:.d$}"));
    let seeds = |v: &[u64]| v.iter().map(u64::to_string).collect::<Vec<_>>().join(";");
    let values = |v: &[f64]| {
        v.iter()
            .map(|x| format!("{x:.4}"))
            .collect::<Vec<_>>()
            .join(";")
    };
    for r in rows {
        let rung = match &r.key.rung {
            Some(Rung::One(n)) => n.to_string(),
            Some(Rung::Named(n)) => n.clone(),
            None => String::new(),
        };
        let _ = writeln!(
            s,
            "{},{},{},{},{rung},{},{},{},{},{},{},{},{},{},{},{},{}",
            crate::eval::report::csv_field(&r.family),
            crate::eval::report::csv_field(&r.key.first),
            crate::eval::report::csv_field(&r.key.second),
            r.key.metric,
            seeds(&r.first_seeds),
            seeds(&r.second_seeds),
            values(&r.first_values),
            values(&r.second_values),
            opt(r.difference, 4),
            opt(r.lo, 4),
            opt(r.hi, 4),
            opt(r.df, 2),
            opt(r.p_welch, 4),
            opt(r.p_permutation, 4),
            opt(r.p_holm, 4),
            r.verdict
        );
    }
    s
}

/// The metric's decimals and seconds per unit.
fn metric_format(metric: &str) -> (usize, Option<f64>) {
    metrics()
        .into_iter()
        .find(|m| m.0 == metric)
        .map_or((3, None), |m| (m.3, m.4))
}

/// `+0.041 [+0.010, +0.072]` (Welch, 1 - alpha), with seconds for TTF.
fn show_difference(r: &SeedVerdict) -> String {
    let (d, secs) = metric_format(&r.key.metric);
    let (Some(x), Some(lo), Some(hi)) = (r.difference, r.lo, r.hi) else {
        return "-".into();
    };
    let mut s = format!("{x:+.d$} [{lo:+.d$}, {hi:+.d$}]");
    if let Some(k) = secs {
        let _ = write!(s, " ({:+.1} s [{:+.1}, {:+.1}])", k * x, k * lo, k * hi);
    }
    s
}

/// The results' opening section: the primary result, its every-seed view, the
/// families (Holm), and what is exploratory.
fn verdicts_markdown(v: &VerdictsResult, s: &mut String) {
    let (spec_alpha, seeds, rows) = (v.alpha, v.seeds.as_str(), &v.rows);
    let Some(primary) = rows.iter().find(|r| r.family == "primary") else {
        return;
    };
    let level = 100.0 * (1.0 - spec_alpha);
    let _ = writeln!(s, "## The pre-registered result\n");
    if let Some(p) = &v.preregistration {
        let _ = writeln!(
            s,
            "Declared in `{p}` before the seeds {seeds} were trained: the primary contrast, its test and the families below.\n"
        );
    }
    let (n1, n2) = (primary.first_values.len(), primary.second_values.len());
    if primary.verdict == "not evaluated" {
        let _ = writeln!(
            s,
            "**Primary: {}, seeds {seeds}: not evaluated yet** ({n1} seeds of {} and {n2} of {} evaluated; two per method are the least a test needs).\n",
            primary.key.show(),
            primary.key.first,
            primary.key.second
        );
    } else {
        let _ = writeln!(
            s,
            "**Primary: {}, seeds {seeds} ({n1} against {n2}): {}, {}.** Welch's t-test on one number per seed (its mean over its last checkpoints and robots), {level:.0}% interval, p = {:.4} (df {:.1}); the exact permutation test over seed labels gives p = {}.\n",
            primary.key.show(),
            show_difference(primary),
            primary.verdict,
            primary.p_welch.unwrap_or(f64::NAN),
            primary.df.unwrap_or(f64::NAN),
            primary.p_permutation.map_or("-".into(), |p| format!("{p:.4}")),
        );
    }
    if let Some(every) = rows.iter().find(|r| r.family == "primary, every seed") {
        let _ = writeln!(
            s,
            "Every seed ({} against {}, not confirmatory: the seeds outside {seeds} suggested the hypothesis): {}, {} (p = {}).\n",
            every.first_values.len(),
            every.second_values.len(),
            show_difference(every),
            every.verdict,
            every.p_welch.map_or("-".into(), |p| format!("{p:.4}")),
        );
    }
    let families: Vec<&str> = {
        let mut f: Vec<&str> = Vec::new();
        for r in rows.iter().filter(|r| !r.family.starts_with("primary")) {
            if !f.contains(&r.family.as_str()) {
                f.push(&r.family);
            }
        }
        f
    };
    for f in families {
        let _ = writeln!(
            s,
            "**Family {f:?}** (seeds {seeds}; Holm-adjusted, familywise alpha {spec_alpha}):\n"
        );
        let _ = writeln!(
            s,
            "| contrast | seeds | difference [Welch {level:.0}%] | p | Holm p | verdict |"
        );
        let _ = writeln!(s, "|---|---|---:|---:|---:|---|");
        for r in rows.iter().filter(|r| r.family == f) {
            let _ = writeln!(
                s,
                "| {} | {} / {} | {} | {} | {} | {} |",
                r.key.show(),
                r.first_values.len(),
                r.second_values.len(),
                show_difference(r),
                r.p_welch.map_or("-".into(), |p| format!("{p:.4}")),
                r.p_holm.map_or("-".into(), |p| format!("{p:.4}")),
                r.verdict
            );
        }
        let _ = writeln!(s);
    }
    if rows
        .iter()
        .any(|r| r.key.metric == super::commands::WORST_CELL_FALLS)
    {
        let _ = writeln!(s, "On the command map's worst cell's fall rate lower is safer: there ahead means a negative difference (the first method's worst cell falls less).\n");
    }
    let _ = writeln!(s, "Everything else below is exploratory (unadjusted; `contrasts.csv`). `verdicts.csv` lists each seed's number behind these verdicts.\n");
}

/// `rall experiment --power`: for the primary and every family contrast, the
/// between-seed spread measured on every evaluated seed and the seeds per method
/// Welch's test needs for 80% power at the observed difference and at `effect`.
pub fn power_lines(
    spec: &ExperimentSpec,
    contrasts: &[Contrast],
    effect: Option<f64>,
) -> Result<Vec<String>> {
    let Some(v) = &spec.verdicts else {
        bail!("the experiment file has no [verdicts] section: nothing to plan");
    };
    let keys = std::iter::once(&v.primary).chain(v.families.iter().flat_map(|f| &f.contrasts));
    let mut out = vec![format!(
        "seeds per method for 80% power (Welch, two-sided, alpha {}), from the spread over every evaluated seed:",
        v.alpha
    )];
    for key in keys {
        let (a, b) = seed_values(spec, contrasts, key);
        let (va, vb): (Vec<f64>, Vec<f64>) = (
            a.iter().map(|x| x.1).collect(),
            b.iter().map(|x| x.1).collect(),
        );
        let sd = pooled_sd(&va, &vb);
        if va.len() < 2 || vb.len() < 2 || !sd.is_finite() {
            out.push(format!(
                "  {}: fewer than two evaluated seeds per method",
                key.show()
            ));
            continue;
        }
        let observed = mean(&va) - mean(&vb);
        let need = |d: f64| -> String {
            if sd == 0.0 {
                return "2".into();
            }
            seeds_for_power(d.abs(), sd, v.alpha, 0.8, 100)
                .map_or("more than 100".into(), |n| n.to_string())
        };
        let (dec, _) = metric_format(&key.metric);
        let mut line = format!(
            "  {}: seed spread (pooled SD) {sd:.dec$} over {} + {} seeds; observed difference {observed:+.dec$} needs {}",
            key.show(),
            va.len(),
            vb.len(),
            need(observed)
        );
        if let Some(e) = effect {
            let _ = write!(line, "; a difference of {e} needs {}", need(e));
        }
        out.push(line);
    }
    Ok(out)
}

/// What the results show of `[verdicts]`: the tested rows and the settings behind them.
#[derive(Debug, Clone, PartialEq)]
pub struct VerdictsResult {
    pub alpha: f64,
    /// The confirmatory seeds, as text (`4-8`).
    pub seeds: String,
    pub preregistration: Option<String>,
    pub rows: Vec<SeedVerdict>,
}

impl VerdictsResult {
    /// `spec`'s `[verdicts]` tested on `contrasts`; `None` without the section.
    pub fn of(spec: &ExperimentSpec, contrasts: &[Contrast]) -> Option<VerdictsResult> {
        let v = spec.verdicts.as_ref()?;
        Some(VerdictsResult {
            alpha: v.alpha,
            seeds: v.seeds_text(),
            preregistration: v.preregistration.as_ref().map(|p| p.display().to_string()),
            rows: judge(spec, contrasts),
        })
    }

    /// The README's opening section.
    pub fn markdown(&self, s: &mut String) {
        verdicts_markdown(self, s);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::experiment::stats::Estimate;

    /// Methods A (seeds 1-5) and B (seeds 1-5); confirmatory seeds 3-5.
    fn spec() -> ExperimentSpec {
        let mut text = String::from(
            "name = \"t\"\nruns_dir = \"r\"\nresults_dir = \"o\"\n\
             [tracking]\nepisodes = 1\nseed = 1\n\
             [ttf]\nmethods = [\"A\"]\nseeds = 1\nrepeats = 1\n\
             [platform]\nmethods = [\"A\"]\nheights_m = [0.4]\nseeds = 1\nrepeats = 1\n\
             [race]\nmethods = [\"A\"]\nagents = 1\nepisodes = 1\n\
             [contrasts]\npairs = [[\"A\", \"B\"]]\n\
             [verdicts]\nseeds = [3, 4, 5]\n\
             primary = { first = \"A\", second = \"B\", metric = \"ttf\", rung = 1 }\n\
             [[verdicts.family]]\nname = \"secondary\"\ncontrasts = [\
               { first = \"A\", second = \"B\", metric = \"ttf\", rung = \"mean\" },\
               { first = \"A\", second = \"B\", metric = \"strict_ttf\", rung = 1 }]\n",
        );
        for (name, label) in [("a", "A"), ("b", "B")] {
            for seed in 1..=5 {
                let l = if seed == 1 {
                    label.to_string()
                } else {
                    format!("{label} seed {seed}")
                };
                text.push_str(&format!(
                    "[[run]]\nname = \"{name}\"\nlabel = \"{l}\"\nconfig = \"c.toml\"\nseed = {seed}\niterations = 1\n"
                ));
            }
        }
        let spec: ExperimentSpec = toml::from_str(&text).unwrap();
        spec.verdicts.as_ref().unwrap().validate(&spec).unwrap();
        spec
    }

    fn contrast(metric: &str, severity: usize, a: &[f64], b: &[f64], labelled: bool) -> Contrast {
        let labels = |m: &str, n: usize| -> Vec<String> {
            if !labelled {
                return Vec::new();
            }
            (1..=n)
                .map(|s| {
                    if s == 1 {
                        m.into()
                    } else {
                        format!("{m} seed {s}")
                    }
                })
                .collect()
        };
        Contrast {
            benchmark: "ttf".into(),
            metric: metric.into(),
            severity,
            first: "A".into(),
            second: "B".into(),
            over_robots: Estimate {
                value: 0.0,
                lo: 0.0,
                hi: 0.0,
            },
            first_seeds: a.to_vec(),
            second_seeds: b.to_vec(),
            first_labels: labels("A", a.len()),
            second_labels: labels("B", b.len()),
        }
    }

    #[test]
    fn the_primary_uses_its_seeds_alone_and_the_family_is_adjusted() {
        let spec = spec();
        // seeds 1-2 favour B strongly, seeds 3-5 favour A
        let a = [0.1, 0.1, 0.50, 0.52, 0.51];
        let b = [0.9, 0.9, 0.40, 0.41, 0.42];
        let rows = judge(
            &spec,
            &[
                contrast("ttf", 0, &a, &b, true),
                contrast("ttf", 1, &a, &b, true),
                contrast("strict_ttf", 1, &[0.3; 5], &[0.3; 5], true),
            ],
        );
        let primary = &rows[0];
        assert_eq!(primary.family, "primary");
        assert_eq!(primary.first_seeds, vec![3, 4, 5]);
        assert_eq!(primary.first_values, vec![0.50, 0.52, 0.51]);
        assert_eq!(primary.verdict, "ahead");
        assert!(primary.p_holm.is_none());
        // every seed: seeds 1-2 pull the other way
        assert_eq!(rows[1].family, "primary, every seed");
        assert_eq!(rows[1].first_seeds.len(), 5);
        assert_eq!(rows[1].verdict, "level");
        // the family: mean over rungs 0 and 1 per seed, and a null contrast
        let fam: Vec<&SeedVerdict> = rows.iter().filter(|r| r.family == "secondary").collect();
        assert_eq!(fam.len(), 2);
        assert_eq!(fam[0].first_values, vec![0.50, 0.52, 0.51]);
        let (p0, p1) = (fam[0].p_welch.unwrap(), fam[1].p_welch.unwrap());
        let adjusted = holm(&[p0, p1]);
        assert_eq!(fam[0].p_holm, Some(adjusted[0]));
        assert_eq!(fam[1].p_holm, Some(adjusted[1]));
        assert!(adjusted[0] > p0, "the family's adjustment is applied");
        assert_eq!(fam[1].verdict, "level");
        // the CSV carries every row
        let csv = verdicts_csv(&rows);
        assert_eq!(csv.lines().count(), 1 + rows.len());
        assert!(csv
            .lines()
            .nth(1)
            .unwrap()
            .starts_with("primary,A,B,ttf,1,3;4;5,"));
    }

    #[test]
    fn seeds_not_yet_evaluated_say_so() {
        let spec = spec();
        // only seeds 1-3 evaluated (results written before labels were kept)
        let rows = judge(
            &spec,
            &[contrast(
                "ttf",
                1,
                &[0.5, 0.6, 0.7],
                &[0.4, 0.5, 0.6],
                false,
            )],
        );
        // one confirmatory seed (3) per method: no test
        assert_eq!(rows[0].first_seeds, vec![3]);
        assert_eq!(rows[0].verdict, "not evaluated");
        assert_eq!(rows[1].first_seeds, vec![1, 2, 3]);
        let v = VerdictsResult::of(&spec, &[contrast("ttf", 1, &[0.5], &[0.4], false)]).unwrap();
        let mut md = String::new();
        v.markdown(&mut md);
        assert!(md.contains("not evaluated yet"), "{md}");
    }

    #[test]
    fn on_the_worst_cell_a_lower_fall_rate_is_ahead() {
        let spec = spec();
        let key = ContrastKey {
            first: "A".into(),
            second: "B".into(),
            metric: "worst_cell_falls".into(),
            rung: None,
        };
        let mut c = contrast(
            "worst_cell_falls",
            0,
            &[0.0, 0.125, 0.0, 0.125, 0.0],
            &[0.5, 0.625, 0.5, 0.625, 0.5],
            true,
        );
        c.benchmark = "commands".into();
        let r = test(
            &spec,
            std::slice::from_ref(&c),
            &key,
            &[],
            "secondary",
            0.05,
        );
        assert!(r.difference.unwrap() < 0.0, "{r:?}");
        assert_eq!(r.verdict, "ahead");
        assert_eq!((c.verdict(), c.pairs_ahead()), ("ahead", (25, 25)));
        assert_eq!(key.show(), "A - B, command map worst cell's fall rate");
        let csv = verdicts_csv(&[r]);
        assert!(
            csv.lines()
                .nth(1)
                .unwrap()
                .starts_with("secondary,A,B,worst_cell_falls,,1;2;3;4;5,"),
            "{csv}"
        );
    }

    #[test]
    fn bad_verdict_keys_are_refused_by_name() {
        let spec = spec();
        let mut v = spec.verdicts.clone().unwrap();
        v.primary.metric = "speed".into();
        let e = v.validate(&spec).unwrap_err().to_string();
        assert!(e.contains("speed") && e.contains("known metrics"), "{e}");
        let mut v = spec.verdicts.clone().unwrap();
        v.primary.second = "C".into();
        assert!(v
            .validate(&spec)
            .unwrap_err()
            .to_string()
            .contains("[contrasts].pairs"));
        let mut v = spec.verdicts.clone().unwrap();
        v.primary.rung = Some(Rung::Named("last".into()));
        assert!(v
            .validate(&spec)
            .unwrap_err()
            .to_string()
            .contains("\"mean\""));
        let mut v = spec.verdicts.clone().unwrap();
        v.alpha = 0.0;
        assert!(v.validate(&spec).is_err());
        assert_eq!(seed_list(&[4, 5, 6, 7, 8]), "4-8");
        assert_eq!(seed_list(&[1, 3]), "1, 3");
    }
}
