//! `rall experiment` with `[commands]` on a tiny slice: each listed run's command
//! map, its tables and figures, the section on the README's first page, the two
//! command-map verdict metrics with one value per seed, `--redraw` from
//! results.json, and the inputs that cannot work refused by name.

mod common;

use std::path::Path;
use std::sync::atomic::AtomicBool;
use std::sync::Arc;

use rall::experiment::commands::CommandsSpec;
use rall::experiment::results::ExperimentResults;
use rall::experiment::{run_experiment, ExperimentOptions, ExperimentSpec};
use rall::learn::CriticKind;

/// A tiny run's config; `max_tilt_rad` small makes every robot fall at once.
fn write_config(
    dir: &Path,
    name: &str,
    (critic, eta): (CriticKind, Option<f32>),
    max_tilt_rad: f64,
) -> String {
    let mut c = common::tiny_config(critic);
    c.learner.cvar_eta = eta;
    c.env.episode.max_tilt_rad = max_tilt_rad;
    let path = dir.join(format!("{name}.toml"));
    std::fs::write(&path, c.to_toml()).unwrap();
    path.display().to_string()
}

const COMMANDS: &str = r#"
[commands]
methods = ["Baseline", "Baseline seed 2", "RALL", "RALL seed 2"]
vx_mps = [0.5, 0.0]
vy_mps = [0.0]
yaw = [-0.5, 0.5]
robots = 3
seed = 2
episode_s = 1.0
max_falls_pct = 5
min_lin_tracking = 0.5
"#;

const VERDICTS: &str = r#"
[verdicts]
alpha = 0.05
primary = { first = "RALL", second = "Baseline", metric = "worst_cell_falls" }

[[verdicts.family]]
name = "secondary"
contrasts = [
    { first = "RALL", second = "Baseline", metric = "safe_share", rung = 0 },
    { first = "RALL", second = "Baseline", metric = "worst_cell_falls" },
]
"#;

/// Two seeds each of Baseline and RALL, the smallest tables, `commands` and
/// `verdicts` appended as they are. Baseline's robots all fall at once (a tilt
/// limit of 1e-4 rad), RALL's stand still: the two barely trained policies track
/// a standing command (vx 0) well and a walking one (vx 0.5) badly.
fn spec_text(dir: &Path, commands: &str, verdicts: &str) -> String {
    let base = write_config(dir, "baseline", (CriticKind::Scalar, None), 1e-4);
    let rall = write_config(dir, "rall", (CriticKind::Iqn, Some(0.5)), 1.2);
    let preface = dir.join("answer.md");
    std::fs::write(&preface, "The slice answers nothing.\n").unwrap();
    let mut runs = String::new();
    for (name, label, config) in [("baseline", "Baseline", &base), ("rall", "RALL", &rall)] {
        for seed in 1..=2 {
            let l = if seed == 1 {
                label.to_string()
            } else {
                format!("{label} seed {seed}")
            };
            runs.push_str(&format!(
                "[[run]]\nname = \"{name}\"\nlabel = \"{l}\"\nconfig = \"{config}\"\nseed = {seed}\niterations = 2\n\n"
            ));
        }
    }
    format!(
        r#"
name = "commands"
preface = "{preface}"
runs_dir = "{runs_dir}"
results_dir = "{results}"
threads = 2

{runs}
[tracking]
episodes = 2
seed = 7

[ttf]
methods = ["Baseline", "RALL"]
seeds = 1
repeats = 1
loads = ["ball"]

[platform]
methods = ["Baseline"]
heights_m = [0.40]
seeds = 1
repeats = 1

[race]
methods = ["Baseline"]
agents = 1
episodes = 1

[bootstrap]
resamples = 20

[contrasts]
pairs = [["RALL", "Baseline"]]
{commands}
{verdicts}
"#,
        preface = preface.display(),
        runs_dir = dir.join("runs").display(),
        results = dir.join("results").display(),
    )
}

