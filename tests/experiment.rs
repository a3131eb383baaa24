//! `rall experiment` on a tiny slice: it trains what is missing, skips what is
//! done, and its evaluation is deterministic (the same checkpoints give the same
//! tables to the byte).

mod common;

use std::path::Path;
use std::sync::atomic::AtomicBool;
use std::sync::Arc;

use rall::experiment::results::ExperimentResults;
use rall::experiment::{
    run_experiment, run_state, ship_all, train_all, ExperimentOptions, ExperimentSpec,
};
use rall::learn::CriticKind;

fn write_config(dir: &Path, name: &str, critic: CriticKind, eta: Option<f32>) -> String {
    let mut c = common::tiny_config(critic);
    c.learner.cvar_eta = eta;
    let path = dir.join(format!("{name}.toml"));
    std::fs::write(&path, c.to_toml()).unwrap();
    path.display().to_string()
}

/// The slice's hand-written preface (written on first use).
fn preface(dir: &Path) -> std::path::PathBuf {
    let p = dir.join("answer.md");
    if !p.exists() {
        std::fs::write(&p, "At this budget the slice answers nothing.\n").unwrap();
    }
    p
}

fn spec_text(dir: &Path, results: &str) -> String {
    let base = write_config(dir, "baseline", CriticKind::Scalar, None);
    let eta1 = write_config(dir, "eta1", CriticKind::Iqn, Some(1.0));
    let rall = write_config(dir, "rall", CriticKind::Iqn, Some(0.5));
    // a second common ground: wider randomisation than any run trained under
    let mut w = common::tiny_config(CriticKind::Scalar);
    w.env.randomization.friction = Some([0.2, 2.5]);
    w.env.randomization.motor_strength = Some([0.8, 1.2]);
    let wide = dir.join("wide.toml");
    std::fs::write(&wide, w.to_toml()).unwrap();
    let wide = wide.display();
    format!(
        r#"
name = "slice"
preface = "{preface}"
runs_dir = "{runs}"
results_dir = "{results}"
shipped_dir = "{shipped}"
threads = 2

[[run]]
name = "baseline"
label = "Baseline"
config = "{base}"
seed = 1
iterations = 2

[[run]]
name = "eta1"
label = "RALL eta=1"
config = "{eta1}"
seed = 1
iterations = 2

[[run]]
name = "rall"
label = "RALL"
config = "{rall}"
seed = 1
iterations = 2

[[run]]
name = "rall"
label = "RALL seed 2"
config = "{rall}"
seed = 2
iterations = 2

[tracking]
episodes = 4
seed = 7
randomization_from = ["{base}", "{wide}"]

[ttf]
methods = ["Baseline", "RALL", "RALL seed 2"]
seeds = 2
repeats = 2
loads = ["ball"]

[platform]
methods = ["Baseline", "RALL", "RALL seed 2"]
heights_m = [0.40]
seeds = 1
repeats = 2

[race]
methods = ["Baseline", "RALL seed 2"]
agents = 2
episodes = 1

[[meta]]
label = "Meta"
risky = "RALL eta=1"
safe = "RALL"
threshold_quantile = 0.9
calibration_robots = 2
hysteresis_fraction = 0.2
min_safe_steps = 5

[[meta]]
label = "Meta seed 2"
risky = "RALL eta=1"
safe = "RALL seed 2"
threshold_quantile = 0.9
calibration_robots = 2
hysteresis_fraction = 0.2
min_safe_steps = 5

[bootstrap]
resamples = 50

[contrasts]
pairs = [["RALL", "Baseline"], ["Meta", "RALL"]]

[critic_tail]
methods = ["Baseline", "RALL", "RALL seed 2"]
robots = 3
steps = 60
window = 5
seed = 9

[[paper.ttf]]
load = "ball"
method = "Baseline"
ttf = [0.539, 0.212, 0.292, 0.189]
"#,
        runs = dir.join("runs").display(),
        preface = preface(dir).display(),
        results = dir.join(results).display(),
        shipped = dir.join("shipped").display(),
    )
}

