//! `rall eval ...`: evaluation commands.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use clap::{Args, Subcommand};

use crate::config::{worker_threads, TrainConfig};
use crate::env::config::CommandConfig;
use crate::eval::commands::parse_axis_values;
use crate::eval::report::write_outputs;
use crate::eval::{
    evaluate_command_map, write_command_map_svg, AxisSpec, CommandGrid, CommandMapOptions,
    SafetyThreshold, SeverityRung,
};
use crate::eval::{
    evaluate_platform, evaluate_race, evaluate_tracking_with_falls, evaluate_ttf, tracking_env,
    with_randomization, ActionMode, FallRecord, GroundKind, Ladder, Load, MetaArg, MetaConfig,
    NamedPolicy, PlatformOptions, RaceOptions, ScenarioParams, TrackingReport, TtfOptions,
    FALL_DEFINITION,
};
use crate::eval::{is_onnx, Policy};
use crate::experiment::curves::{
    curve_csv, curve_markdown, platform_point, race_point, ttf_point, CurvePoint, Resampling,
};
use crate::experiment::TrackingEstimates;
use crate::learn::Distortion;
use crate::runner::{load_policy, Progress, RunDir};

#[derive(Debug, Args)]
pub struct EvalArgs {
    #[command(subcommand)]
    pub what: EvalCommand,
}

#[derive(Debug, Subcommand)]
pub enum EvalCommand {
    /// Velocity-command tracking on flat ground (noise and PD as in training).
    Tracking(TrackingArgs),
    /// Time to Fall with payloads (ball, frozen arm, moving arm) x terrain (flat,
    /// random) x pushes (off, on): the paper's table I.
    Ttf(TtfArgs),
    /// Success rate of walking off a platform: the paper's table II.
    Platform(PlatformArgs),
    /// Race-track returns (quantiles 0.25/0.5/0.75) per policy and for the IQR meta controller.
    Race(RaceArgs),
    /// The critic's value quantiles and IQR in the last steps before falls against
    /// everywhere else, in the checkpoint's own training env: does the
    /// distribution's lower tail move, does the IQR rise, before the robot falls?
    Falls(FallsArgs),
    /// A command-space safety map: over a grid of the policy's command ranges (vx,
    /// vy, yaw rate), robots holding each fixed command for one episode; per cell
    /// the fall rate, the strict fall rate and the tracking scores with 95%
    /// intervals, the worst cell and the share of safe cells.
    Commands(CommandsArgs),
}

/// `rall eval commands`.
#[derive(Debug, Args)]
#[command(after_help = COMMANDS_AFTER_HELP)]
pub struct CommandsArgs {
    /// Checkpoint (.safetensors) written by `rall train` (an actor-only copy is fine).
    #[arg(long, required_unless_present = "onnx", conflicts_with = "onnx")]
    pub checkpoint: Option<PathBuf>,
    /// An ONNX policy with its JSON sidecar POLICY.json beside it (see
    /// docs/outside-policies.md), instead of a checkpoint.
    #[arg(long, value_name = "POLICY.onnx")]
    pub onnx: Option<PathBuf>,
    /// Forward speeds evenly spaced over the policy's vx range, both ends included
    /// (and 0 when the range spans it).
    #[arg(long, value_name = "N", default_value = "7", value_parser = parse_count, allow_hyphen_values = true)]
    pub vx_cells: usize,
    /// Lateral speeds evenly spaced over the policy's vy range.
    #[arg(long, value_name = "N", default_value = "5", value_parser = parse_count, allow_hyphen_values = true)]
    pub vy_cells: usize,
    /// Yaw rates evenly spaced over the policy's yaw-rate range.
    #[arg(long, value_name = "N", default_value = "5", value_parser = parse_count, allow_hyphen_values = true)]
    pub yaw_cells: usize,
    /// Forward speeds to map instead (m/s), e.g. -1,-0.5,0,0.5,1.
    #[arg(
        long,
        value_name = "LIST",
        conflicts_with = "vx_cells",
        allow_hyphen_values = true
    )]
    pub vx: Option<String>,
    /// Lateral speeds to map instead (m/s).
    #[arg(
        long,
        value_name = "LIST",
        conflicts_with = "vy_cells",
        allow_hyphen_values = true
    )]
    pub vy: Option<String>,
    /// Yaw rates to map instead (rad/s).
    #[arg(
        long,
        value_name = "LIST",
        conflicts_with = "yaw_cells",
        allow_hyphen_values = true
    )]
    pub yaw: Option<String>,
    /// Robots per cell, one episode each.
    #[arg(long, value_name = "N", default_value = "16", value_parser = parse_count, allow_hyphen_values = true)]
    pub robots: usize,
    /// Episode length in seconds (default: the checkpoint's, as `rall eval tracking`).
    #[arg(long, value_name = "S", allow_hyphen_values = true)]
    pub seconds: Option<f64>,
    /// Seed of the robots (randomisation draws, noise) and of the ground; every
    /// cell runs the same robots.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Worker threads (0 = all cores); the numbers do not depend on it.
    #[arg(long, default_value_t = 0)]
    pub threads: usize,
    /// Run every cell on this rung of the severity ladder: its friction, added mass
    /// and pushes on its rough ground, as the TTF benchmark applies them (default:
    /// flat ground, no pushes, the checkpoint's own randomisation).
    #[arg(long, value_name = "N")]
    pub severity: Option<usize>,
    /// A severity ladder file (default: the built-in experiments/severity-ladder.toml).
    #[arg(long, value_name = "FILE", requires = "severity")]
    pub ladder: Option<PathBuf>,
    /// A payload to carry: ball, frozen_arm or moving_arm (default none). A payload
    /// part on the ground counts as a fall, as in the TTF benchmark.
    #[arg(long)]
    pub load: Option<String>,
    /// A safe cell has a fall rate below this (percent) ...
    #[arg(
        long,
        value_name = "PCT",
        default_value_t = 5.0,
        allow_hyphen_values = true
    )]
    pub max_falls_pct: f64,
    /// ... and a linear tracking score of at least this.
    #[arg(
        long,
        value_name = "SCORE",
        default_value_t = 0.8,
        allow_hyphen_values = true
    )]
    pub min_tracking: f64,
    /// Write one row per cell (command, robots, falls, strict falls and the two
    /// tracking scores with their intervals, safe) to this CSV file.
    #[arg(long, value_name = "FILE")]
    pub csv: Option<PathBuf>,
    /// Draw the map to this SVG file: vx across, yaw rate up, one panel per vy,
    /// colour = fall rate, a black frame around each cell failing the threshold.
    #[arg(long, value_name = "FILE.svg")]
    pub figure: Option<PathBuf>,
    /// Write the whole map (every cell and robot, the grid and the options) as JSON.
    #[arg(long, value_name = "FILE")]
    pub json: Option<PathBuf>,
}