/// A CSV file's rows, each a map from column name to field (no quoted fields here).
fn rows(path: &Path) -> Vec<std::collections::HashMap<String, String>> {
    let text = std::fs::read_to_string(path).unwrap();
    let mut lines = text.lines();
    let header: Vec<String> = lines
        .next()
        .unwrap()
        .split(',')
        .map(str::to_string)
        .collect();
    lines
        .map(|l| {
            let fields: Vec<&str> = l.split(',').collect();
            assert_eq!(fields.len(), header.len(), "{l}");
            header
                .iter()
                .cloned()
                .zip(fields.iter().map(|f| f.to_string()))
                .collect()
        })
        .collect()
}

fn num(row: &std::collections::HashMap<String, String>, key: &str) -> f64 {
    row[key]
        .parse()
        .unwrap_or_else(|_| panic!("{key}: {:?}", row[key]))
}

/// The per-seed values of a `;`-joined field.
fn list(field: &str) -> Vec<f64> {
    field.split(';').map(|x| x.parse().unwrap()).collect()
}

/// Checks `commands.csv` against the threshold and returns each run's (label,
/// safe share, worst cell's fall rate) from its cells.
fn check_cells(out: &Path) -> Vec<(String, f64, f64)> {
    let cells = rows(&out.join("commands.csv"));
    // 4 runs x 2 vx x 1 vy x 2 yaw rates, in the file's order
    assert_eq!(cells.len(), 4 * 4);
    let labels: Vec<&str> = cells
        .iter()
        .step_by(4)
        .map(|r| r["label"].as_str())
        .collect();
    assert_eq!(
        labels,
        ["Baseline", "Baseline seed 2", "RALL", "RALL seed 2"]
    );
    let mut per_run: Vec<(String, f64, f64)> = Vec::new();
    for run in cells.chunks(4) {
        let vx: Vec<f64> = run.iter().map(|r| num(r, "vx_mps")).collect();
        assert_eq!(vx, [0.0, 0.0, 0.5, 0.5], "grid order, sorted");
        let mut safe = 0;
        let mut worst: f64 = 0.0;
        for r in run {
            assert_eq!(r["checkpoint_iteration"], "2");
            assert_eq!(r["robots"], "3");
            let rate = num(r, "fall_rate");
            assert!((rate - num(r, "falls") / 3.0).abs() < 1e-4, "{r:?}");
            assert!(num(r, "fall_rate_lo") <= rate && rate <= num(r, "fall_rate_hi"));
            let lin = num(r, "lin_tracking");
            if r["method"] == "Baseline" {
                assert_eq!(r["falls"], "3", "every Baseline robot falls: {r:?}");
            }
            let is_safe = rate < 0.05 && lin >= 0.5;
            assert_eq!(r["safe"], is_safe.to_string(), "{r:?}");
            safe += is_safe as usize;
            worst = worst.max(rate);
        }
        per_run.push((run[0]["label"].clone(), safe as f64 / 4.0, worst));
    }
    per_run
}

