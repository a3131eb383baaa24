//! A `play` episode (default networks, flat ground, 20 s = 1000 policy steps) with
//! rerun logging to an .rrd file versus without logging, side by side:
//!
//! - `no recording`: policy + physics only (what `play` costs without a viewer);
//! - `disabled recording`: everything the logger does (critic read, columns built)
//!   with rerun's disabled stream (no serialisation, no I/O);
//! - `recording to file`: the full thing, as `rall play --save` (the critic read
//!   and logged every `VALUE_EVERY_FRAMES` frames);
//! - `recording to file, value every step`: the same with the critic read and
//!   logged every policy step (what `value_every_frames = 1` does).
//!
//! After criterion, runs every variant once per round for `PLAY_BENCH_ROUNDS` (21)
//! rounds and prints each overhead as the median and quartiles of its ratio to the
//! same round's run without a recording (paired, so a busy spell on the shared
//! machine hits both sides), a recording's fixed cost (open with the layout, then
//! finish, with no steps) and the .rrd size per simulated minute.
//!
//! `cargo bench --bench play` (the side-by-side part alone: `cargo bench --bench play -- none`)

/// The allocator the `rall` binary runs with (large buffers on huge pages).
#[global_allocator]
static ALLOCATOR: rall::memory::HugePageAlloc = rall::memory::HugePageAlloc;

use std::hint::black_box;
use std::path::Path;
use std::time::{Duration, Instant};

use criterion::Criterion;
use rall::env::{EnvConfig, ACT_DIM, OBS_DIM};
use rall::learn::{Learner, LearnerConfig};
use rall::viz::{self, PlayOptions, RerunTarget};

const STEPS: usize = 1000;

fn setup() -> (Learner, EnvConfig, PlayOptions) {
    let learner = Learner::new(OBS_DIM, ACT_DIM, &LearnerConfig::default(), 0).expect("learner");
    let mut env = EnvConfig::default();
    env.terrain.kind = rall::env::terrain::TerrainKind::Flat;
    env.episode.length_s = STEPS as f64 * env.control.policy_dt_s();
    let opts = PlayOptions {
        episodes: 1,
        max_steps: Some(STEPS),
        ..PlayOptions::default()
    };
    (learner, env, opts)
}

/// Plays until `STEPS` policy steps are simulated (a new episode if the robot
/// falls), all into one recording; returns the steps.
fn run(
    learner: &Learner,
    env: &EnvConfig,
    opts: &PlayOptions,
    mut rec: Option<rerun::RecordingStream>,
) -> usize {
    let (mut total, mut seed) = (0, opts.seed);
    while total < STEPS {
        let o = PlayOptions {
            episodes: 1,
            seed,
            max_steps: Some(STEPS - total),
            ..opts.clone()
        };
        let (report, back) = viz::play(learner, env, &o, rec).expect("play");
        total += black_box(report).policy_steps;
        rec = back;
        seed += 1;
    }
    if let Some(rec) = rec {
        viz::finish_recording(rec).expect("finish");
    }
    total
}

fn file_recording(path: &Path) -> rerun::RecordingStream {
    viz::open_recording(
        viz::PLAY_APP_ID,
        "bench",
        &RerunTarget::Save(path.into()),
        viz::play_blueprint(),
    )
    .expect("recording")
}

