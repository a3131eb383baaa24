//! `rall eval commands`: the command-space safety map finds a planted unsafe
//! command, passes a walking policy where it walks, refuses bad input naming the
//! flag, and writes a CSV and an SVG that read back.

use std::path::{Path, PathBuf};
use std::process::Command;

use rall::env::{ACT_DIM, OBS_DIM};
use rall::eval::commands::CSV_HEADER;
use rall::eval::commands_plot::FAIL_FRAME_PX;
use rall::eval::{
    evaluate_command_map, write_command_map_svg, Actor, CommandGrid, CommandMap, CommandMapOptions,
    NamedPolicy, Policy, SafetyThreshold,
};

const RALL: &str = env!("CARGO_BIN_EXE_rall");

/// The shipped walking policy of flat ground.
fn walking_checkpoint() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("policies/time-to-walk.safetensors")
}

fn walking_policy() -> NamedPolicy {
    NamedPolicy::load("walking", &walking_checkpoint()).unwrap()
}

/// Where the command sits in rall's observation row (after base linear and
/// angular velocity and gravity, 3 each).
const COMMAND_COLUMN: usize = 9;

/// Where the previous action sits in the observation row (after the command and
/// the 12 joint positions and 12 velocities).
const PREVIOUS_ACTION_COLUMN: usize = 36;

/// The walking policy, except at one command: there every joint's target swings
/// between its limits from one step to the next (each robot's swing reads its own
/// previous action, so the rollout is the same whatever runs beside it).
struct PlantedFall {
    walking: Policy,
    /// The planted command as it appears in the observation (times the scales).
    observed: [f32; 3],
}

impl PlantedFall {
    fn new(p: NamedPolicy, command: [f64; 3]) -> PlantedFall {
        let scale = p.env.observation.command_scale;
        PlantedFall {
            walking: p.policy,
            observed: [0, 1, 2].map(|k| (command[k] * scale[k]) as f32),
        }
    }
}

impl Actor for PlantedFall {
    fn actions(&self, obs: &[f32]) -> anyhow::Result<Vec<f32>> {
        let mut actions = self.walking.actions(obs)?;
        for (row, out) in obs
            .chunks_exact(OBS_DIM)
            .zip(actions.chunks_exact_mut(ACT_DIM))
        {
            let command = &row[COMMAND_COLUMN..COMMAND_COLUMN + 3];
            if command
                .iter()
                .zip(&self.observed)
                .all(|(a, b)| (a - b).abs() < 1e-6)
            {
                let swing = if row[PREVIOUS_ACTION_COLUMN] > 0.0 {
                    -40.0
                } else {
                    40.0
                };
                out.fill(swing);
            }
        }
        Ok(actions)
    }
}

fn options(robots: usize, seconds: f64) -> CommandMapOptions {
    CommandMapOptions {
        robots,
        episode_length_s: Some(seconds),
        seed: 3,
        resamples: 200,
        ..CommandMapOptions::default()
    }
}

fn small_grid() -> CommandGrid {
    CommandGrid::new(vec![0.0, 0.5], vec![0.0], vec![0.0, 0.5]).unwrap()
}

#[test]
fn a_fall_planted_at_one_command_fails_that_cell_alone() {
    let walking = walking_policy();
    let env = walking.env.clone();
    let planted_at = [0.5, 0.0, 0.0];
    let planted = PlantedFall::new(walking, planted_at);
    let map = evaluate_command_map(&planted, &env, &small_grid(), &options(4, 3.0), 1).unwrap();
    let t = SafetyThreshold::default();
    assert_eq!(map.cells.len(), 4);
    let failing: Vec<[f64; 3]> = map
        .cells
        .iter()
        .filter(|c| !c.is_safe(&t))
        .map(|c| c.command())
        .collect();
    assert_eq!(failing, vec![planted_at], "{}", map.table(&t));
    let worst = map.worst_cell().unwrap();
    assert_eq!(worst.command(), planted_at);
    assert!(worst.falls > 0, "{worst:?}");
    assert!(worst.strict_falls >= worst.falls);
    assert!((map.safe_share(&t) - 0.75).abs() < 1e-12);
    // the same seed gives the same map, whatever the threads
    let planted = PlantedFall::new(walking_policy(), planted_at);
    let again = evaluate_command_map(&planted, &env, &small_grid(), &options(4, 3.0), 2).unwrap();
    assert_eq!(again.to_csv(&t), map.to_csv(&t));
}

