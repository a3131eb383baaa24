//! A benchmark defined outside the crate: each listed run's mean episode length
//! on flat ground under the tracking protocol's commands, registered with one
//! `register_benchmark` call and run by `rall experiment` from its section
//! `[benchmarks.episode_length]` on a tiny experiment. Its CSV file, README
//! section and results.json entry hold the numbers a direct evaluation gives,
//! its metric is a contrast `[verdicts]` can name (one number per seed),
//! `--redraw` writes them again from results.json, and a bad section or verdict
//! is refused by name.

mod common;

use std::fmt::Write as _;
use std::path::Path;
use std::sync::atomic::AtomicBool;
use std::sync::{Arc, OnceLock};

use anyhow::{ensure, Context, Result};
use rall::eval::{evaluate_tracking, tracking_env, ActionMode, NamedPolicy};
use rall::experiment::benchmark::{BenchmarkMetric, Evaluated};
use rall::experiment::contrasts::Contrast;
use rall::experiment::pooled::Method;
use rall::experiment::results::ExperimentResults;
use rall::experiment::stats::Estimate;
use rall::experiment::{
    newest_checkpoint, register_benchmark, run_experiment, Benchmark, BenchmarkContext,
    BenchmarkOutput, ExperimentOptions, ExperimentSpec,
};
use rall::learn::CriticKind;
use serde::{Deserialize, Serialize};

/// `[benchmarks.episode_length]`: the runs, and the episodes each runs.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct LengthSpec {
    methods: Vec<String>,
    episodes: usize,
    #[serde(default)]
    seed: u64,
}

/// One run's mean episode length (policy steps).
#[derive(Debug, Clone, Serialize, Deserialize)]
struct RunLength {
    method: String,
    label: String,
    mean_steps: f64,
}

/// What the benchmark measured: each run, and each method's mean over its seeds.
#[derive(Debug, Clone, Serialize, Deserialize)]
struct Lengths {
    runs: Vec<RunLength>,
    methods: Vec<(String, f64)>,
}

impl BenchmarkOutput for Lengths {
    fn csv_files(&self) -> Vec<(String, String)> {
        let mut s = String::from("method,label,mean_steps\n");
        for r in &self.runs {
            let _ = writeln!(s, "{},{},{:.4}", r.method, r.label, r.mean_steps);
        }
        vec![("episode_length.csv".into(), s)]
    }

    fn markdown(&self, s: &mut String) {
        let _ = writeln!(
            s,
            "## Episode length\n\n| Method | mean steps |\n|---|---:|"
        );
        for (m, steps) in &self.methods {
            let _ = writeln!(s, "| {m} | {steps:.2} |");
        }
        let _ = writeln!(s);
    }
}

struct EpisodeLength;

/// The benchmark's one metric, a contrast per `[contrasts]` pair.
const MEAN_STEPS: &str = "mean_steps";

/// The mean of each seed of the method whose seeds hold `label`, and their labels.
fn seeds_of(methods: &[Method], runs: &[RunLength], label: &str) -> (Vec<f64>, Vec<String>) {
    let method = methods.iter().find(|m| m.seeds.iter().any(|s| s == label));
    runs.iter()
        .filter(|r| method.is_some_and(|m| m.label == r.method))
        .map(|r| (r.mean_steps, r.label.clone()))
        .unzip()
}

/// Each `[contrasts]` pair whose two methods were measured, on the mean episode
/// length (its interval over robots left as the value: a toy).
fn contrasts(spec: &ExperimentSpec, methods: &[Method], runs: &[RunLength]) -> Vec<Contrast> {
    let pairs = spec.contrasts.as_ref().map_or(&[][..], |c| &c.pairs[..]);
    let mut out = Vec::new();
    for [a, b] in pairs {
        let ((fa, la), (fb, lb)) = (seeds_of(methods, runs, a), seeds_of(methods, runs, b));
        if fa.is_empty() || fb.is_empty() {
            continue;
        }
        let d = fa.iter().sum::<f64>() / fa.len() as f64 - fb.iter().sum::<f64>() / fb.len() as f64;
        out.push(Contrast {
            benchmark: "episode_length".into(),
            metric: MEAN_STEPS.into(),
            severity: 0,
            first: a.clone(),
            second: b.clone(),
            over_robots: Estimate {
                value: d,
                lo: d,
                hi: d,
            },
            first_seeds: fa,
            second_seeds: fb,
            first_labels: la,
            second_labels: lb,
        });
    }
    out
}

/// The mean episode length of `policy` over `episodes` tracking episodes.
fn mean_length(policy: &NamedPolicy, episodes: usize, threads: usize, seed: u64) -> Result<f64> {
    let env = tracking_env(&policy.env);
    let report = evaluate_tracking(
        &policy.policy,
        &env,
        episodes,
        threads,
        seed,
        ActionMode::Mean,
    )?;
    Ok(report.mean_episode_length_steps)
}

impl Benchmark for EpisodeLength {
    type Section = LengthSpec;
    type Output = Lengths;