#[test]
fn an_experiment_trains_then_skips_and_evaluates_reproducibly() {
    let dir = tempfile::tempdir().unwrap();
    let stop = Arc::new(AtomicBool::new(false));
    let file = dir.path().join("slice.toml");
    std::fs::write(&file, spec_text(dir.path(), "results-a")).unwrap();
    let spec = ExperimentSpec::from_file(&file).unwrap();
    assert!(spec
        .runs
        .iter()
        .all(|r| run_state(&spec, r).unwrap().progress.is_none()));
    let all = ExperimentOptions {
        train: true,
        evaluate: true,
        allow_unfinished: false,
        fresh_rollouts: false,
    };
    run_experiment(&spec, &all, stop.clone()).unwrap();
    for r in &spec.runs {
        let s = run_state(&spec, r).unwrap();
        assert!(s.done(), "{}: {:?}", r.label, s.progress);
    }
    let mtime = |spec: &ExperimentSpec| {
        std::fs::metadata(spec.run_dir(&spec.runs[0]).join("latest.safetensors"))
            .unwrap()
            .modified()
            .unwrap()
    };
    let before = mtime(&spec);
    // the same command again: nothing to train, the same tables (every rollout run
    // again, not read from the rollout cache, so that this checks the evaluation)
    std::fs::write(&file, spec_text(dir.path(), "results-b")).unwrap();
    let again = ExperimentSpec::from_file(&file).unwrap();
    let fresh = ExperimentOptions {
        fresh_rollouts: true,
        ..all
    };
    run_experiment(&again, &fresh, stop).unwrap();
    assert_eq!(
        mtime(&again),
        before,
        "a finished run is skipped, not retrained"
    );
    for f in [
        "README.md",
        "runs.csv",
        "ttf.csv",
        "platform.csv",
        "race.csv",
        "ttf_by_method.csv",
        "platform_by_method.csv",
        "race_by_method.csv",
        "contrasts.csv",
        "critic_tail.csv",
        "results.json",
    ] {
        let a = std::fs::read_to_string(dir.path().join("results-a").join(f)).unwrap();
        let b = std::fs::read_to_string(dir.path().join("results-b").join(f)).unwrap();
        assert_eq!(
            a, b,
            "{f} differs between two evaluations of the same checkpoints"
        );
    }
    // the figures drawn again from results.json alone are the same files
    let figures = dir.path().join("results-a/figures");
    let read_all = || {
        let mut files: Vec<(std::path::PathBuf, Vec<u8>)> = std::fs::read_dir(&figures)
            .unwrap()
            .map(|e| {
                let p = e.unwrap().path();
                let bytes = std::fs::read(&p).unwrap();
                (p, bytes)
            })
            .collect();
        files.sort();
        files
    };
    let drawn_by_the_evaluation = read_all();
    let readme = std::fs::read_to_string(dir.path().join("results-a/README.md")).unwrap();
    let preface_text = std::fs::read_to_string(preface(dir.path())).unwrap();
    let redrawn =
        ExperimentResults::redraw(&dir.path().join("results-a"), Some(preface_text), None).unwrap();
    assert!(redrawn.len() > drawn_by_the_evaluation.len());
    assert!(
        read_all() == drawn_by_the_evaluation,
        "figures redrawn from results.json differ from the evaluation's"
    );
    assert_eq!(
        std::fs::read_to_string(dir.path().join("results-a/README.md")).unwrap(),
        readme,
        "the README written again from results.json differs from the evaluation's"
    );
    // a preface edited after the evaluation: the README takes it, nothing else changes
    let json = std::fs::read(dir.path().join("results-a/results.json")).unwrap();
    ExperimentResults::redraw(
        &dir.path().join("results-a"),
        Some("Edited.\n".into()),
        None,
    )
    .unwrap();
    let edited = std::fs::read_to_string(dir.path().join("results-a/README.md")).unwrap();
    assert!(
        edited.starts_with("# Results: slice\n\nEdited.\n"),
        "{edited}"
    );
    assert!(!edited.contains("answers nothing"));
    assert_eq!(
        std::fs::read(dir.path().join("results-a/results.json")).unwrap(),
        json
    );
    let preface_text = std::fs::read_to_string(preface(dir.path())).unwrap();
    ExperimentResults::redraw(&dir.path().join("results-a"), Some(preface_text), None).unwrap();
    // method against method: every benchmark both ran, at rung 0 (no ladder here)
    assert!(
        readme.contains("At this budget the slice answers nothing."),
        "{readme}"
    );
    assert!(readme.contains("**RALL against Baseline.**"), "{readme}");
    let contrasts = std::fs::read_to_string(dir.path().join("results-a/contrasts.csv")).unwrap();
    let rows: Vec<Vec<&str>> = contrasts
        .lines()
        .skip(1)
        .map(|l| l.split(',').collect())
        .collect();
    let metrics = |a: &str, b: &str| -> Vec<String> {
        rows.iter()
            .filter(|r| r[0] == a && r[1] == b)
            .map(|r| r[3].to_string())
            .collect()
    };
    assert_eq!(
        metrics("RALL", "Baseline"),
        ["ttf", "strict_ttf", "success_pct", "return_q25"],
        "{contrasts}"
    );
    // the meta controller ran the race alone
    assert_eq!(metrics("Meta", "RALL"), ["return_q25"], "{contrasts}");
    let header: Vec<&str> = contrasts.lines().next().unwrap().split(',').collect();
    let col = |name: &str| header.iter().position(|h| *h == name).unwrap();
    for r in &rows {
        let [d, rlo, rhi]: [f64; 3] = std::array::from_fn(|k| r[5 + k].parse().unwrap());
        assert!(rlo <= d && d <= rhi, "{r:?}");
        // RALL's two seeds against Baseline's one: two seed pairs, and no seed-level
        // test (Welch needs two seeds a side): level, its columns empty
        let seeds = |name: &str| -> Vec<f64> {
            r[col(name)]
                .split(';')
                .map(|x| x.parse().unwrap())
                .collect()
        };
        if r[0] == "RALL" {
            assert_eq!(
                (
                    seeds("first_seeds").len(),
                    seeds("second_seeds").len(),
                    r[col("seed_pairs")]
                ),
                (2, 1, "2"),
                "{r:?}"
            );
            assert_eq!(r[col("welch_p")], "", "{r:?}");
            assert_eq!(r[col("verdict")], "level", "{r:?}");
        }
        // on TTF and platform every seed has as many cells: the difference is that
        // of the seeds' means
        if r[3] != "return_q25" {
            let m = |v: Vec<f64>| v.iter().sum::<f64>() / v.len() as f64;
            assert!(
                (d - (m(seeds("first_seeds")) - m(seeds("second_seeds")))).abs() < 2e-3,
                "{r:?}"
            );
        }
    }
    // ... and the seeds' TTF is the by-method table's over its cells
    let by_method_ttf =
        std::fs::read_to_string(dir.path().join("results-a/ttf_by_method.csv")).unwrap();
    let rall_cells: Vec<f64> = by_method_ttf
        .lines()
        .filter(|l| l.starts_with("RALL,"))
        .map(|l| l.split(',').nth(5).unwrap().parse().unwrap())
        .collect();
    let ttf_row = rows
        .iter()
        .find(|r| r[0] == "RALL" && r[3] == "ttf")
        .unwrap();
    let seeds_mean: f64 = ttf_row[col("first_seeds")]
        .split(';')
        .map(|x| x.parse::<f64>().unwrap())
        .sum::<f64>()
        / 2.0;
    let cells_mean = rall_cells.iter().sum::<f64>() / rall_cells.len() as f64;
    assert!(
        (seeds_mean - cells_mean).abs() < 2e-3,
        "{seeds_mean} {cells_mean}"
    );
    let md = std::fs::read_to_string(dir.path().join("results-a/README.md")).unwrap();
    assert!(
        md.contains("Table I") && md.contains("(paper 0.539)"),
        "{md}"
    );
    assert!(md.contains("Meta"), "{md}");
    // each listed run's critic before falls: a scalar V for Baseline, quantiles for RALL
    assert!(md.contains("## What the critics saw before falls"), "{md}");
    let tail = std::fs::read_to_string(dir.path().join("results-a/critic_tail.csv")).unwrap();
    let critics: Vec<(&str, &str)> = tail
        .lines()
        .skip(1)
        .map(|l| {
            let f: Vec<&str> = l.split(',').collect();
            (f[0], f[2])
        })
        .collect();
    assert_eq!(
        critics,
        [
            ("Baseline", "scalar"),
            ("RALL", "distribution"),
            ("RALL seed 2", "distribution")
        ],
        "{tail}"
    );
    // every run also tracked under each common randomisation; the first is its own:
    // the same episodes to the digit (the override changes the draws' ranges, nothing
    // else); the second (wider) gives other episodes
    assert!(md.contains("Tracking on common ground"), "{md}");
    assert!(md.contains("wide.toml`'s |"), "{md}");
    let runs = std::fs::read_to_string(dir.path().join("results-a/runs.csv")).unwrap();
    let header = runs.lines().next().unwrap();
    assert!(
        header.contains(",on_baseline_lin_tracking,") && header.contains(",on_wide_fall_rate_hi"),
        "{header}"
    );
    let mut differs = false;
    for line in runs.lines().skip(1) {
        let v: Vec<&str> = line.split(',').collect();
        assert_eq!(v.len(), 35, "{line}");
        assert_eq!(
            v[8..17],
            v[17..26],
            "own and common tracking differ: {line}"
        );
        differs |= v[8..17] != v[26..35];
        // each figure inside its interval
        for k in [8, 11, 14, 26, 29, 32] {
            let [x, lo, hi] = [v[k], v[k + 1], v[k + 2]].map(|s| s.parse::<f64>().unwrap());
            assert!(lo <= x && x <= hi, "{line}");
        }
    }
    assert!(
        differs,
        "the wider randomisation changed no run's tracking: {runs}"
    );
    let ttf = std::fs::read_to_string(dir.path().join("results-a/ttf.csv")).unwrap();
    assert_eq!(ttf.lines().count(), 1 + 3 * 4, "{ttf}");
    for line in ttf.lines().skip(1) {
        let v: Vec<f64> = line
            .split(',')
            .skip(4)
            .take(3)
            .map(|x| x.parse().unwrap())
            .collect();
        assert!(
            v[1] <= v[0] && v[0] <= v[2],
            "interval must hold the estimate: {line}"
        );
    }
    // one row per method: RALL's two seeds pooled (equal weights, each seed's value
    // kept), Baseline's one seed exactly its run's row
    let by_method =
        std::fs::read_to_string(dir.path().join("results-a/ttf_by_method.csv")).unwrap();
    assert_eq!(by_method.lines().count(), 1 + 2 * 4, "{by_method}");
    let fields = |l: &str| l.split(',').map(str::to_string).collect::<Vec<_>>();
    for method in by_method.lines().skip(1) {
        let m = fields(method);
        if m[0] == "Baseline" {
            assert_eq!(m[1], "Baseline");
            let run = ttf
                .lines()
                .map(fields)
                .find(|r| r[..4] == [&m[..1], &m[2..5]].concat())
                .unwrap();
            assert_eq!(run[4..7], m[5..8], "{run:?} / {method}");
        } else {
            assert_eq!((m[0].as_str(), m[1].as_str()), ("RALL", "RALL;RALL seed 2"));
            let seeds: Vec<f64> = m[8].split(';').map(|x| x.parse().unwrap()).collect();
            let v: f64 = m[5].parse().unwrap();
            assert_eq!(seeds.len(), 2, "{method}");
            assert!((v - (seeds[0] + seeds[1]) / 2.0).abs() < 1e-3, "{method}");
            assert_eq!(m[9], "8", "robots of both seeds: {method}");
        }
    }
    assert!(md.contains("RALL (2 seeds)"), "{md}");
    // the two meta controllers switch between runs of the same two names: one method
    assert!(md.contains("| Meta (2 seeds) |"), "{md}");
    for fig in ["ttf.svg", "platform.svg", "race.svg", "race_iqr.svg"] {
        let svg = std::fs::read_to_string(dir.path().join("results-a/figures").join(fig)).unwrap();
        assert!(svg.starts_with("<svg") && svg.len() > 500, "{fig}");
    }

    // shipped checkpoints: a clone without runs/ evaluates them to the same tables ...
    ship_all(&again, &file).unwrap();
    std::fs::remove_dir_all(dir.path().join("runs")).unwrap();
    std::fs::write(&file, spec_text(dir.path(), "results-c")).unwrap();
    let shipped = ExperimentSpec::from_file(&file).unwrap();
    assert!(shipped
        .runs
        .iter()
        .all(|r| run_state(&shipped, r).unwrap().done()));
    let eval_only = ExperimentOptions {
        train: false,
        ..all
    };
    run_experiment(&shipped, &eval_only, Arc::new(AtomicBool::new(false))).unwrap();
    for f in ["ttf.csv", "platform.csv", "race.csv"] {
        let a = std::fs::read_to_string(dir.path().join("results-a").join(f)).unwrap();
        let c = std::fs::read_to_string(dir.path().join("results-c").join(f)).unwrap();
        assert_eq!(
            a, c,
            "{f}: shipped checkpoints must evaluate as the originals"
        );
    }
    // ... and training starts from them (here: done, so nothing is trained)
    train_all(&shipped, Arc::new(AtomicBool::new(false))).unwrap();
    assert!(shipped
        .run_dir(&shipped.runs[0])
        .join("latest.safetensors")
        .exists());

    // a method config edited after its run was trained: the run is refused, naming
    // the key, instead of being counted as done (or resumed) under the new config
    let mut edited = common::tiny_config(CriticKind::Scalar);
    edited.learner.ppo.entropy_coef *= 2.0;
    std::fs::write(dir.path().join("baseline.toml"), edited.to_toml()).unwrap();
    let err = run_state(&shipped, &shipped.runs[0]).unwrap_err();
    let msg = format!("{err:#}");
    assert!(
        msg.contains("\"Baseline\"") && msg.contains("learner.ppo.entropy_coef"),
        "{msg}"
    );
    // a larger budget alone is no such change: the run continues
    let mut longer = common::tiny_config(CriticKind::Scalar);
    longer.runner.iterations += 5;
    longer.runner.threads = 1;
    std::fs::write(dir.path().join("baseline.toml"), longer.to_toml()).unwrap();
    assert!(run_state(&shipped, &shipped.runs[0]).is_ok());
    // a last stage not reached yet is added by training on; one already passed is a change
    for (after_iteration, ok) in [(1000, true), (0, false)] {
        let mut staged = longer.clone();
        staged.runner.action_std_reset = Some(rall::config::ActionStdReset {
            after_iteration,
            action_std: 0.5,
        });
        std::fs::write(dir.path().join("baseline.toml"), staged.to_toml()).unwrap();
        let state = run_state(&shipped, &shipped.runs[0]);
        assert_eq!(state.is_ok(), ok, "after {after_iteration}: {state:?}");
        if let Err(e) = state {
            assert!(
                format!("{e:#}").contains("runner.action_std_reset"),
                "{e:#}"
            );
        }
    }
}