const COMMANDS_AFTER_HELP: &str = "\
Each cell runs --robots robots holding its command (vx, vy, yaw rate) for one episode with \
the policy's own observation noise, PD and randomisation (on a --severity rung: the rung's \
friction, added mass, pushes and rough ground); every cell runs the same robots. A fall is \
the env's termination (trunk tilted past its limit or on the ground) or a payload part on \
the ground; a strict fall is any non-foot part on the ground. Tracking is `rall eval \
tracking`'s score (1 = perfect). Rates carry 95% Wilson intervals, tracking a 95% bootstrap \
over robots. A cell is safe when its fall rate is below --max-falls-pct and its linear \
tracking at least --min-tracking (point estimates: at 5% and 16 robots, one fall fails a \
cell). Printed: the worst cell (most falls, then the lowest tracking), the safe share, and a \
table per vy value. Commands outside the policy's training ranges (or slower than the speed \
training zeroed) are allowed: they run, with a warning, and are marked ~ in the table and \
commanded_in_training = false in the CSV.

Example: rall eval commands --checkpoint policies/time-to-walk.safetensors --threads 1 \
--figure map.svg --csv map.csv";

/// A count given on the command line: a whole number, never negative.
fn parse_count(s: &str) -> std::result::Result<usize, String> {
    match s.trim().parse::<i64>() {
        Ok(n) if n < 0 => Err("a count cannot be negative".into()),
        Ok(n) => usize::try_from(n).map_err(|e| e.to_string()),
        Err(_) => Err("expected a whole number".into()),
    }
}

#[derive(Debug, Args)]
pub struct FallsArgs {
    /// Checkpoint (.safetensors) written by `rall train`; several compare them.
    #[arg(long, required_unless_present = "onnx")]
    pub checkpoint: Vec<PathBuf>,
    /// An ONNX policy: refused with the reason (this benchmark reads a critic, which an
    /// ONNX file does not hold).
    #[arg(long, value_name = "POLICY.onnx")]
    pub onnx: Option<PathBuf>,
    /// Robots walking at once.
    #[arg(long, default_value_t = 256)]
    pub robots: usize,
    /// Policy steps (50 Hz) each robot walks (episodes restart after a fall).
    #[arg(long, default_value_t = 750)]
    pub steps: usize,
    /// Steps before a fall that count as "before a fall" (25 = 0.5 s).
    #[arg(long, default_value_t = 25)]
    pub window: usize,
    #[arg(long, default_value_t = 4242)]
    pub seed: u64,
    /// Worker threads (0 = all cores).
    #[arg(long, default_value_t = 0)]
    pub threads: usize,
}

/// Options shared by the robustness benchmarks.
#[derive(Debug, Args)]
pub struct BenchmarkArgs {
    /// A policy to evaluate, as NAME=PATH (a checkpoint written by `rall train`, or an ONNX
    /// policy POLICY.onnx with its JSON sidecar POLICY.json beside it); repeat it. Each runs
    /// with its own checkpoint's (or sidecar's) observation noise, PD, commands and rewards.
    #[arg(long = "policy", value_name = "NAME=PATH")]
    pub policies: Vec<String>,
    /// Worker threads for the robots (0 = all cores).
    #[arg(long, default_value_t = 0)]
    pub threads: usize,
    /// Folder for the .md, .csv and .json results.
    #[arg(long, default_value = "eval-results")]
    pub out: PathBuf,
    /// Episode length in seconds (default: the checkpoint's; 8 s on the platform, 30 s on the race track).
    #[arg(long, value_name = "S")]
    pub episode_s: Option<f64>,
    /// Push force (N), period and hold (policy steps) of the evaluation pushes.
    #[arg(long, default_value_t = 100.0)]
    pub push_force: f64,
    #[arg(long, default_value_t = 300)]
    pub push_every: usize,
    #[arg(long, default_value_t = 50)]
    pub push_hold: usize,
    /// Turn off the friction and added-mass randomisation (paper table III ranges by default).
    #[arg(long)]
    pub no_randomization: bool,
    /// Rungs of the severity ladder to run, e.g. 0,1,2,3: rung 0 is the paper's protocol,
    /// each higher rung harder on every axis (printed with the results). Writes one table
    /// per rung (<benchmark>-severity<N>.*) and the curve (<benchmark>-curve.csv/.md).
    #[arg(long, value_name = "LIST", conflicts_with_all = ["push_force", "push_every"])]
    pub severity: Option<String>,
    /// A severity ladder file with every axis in every rung (default: the built-in
    /// experiments/severity-ladder.toml).
    #[arg(long, value_name = "FILE", requires = "severity")]
    pub ladder: Option<PathBuf>,
}