#[test]
fn the_walking_policy_is_safe_at_low_speeds() {
    let walking = walking_policy();
    // standing, walking slowly forward, sideways and both: cells the full map (16
    // robots, 20 s, seed 0) also finds safe; turning in place clockwise is not
    let grid = CommandGrid::new(vec![0.0, 0.3], vec![0.0, 0.5], vec![0.0]).unwrap();
    let map =
        evaluate_command_map(&walking.policy, &walking.env, &grid, &options(8, 6.0), 1).unwrap();
    let t = SafetyThreshold::default();
    assert_eq!(map.safe_share(&t), 1.0, "{}", map.table(&t));
    for c in &map.cells {
        assert_eq!(c.falls, 0);
        assert_eq!((c.fall_rate.lo, c.fall_rate.value), (0.0, 0.0));
        // Wilson: no fall of 8 robots still leaves up to a third
        assert!(c.fall_rate.hi > 0.3 && c.fall_rate.hi < 0.35, "{c:?}");
        assert!(c.lin_tracking.lo <= c.lin_tracking.value);
        assert!(c.lin_tracking.value <= c.lin_tracking.hi);
        assert!(c.commanded_in_training);
        assert_eq!(c.time_to_fall, 1.0);
    }
    assert_eq!(map.episode_steps, 300);
}