#[test]
fn command_maps_are_tabled_drawn_judged_by_seed_and_redrawn_from_json() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("commands.toml");
    std::fs::write(&file, spec_text(dir.path(), COMMANDS, VERDICTS)).unwrap();
    let spec = ExperimentSpec::from_file(&file).unwrap();
    let all = ExperimentOptions {
        train: true,
        evaluate: true,
        allow_unfinished: false,
        fresh_rollouts: false,
    };
    run_experiment(&spec, &all, Arc::new(AtomicBool::new(false))).unwrap();
    let out = dir.path().join("results");
    let per_run = check_cells(&out);

    // per method: the mean of its seeds' numbers, each seed's number from its cells
    let methods = rows(&out.join("commands_by_method.csv"));
    assert_eq!(methods.len(), 2);
    for (m, seeds) in methods.iter().zip([&per_run[..2], &per_run[2..]]) {
        assert_eq!(m["method"], seeds[0].0);
        assert_eq!(m["n_seeds"], "2");
        let safe: Vec<f64> = seeds.iter().map(|s| s.1).collect();
        let worst: Vec<f64> = seeds.iter().map(|s| s.2).collect();
        assert_eq!(list(&m["safe_share_per_seed"]), safe, "{m:?}");
        let worst_listed = list(&m["worst_cell_fall_rate_per_seed"]);
        for (a, b) in worst_listed.iter().zip(&worst) {
            assert!((a - b).abs() < 1e-4, "{m:?}");
        }
        let mean = (safe[0] + safe[1]) / 2.0;
        assert!((num(m, "safe_share") - mean).abs() < 1e-4, "{m:?}");
        // two seeds: a t-interval around the mean
        assert!(num(m, "safe_share_lo") <= mean + 1e-4 && mean - 1e-4 <= num(m, "safe_share_hi"));
        let highest = worst.iter().cloned().fold(0.0, f64::max);
        assert!((num(m, "worst_robots") * highest - num(m, "worst_falls")).abs() < 1e-3);
        let fig = out
            .join("figures")
            .join(format!("commands_{}.svg", m["method"].to_lowercase()));
        let svg = std::fs::read_to_string(&fig).unwrap();
        assert!(
            svg.starts_with("<svg") && svg.contains("vy = +0.00 m/s"),
            "{fig:?}"
        );
    }

    // the two verdict metrics: one value per seed, the seeds' own numbers
    let verdicts = rows(&out.join("verdicts.csv"));
    let metric_rows: Vec<_> = verdicts
        .iter()
        .filter(|r| r["metric"] == "safe_share" || r["metric"] == "worst_cell_falls")
        .collect();
    assert_eq!(metric_rows.len(), 3, "{verdicts:?}");
    for r in metric_rows {
        let (first, second) = (list(&r["first_values"]), list(&r["second_values"]));
        let k = if r["metric"] == "safe_share" { 1 } else { 2 };
        let of = |s: &(String, f64, f64)| if k == 1 { s.1 } else { s.2 };
        for (v, s) in first
            .iter()
            .zip(&per_run[2..])
            .chain(second.iter().zip(&per_run[..2]))
        {
            assert!((v - of(s)).abs() < 1e-4, "{r:?} {per_run:?}");
        }
        assert_eq!((first.len(), second.len()), (2, 2), "{r:?}");
        assert_eq!(r["first_seeds"], "1;2");
        // Baseline falls in every cell: RALL is ahead on both, with a higher safe
        // share and a lower worst-cell fall rate (lower is safer)
        let difference = num(r, "difference");
        assert!(
            if k == 1 {
                difference > 0.0
            } else {
                difference < 0.0
            },
            "{r:?}"
        );
        assert_eq!(r["verdict"], "ahead", "{r:?}");
    }
    let contrasts = rows(&out.join("contrasts.csv"));
    let on_map: Vec<&str> = contrasts
        .iter()
        .filter(|r| r["benchmark"] == "commands")
        .map(|r| r["metric"].as_str())
        .collect();
    assert_eq!(on_map, ["safe_share", "worst_cell_falls"]);

    // the section sits on the first page: after the verdicts and the preface,
    // before every long table
    let readme = std::fs::read_to_string(out.join("README.md")).unwrap();
    let at = |h: &str| readme.find(h).unwrap_or_else(|| panic!("{h}: {readme}"));
    let section = at("## Commands a policy cannot hold");
    assert!(at("## The pre-registered result") < section);
    assert!(at("The slice answers nothing.") < section);
    assert!(section < at("## Method against method") && section < at("## Training runs"));
    assert!(readme.contains("| RALL (2 seeds) |"), "{readme}");
    let baseline = readme
        .lines()
        .find(|l| l.starts_with("| Baseline (2 seeds) | 0.0%"))
        .unwrap_or_else(|| panic!("{readme}"));
    assert!(
        baseline.contains("| 100.0% [100.0, 100.0] {100.0, 100.0} | 2 of 2 | ")
            && baseline.contains("3 of 3 robots fell"),
        "{baseline}"
    );
    assert!(
        readme.contains("iteration 2 (its last checkpoint)"),
        "{readme}"
    );
    assert!(readme.contains("(figures/commands_rall.svg)"), "{readme}");

    // --redraw: the README, tables and figures again from results.json alone
    let read = |f: &str| std::fs::read(out.join(f)).unwrap();
    let files = [
        "README.md",
        "commands.csv",
        "commands_by_method.csv",
        "verdicts.csv",
        "figures/commands_rall.svg",
        "figures/commands_baseline.svg",
    ];
    let before: Vec<Vec<u8>> = files.iter().map(|f| read(f)).collect();
    std::fs::remove_file(out.join("commands.csv")).unwrap();
    std::fs::remove_file(out.join("figures/commands_rall.svg")).unwrap();
    let preface = spec.preface_text().unwrap();
    ExperimentResults::redraw(&out, preface, Some(&spec)).unwrap();
    for (f, b) in files.iter().zip(&before) {
        assert!(read(f) == *b, "{f} redrawn from results.json differs");
    }
}