impl BenchmarkArgs {
    /// The ladder and the chosen rungs, or `None` without `--severity`.
    fn rungs(&self) -> Result<Option<(Ladder, Vec<usize>)>> {
        let Some(list) = &self.severity else {
            return Ok(None);
        };
        let ladder = match &self.ladder {
            Some(path) => Ladder::from_toml_file(path)?,
            None => Ladder::builtin(),
        };
        let rungs = ladder.parse_list(list)?;
        Ok(Some((ladder, rungs)))
    }
}

#[derive(Debug, Args)]
pub struct TtfArgs {
    #[command(flatten)]
    pub common: BenchmarkArgs,
    /// Trials with different seeds (scene and env).
    #[arg(long, default_value_t = 3)]
    pub seeds: usize,
    /// Robots per seed, one episode each (in parallel).
    #[arg(long, default_value_t = 10)]
    pub repeats: usize,
    /// First seed (the seeds are first, first + 1, ...).
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Fixed command "vx,vy,yaw_rate" instead of the checkpoint's random commands.
    #[arg(long, value_name = "VX,VY,WZ")]
    pub command: Option<String>,
    /// Loads to run (default all): ball, frozen_arm, moving_arm.
    #[arg(long = "load", value_name = "LOAD")]
    pub loads: Vec<String>,
    /// Amplitude of the random rough terrain (m).
    #[arg(long, default_value_t = 0.05, conflicts_with = "severity")]
    pub rough_amplitude: f64,
}

#[derive(Debug, Args)]
pub struct PlatformArgs {
    #[command(flatten)]
    pub common: BenchmarkArgs,
    /// Platform heights (m); repeat it (default 0.40 and 0.45; with --severity, the rung's).
    #[arg(long = "height", value_name = "M", conflicts_with = "severity")]
    pub heights: Vec<f64>,
    #[arg(long, default_value_t = 3)]
    pub seeds: usize,
    /// Robots per seed and height (in parallel).
    #[arg(long, default_value_t = 50)]
    pub repeats: usize,
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Forward speed command (m/s).
    #[arg(long, default_value_t = 0.6)]
    pub speed: f64,
    /// The robot must still be up this long after the drop (s).
    #[arg(long, default_value_t = 2.0)]
    pub settle_s: f64,
    /// Payload to carry on the drop (ball, frozen_arm, moving_arm; default none).
    #[arg(long)]
    pub load: Option<String>,
}

#[derive(Debug, Args)]
pub struct RaceArgs {
    #[command(flatten)]
    pub common: BenchmarkArgs,
    /// The meta controller: RISKY=PATH,SAFE=PATH,THRESHOLD=x[,HYSTERESIS=h][,HOLD=steps][,NAME=label].
    /// RISKY is the CVaR_1 policy whose critic's IQR drives the switch, SAFE the CVaR_0.5 one;
    /// PATH may be a checkpoint or the NAME of a --policy.
    #[arg(long, value_name = "SPEC")]
    pub meta: Option<String>,
    #[arg(long, default_value_t = 50)]
    pub agents: usize,
    /// Episodes per agent.
    #[arg(long, default_value_t = 10)]
    pub episodes: usize,
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Seed of the course's obstacles and rough patches.
    #[arg(long, default_value_t = 0)]
    pub course_seed: u64,
    /// Forward speed command (m/s).
    #[arg(long, default_value_t = 0.6)]
    pub speed: f64,
}

#[derive(Debug, Args)]
pub struct TrackingArgs {
    /// Checkpoint (.safetensors) written by `rall train`.
    #[arg(long, required_unless_present_any = ["run_dir", "onnx"], conflicts_with_all = ["run_dir", "onnx"])]
    pub checkpoint: Option<PathBuf>,
    /// An ONNX policy (trained anywhere) with its JSON sidecar POLICY.json beside it
    /// (see docs/outside-policies.md), instead of a checkpoint.
    #[arg(long, value_name = "POLICY.onnx", conflicts_with = "run_dir")]
    pub onnx: Option<PathBuf>,
    /// A tracking curve instead: every numbered checkpoint of this run directory, oldest
    /// first, one line each (and `--curve-csv`).
    #[arg(long, value_name = "DIR")]
    pub run_dir: Option<PathBuf>,
    /// With --run-dir: only checkpoints whose iteration is a multiple of K.
    #[arg(long, value_name = "K", default_value_t = 1, requires = "run_dir")]
    pub every: usize,
    /// With --run-dir: write the curve (iteration, env steps, wall clock, each figure
    /// with its 95% interval) to this CSV file.
    #[arg(long, value_name = "FILE", requires = "run_dir")]
    pub curve_csv: Option<PathBuf>,
    /// Robots, one full episode each (run in parallel).
    #[arg(long, default_value_t = 64)]
    pub episodes: usize,
    #[arg(long, default_value_t = 12345)]
    pub seed: u64,
    /// Worker threads (0 = all cores).
    #[arg(long, default_value_t = 0)]
    pub threads: usize,
    /// Sample actions from the policy's Gaussian as in training (default: its mean).
    #[arg(long)]
    pub stochastic: bool,
    /// Also write how each robot fell (one CSV row per fall: command, attitude,
    /// velocity and foot contacts at its last step, steps with a motor at its torque
    /// limit among the last 25, steps since the command last changed and the command
    /// before it, randomisation draws: friction, added mass, weakest and mean motor
    /// strength, PD gain factors, centre-of-mass offset) to this file.
    #[arg(long, value_name = "FILE")]
    pub falls_csv: Option<PathBuf>,
    /// Draw friction, added mass, motor strength, PD factors and centre of mass from this
    /// run config's [env.randomization] instead of the checkpoint's own (e.g.
    /// configs/baseline.toml, the paper's table III), so that policies trained under
    /// different randomisation are judged on the same ground. Pushes stay off.
    #[arg(long, value_name = "CONFIG")]
    pub randomization_from: Option<PathBuf>,
}