fn main() {
    let (learner, env, opts) = setup();
    let dir = tempfile::tempdir().expect("tempdir");
    let path = dir.path().join("bench.rrd");
    let mut c = Criterion::default()
        .configure_from_args()
        .sample_size(10)
        .measurement_time(Duration::from_secs(20));
    {
        let mut g = c.benchmark_group(format!("play {STEPS} steps"));
        g.bench_function("no recording", |b| {
            b.iter(|| run(&learner, &env, &opts, None))
        });
        g.bench_function("disabled recording", |b| {
            b.iter(|| {
                run(
                    &learner,
                    &env,
                    &opts,
                    Some(rerun::RecordingStream::disabled()),
                )
            })
        });
        g.bench_function("recording to file", |b| {
            b.iter(|| run(&learner, &env, &opts, Some(file_recording(&path))))
        });
        g.finish();
    }
    c.final_summary();

    // Side by side, interleaved (the machine may be busy): every round runs each
    // variant once, and the overheads are the medians (and quartiles) over rounds of
    // the ratio to that round's run without a recording.
    let every_step = PlayOptions {
        value_every_frames: 1,
        ..opts.clone()
    };
    let rounds: usize = std::env::var("PLAY_BENCH_ROUNDS")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(21);
    let mut t = [Vec::new(), Vec::new(), Vec::new(), Vec::new(), Vec::new()];
    for _ in 0..rounds {
        for (k, times) in t.iter_mut().enumerate() {
            let t0 = Instant::now();
            match k {
                0 => run(&learner, &env, &opts, None),
                1 => run(
                    &learner,
                    &env,
                    &opts,
                    Some(rerun::RecordingStream::disabled()),
                ),
                2 => run(&learner, &env, &opts, Some(file_recording(&path))),
                3 => run(
                    &learner,
                    &env,
                    &every_step,
                    Some(file_recording(&dir.path().join("every-step.rrd"))),
                ),
                // A recording's fixed cost: open (threads, file, layout) and finish.
                _ => {
                    let rec = file_recording(&dir.path().join("empty.rrd"));
                    viz::finish_recording(rec).expect("finish");
                    0
                }
            };
            times.push(t0.elapsed().as_secs_f64());
        }
    }
    let quartiles = |mut v: Vec<f64>| {
        v.sort_by(|a, b| a.total_cmp(b));
        let n = v.len();
        (v[n / 4], v[n / 2], v[(3 * n) / 4])
    };
    let ratio_to =
        |k: usize, base: usize| quartiles(t[k].iter().zip(&t[base]).map(|(a, b)| a / b).collect());
    let median = |k: usize| quartiles(t[k].clone()).1;
    let (none, disabled, file, file_every, empty) =
        (median(0), median(1), median(2), median(3), median(4));
    let sim_min = STEPS as f64 * env.control.policy_dt_s() / 60.0;
    let bytes = std::fs::metadata(&path).map(|m| m.len()).unwrap_or(0);
    println!(
        "\nplay, {STEPS} policy steps ({:.1} s simulated), {rounds} interleaved rounds (medians):",
        sim_min * 60.0
    );
    println!(
        "  no recording       {:8.1} ms  ({:.0} steps/s)",
        none * 1e3,
        STEPS as f64 / none
    );
    println!(
        "  disabled recording {:8.1} ms  (critic + logger, no rerun I/O)",
        disabled * 1e3
    );
    println!(
        "  recording to file  {:8.1} ms  (critic every {} frames)",
        file * 1e3,
        viz::episode::VALUE_EVERY_FRAMES
    );
    println!("  same, critic every step {:8.1} ms", file_every * 1e3);
    let show = |label: &str, (q1, q2, q3): (f64, f64, f64)| {
        println!(
            "  {label:52} {:+5.1}%  (quartiles {:+.1}% .. {:+.1}%)",
            (q2 - 1.0) * 100.0,
            (q1 - 1.0) * 100.0,
            (q3 - 1.0) * 100.0
        );
    };
    show(
        "overhead of logging to a file vs no recording:",
        ratio_to(2, 0),
    );
    show("the same with the critic read every step:", ratio_to(3, 0));
    show(
        "critic + logger without rerun I/O vs no recording:",
        ratio_to(1, 0),
    );
    println!(
        "  a recording's fixed cost (open, layout, finish, nothing logged): {:.1} ms, {:.1}% of no recording",
        empty * 1e3,
        empty / none * 100.0
    );
    println!(
        "  .rrd size: {:.2} MB for {:.2} simulated min = {:.2} MB per simulated minute",
        bytes as f64 / 1e6,
        sim_min,
        bytes as f64 / 1e6 / sim_min
    );
}