/// The error of reading an experiment file with `text`.
fn refusal(dir: &Path, text: &str) -> String {
    let file = dir.join("bad.toml");
    std::fs::write(&file, text).unwrap();
    format!("{:#}", ExperimentSpec::from_file(&file).unwrap_err())
}

#[test]
fn bad_commands_sections_and_command_verdicts_are_refused_by_name() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    // the section as written parses (`yaw` is read as yaw_rate_rad_s)
    let file = d.join("good.toml");
    std::fs::write(&file, spec_text(d, COMMANDS, VERDICTS)).unwrap();
    let spec = ExperimentSpec::from_file(&file).unwrap();
    let commands = CommandsSpec::of(&spec).unwrap().unwrap();
    assert_eq!(commands.yaw_rate_rad_s, [-0.5, 0.5]);
    for (commands, verdicts, names) in [
        // an unknown key
        (
            COMMANDS.replace("robots = 3", "robot = 3"),
            VERDICTS,
            "`robot`",
        ),
        // an empty axis: no cell
        (
            COMMANDS.replace("vy_mps = [0.0]", "vy_mps = []"),
            VERDICTS,
            "commands.vy_mps",
        ),
        (
            COMMANDS.replace("vx_mps = [0.5, 0.0]", "vx_mps = [0.5, 0.5]"),
            VERDICTS,
            "twice",
        ),
        (
            COMMANDS.replace("\"RALL seed 2\"]", "\"RALL seed 9\"]"),
            VERDICTS,
            "RALL seed 9",
        ),
        (
            COMMANDS.replace("robots = 3", "robots = 0"),
            VERDICTS,
            "commands.robots",
        ),
        (
            COMMANDS.replace("episode_s = 1.0", "episode_s = -1.0"),
            VERDICTS,
            "commands.episode_s",
        ),
        (
            COMMANDS.replace("max_falls_pct = 5", "max_falls_pct = 500"),
            VERDICTS,
            "commands.max_falls_pct",
        ),
        // a command-map verdict without a [commands] section, or on a rung
        (String::new(), VERDICTS, "no [commands] section"),
        (
            COMMANDS.to_string(),
            &*VERDICTS.replace("rung = 0", "rung = 3"),
            "has no severity rung",
        ),
        // a command-map verdict on a method the section does not map
        (
            COMMANDS.replace("\"Baseline\", \"Baseline seed 2\", ", ""),
            VERDICTS,
            "lists no run of \"Baseline\"'s method",
        ),
        // a benchmark's metric still needs its rung
        (
            COMMANDS.to_string(),
            &*VERDICTS.replace("metric = \"safe_share\", rung = 0", "metric = \"ttf\""),
            "gives no rung",
        ),
    ] {
        let e = refusal(d, &spec_text(d, &commands, verdicts));
        assert!(e.contains(names), "expected {names:?} in: {e}");
    }
}