pub fn run(args: &EvalArgs) -> Result<()> {
    match &args.what {
        EvalCommand::Tracking(a) => tracking(a),
        EvalCommand::Ttf(a) => ttf(a),
        EvalCommand::Platform(a) => platform(a),
        EvalCommand::Race(a) => race(a),
        EvalCommand::Falls(a) => falls(a),
        EvalCommand::Commands(a) => commands(a),
    }
}

fn falls(a: &FallsArgs) -> Result<()> {
    anyhow::ensure!(
        a.robots > 0 && a.steps > 0 && a.window > 0,
        "--robots, --steps and --window must be at least 1"
    );
    println!(
        "{} robots x {} steps in each checkpoint's training env; \"before a fall\" = the last {} steps of an episode that ended in a fall",
        a.robots, a.steps, a.window
    );
    println!(
        "| checkpoint | iteration | falls | states | Z_0.01 | Z_0.05 | Z_0.25 | Z_0.5 | Z_0.75 | Z_0.95 | IQR |"
    );
    if let Some(onnx) = &a.onnx {
        anyhow::bail!(
            "--onnx {}: `rall eval falls` reads the critic's value distribution before falls, and an ONNX file holds the actor alone; `rall eval tracking --onnx` counts and describes its falls",
            onnx.display()
        );
    }
    println!("|---|---:|---:|---|---:|---:|---:|---:|---:|---:|---:|");
    for path in &a.checkpoint {
        let p = load_policy(path)?;
        anyhow::ensure!(
            !p.actor_only,
            "{} is an actor-only copy: `rall eval falls` reads the critic, which it does not hold; give the full checkpoint",
            path.display()
        );
        let r = crate::eval::critic_before_falls(
            &p.learner,
            &p.config,
            p.progress.terrain_levels.as_deref(),
            (a.robots, a.steps, a.window),
            worker_threads(a.threads),
            a.seed,
        )?;
        for (what, m) in [
            ("before a fall", &r.before_fall),
            ("elsewhere", &r.elsewhere),
        ] {
            let q: Vec<String> = m.quantiles.iter().map(|v| format!("{v:.3}")).collect();
            println!(
                "| {} | {} | {} | {what}: {} | {} | {:.3} |",
                path.display(),
                p.progress.iteration,
                r.falls,
                m.states,
                q.join(" | "),
                m.iqr
            );
        }
    }
    Ok(())
}

/// One checkpoint's tracking episodes under `a`'s settings, with 95% percentile
/// bootstrap intervals over robots (as `rall experiment` reports them).
struct Tracked {
    /// The checkpoint's progress (default for an ONNX policy).
    progress: Progress,
    report: TrackingReport,
    falls: Vec<FallRecord>,
    mode: ActionMode,
    estimates: TrackingEstimates,
}

fn track_checkpoint(a: &TrackingArgs, checkpoint: &Path) -> Result<Tracked> {
    anyhow::ensure!(a.episodes > 0, "--episodes must be at least 1");
    let (policy, training_env, progress) = if is_onnx(checkpoint) {
        let p = NamedPolicy::load("policy", checkpoint)?;
        (p.policy, p.env, Progress::default())
    } else {
        let p = load_policy(checkpoint)?;
        (
            Policy::Checkpoint(Box::new(p.learner)),
            p.config.env,
            p.progress,
        )
    };
    let mut env = tracking_env(&training_env);
    if let Some(path) = &a.randomization_from {
        let from = TrainConfig::from_toml_file(path)
            .with_context(|| format!("--randomization-from {}", path.display()))?;
        env = with_randomization(env, &from.env.randomization);
    }
    let mode = if a.stochastic {
        ActionMode::Sampled
    } else {
        ActionMode::Mean
    };
    let (report, falls) = evaluate_tracking_with_falls(
        &policy,
        &env,
        a.episodes,
        worker_threads(a.threads),
        a.seed,
        mode,
    )?;
    let estimates = TrackingEstimates::new(&report, 1000, 0.95, |_| a.seed);
    Ok(Tracked {
        progress,
        report,
        falls,
        mode,
        estimates,
    })
}

fn tracking(a: &TrackingArgs) -> Result<()> {
    match (a.checkpoint.as_ref().or(a.onnx.as_ref()), &a.run_dir) {
        (Some(checkpoint), _) => tracking_one(a, checkpoint),
        (None, Some(dir)) => tracking_curve(a, dir),
        (None, None) => anyhow::bail!("give --checkpoint PATH or --run-dir DIR"),
    }
}