#[test]
fn a_single_meta_table_is_one_controller_and_a_bad_key_in_it_is_named() {
    let dir = tempfile::tempdir().unwrap();
    let text = spec_text(dir.path(), "r");
    // the file as it was before [[meta]]: one [meta] table
    let cut = text.find("[[meta]]\nlabel = \"Meta seed 2\"").unwrap();
    let end = text.find("[bootstrap]").unwrap();
    let single = format!("{}{}", &text[..cut], &text[end..]).replace("[[meta]]", "[meta]");
    let file = dir.path().join("single.toml");
    std::fs::write(&file, &single).unwrap();
    let spec = ExperimentSpec::from_file(&file).unwrap();
    assert_eq!(spec.meta.len(), 1);
    assert_eq!(spec.meta[0].label, "Meta");
    std::fs::write(
        &file,
        single.replace("min_safe_steps = 5", "min_safe_step = 5"),
    )
    .unwrap();
    let e = format!("{:#}", ExperimentSpec::from_file(&file).unwrap_err());
    assert!(e.contains("min_safe_step"), "{e}");
}

/// The error `ExperimentSpec::from_file` gives for `text` as an experiment file.
fn refusal(dir: &Path, text: &str) -> String {
    let file = dir.join("bad.toml");
    std::fs::write(&file, text).unwrap();
    format!("{:#}", ExperimentSpec::from_file(&file).unwrap_err())
}