/// `rall eval commands ARGS` on the walking checkpoint: (success, stdout, stderr).
fn rall_commands(args: &[&str]) -> (bool, String, String) {
    let checkpoint = walking_checkpoint();
    let out = Command::new(RALL)
        .args(["eval", "commands", "--checkpoint"])
        .arg(&checkpoint)
        .args(["--threads", "1"])
        .args(args)
        .output()
        .unwrap();
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

#[test]
fn bad_input_is_refused_naming_the_flag() {
    for (args, flag, why) in [
        (&["--vx-cells", "0"][..], "--vx-cells 0", "at least 1 cell"),
        (&["--yaw", ""][..], "--yaw", "empty"),
        (&["--vy", "0,zero"][..], "--vy", "not a finite number"),
        (&["--vx", "0.5,0.5"][..], "--vx", "twice"),
        (&["--robots", "0"][..], "--robots 0", "at least 1 robot"),
        (&["--robots", "-3"][..], "--robots", "cannot be negative"),
        (&["--seconds", "-1"][..], "--seconds -1", "positive"),
        (
            &["--max-falls-pct", "150"][..],
            "--max-falls-pct",
            "[0, 100]",
        ),
        (
            &["--severity", "99"][..],
            "severity 99",
            "not on the ladder",
        ),
        (&["--load", "piano"][..], "--load", "unknown load"),
    ] {
        let (ok, _, err) = rall_commands(args);
        assert!(!ok, "{args:?} was accepted");
        assert!(err.contains(flag) && err.contains(why), "{args:?}: {err}");
        assert!(!err.contains("panicked"), "{args:?}: {err}");
    }
}

#[test]
fn a_command_outside_the_training_ranges_runs_with_a_warning() {
    let (ok, out, err) = rall_commands(&[
        "--vx",
        "1.5",
        "--vy",
        "0",
        "--yaw",
        "0",
        "--robots",
        "1",
        "--seconds",
        "0.2",
    ]);
    assert!(ok, "{err}");
    assert!(
        err.contains("warning: --vx 1.5: outside the policy's training range [-1, 1]"),
        "{err}"
    );
    assert!(out.contains("worst cell   vx +1.50 m/s"), "{out}");
    // the table marks the cell
    let row = out
        .lines()
        .find(|l| l.trim_start().starts_with("+1.50"))
        .unwrap();
    assert!(row.ends_with('~'), "{row}");
}

/// Checks that `svg` is well formed as far as its tags go: every element closed
/// in order, one root `svg`. Returns the element names in order.
fn svg_elements(svg: &str) -> Vec<String> {
    let mut open: Vec<String> = Vec::new();
    let mut names = Vec::new();
    let mut rest = svg;
    while let Some(start) = rest.find('<') {
        let end = rest[start..].find('>').expect("an unclosed tag") + start;
        let tag = &rest[start + 1..end];
        rest = &rest[end + 1..];
        if tag.starts_with('?') || tag.starts_with('!') {
            continue;
        }
        if let Some(name) = tag.strip_prefix('/') {
            assert_eq!(
                open.pop().as_deref(),
                Some(name.trim()),
                "mismatched </{name}>"
            );
            continue;
        }
        let name = tag.split_whitespace().next().unwrap().trim_end_matches('/');
        names.push(name.to_string());
        if !tag.ends_with('/') {
            assert!(
                !open.is_empty() || name == "svg",
                "{name} outside the root element"
            );
            open.push(name.to_string());
        }
    }
    assert!(open.is_empty(), "unclosed elements {open:?}");
    assert_eq!(names.first().map(String::as_str), Some("svg"));
    names
}

/// Frames around failing cells in a figure.
fn frames(svg: &str) -> usize {
    svg.matches(&format!("stroke-width=\"{FAIL_FRAME_PX}\""))
        .count()
}

#[test]
fn the_csv_and_the_svg_read_back() {
    let walking = walking_policy();
    let grid = CommandGrid::new(vec![-0.5, 0.0, 0.5], vec![-0.5, 0.0], vec![0.0]).unwrap();
    let map =
        evaluate_command_map(&walking.policy, &walking.env, &grid, &options(2, 1.0), 1).unwrap();
    let t = SafetyThreshold::default();
    let csv = map.to_csv(&t);
    let mut lines = csv.lines();
    let header: Vec<&str> = lines.next().unwrap().split(',').collect();
    assert_eq!(header, CSV_HEADER.split(',').collect::<Vec<_>>());
    let col = |name: &str| header.iter().position(|h| *h == name).unwrap();
    let rows: Vec<Vec<&str>> = lines.map(|l| l.split(',').collect()).collect();
    assert_eq!(rows.len(), 6);
    for (row, cell) in rows.iter().zip(&map.cells) {
        assert_eq!(row.len(), header.len());
        let num = |name: &str| row[col(name)].parse::<f64>().unwrap();
        assert_eq!(
            [num("vx_mps"), num("vy_mps"), num("yaw_rate_rad_s")],
            cell.command()
        );
        assert_eq!(num("robots"), 2.0);
        assert!(num("fall_rate_lo") <= num("fall_rate") && num("fall_rate") <= num("fall_rate_hi"));
        assert!(num("lin_tracking_lo") <= num("lin_tracking_hi"));
        assert!(num("strict_falls") >= num("falls"));
        let safe: bool = row[col("safe")].parse().unwrap();
        assert_eq!(safe, cell.is_safe(&t));
    }
    // the map reads back from its JSON
    let back: CommandMap = serde_json::from_str(&serde_json::to_string(&map).unwrap()).unwrap();
    assert_eq!(back, map);

    // the figure: well formed, two panels (one per vy), the axes named, and a
    // frame around each failing cell
    let dir = tempfile::tempdir().unwrap();
    let draw = |t: &SafetyThreshold, name: &str| {
        let path = dir.path().join(name);
        write_command_map_svg(&map, t, &path).unwrap();
        std::fs::read_to_string(path).unwrap()
    };
    let none_pass = SafetyThreshold::new(0.0, 1.0).unwrap();
    let all_pass = SafetyThreshold::new(100.0, 0.0).unwrap();
    let (framed, clean) = (draw(&none_pass, "framed.svg"), draw(&all_pass, "clean.svg"));
    let names = svg_elements(&framed);
    assert!(
        names.iter().filter(|n| *n == "rect").count() >= 6,
        "{names:?}"
    );
    assert_eq!(framed.matches("vy = ").count(), 2);
    for label in [
        "vy = -0.50 m/s",
        "vy = +0.00 m/s",
        "vx (m/s)",
        "yaw rate (rad/s)",
        "fall rate",
    ] {
        assert!(framed.contains(label), "no {label:?} in the figure");
    }
    let failing = |t: &SafetyThreshold| map.cells.iter().filter(|c| !c.is_safe(t)).count();
    assert_eq!(failing(&none_pass), 6);
    assert_eq!(frames(&framed) - frames(&clean), 6 - failing(&all_pass));
}