/// Every numbered checkpoint of a run: a line each, and a CSV.
fn tracking_curve(a: &TrackingArgs, dir: &Path) -> Result<()> {
    anyhow::ensure!(a.every > 0, "--every must be at least 1");
    let checkpoints: Vec<(usize, PathBuf)> = RunDir {
        root: dir.to_path_buf(),
    }
    .checkpoints_by_iteration()
    .into_iter()
    .filter(|(it, _)| it % a.every == 0)
    .collect();
    anyhow::ensure!(
        !checkpoints.is_empty(),
        "{} has no checkpoints/model_<iteration>.safetensors{}",
        dir.display(),
        if a.every > 1 {
            format!(" at a multiple of {} iterations", a.every)
        } else {
            String::new()
        }
    );
    let mut csv = String::from("iteration,env_steps,wall_clock_min,lin_tracking,lin_tracking_lo,lin_tracking_hi,yaw_tracking,yaw_tracking_lo,yaw_tracking_hi,fall_rate,fall_rate_lo,fall_rate_hi\n");
    println!(
        "{} episodes each, seed {}; 95% bootstrap over robots; * = meets linear >= 0.8, yaw >= 0.7, falls < 5%",
        a.episodes, a.seed
    );
    println!(
        "{:>9} {:>10} {:>8}  {:<21} {:<21} {:<20}",
        "iteration", "env steps", "minutes", "lin", "yaw", "falls %"
    );
    for (_, path) in &checkpoints {
        let Tracked {
            progress: p,
            estimates,
            ..
        } = track_checkpoint(a, path)?;
        println!(
            "{:>9} {:>10} {:>8.1}  {:<21} {:<21} {:<20}{}",
            p.iteration,
            p.total_env_steps,
            p.wall_s / 60.0,
            estimates.lin.show(3),
            estimates.yaw.show(3),
            estimates.falls.percent().show(1),
            if estimates.meets_targets() { " *" } else { "" }
        );
        csv.push_str(&format!(
            "{},{},{:.2},{}\n",
            p.iteration,
            p.total_env_steps,
            p.wall_s / 60.0,
            estimates.csv()
        ));
    }
    if let Some(path) = &a.curve_csv {
        crate::fsio::write_atomic(path, csv.as_bytes())?;
        println!("curve -> {}", path.display());
    }
    Ok(())
}

fn tracking_one(a: &TrackingArgs, checkpoint: &Path) -> Result<()> {
    let Tracked {
        progress,
        report: r,
        falls,
        mode,
        estimates,
    } = track_checkpoint(a, checkpoint)?;
    if is_onnx(checkpoint) {
        println!(
            "ONNX policy {} (env from its sidecar)",
            checkpoint.display()
        );
    } else {
        println!(
            "checkpoint {} (iteration {}, {} env steps)",
            checkpoint.display(),
            progress.iteration,
            progress.total_env_steps
        );
    }
    println!("episodes             {} ({:?} actions)", r.episodes, mode);
    if let Some(path) = &a.randomization_from {
        println!("randomisation        of {}", path.display());
    }
    println!(
        "lin-vel tracking     {}   (mean exp(-|v_cmd - v|^2 / sigma), 1 = perfect; 95% bootstrap over robots)",
        estimates.lin.show(3)
    );
    println!("yaw-rate tracking    {}", estimates.yaw.show(3));
    println!(
        "fall rate            {}   (trunk contact {}, tilt {}, physics failure {})",
        estimates.falls.show_percent(),
        r.trunk_contacts,
        r.tilts,
        r.unstable
    );
    println!(
        "mean episode length  {:.0} / {} steps",
        r.mean_episode_length_steps, r.max_episode_length_steps
    );
    if !falls.is_empty() {
        let count = |d: &str| falls.iter().filter(|f| f.direction() == d).count();
        println!(
            "falls by direction   nose down {}, nose up {}, left side down {}, right side down {}",
            count("nose down"),
            count("nose up"),
            count("left side down"),
            count("right side down")
        );
    }
    if let Some(path) = &a.falls_csv {
        let mut text = String::from(FallRecord::CSV_HEADER);
        text.push('\n');
        for f in &falls {
            text.push_str(&f.csv_row());
            text.push('\n');
        }
        crate::fsio::write_atomic(path, text.as_bytes())?;
        println!(
            "falls                {} rows -> {}",
            falls.len(),
            path.display()
        );
    }
    Ok(())
}

/// The `--policy` list of a benchmark run `seeds` x `repeats` times, checked.
fn repeated_policies(args: &[String], seeds: usize, repeats: usize) -> Result<Vec<NamedPolicy>> {
    let policies = load_policies(args)?;
    anyhow::ensure!(!policies.is_empty(), "give at least one --policy NAME=PATH");
    anyhow::ensure!(
        seeds > 0 && repeats > 0,
        "--seeds and --repeats must be at least 1"
    );
    Ok(policies)
}

fn load_policies(args: &[String]) -> Result<Vec<NamedPolicy>> {
    let mut out: Vec<NamedPolicy> = Vec::new();
    for a in args {
        let (name, path) = NamedPolicy::parse_arg(a)?;
        anyhow::ensure!(
            out.iter().all(|p| p.name != name),
            "--policy {name} is given twice"
        );
        out.push(NamedPolicy::load(&name, &path)?);
    }
    Ok(out)
}

fn scenario_params(c: &BenchmarkArgs) -> Result<ScenarioParams> {
    anyhow::ensure!(
        c.push_every > 0 && c.push_hold <= c.push_every,
        "--push-hold must be <= --push-every (> 0)"
    );
    let mut p = ScenarioParams {
        episode_length_s: c.episode_s,
        push_force_n: c.push_force,
        push_every_steps: c.push_every,
        push_hold_steps: c.push_hold,
        ..ScenarioParams::default()
    };
    if c.no_randomization {
        p.friction = None;
        p.added_base_mass_kg = None;
    }
    Ok(p)
}

