//! `rall experiment` with `[curves]` and `[checkpoints]` on a tiny slice: every
//! method on every listed rung of the severity ladder, each run judged on its last
//! checkpoints, and the inputs that cannot work refused by name.

mod common;

use std::path::Path;
use std::sync::atomic::AtomicBool;
use std::sync::Arc;

use rall::experiment::{run_experiment, ship_all, ExperimentOptions, ExperimentSpec};
use rall::learn::CriticKind;

fn write_config(dir: &Path, name: &str, critic: CriticKind, eta: Option<f32>) -> String {
    let mut c = common::tiny_config(critic);
    c.learner.cvar_eta = eta;
    let path = dir.join(format!("{name}.toml"));
    std::fs::write(&path, c.to_toml()).unwrap();
    path.display().to_string()
}

fn spec_text(dir: &Path, results: &str, extra: &str) -> String {
    let base = write_config(dir, "baseline", CriticKind::Scalar, None);
    let eta1 = write_config(dir, "eta1", CriticKind::Iqn, Some(1.0));
    let rall = write_config(dir, "rall", CriticKind::Iqn, Some(0.5));
    format!(
        r#"
name = "curves"
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

[tracking]
episodes = 2
seed = 7

[ttf]
methods = ["Baseline", "RALL"]
seeds = 1
repeats = 2
loads = ["ball"]

[platform]
methods = ["Baseline", "RALL"]
heights_m = [0.40]
seeds = 1
repeats = 2

[race]
methods = ["Baseline"]
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

[bootstrap]
resamples = 20

[[paper.ttf]]
load = "ball"
method = "Baseline"
ttf = [0.539, 0.212, 0.292, 0.189]

{extra}
"#,
        runs = dir.join("runs").display(),
        results = dir.join(results).display(),
        shipped = dir.join("shipped").display(),
    )
}

const CURVES: &str = "[curves]
severity = [0, 4]
ttf_seeds = 1
ttf_repeats = 2
platform_seeds = 1
platform_repeats = 2
race_agents = 2
race_episodes = 1
";

/// Asserts that each of `files` is the same in `a` and `b` (`how` b was written).
fn same_files(a: &Path, b: &Path, files: &[&str], how: &str) {
    for f in files {
        let read = |dir: &Path| std::fs::read_to_string(dir.join(f)).unwrap();
        assert_eq!(read(a), read(b), "{f}: {how} must give the same bytes");
    }
}

