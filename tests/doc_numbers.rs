//! Every number the documents quote comes from the results file.
//! - README.md's results table is rebuilt here from `results/paper/results.json`
//!   (the curves and the seed-level contrasts) and must match it line for line.
//! - Every interval quoted as `x [lo, hi]` in README.md and `results/paper/about.md`
//!   (the answer paragraph) must be one the results hold at the precision quoted: a
//!   curve point, a contrast over robots or by Welch's test on seeds, or a verdict.

use std::fmt::Write as _;
use std::path::Path;

use rall::experiment::results::ExperimentResults;
use rall::experiment::spec::ExperimentSpec;
use rall::experiment::verdicts::VerdictsResult;

const RESULTS: &str = "results/paper";
const TABLE_START: &str = "<!-- results table: rebuilt by tests/doc_numbers.rs -->";
const TABLE_END: &str = "<!-- end of results table -->";
const METHODS: [&str; 5] = ["Baseline", "Baseline + risk", "RALL", "DR", "RMA"];

fn results() -> ExperimentResults {
    ExperimentResults::read(Path::new(RESULTS)).expect("results/paper/results.json")
}

/// The README's results table: TTF and strict TTF per rung and method, then
/// RALL - Baseline by Welch's test on the seeds' numbers.
fn results_table(r: &ExperimentResults) -> String {
    let point = |metric: &str, policy: &str, rung: usize| {
        r.curves
            .iter()
            .find(|p| p.metric == metric && p.policy == policy && p.severity == rung)
            .map_or("-".to_string(), |p| format!("{:.3}", p.estimate.value))
    };
    let welch = |metric: &str, rung: usize| {
        r.contrasts
            .iter()
            .find(|c| {
                c.first == "RALL"
                    && c.second == "Baseline"
                    && c.metric == metric
                    && c.severity == rung
            })
            .and_then(|c| Some((c.welch()?, c.verdict())))
            .map_or("-".to_string(), |(w, v)| {
                format!("{:+.3} [{:+.3}, {:+.3}] {v}", w.difference, w.lo, w.hi)
            })
    };
    let mut s = String::new();
    let _ = writeln!(
        s,
        "| rung | {} | RALL - Baseline (Welch 95%, seeds 1-3) |",
        METHODS.join(" | ")
    );
    let _ = writeln!(s, "|---:|{}---|", "---:|".repeat(METHODS.len()));
    for (metric, title) in [
        ("ttf", "TTF (the paper's fall definition)"),
        ("strict_ttf", "strict TTF (any non-foot contact is a fall)"),
    ] {
        let _ = writeln!(s, "| | **{title}** |{}", " |".repeat(METHODS.len()));
        for rung in 0..=4 {
            let cells: Vec<String> = METHODS.iter().map(|m| point(metric, m, rung)).collect();
            let _ = writeln!(
                s,
                "| {rung} | {} | {} |",
                cells.join(" | "),
                welch(metric, rung)
            );
        }
    }
    s
}

#[test]
fn the_readme_results_table_is_the_results_files() {
    let readme = std::fs::read_to_string("README.md").unwrap();
    let start = readme
        .find(TABLE_START)
        .expect("README has the results table marker");
    let end = readme
        .find(TABLE_END)
        .expect("README has the end-of-table marker");
    let quoted = readme[start + TABLE_START.len()..end].trim();
    let rebuilt = results_table(&results());
    assert_eq!(
        quoted,
        rebuilt.trim(),
        "README.md's results table differs from results/paper/results.json; it should read:\n{rebuilt}"
    );
}

/// Every `x [lo, hi]` in `text`, each number with its decimals as written.
fn quoted_intervals(text: &str) -> Vec<[(f64, usize); 3]> {
    let number = |s: &str| -> Option<(f64, usize)> {
        let s = s.trim().trim_end_matches('%');
        let v: f64 = s.parse().ok()?;
        let decimals = s.split('.').nth(1).map_or(0, str::len);
        Some((v, decimals))
    };
    let mut out = Vec::new();
    for (i, _) in text.match_indices(" [") {
        let before = &text[..i];
        let x = before
            .rsplit(|c: char| c.is_whitespace() || c == '(')
            .next()
            .unwrap_or("");
        let Some(close) = text[i + 2..].find(']') else {
            continue;
        };
        let inside: Vec<&str> = text[i + 2..i + 2 + close].split(", ").collect();
        if inside.len() != 2 {
            continue;
        }
        if let (Some(x), Some(lo), Some(hi)) = (number(x), number(inside[0]), number(inside[1])) {
            out.push([x, lo, hi]);
        }
    }
    out
}

/// Every (value, lo, hi) the results hold.
fn held_intervals(r: &ExperimentResults, spec: &ExperimentSpec) -> Vec<[f64; 3]> {
    let mut out: Vec<[f64; 3]> = r
        .curves
        .iter()
        .map(|p| [p.estimate.value, p.estimate.lo, p.estimate.hi])
        .collect();
    for c in &r.contrasts {
        out.push([c.over_robots.value, c.over_robots.lo, c.over_robots.hi]);
        if let Some(w) = c.welch() {
            out.push([w.difference, w.lo, w.hi]);
        }
    }
    if let Some(v) = VerdictsResult::of(spec, &r.contrasts) {
        for row in v.rows {
            if let (Some(d), Some(lo), Some(hi)) = (row.difference, row.lo, row.hi) {
                out.push([d, lo, hi]);
                out.push([20.0 * d, 20.0 * lo, 20.0 * hi]);
            }
        }
    }
    out
}

fn same_at(quoted: (f64, usize), held: f64) -> bool {
    let (v, d) = quoted;
    format!("{:.d$}", held) == format!("{:.d$}", v)
        || format!("{:.d$}", held) == format!("{:+.d$}", v).trim_start_matches('+')
}

#[test]
fn every_quoted_interval_is_in_the_results() {
    let r = results();
    let spec = ExperimentSpec::from_file(Path::new("experiments/paper.toml")).unwrap();
    let held = held_intervals(&r, &spec);
    for doc in ["README.md", "results/paper/about.md"] {
        let text = std::fs::read_to_string(doc).unwrap();
        let quoted = quoted_intervals(&text);
        assert!(
            !quoted.is_empty() || doc == "README.md",
            "{doc} quotes no interval"
        );
        for q in quoted {
            let found = held
                .iter()
                .any(|h| same_at(q[0], h[0]) && same_at(q[1], h[1]) && same_at(q[2], h[2]));
            assert!(
                found,
                "{doc} quotes {} [{}, {}], which no curve, contrast or verdict of {RESULTS} holds",
                q[0].0, q[1].0, q[2].0
            );
        }
    }
}

#[test]
fn the_scanner_reads_intervals_as_written() {
    let q = quoted_intervals(
        "TTF +0.061 [+0.008, +0.114], race (-13.4 [-23.6, -3.3]) and 71.0 [60.2, 80.1]%",
    );
    assert_eq!(q.len(), 3);
    assert_eq!(q[0], [(0.061, 3), (0.008, 3), (0.114, 3)]);
    assert_eq!(q[1], [(-13.4, 1), (-23.6, 1), (-3.3, 1)]);
    assert!(same_at((0.061, 3), 0.0608) && !same_at((0.061, 3), 0.0604));
}