fn parse_load(s: &str) -> Result<Load> {
    Ok(match s.trim() {
        "ball" => Load::Ball,
        "frozen_arm" | "frozen-arm" => Load::FrozenArm,
        "moving_arm" | "moving-arm" => Load::MovingArm,
        "none" => Load::None,
        other => anyhow::bail!("unknown load {other:?} (ball, frozen_arm, moving_arm, none)"),
    })
}

fn seeds(first: u64, n: usize) -> Vec<u64> {
    (0..n as u64).map(|i| first + i).collect()
}

fn finish(
    out: &std::path::Path,
    stem: &str,
    md: &str,
    csv: &str,
    json: &serde_json::Value,
) -> Result<()> {
    println!("\n{md}");
    let files = write_outputs(out, stem, md, csv, json)?;
    let names: Vec<String> = files.iter().map(|f| f.display().to_string()).collect();
    println!("wrote {}", names.join(", "));
    Ok(())
}

fn ttf(a: &TtfArgs) -> Result<()> {
    let policies = repeated_policies(&a.common.policies, a.seeds, a.repeats)?;
    let mut params = scenario_params(&a.common)?;
    params.rough.amplitude_m = a.rough_amplitude;
    if let Some(c) = &a.command {
        let v: Vec<f64> = c
            .split(',')
            .map(|x| x.trim().parse::<f64>())
            .collect::<std::result::Result<_, _>>()
            .map_err(|_| anyhow::anyhow!("--command {c:?}: expected VX,VY,WZ"))?;
        anyhow::ensure!(v.len() == 3, "--command {c:?}: expected VX,VY,WZ");
        params.command = Some([v[0], v[1], v[2]]);
    }
    let loads = if a.loads.is_empty() {
        Load::PAYLOADS.to_vec()
    } else {
        a.loads
            .iter()
            .map(|l| parse_load(l))
            .collect::<Result<_>>()?
    };
    let opts = TtfOptions {
        seeds: seeds(a.seed, a.seeds),
        repeats: a.repeats,
        threads: worker_threads(a.common.threads),
        loads,
        terrains: vec![GroundKind::Flat, GroundKind::Rough],
        pushes: vec![false, true],
        params,
    };
    let run = |opts: &TtfOptions| {
        evaluate_ttf(&policies, opts, |c| {
            eprintln!(
                "{:<12} {:<7} push {:<5} {:<12} TTF {:.3}, strict {:.3} ({} of {} robots fell, {} strictly; progress along the command {:.0}% of the commanded path)",
                c.load.name(),
                c.terrain,
                c.push,
                c.policy,
                c.ttf,
                c.strict_ttf,
                c.falls,
                c.robots,
                c.strict_falls,
                100.0 * c.progress_ratio
            )
        })
    };
    let Some((ladder, rungs)) = a.common.rungs()? else {
        let report = run(&opts)?;
        return finish_report(&a.common.out, "ttf", &report);
    };
    run_ladder(&a.common.out, "ttf", &ladder, &rungs, |s, rung| {
        let report = run(&TtfOptions {
            params: rung.apply(&opts.params),
            ..opts.clone()
        })?;
        let mut points = Vec::new();
        for p in &policies {
            let one = [p.name.clone()];
            let r = Resampling::default();
            points.extend(ttf_point(&report, &one, &p.name, s, false, r));
            points.extend(ttf_point(&report, &one, &p.name, s, true, r));
        }
        Ok((report.markdown(), report.csv(), report.json(), points))
    })
}

/// A benchmark's report as the three files `finish` writes.
trait Tables {
    fn markdown(&self) -> String;
    fn csv(&self) -> String;
    fn json(&self) -> serde_json::Value;
}

macro_rules! tables {
    ($($t:ty),*) => {$(
        impl Tables for $t {
            fn markdown(&self) -> String {
                <$t>::markdown(self)
            }
            fn csv(&self) -> String {
                <$t>::csv(self)
            }
            fn json(&self) -> serde_json::Value {
                <$t>::json(self)
            }
        }
    )*};
}
tables!(
    crate::eval::TtfReport,
    crate::eval::PlatformReport,
    crate::eval::RaceReport
);

fn finish_report(out: &Path, stem: &str, report: &impl Tables) -> Result<()> {
    finish(out, stem, &report.markdown(), &report.csv(), &report.json())
}

/// One rung's table (markdown, CSV, JSON) and curve points.
type RungOutput = (String, String, serde_json::Value, Vec<CurvePoint>);

/// Runs `one` on every chosen rung, then writes every rung's table and the curve.
fn run_ladder(
    out: &Path,
    benchmark: &str,
    ladder: &Ladder,
    rungs: &[usize],
    mut one: impl FnMut(usize, &crate::eval::Rung) -> Result<RungOutput>,
) -> Result<()> {
    let mut outputs = Vec::new();
    let mut points = Vec::new();
    for &s in rungs {
        eprintln!("severity rung {s}");
        let (md, csv, json, p) = one(s, ladder.rung(s)?)?;
        let md = format!("Severity rung {s}\n\n{}\n{md}", ladder.markdown(&[s]));
        outputs.push((format!("{benchmark}-severity{s}"), md, csv, json));
        points.extend(p);
    }
    finish_ladder(out, benchmark, ladder, rungs, outputs, &points)
}