    fn name(&self) -> &'static str {
        "episode_length"
    }

    fn stage(&self) -> &'static str {
        "mean episode length"
    }

    fn validate(&self, s: &LengthSpec, spec: &ExperimentSpec) -> Result<()> {
        for m in &s.methods {
            ensure!(
                spec.run(m).is_some(),
                "benchmarks.episode_length.methods names {m:?}, which is no run"
            );
        }
        ensure!(s.episodes > 0, "benchmarks.episode_length.episodes is 0");
        Ok(())
    }

    fn evaluate(&self, s: &LengthSpec, cx: &BenchmarkContext) -> Result<Evaluated<Lengths>> {
        let labels = cx.available_runs(&s.methods);
        let methods = cx.methods(&labels);
        let mut runs = Vec::new();
        for label in &labels {
            let (policy, _) = cx.final_policy(label)?;
            let method = methods.iter().find(|m| m.seeds.contains(label));
            runs.push(RunLength {
                method: method.context("every run has a method")?.label.clone(),
                label: label.clone(),
                mean_steps: mean_length(&policy, s.episodes, cx.threads, s.seed)?,
            });
        }
        let pooled = methods
            .iter()
            .map(|m| {
                let of: Vec<f64> = runs
                    .iter()
                    .filter(|r| r.method == m.label)
                    .map(|r| r.mean_steps)
                    .collect();
                (m.label.clone(), of.iter().sum::<f64>() / of.len() as f64)
            })
            .collect();
        Ok(Evaluated {
            contrasts: contrasts(cx.spec, &methods, &runs),
            output: Lengths {
                runs,
                methods: pooled,
            },
        })
    }

    fn metrics(&self) -> Vec<BenchmarkMetric> {
        vec![BenchmarkMetric {
            name: MEAN_STEPS,
            title: "mean episode length (steps)",
            contrast_title: "episode length: mean steps",
            decimals: 2,
            lower_is_safer: false,
        }]
    }
}

/// Registers the benchmark once per test process.
fn registered() {
    static ONCE: OnceLock<()> = OnceLock::new();
    ONCE.get_or_init(|| register_benchmark(EpisodeLength).unwrap());
}

const SECTION: &str = r#"
[benchmarks.episode_length]
methods = ["Baseline", "Baseline seed 2", "RALL", "RALL seed 2"]
episodes = 3
seed = 5
"#;

const VERDICTS: &str = r#"
[contrasts]
pairs = [["RALL", "Baseline"]]

[verdicts]
primary = { first = "RALL", second = "Baseline", metric = "mean_steps" }
"#;

/// The runs, in the file's order.
const LABELS: [&str; 4] = ["Baseline", "Baseline seed 2", "RALL", "RALL seed 2"];

/// A tiny run's config; `max_tilt_rad` small makes every robot fall at once.
fn write_config(dir: &Path, name: &str, critic: CriticKind, max_tilt_rad: f64) -> String {
    let mut c = common::tiny_config(critic);
    c.env.episode.max_tilt_rad = max_tilt_rad;
    let path = dir.join(format!("{name}.toml"));
    std::fs::write(&path, c.to_toml()).unwrap();
    path.display().to_string()
}

/// Two seeds each of Baseline (its robots fall at once) and RALL (they stand),
/// the smallest tables, and `section` appended.
fn spec_text(dir: &Path, section: &str) -> String {
    let base = write_config(dir, "baseline", CriticKind::Scalar, 1e-4);
    let rall = write_config(dir, "rall", CriticKind::Iqn, 1.2);
    let mut runs = String::new();
    for (name, label, config, seed) in [
        ("baseline", "Baseline", &base, 1),
        ("baseline", "Baseline seed 2", &base, 2),
        ("rall", "RALL", &rall, 1),
        ("rall", "RALL seed 2", &rall, 2),
    ] {
        runs.push_str(&format!(
            "[[run]]\nname = \"{name}\"\nlabel = \"{label}\"\nconfig = \"{config}\"\nseed = {seed}\niterations = 2\n\n"
        ));
    }
    format!(
        "name = \"toy\"\nruns_dir = \"{}\"\nresults_dir = \"{}\"\nthreads = 2\n\n{runs}\
         [tracking]\nepisodes = 2\nseed = 7\n\n\
         [ttf]\nmethods = [\"Baseline\"]\nseeds = 1\nrepeats = 1\nloads = [\"ball\"]\n\n\
         [platform]\nmethods = [\"Baseline\"]\nheights_m = [0.40]\nseeds = 1\nrepeats = 1\n\n\
         [race]\nmethods = [\"Baseline\"]\nagents = 1\nepisodes = 1\n\n\
         [bootstrap]\nresamples = 20\n{section}",
        dir.join("runs").display(),
        dir.join("results").display(),
    )
}