#[test]
fn an_experiment_file_naming_an_unknown_method_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let text = spec_text(dir.path(), "r").replace(
        "methods = [\"Baseline\", \"RALL seed 2\"]\nagents",
        "methods = [\"Baselin\"]\nagents",
    );
    let e = refusal(dir.path(), &text);
    assert!(e.contains("race.methods") && e.contains("Baselin"), "{e}");
    let good = spec_text(dir.path(), "r");
    let tail = "methods = [\"Baseline\", \"RALL\", \"RALL seed 2\"]\nrobots";
    assert!(good.contains(tail));
    let e = refusal(
        dir.path(),
        &good.replace(tail, "methods = [\"RAL\"]\nrobots"),
    );
    assert!(
        e.contains("critic_tail.methods") && e.contains("RAL"),
        "{e}"
    );
    let e = refusal(dir.path(), &good.replace("window = 5\n", "window = 60\n"));
    assert!(e.contains("critic_tail.window"), "{e}");
}

#[test]
fn a_contrast_of_an_unknown_or_the_same_method_and_a_missing_preface_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let good = spec_text(dir.path(), "r");
    let pairs = "pairs = [[\"RALL\", \"Baseline\"], [\"Meta\", \"RALL\"]]";
    assert!(good.contains(pairs));
    let e = refusal(
        dir.path(),
        &good.replace(pairs, "pairs = [[\"RALL\", \"DR\"]]"),
    );
    assert!(e.contains("contrasts.pairs") && e.contains("\"DR\""), "{e}");
    // two seeds of one method, and two meta controllers over the same pair of methods
    for same in [["RALL", "RALL seed 2"], ["Meta", "Meta seed 2"]] {
        let text = good.replace(
            pairs,
            &format!("pairs = [[\"{}\", \"{}\"]]", same[0], same[1]),
        );
        let e = refusal(dir.path(), &text);
        assert!(e.contains("same method"), "{e}");
    }
    let e = refusal(dir.path(), &good.replace(pairs, "pairs = []"));
    assert!(e.contains("contrasts.pairs lists no pair"), "{e}");
    let missing = dir.path().join("no-such-answer.md");
    let text = good.replace(
        &preface(dir.path()).display().to_string(),
        &missing.display().to_string(),
    );
    let e = refusal(dir.path(), &text);
    assert!(
        e.contains("preface") && e.contains("no-such-answer.md"),
        "{e}"
    );
}