/// Writes every rung's table and the curve, once every rung has been evaluated
/// (a failed rung writes nothing).
fn finish_ladder(
    out: &Path,
    benchmark: &str,
    ladder: &Ladder,
    rungs: &[usize],
    outputs: Vec<(String, String, String, serde_json::Value)>,
    points: &[CurvePoint],
) -> Result<()> {
    for (stem, md, csv, json) in &outputs {
        finish(out, stem, md, csv, json)?;
    }
    let mut md = format!("Severity ladder\n\n{}\n", ladder.markdown(rungs));
    let mut metrics: Vec<&str> = Vec::new();
    for p in points {
        if !metrics.contains(&p.metric) {
            metrics.push(p.metric);
        }
    }
    for m in metrics {
        let these: Vec<CurvePoint> = points.iter().filter(|p| p.metric == m).cloned().collect();
        let digits = if m == "ttf" || m == "strict_ttf" {
            3
        } else {
            1
        };
        md.push_str(&format!(
            "\n{benchmark}: {m} against severity (95% bootstrap over robots)\n\n{}",
            curve_markdown(&these, digits)
        ));
    }
    if benchmark != "race" {
        md.push_str(&format!("\n{FALL_DEFINITION}\n"));
    }
    let json = serde_json::json!({ "ladder": ladder, "rungs": rungs, "points": points });
    finish(
        out,
        &format!("{benchmark}-curve"),
        &md,
        &curve_csv(points),
        &json,
    )
}

fn platform(a: &PlatformArgs) -> Result<()> {
    let policies = repeated_policies(&a.common.policies, a.seeds, a.repeats)?;
    let mut params = scenario_params(&a.common)?;
    params.forward_mps = a.speed;
    let heights = if a.heights.is_empty() {
        vec![0.40, 0.45]
    } else {
        a.heights.clone()
    };
    for &h in &heights {
        anyhow::ensure!(h > 0.0 && h < 2.0, "--height {h}: must be in (0, 2) m");
    }
    let opts = PlatformOptions {
        heights_m: heights,
        seeds: seeds(a.seed, a.seeds),
        repeats: a.repeats,
        threads: worker_threads(a.common.threads),
        settle_s: a.settle_s,
        load: a
            .load
            .as_deref()
            .map(parse_load)
            .transpose()?
            .unwrap_or(Load::None),
        params,
    };
    let run = |opts: &PlatformOptions| {
        evaluate_platform(&policies, opts, |c| {
            eprintln!(
                "{:.2} m  {:<12} success {:.1}% ({} of {}; fell {}, not landed {}, fell before the edge {}, not reached {}; ends {:?})",
                c.height_m,
                c.policy,
                c.success_pct,
                c.success,
                c.robots,
                c.fell,
                c.not_landed,
                c.fell_before_drop,
                c.not_reached,
                c.ends
            )
        })
    };
    let Some((ladder, rungs)) = a.common.rungs()? else {
        let report = run(&opts)?;
        return finish_report(&a.common.out, "platform", &report);
    };
    run_ladder(&a.common.out, "platform", &ladder, &rungs, |s, rung| {
        let report = run(&PlatformOptions {
            heights_m: rung.platform_heights_m.clone(),
            params: rung.apply(&opts.params),
            ..opts.clone()
        })?;
        let mut points = Vec::new();
        for p in &policies {
            let one = [p.name.clone()];
            points.extend(platform_point(
                &report,
                &one,
                &p.name,
                s,
                Resampling::default(),
            ));
        }
        Ok((report.markdown(), report.csv(), report.json(), points))
    })
}

fn race(a: &RaceArgs) -> Result<()> {
    let mut policies = load_policies(&a.common.policies)?;
    let meta = match &a.meta {
        None => None,
        Some(spec) => {
            let m = MetaArg::parse(spec)?;
            // A path not given as a --policy becomes a row of its own, named by its role.
            let mut resolve = |role: &str, v: &str| -> Result<String> {
                if policies.iter().any(|p| p.name == v) {
                    return Ok(v.to_string());
                }
                let path = std::path::Path::new(v);
                if let Some(p) = policies.iter().find(|p| p.path.as_deref() == Some(path)) {
                    return Ok(p.name.clone());
                }
                let name = if policies.iter().any(|p| p.name == role) {
                    format!("{role}:{v}")
                } else {
                    role.to_string()
                };
                policies.push(NamedPolicy::load(&name, path)?);
                Ok(name)
            };
            let risky = resolve("RISKY", &m.risky)?;
            let safe = resolve("SAFE", &m.safe)?;
            let rp = policies.iter().find(|p| p.name == risky).expect("resolved");
            let rp = rp
                .critic()
                .context("--meta RISKY: the switch reads its critic's IQR")?;
            let critic = rp.config().critic;
            if !critic.has_quantiles() {
                eprintln!("warning: the RISKY policy {risky} has a {critic} critic: its IQR is 0, the meta controller never switches");
            }
            let risk = rp.config().distortion();
            if risk != (Distortion::Cvar { eta: 1.0 }) {
                eprintln!(
                    "note: the RISKY policy {risky} follows {risk:?} (the paper's RISKY is CVaR_1)"
                );
            }
            Some(MetaConfig {
                name: m.name,
                risky,
                safe,
                threshold: m.threshold,
                hysteresis: m.hysteresis,
                min_safe_steps: m.min_safe_steps,
            })
        }
    };
    anyhow::ensure!(
        !policies.is_empty(),
        "give at least one --policy NAME=PATH or --meta"
    );
    let mut params = scenario_params(&a.common)?;
    params.forward_mps = a.speed;
    let opts = RaceOptions {
        agents: a.agents,
        episodes: a.episodes,
        threads: worker_threads(a.common.threads),
        seed: a.seed,
        course_seed: a.course_seed,
        params,
    };
    let run = |opts: &RaceOptions| {
        evaluate_race(&policies, meta.as_slice(), opts, |r| {
            eprintln!(
                "{:<16} returns q0.25 {:.3}  q0.5 {:.3}  q0.75 {:.3}  ({} episodes, {:.1}% falls)",
                r.name,
                r.q25,
                r.q50,
                r.q75,
                r.episodes,
                100.0 * r.fall_fraction
            )
        })
    };
    let Some((ladder, rungs)) = a.common.rungs()? else {
        let report = run(&opts)?;
        return finish_report(&a.common.out, "race", &report);
    };
    run_ladder(&a.common.out, "race", &ladder, &rungs, |s, rung| {
        let report = run(&RaceOptions {
            params: rung.apply_race(&opts.params),
            ..opts.clone()
        })?;
        let mut points = Vec::new();
        for row in &report.rows {
            let one = [row.name.clone()];
            points.extend(race_point(
                &report,
                &one,
                &row.name,
                s,
                Resampling::default(),
            ));
        }
        Ok((report.markdown(), report.csv(), report.json(), points))
    })
}