#[test]
fn curves_cover_every_method_and_rung_and_runs_are_judged_on_their_last_checkpoints() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("curves.toml");
    let extra = format!("{CURVES}\n[checkpoints]\nlast = 2\nevery = 1\n");
    std::fs::write(&file, spec_text(dir.path(), "results", &extra)).unwrap();
    let spec = ExperimentSpec::from_file(&file).unwrap();
    let all = ExperimentOptions {
        train: true,
        evaluate: true,
        allow_unfinished: false,
        fresh_rollouts: false,
    };
    run_experiment(&spec, &all, Arc::new(AtomicBool::new(false))).unwrap();
    let out = dir.path().join("results");
    let curves = std::fs::read_to_string(out.join("curves.csv")).unwrap();
    // ttf and strict ttf for 2 methods, platform for 2, race for Baseline + RALL
    // eta=1 + RALL + Meta: 10 points per rung, 2 rungs
    assert_eq!(curves.lines().count(), 1 + 2 * 10, "{curves}");
    for line in curves.lines().skip(1) {
        let v: Vec<&str> = line.split(',').collect();
        let [x, lo, hi] = [v[4], v[5], v[6]].map(|s| s.parse::<f64>().unwrap());
        assert!(lo <= x && x <= hi, "{line}");
        assert!(v[3] == "0" || v[3] == "4", "{line}");
    }
    // where the evaluation's time went: every stage, and each higher rung's benchmarks
    let time = std::fs::read_to_string(out.join("evaluation_time.txt")).unwrap();
    for phase in [
        "velocity tracking of every policy",
        "table I: time to fall",
        "race track",
        "robustness curves over the severity ladder",
        "curves, rung 4, time to fall",
        "curves, rung 4, race",
    ] {
        assert!(time.contains(&format!("  {phase}: ")), "{phase}: {time}");
    }
    assert!(!time.contains("rung 0"), "rung 0 reuses the tables: {time}");
    // each run's number is over its last two checkpoints, with the spread kept
    let spread = std::fs::read_to_string(out.join("checkpoints.csv")).unwrap();
    assert!(spread.contains("ttf,Baseline,2,") && spread.contains("ttf,Baseline,1,"));
    assert!(spread.contains("platform,RALL,2,") && spread.contains("platform,RALL,1,"));
    // robots of both checkpoints (1 seed x 1 robot each) pooled in every cell
    let ttf = std::fs::read_to_string(out.join("ttf.csv")).unwrap();
    for line in ttf.lines().skip(1) {
        assert_eq!(line.split(',').nth(7), Some("2"), "{line}");
    }
    let md = std::fs::read_to_string(out.join("README.md")).unwrap();
    assert!(
        md.contains("## Robustness curves") && md.contains("rung 4"),
        "{md}"
    );
    assert!(md.contains("## From checkpoint to checkpoint"), "{md}");
    assert!(md.contains("Strict: any contact"), "{md}");
    // the curves are drawn in the README and listed first among the figures
    assert!(
        md.contains(
            "![Time to Fall against severity (mean over table I's cells)](figures/curve_ttf.svg)"
        ),
        "{md}"
    );
    let figures = &md[md.find("## Figures").unwrap()..];
    assert!(figures.find("curve_ttf.svg").unwrap() < figures.find("(figures/ttf.svg)").unwrap());
    for fig in ["curve_ttf.svg", "curve_platform.svg", "curve_race.svg"] {
        let svg = std::fs::read_to_string(out.join("figures").join(fig)).unwrap();
        assert!(svg.starts_with("<svg") && svg.contains("rung 4"), "{fig}");
    }
    let ttf_svg = std::fs::read_to_string(out.join("figures/curve_ttf.svg")).unwrap();
    assert!(
        ttf_svg.contains("the paper&apos;s number at rung 0")
            || ttf_svg.contains("the paper's number at rung 0")
    );

    // evaluated again, every rollout comes from the rollout cache, to the same bytes
    assert!(time.contains(" read from the rollout cache"), "{time}");
    assert!(!time.contains("rollouts: 0 run now"), "{time}");
    std::fs::write(&file, spec_text(dir.path(), "results-again", &extra)).unwrap();
    let again = ExperimentSpec::from_file(&file).unwrap();
    let eval_again = ExperimentOptions {
        train: false,
        ..all
    };
    run_experiment(&again, &eval_again, Arc::new(AtomicBool::new(false))).unwrap();
    let again_dir = dir.path().join("results-again");
    let time = std::fs::read_to_string(again_dir.join("evaluation_time.txt")).unwrap();
    assert!(time.contains("rollouts: 0 run now, "), "{time}");
    let all_tables = [
        "runs.csv",
        "ttf.csv",
        "platform.csv",
        "race.csv",
        "checkpoints.csv",
        "curves.csv",
        "results.json",
    ];
    same_files(
        &out,
        &again_dir,
        &all_tables,
        "rollouts read from the cache",
    );
    // an evaluation stopped part way (half the rollouts kept) ends as one that was not
    let cache = dir.path().join("runs/rollout-cache");
    let mut kept: Vec<_> = std::fs::read_dir(&cache)
        .unwrap()
        .map(|e| e.unwrap().path())
        .collect();
    kept.sort();
    for lost in kept.iter().step_by(2) {
        std::fs::remove_file(lost).unwrap();
    }
    std::fs::write(&file, spec_text(dir.path(), "results-resumed", &extra)).unwrap();
    let resumed = ExperimentSpec::from_file(&file).unwrap();
    run_experiment(&resumed, &eval_again, Arc::new(AtomicBool::new(false))).unwrap();
    let resumed_dir = dir.path().join("results-resumed");
    let time = std::fs::read_to_string(resumed_dir.join("evaluation_time.txt")).unwrap();
    let lost = kept.len().div_ceil(2);
    assert!(
        time.contains(&format!(
            "rollouts: {lost} run now, {} read",
            kept.len() - lost
        )),
        "{time}"
    );
    same_files(&out, &resumed_dir, &all_tables, "a resumed evaluation");

    // shipped as actor-only copies, the checkpoints evaluate to the same tables
    ship_all(&spec, &file).unwrap();
    let copy = dir
        .path()
        .join("shipped/rall-s1/checkpoints/model_000001.safetensors");
    let full = dir
        .path()
        .join("runs/rall-s1/checkpoints/model_000001.safetensors");
    let size = |p: &Path| std::fs::metadata(p).unwrap().len();
    assert!(
        size(&copy) < size(&full),
        "{} >= {}",
        size(&copy),
        size(&full)
    );
    std::fs::remove_dir_all(dir.path().join("runs")).unwrap();
    std::fs::write(&file, spec_text(dir.path(), "results-shipped", &extra)).unwrap();
    let shipped = ExperimentSpec::from_file(&file).unwrap();
    run_experiment(&shipped, &eval_again, Arc::new(AtomicBool::new(false))).unwrap();
    for f in ["ttf.csv", "platform.csv", "checkpoints.csv", "curves.csv"] {
        let a = std::fs::read_to_string(out.join(f)).unwrap();
        let b = std::fs::read_to_string(dir.path().join("results-shipped").join(f)).unwrap();
        assert_eq!(
            a, b,
            "{f}: actor-only copies must evaluate as the checkpoints"
        );
    }
    // an actor-only copy acts, but is never resumed
    let loaded = rall::runner::load_policy(&copy).unwrap();
    assert!(loaded.actor_only && !loaded.exact);

    // more checkpoints than a run keeps: refused, naming the missing one; nothing
    // already written is touched
    let before = std::fs::read_to_string(out.join("README.md")).unwrap();
    let extra = format!("{CURVES}\n[checkpoints]\nlast = 2\nevery = 5\n");
    std::fs::write(&file, spec_text(dir.path(), "results", &extra)).unwrap();
    let spec = ExperimentSpec::from_file(&file).unwrap();
    let err = format!(
        "{:#}",
        run_experiment(&spec, &eval_again, Arc::new(AtomicBool::new(false))).unwrap_err()
    );
    assert!(err.contains("[checkpoints]"), "{err}");
    assert_eq!(
        std::fs::read_to_string(out.join("README.md")).unwrap(),
        before
    );
}

#[test]
fn a_rung_off_the_ladder_or_a_ladder_missing_an_axis_is_refused_by_name() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("curves.toml");
    let bad = CURVES.replace("[0, 4]", "[0, 9]");
    std::fs::write(&file, spec_text(dir.path(), "results", &bad)).unwrap();
    let err = format!("{:#}", ExperimentSpec::from_file(&file).unwrap_err());
    assert!(err.contains("severity 9"), "{err}");

    let ladder = dir.path().join("ladder.toml");
    std::fs::write(
        &ladder,
        rall::eval::severity::BUILTIN_LADDER_TOML.replace("rough_amplitude_m = 0.05\n", ""),
    )
    .unwrap();
    let missing = CURVES.replace(
        "severity = [0, 4]",
        &format!("severity = [0, 4]\nladder = \"{}\"", ladder.display()),
    );
    std::fs::write(&file, spec_text(dir.path(), "results", &missing)).unwrap();
    let err = format!("{:#}", ExperimentSpec::from_file(&file).unwrap_err());
    assert!(err.contains("rough_amplitude_m"), "{err}");
}