#[test]
fn unfinished_runs_are_refused_unless_allowed_and_missing_ones_are_left_out() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("slice.toml");
    std::fs::write(&file, spec_text(dir.path(), "results")).unwrap();
    let spec = ExperimentSpec::from_file(&file).unwrap();
    let stop = || Arc::new(AtomicBool::new(false));
    let eval_only = ExperimentOptions {
        train: false,
        evaluate: true,
        allow_unfinished: false,
        fresh_rollouts: false,
    };
    let e = format!(
        "{:#}",
        run_experiment(&spec, &eval_only, stop()).unwrap_err()
    );
    assert!(
        e.contains("not finished") && e.contains("--allow-unfinished"),
        "{e}"
    );
    let allowed = ExperimentOptions {
        allow_unfinished: true,
        ..eval_only
    };
    run_experiment(&spec, &allowed, stop()).unwrap();
    let md = std::fs::read_to_string(dir.path().join("results/README.md")).unwrap();
    assert_eq!(md.matches("(not started)").count(), 4, "{md}");
}

#[test]
fn common_grounds_with_the_same_file_name_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let text = spec_text(dir.path(), "r");
    let base = dir.path().join("baseline.toml");
    let other = dir.path().join("other");
    std::fs::create_dir(&other).unwrap();
    std::fs::copy(&base, other.join("baseline.toml")).unwrap();
    let text = text.replace(
        &format!("\"{}\"]", dir.path().join("wide.toml").display()),
        &format!("\"{}\"]", other.join("baseline.toml").display()),
    );
    let e = refusal(dir.path(), &text);
    assert!(
        e.contains("randomization_from") && e.contains("baseline"),
        "{e}"
    );
}

#[test]
fn a_common_ground_that_is_not_a_path_is_refused_with_what_it_takes() {
    let dir = tempfile::tempdir().unwrap();
    let text = spec_text(dir.path(), "r");
    let start = text.find("randomization_from = ").unwrap();
    let end = start + text[start..].find('\n').unwrap();
    let text = format!("{}randomization_from = 3{}", &text[..start], &text[end..]);
    let e = refusal(dir.path(), &text);
    assert!(
        e.contains("randomization_from") && e.contains("a config path or a list of config paths"),
        "{e}"
    );
}