/// The grid of `a` over the policy's command `ranges`.
fn command_grid(a: &CommandsArgs, ranges: &CommandConfig) -> Result<CommandGrid> {
    let axis = |values: &Option<String>, flag: &str, cells: usize| -> Result<AxisSpec> {
        Ok(match values {
            Some(text) => AxisSpec::Values(parse_axis_values(flag, text)?),
            None => AxisSpec::Cells(cells),
        })
    };
    let vx = axis(&a.vx, "--vx", a.vx_cells)?;
    let vy = axis(&a.vy, "--vy", a.vy_cells)?;
    let yaw = axis(&a.yaw, "--yaw", a.yaw_cells)?;
    CommandGrid::from_specs([&vx, &vy, &yaw], ranges)
}

/// The map's options from `a`, the severity rung read from its ladder.
fn command_map_options(a: &CommandsArgs) -> Result<CommandMapOptions> {
    let severity = match a.severity {
        None => None,
        Some(index) => {
            let ladder = match &a.ladder {
                Some(path) => Ladder::from_toml_file(path)?,
                None => Ladder::builtin(),
            };
            let rung = ladder.rung(index).context("--severity")?.clone();
            Some(SeverityRung { index, rung })
        }
    };
    let options = CommandMapOptions {
        robots: a.robots,
        seed: a.seed,
        episode_length_s: a.seconds,
        load: a
            .load
            .as_deref()
            .map(parse_load)
            .transpose()
            .context("--load")?
            .unwrap_or(Load::None),
        severity,
        ..CommandMapOptions::default()
    };
    Ok(options)
}

fn commands(a: &CommandsArgs) -> Result<()> {
    let threshold = SafetyThreshold::new(a.max_falls_pct, a.min_tracking)?;
    let options = command_map_options(a)?;
    let path = a
        .checkpoint
        .as_ref()
        .or(a.onnx.as_ref())
        .context("give --checkpoint FILE or --onnx FILE")?;
    let policy = NamedPolicy::load("policy", path)?;
    let ranges = &policy.env.commands;
    let grid = command_grid(a, ranges)?;
    for w in grid.untrained_commands(ranges) {
        eprintln!("warning: {w}; its cells run and are marked ~");
    }
    eprintln!(
        "mapping {} cells ({} vx x {} vy x {} yaw rate) of {} robots each: {}, seed {}",
        grid.len(),
        grid.vx_mps.len(),
        grid.vy_mps.len(),
        grid.yaw_rate_rad_s.len(),
        options.robots,
        options.describe(),
        options.seed
    );
    let map = evaluate_command_map(
        &policy.policy,
        &policy.env,
        &grid,
        &options,
        worker_threads(a.threads),
    )?;
    println!("{}", map.summary(&threshold));
    let seconds = map.episode_steps as f64 * policy.env.control.policy_dt_s();
    let show = |r: [f64; 2]| format!("[{}, {}]", r[0], r[1]);
    println!(
        "\npolicy {} ({}): command ranges vx {} m/s, vy {} m/s, yaw rate {} rad/s",
        path.display(),
        if is_onnx(path) {
            "ONNX, env from its sidecar"
        } else {
            "checkpoint"
        },
        show(ranges.vx_mps),
        show(ranges.vy_mps),
        show(ranges.yaw_rate_rad_s)
    );
    println!(
        "{} cells x {} robots, one {seconds:.1} s episode ({} steps) each; {}; seed {}; falls with 95% Wilson intervals, tracking with 95% bootstrap over robots",
        map.cells.len(),
        options.robots,
        map.episode_steps,
        options.describe(),
        options.seed
    );
    println!("\n{}", map.table(&threshold));
    println!("{FALL_DEFINITION}");
    if let Some(file) = &a.csv {
        crate::fsio::write_atomic(file, map.to_csv(&threshold).as_bytes())?;
        println!("cells -> {}", file.display());
    }
    if let Some(file) = &a.json {
        let text = serde_json::to_string_pretty(&map)? + "\n";
        crate::fsio::write_atomic(file, text.as_bytes())?;
        println!("map -> {}", file.display());
    }
    if let Some(file) = &a.figure {
        write_command_map_svg(&map, &threshold, file)?;
        println!("figure -> {}", file.display());
    }
    Ok(())
}