/// Run `label`'s mean episode length evaluated directly, as the benchmark should.
fn direct(spec: &ExperimentSpec, label: &str) -> f64 {
    let r = spec.run(label).unwrap();
    let path = newest_checkpoint(spec, r).unwrap().unwrap();
    let policy = NamedPolicy::load(label, &path).unwrap();
    let threads = rall::config::worker_threads(spec.threads);
    mean_length(&policy, 3, threads, 5).unwrap()
}

#[test]
fn a_benchmark_registered_outside_the_crate_runs_in_an_experiment() {
    registered();
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("toy.toml");
    let text = spec_text(dir.path(), &format!("{SECTION}{VERDICTS}"));
    std::fs::write(&file, text).unwrap();
    let spec = ExperimentSpec::from_file(&file).unwrap();
    let all = ExperimentOptions {
        train: true,
        evaluate: true,
        allow_unfinished: false,
        fresh_rollouts: false,
    };
    run_experiment(&spec, &all, Arc::new(AtomicBool::new(false))).unwrap();
    let out = dir.path().join("results");
    let expected: Vec<f64> = LABELS.iter().map(|l| direct(&spec, l)).collect();
    // Baseline's robots fall at once, RALL's stand to the time-out
    assert!(expected[0] < expected[2], "{expected:?}");

    let csv = std::fs::read_to_string(out.join("episode_length.csv")).unwrap();
    let mut want = String::from("method,label,mean_steps\n");
    for (l, e) in LABELS.iter().zip(&expected) {
        let method = l.trim_end_matches(" seed 2");
        want.push_str(&format!("{method},{l},{e:.4}\n"));
    }
    assert_eq!(csv, want);

    let (base_mean, rall_mean) = (
        (expected[0] + expected[1]) / 2.0,
        (expected[2] + expected[3]) / 2.0,
    );
    let readme = std::fs::read_to_string(out.join("README.md")).unwrap();
    let rows = format!(
        "## Episode length\n\n| Method | mean steps |\n|---|---:|\n| Baseline | {base_mean:.2} |\n| RALL | {rall_mean:.2} |\n"
    );
    assert!(readme.contains(&rows), "{readme}");
    assert!(
        readme.contains("- episode length: mean steps: "),
        "{readme}"
    );

    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("results.json")).unwrap()).unwrap();
    let entry = &json["episode_length"];
    let runs = entry["runs"].as_array().unwrap();
    assert_eq!(runs.len(), 4);
    for (r, e) in runs.iter().zip(&expected) {
        assert_eq!(r["mean_steps"].as_f64().unwrap(), *e, "{r}");
    }
    assert_eq!(entry["methods"][1][0], "RALL");
    assert!((entry["methods"][1][1].as_f64().unwrap() - rall_mean).abs() < 1e-12);

    // the primary verdict is tested on each seed's own number
    let verdicts = std::fs::read_to_string(out.join("verdicts.csv")).unwrap();
    let row = verdicts.lines().nth(1).unwrap();
    let values = |v: &[f64]| format!("{:.4};{:.4}", v[0], v[1]);
    let wanted = format!(
        ",RALL,Baseline,mean_steps,,1;2,1;2,{},{},",
        values(&expected[2..]),
        values(&expected[..2])
    );
    assert!(row.contains(&wanted), "{row} lacks {wanted}");

    // --redraw writes the table and the README again from results.json alone
    std::fs::remove_file(out.join("episode_length.csv")).unwrap();
    ExperimentResults::redraw(&out, None, Some(&spec)).unwrap();
    assert_eq!(
        std::fs::read_to_string(out.join("episode_length.csv")).unwrap(),
        want
    );
    let redrawn = std::fs::read_to_string(out.join("README.md")).unwrap();
    assert!(redrawn.contains(&rows), "{redrawn}");
}

#[test]
fn bad_sections_verdicts_and_names_are_refused() {
    registered();
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let with_verdicts = |s: String| format!("{s}{VERDICTS}");
    for (section, names) in [
        (SECTION.replace("episodes = 3", "episode = 3"), "`episode`"),
        // the benchmark's metric has no rung, and needs the benchmark's section
        (
            with_verdicts(SECTION.into()).replace("\"mean_steps\"", "\"mean_steps\", rung = 2"),
            "has no severity rung",
        ),
        (VERDICTS.into(), "no [benchmarks.episode_length] section"),
        (
            SECTION.replace("episodes = 3", "episodes = 0"),
            "benchmarks.episode_length.episodes",
        ),
        (
            SECTION.replace("\"RALL seed 2\"", "\"RALL seed 9\""),
            "\"RALL seed 9\"",
        ),
        (
            SECTION.replace("episode_length", "episode_lengths"),
            "no benchmark is registered as \"episode_lengths\"",
        ),
    ] {
        let file = d.join("bad.toml");
        std::fs::write(&file, spec_text(d, &section)).unwrap();
        let e = format!("{:#}", ExperimentSpec::from_file(&file).unwrap_err());
        assert!(e.contains(names), "expected {names:?} in: {e}");
    }
    let again = register_benchmark(EpisodeLength).unwrap_err().to_string();
    assert!(again.contains("already taken"), "{again}");
}