/// A selection CSV's candidates (iteration, falls %) and the chosen iteration,
/// checking that exactly one is chosen and that no candidate falls less.
fn chosen_in(csv: &str) -> (Vec<(usize, f64)>, usize) {
    let rows: Vec<Vec<&str>> = csv
        .lines()
        .skip(2)
        .map(|l| l.split(',').collect())
        .collect();
    let chosen: Vec<_> = rows.iter().filter(|c| c[4] == "1").collect();
    assert_eq!(chosen.len(), 1, "{csv}");
    let candidates: Vec<(usize, f64)> = rows
        .iter()
        .map(|c| (c[0].parse().unwrap(), c[1].parse().unwrap()))
        .collect();
    let least = candidates.iter().map(|c| c.1).fold(f64::MAX, f64::min);
    assert_eq!(chosen[0][1].parse::<f64>().unwrap(), least, "{csv}");
    (candidates, chosen[0][0].parse().unwrap())
}

#[test]
fn a_selection_rule_chooses_each_final_policy_on_validation_episodes_and_ships_it() {
    use rall::experiment::{choose_final_policies, selected_checkpoint};
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("slice.toml");
    let rule = "\n[selection]\nwindow = 2\nevery = 1\nepisodes = 4\nseed = 8\n";
    std::fs::write(&file, spec_text(dir.path(), "results") + rule).unwrap();
    let spec = ExperimentSpec::from_file(&file).unwrap();
    // training chooses each final policy as its run finishes, while the window's
    // checkpoints exist (a fresh clone would not have them: runs/ is not committed)
    train_all(&spec, Arc::new(AtomicBool::new(false))).unwrap();
    for r in &spec.runs {
        let run = spec.run_dir(r);
        let csv = std::fs::read_to_string(run.join("selection.csv")).unwrap();
        // both checkpoints of the window are candidates, one is chosen, and it falls least
        let (candidates, it) = chosen_in(&csv);
        assert_eq!(candidates.len(), 2, "{csv}");
        if candidates[0].1 == candidates[1].1 {
            assert_eq!(it, 2, "a tie goes to the later checkpoint: {csv}");
        }
        let ckpt = run.join(format!("checkpoints/model_{it:06}.safetensors"));
        assert_eq!(
            std::fs::read(run.join("selected.safetensors")).unwrap(),
            std::fs::read(&ckpt).unwrap()
        );
        assert_eq!(
            selected_checkpoint(&spec, r).unwrap(),
            Some(run.join("selected.safetensors"))
        );
    }
    // a stored choice is reused (no candidate needed any more) ...
    let first = spec.run_dir(&spec.runs[0]);
    std::fs::remove_dir_all(first.join("checkpoints")).unwrap();
    choose_final_policies(&spec, 2).unwrap();
    // ... and travels with the shipped run: a fresh clone evaluates the same policy
    ship_all(&spec, &file).unwrap();
    std::fs::remove_dir_all(dir.path().join("runs")).unwrap();
    let eval_only = ExperimentOptions {
        train: false,
        evaluate: true,
        allow_unfinished: false,
        fresh_rollouts: false,
    };
    run_experiment(&spec, &eval_only, Arc::new(AtomicBool::new(false))).unwrap();
    let md = std::fs::read_to_string(dir.path().join("results/README.md")).unwrap();
    assert_eq!(md.matches(", policy of ").count(), 4, "{md}");
    // a finished, chosen run ships `latest` as its actor alone (the evaluation, the
    // meta controller's critic included, reads `selected`, shipped whole), read
    // where it is: training restores and trains nothing
    for r in &spec.runs {
        let copy = spec.shipped_copy(r).unwrap();
        let load = |f: &str| rall::runner::load_policy(&copy.join(f)).unwrap();
        assert!(load("latest.safetensors").actor_only, "{}", r.label);
        assert!(!load("selected.safetensors").actor_only, "{}", r.label);
    }
    train_all(&spec, Arc::new(AtomicBool::new(false))).unwrap();
    // (runs/ holds only the evaluation's rollout cache)
    for r in &spec.runs {
        assert!(!spec.run_dir(r).exists(), "{}", r.label);
    }
    assert!(dir.path().join("runs/rollout-cache").is_dir());
    // a larger budget for one of them is refused, saying why, instead of training
    // it from nothing
    let longer =
        (spec_text(dir.path(), "results") + rule).replacen("iterations = 2", "iterations = 4", 1);
    std::fs::write(&file, longer).unwrap();
    let e = format!(
        "{:#}",
        train_all(
            &ExperimentSpec::from_file(&file).unwrap(),
            Arc::new(AtomicBool::new(false))
        )
        .unwrap_err()
    );
    assert!(
        e.contains("Baseline") && e.contains("evaluation copy") && e.contains("4 iterations"),
        "{e}"
    );
    // another rule chooses anew, and cannot without the candidates
    let other = spec_text(dir.path(), "results") + &rule.replace("seed = 8", "seed = 9");
    std::fs::write(&file, other).unwrap();
    let spec = ExperimentSpec::from_file(&file).unwrap();
    // training skips the finished runs and leaves the choice it cannot make to the evaluation
    train_all(&spec, Arc::new(AtomicBool::new(false))).unwrap();
    let e = format!("{:#}", choose_final_policies(&spec, 2).unwrap_err());
    assert!(e.contains("no checkpoint of iteration"), "{e}");
}

#[test]
fn choosing_the_final_policy_on_the_tracking_episodes_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let rule = "\n[selection]\nwindow = 2\nevery = 1\nepisodes = 4\nseed = 7\n";
    let e = refusal(dir.path(), &(spec_text(dir.path(), "results") + rule));
    assert!(e.contains("other episodes"), "{e}");
}

#[test]
fn an_rma_run_trains_phase_two_on_the_teacher_its_rule_chose_and_ships_the_choice() {
    use rall::runner::load_policy;
    let dir = tempfile::tempdir().unwrap();
    let mut rma = common::tiny_method("rma");
    rma.learner.adaptation.as_mut().unwrap().iterations = 2;
    let config = dir.path().join("rma.toml");
    std::fs::write(&config, rma.to_toml()).unwrap();
    let file = dir.path().join("rma-slice.toml");
    std::fs::write(
        &file,
        format!(
            r#"
name = "rma-slice"
runs_dir = "{runs}"
results_dir = "{results}"
shipped_dir = "{shipped}"
threads = 2
meta = []

[[run]]
name = "rma"
label = "RMA"
config = "{config}"
seed = 1
iterations = 3

[tracking]
episodes = 4
seed = 7

[selection]
window = 2
every = 1
episodes = 4
seed = 8

[ttf]
methods = ["RMA"]
seeds = 1
repeats = 1
loads = ["ball"]

[platform]
methods = ["RMA"]
heights_m = [0.40]
seeds = 1
repeats = 1

[race]
methods = ["RMA"]
agents = 1
episodes = 1
"#,
            runs = dir.path().join("runs").display(),
            results = dir.path().join("results").display(),
            shipped = dir.path().join("shipped").display(),
            config = config.display(),
        ),
    )
    .unwrap();
    let spec = ExperimentSpec::from_file(&file).unwrap();
    train_all(&spec, Arc::new(AtomicBool::new(false))).unwrap();
    let run = spec.run_dir(&spec.runs[0]);
    // the teacher: chosen among phase 1's last two checkpoints, the one that falls least
    let csv = std::fs::read_to_string(run.join("teacher-selection.csv")).unwrap();
    assert!(csv.starts_with("# RMA teacher"), "{csv}");
    let (candidates, teacher_it) = chosen_in(&csv);
    assert_eq!(
        candidates.iter().map(|c| c.0).collect::<Vec<_>>(),
        [2, 3],
        "{csv}"
    );
    // phase 2 ran on that teacher: every teacher tensor of the student is the chosen one's
    let teacher =
        load_policy(&run.join(format!("checkpoints/model_{teacher_it:06}.safetensors"))).unwrap();
    let student = load_policy(&run.join("latest.safetensors")).unwrap();
    assert_eq!(student.progress.iteration, 5);
    let frozen = |p: &rall::runner::LoadedPolicy| -> Vec<_> {
        p.learner
            .state()
            .into_iter()
            .filter(|t| !t.name.contains("adapt"))
            .filter(|t| t.name.starts_with("actor.") || t.name.starts_with("critic."))
            .map(|t| (t.name, t.data))
            .collect()
    };
    let (s, t) = (frozen(&student), frozen(&teacher));
    assert!(!s.is_empty());
    let differ: Vec<_> = s
        .iter()
        .zip(&t)
        .filter(|(a, b)| a != b)
        .map(|(a, b)| (&a.0, &b.0))
        .collect();
    assert!(differ.is_empty() && s.len() == t.len(), "{differ:?}");
    // phase 1's numbered checkpoints are left as trained (the choice is a candidate again)
    let last_teacher = load_policy(&run.join("checkpoints/model_000003.safetensors")).unwrap();
    assert_eq!(last_teacher.progress.iteration, 3);
    // phase 2's log starts where phase 1 ended; the final policy is chosen among phase 2's
    let adaptation = std::fs::read_to_string(run.join("adaptation.csv")).unwrap();
    let logged: Vec<&str> = adaptation
        .lines()
        .skip(1)
        .map(|l| l.split(',').next().unwrap())
        .collect();
    assert_eq!(logged, ["4", "5"]);
    let finals = std::fs::read_to_string(run.join("selection.csv")).unwrap();
    assert!(finals.starts_with("# final policy"), "{finals}");
    assert!(
        finals.contains("\n4,") && finals.contains("\n5,"),
        "{finals}"
    );
    // the teacher's choice ships with the run
    ship_all(&spec, &file).unwrap();
    assert_eq!(
        std::fs::read_to_string(dir.path().join("shipped/rma-s1/teacher-selection.csv")).unwrap(),
        csv
    );
    let readme = std::fs::read_to_string(dir.path().join("shipped/rma-s1/README.md")).unwrap();
    assert!(
        readme.contains(&format!("the teacher of iteration {teacher_it}")),
        "{readme}"
    );
}

/// An experiment with one run and no meta controller: the shape of a pilot that
/// judges TTF alone.
fn one_run_spec(dir: &Path) -> String {
    let rall = write_config(dir, "rall", CriticKind::Iqn, Some(0.5));
    format!(
        r#"
name = "pilot"
runs_dir = "{runs}"
results_dir = "{results}"
shipped_dir = "{shipped}"
threads = 2

[[run]]
name = "rall"
label = "RALL"
config = "{rall}"
seed = 1
iterations = 2

[tracking]
episodes = 2
seed = 7

[ttf]
methods = ["RALL"]
seeds = 1
repeats = 2
loads = ["ball"]

[platform]
methods = []
heights_m = [0.40]
seeds = 1
repeats = 1

[race]
methods = []
agents = 1
episodes = 1

[checkpoints]
last = 2
every = 1
"#,
        runs = dir.join("runs").display(),
        results = dir.join("results").display(),
        shipped = dir.join("shipped").display(),
    )
}

#[test]
fn a_finished_run_shipped_as_numbered_checkpoints_alone_evaluates_without_meta() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("pilot.toml");
    std::fs::write(&file, one_run_spec(dir.path())).unwrap();
    let spec = ExperimentSpec::from_file(&file).unwrap();
    assert!(spec.meta.is_empty());
    let stop = Arc::new(AtomicBool::new(false));
    train_all(&spec, stop.clone()).unwrap();
    // ship the run as its numbered checkpoints only (no latest, no metrics), as a
    // finished pilot run is committed, and drop the run directory
    let run_dir = spec.run_dir(&spec.runs[0]);
    let shipped = dir.path().join("shipped").join("rall-s1");
    std::fs::create_dir_all(&shipped).unwrap();
    std::fs::rename(run_dir.join("checkpoints"), shipped.join("checkpoints")).unwrap();
    std::fs::remove_dir_all(&run_dir).unwrap();
    let state = run_state(&spec, &spec.runs[0]).unwrap();
    assert!(state.done(), "{:?}", state.progress);
    let eval_only = ExperimentOptions {
        train: false,
        evaluate: true,
        allow_unfinished: false,
        fresh_rollouts: false,
    };
    run_experiment(&spec, &eval_only, stop).unwrap();
    let ttf = std::fs::read_to_string(dir.path().join("results/ttf.csv")).unwrap();
    assert!(ttf.lines().count() > 1, "{ttf}");
    assert!(
        !run_dir.exists(),
        "evaluating must not restore or train the run"
    );
}

#[test]
fn experiment_run_filter_refuses_an_unknown_label_naming_the_known_ones() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("pilot.toml");
    std::fs::write(&file, one_run_spec(dir.path())).unwrap();
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_rall"))
        .args(["experiment", file.to_str().unwrap(), "--train-only"])
        .args(["--run", "RALL seed 9", "--threads", "1"])
        .output()
        .unwrap();
    assert!(!out.status.success());
    let e = String::from_utf8_lossy(&out.stderr);
    assert!(
        e.contains("RALL seed 9") && e.contains("it has: RALL"),
        "{e}"
    );
    assert!(!dir.path().join("runs").exists(), "nothing trained");
    // --run without --train-only is refused by the command line
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_rall"))
        .args(["experiment", file.to_str().unwrap(), "--run", "RALL"])
        .output()
        .unwrap();
    assert!(!out.status.success());
}

#[test]
fn a_run_with_its_own_shipped_folder_ships_there_and_is_reused_from_it() {
    let dir = tempfile::tempdir().unwrap();
    let elsewhere = dir.path().join("other-experiment/rall-s1");
    let text = one_run_spec(dir.path()).replace(
        "iterations = 2\n",
        &format!("iterations = 2\nshipped = \"{}\"\n", elsewhere.display()),
    );
    let file = dir.path().join("pilot.toml");
    std::fs::write(&file, text).unwrap();
    let spec = ExperimentSpec::from_file(&file).unwrap();
    train_all(&spec, Arc::new(AtomicBool::new(false))).unwrap();
    ship_all(&spec, &file).unwrap();
    assert!(
        !dir.path().join("shipped").exists(),
        "nothing in shipped_dir"
    );
    assert!(elsewhere.join("latest.safetensors").exists());
    let ckpt = elsewhere.join("checkpoints/model_000002.safetensors");
    assert!(ckpt.exists());
    // another experiment reusing it reads it from there, finished, without training
    std::fs::remove_dir_all(dir.path().join("runs")).unwrap();
    let state = run_state(&spec, &spec.runs[0]).unwrap();
    assert!(state.done(), "{:?}", state.progress);
    // the shipped headline checkpoints are actor-only: they act, and refuse to stand
    // in for a critic (the meta controller's IQR, `rall eval falls`)
    let p = rall::eval::NamedPolicy::load("copy", &ckpt).unwrap();
    assert!(p.actor_only);
    let e = match p.critic() {
        Ok(_) => panic!("an actor-only copy gave a critic"),
        Err(e) => format!("{e:#}"),
    };
    assert!(e.contains("actor-only") && e.contains("copy"), "{e}");
    let full =
        rall::eval::NamedPolicy::load("full", &elsewhere.join("latest.safetensors")).unwrap();
    assert!(full.critic().is_ok(), "a full checkpoint has its critic");
}
