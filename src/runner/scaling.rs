//! `rall bench scaling`: where an iteration's time goes on 1 and 2 threads, and a
//! projection of a training iteration to more cores, so a user can size a
//! workstation. The measurement ([`measure`]) runs real iterations (collection
//! through `VecEnv`, the PPO update) of a config; the projection ([`project`]) is
//! plain arithmetic on the measured phase times, tested on given numbers.
//!
//! The model, stated beside its numbers by [`ASSUMPTIONS`]:
//! - **Amdahl per phase.** A phase measured at `t1` on one thread and `t2` on two
//!   has the serial fraction `s = 2 t2 / t1 - 1` (clamped to `[0, 1]`): the two
//!   measurements fit `t(n) = t1 (s + (1 - s) / n)` exactly, so noise in `t2` moves
//!   `s` directly (measure on a quiet machine).
//! - **Work grows with the envs.** The projected machine runs `envs_per_core` envs
//!   per core (by default the measured envs over 2), the same steps per env and the
//!   same number of mini-batches, so every phase that works per sample (physics,
//!   task, resets, inference, storage, the critic pass over the rollout, gathering,
//!   forward, loss, backward) has `cores x envs_per_core / envs` times the work; its
//!   serial part grows with it (Gustafson's workload, Amdahl's serial part: a
//!   serial loop over envs or samples stays serial). Gradient clipping and Adam work
//!   per parameter and keep their size.
//! - **GEMM by thread count.** The matrix products inside the update's forward and
//!   backward passes run in one shard of rows per thread, so they have no serial
//!   part: `t(n) = t1 x work / (n x efficiency)`, the efficiency per core given
//!   (default: the measured 2-thread one, `t1 / (2 t2)`, capped at 1).
//! - Not modelled: memory bandwidth shared by many cores, SMT, clock changes with
//!   load, NUMA; one process (several MPI ranks add the all-reduce of
//!   `rall bench comm`). A larger batch changes learning, not only speed.

use std::sync::Arc;
use std::time::Instant;

use anyhow::{Context, Result};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

use crate::config::TrainConfig;
use crate::env::{build_scene, VecEnv, ACT_DIM};
use crate::learn::{mat, Learner, Rollout};

/// The model's assumptions, printed beside the projection.
pub const ASSUMPTIONS: &str = "\
assumptions: each phase follows Amdahl's law with the serial fraction s = 2 t2/t1 - 1 \
fitted to the 1- and 2-thread times (clamped to [0, 1]; noise in t2 moves s directly); \
the projected machine runs envs_per_core envs per core with the same steps per env and \
mini-batch count, so per-sample phases get cores x envs_per_core / envs times the work \
(their serial part too) while clip and Adam (per parameter) keep theirs; the update's \
GEMMs run one shard per thread with no serial part, at the stated efficiency per core; \
memory bandwidth, SMT, clock changes, NUMA and MPI are not modelled";

/// How a phase's work grows on the projected machine.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Growth {
    /// Work per env or sample; Amdahl with the measured serial fraction.
    PerSample,
    /// Work per parameter (clip, Adam): constant; Amdahl.
    PerParameter,
    /// The update's GEMMs in per-thread shards: per sample, no serial part,
    /// parallel at the stated efficiency.
    ShardedGemm,
}

/// One phase's measured wall time per iteration on 1 and 2 threads.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Phase {
    pub name: &'static str,
    /// Part of collection (else of learning).
    pub collect: bool,
    pub growth: Growth,
    pub t1_s: f64,
    pub t2_s: f64,
}

impl Phase {
    /// Amdahl's serial fraction fitted to the two times, in `[0, 1]`.
    pub fn serial_fraction(&self) -> f64 {
        if self.t1_s <= 0.0 {
            return 0.0;
        }
        (2.0 * self.t2_s / self.t1_s - 1.0).clamp(0.0, 1.0)
    }
}

/// The projected machine.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Target {
    pub cores: usize,
    /// Envs of the measurement.
    pub envs_measured: usize,
    pub envs_per_core: f64,
    /// Parallel efficiency per core of the sharded GEMMs (1 = perfect).
    pub gemm_efficiency: f64,
}

/// Projected seconds per iteration of one phase on `t.cores` cores.
pub fn project_phase(p: &Phase, t: &Target) -> f64 {
    let n = t.cores.max(1) as f64;
    let work = match p.growth {
        Growth::PerParameter => 1.0,
        _ => n * t.envs_per_core / t.envs_measured.max(1) as f64,
    };
    match p.growth {
        Growth::ShardedGemm => p.t1_s * work / (n * t.gemm_efficiency.clamp(1e-3, 1.0)),
        _ => {
            let s = p.serial_fraction();
            p.t1_s * work * (s + (1.0 - s) / n)
        }
    }
}

/// One projected machine's iteration.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Projection {
    pub cores: usize,
    pub envs: f64,
    pub collect_s: f64,
    pub learn_s: f64,
    /// Seconds of the phases' serial parts (Amdahl's `s` share of each).
    pub serial_s: f64,
    pub env_steps_per_s: f64,
}

/// Every phase projected to `t`, `steps` steps per env.
pub fn project(phases: &[Phase], t: &Target, steps: usize) -> Projection {
    let (mut collect_s, mut learn_s, mut serial_s) = (0.0, 0.0, 0.0);
    for p in phases {
        let s = project_phase(p, t);
        if p.collect {
            collect_s += s;
        } else {
            learn_s += s;
        }
        if p.growth != Growth::ShardedGemm {
            let n = t.cores.max(1) as f64;
            let f = p.serial_fraction();
            serial_s += s * f / (f + (1.0 - f) / n).max(1e-12);
        }
    }
    let envs = t.cores as f64 * t.envs_per_core;
    Projection {
        cores: t.cores,
        envs,
        collect_s,
        learn_s,
        serial_s,
        env_steps_per_s: envs * steps as f64 / (collect_s + learn_s).max(1e-12),
    }
}

/// Mean wall time per iteration of each phase at one thread count.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct PhaseTimes {
    pub physics_s: f64,
    pub task_s: f64,
    pub reset_s: f64,
    pub inference_s: f64,
    pub storage_s: f64,
    pub targets_s: f64,
    pub gather_s: f64,
    /// Forward and backward passes without their GEMMs.
    pub forward_backward_other_s: f64,
    /// The GEMMs of the forward and backward passes (wall time: the shards' summed
    /// GEMM time over the thread count).
    pub gemm_s: f64,
    pub loss_s: f64,
    pub clip_s: f64,
    pub adam_s: f64,
}

/// A phase's name, whether it is collection, its growth and where its time is.
type PhaseRow = (&'static str, bool, Growth, fn(&PhaseTimes) -> f64);

/// The phases of a 1-thread and a 2-thread measurement, side by side.
pub fn phases(one: &PhaseTimes, two: &PhaseTimes) -> Vec<Phase> {
    use Growth::*;
    let rows: [PhaseRow; 12] = [
        ("collect: physics", true, PerSample, |t| t.physics_s),
        ("collect: task (obs, reward, risk)", true, PerSample, |t| {
            t.task_s
        }),
        ("collect: resets, counters", true, PerSample, |t| t.reset_s),
        ("collect: policy inference", true, PerSample, |t| {
            t.inference_s
        }),
        ("collect: rollout storage", true, PerSample, |t| t.storage_s),
        (
            "learn: critic over rollout (targets)",
            false,
            PerSample,
            |t| t.targets_s,
        ),
        ("learn: mini-batch gather", false, PerSample, |t| t.gather_s),
        ("learn: forward+backward GEMM", false, ShardedGemm, |t| {
            t.gemm_s
        }),
        ("learn: forward+backward other", false, PerSample, |t| {
            t.forward_backward_other_s
        }),
        ("learn: losses", false, PerSample, |t| t.loss_s),
        ("learn: gradient clip", false, PerParameter, |t| t.clip_s),
        ("learn: Adam", false, PerParameter, |t| t.adam_s),
    ];
    rows.iter()
        .map(|&(name, collect, growth, get)| Phase {
            name,
            collect,
            growth,
            t1_s: get(one),
            t2_s: get(two),
        })
        .collect()
}

/// Runs `warmup + iterations` training iterations of `cfg` (fresh networks, no
/// checkpoints) on `threads` threads and returns the mean phase times of the last
/// `iterations`.
pub fn measure(
    cfg: &TrainConfig,
    threads: usize,
    warmup: usize,
    iterations: usize,
) -> Result<PhaseTimes> {
    anyhow::ensure!(
        threads > 0 && iterations > 0,
        "threads and iterations must be at least 1"
    );
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .with_context(|| format!("starting {threads} threads"))?;
    pool.install(|| measure_on_this_pool(cfg, threads, warmup, iterations))
}

fn measure_on_this_pool(
    cfg: &TrainConfig,
    threads: usize,
    warmup: usize,
    iterations: usize,
) -> Result<PhaseTimes> {
    let r = &cfg.runner;
    let scene = build_scene(&cfg.env, r.seed).context("building the scene")?;
    let env_cfg = Arc::new(cfg.env.clone());
    let mut envs = VecEnv::new(
        env_cfg,
        &scene.model,
        scene.terrain.clone(),
        r.num_envs,
        threads,
        r.seed,
    )?;
    let mut learner = Learner::with_layout(&cfg.env.obs_layout(), ACT_DIM, &cfg.learner, r.seed)?;
    let mut rng = ChaCha8Rng::seed_from_u64(r.seed);
    let mut rollout = Rollout::new(r.steps_per_env, r.num_envs, envs.obs_width(), ACT_DIM);
    let mut obs = envs.batch().obs.clone();
    let mut sum = PhaseTimes::default();
    for it in 0..warmup + iterations {
        let t = iteration_times(&mut envs, &mut learner, &mut rollout, &mut obs, &mut rng)?;
        if it >= warmup {
            sum = add_times(&sum, &t, 1.0 / iterations as f64);
        }
    }
    Ok(sum)
}

/// `a + w b`, phase by phase.
fn add_times(a: &PhaseTimes, b: &PhaseTimes, w: f64) -> PhaseTimes {
    PhaseTimes {
        physics_s: a.physics_s + w * b.physics_s,
        task_s: a.task_s + w * b.task_s,
        reset_s: a.reset_s + w * b.reset_s,
        inference_s: a.inference_s + w * b.inference_s,
        storage_s: a.storage_s + w * b.storage_s,
        targets_s: a.targets_s + w * b.targets_s,
        gather_s: a.gather_s + w * b.gather_s,
        forward_backward_other_s: a.forward_backward_other_s + w * b.forward_backward_other_s,
        gemm_s: a.gemm_s + w * b.gemm_s,
        loss_s: a.loss_s + w * b.loss_s,
        clip_s: a.clip_s + w * b.clip_s,
        adam_s: a.adam_s + w * b.adam_s,
    }
}

/// One collection and one update, timed phase by phase (as `rall train` does).
fn iteration_times(
    envs: &mut VecEnv,
    learner: &mut Learner,
    rollout: &mut Rollout,
    obs: &mut [f32],
    rng: &mut ChaCha8Rng,
) -> Result<PhaseTimes> {
    let t0 = Instant::now();
    rollout.clear();
    let mut inference_s = 0.0;
    for _ in 0..rollout.num_steps {
        let ti = Instant::now();
        let out = learner.act(obs, rng);
        inference_s += ti.elapsed().as_secs_f64();
        let b = envs.step(&out.actions);
        rollout.push(obs, &out, &b.rewards, &b.dones, &b.time_outs, &b.final_obs)?;
        obs.copy_from_slice(&b.obs);
        envs.drain_episodes().for_each(drop);
    }
    rollout.set_last_obs(obs)?;
    let collect_s = t0.elapsed().as_secs_f64();
    let st = envs.take_times();
    mat::take_shard_gemm_s();
    let u = mat::with_gemm_clock(|| learner.update(rollout))?.time;
    let threads = rayon::current_num_threads().max(1) as f64;
    let gemm_s = (mat::take_shard_gemm_s() / threads).min(u.forward_s + u.backward_s);
    Ok(PhaseTimes {
        physics_s: st.physics_s,
        task_s: st.task_s,
        reset_s: st.reset_s,
        inference_s,
        storage_s: (collect_s - inference_s - st.physics_s - st.task_s - st.reset_s).max(0.0),
        targets_s: u.targets_s,
        gather_s: u.gather_s,
        forward_backward_other_s: u.forward_s + u.backward_s - gemm_s,
        gemm_s,
        loss_s: u.loss_s,
        clip_s: u.clip_s,
        adam_s: u.adam_s,
    })
}

/// The report: the measured phases with their serial fractions, then the
/// projection to each core count, then [`ASSUMPTIONS`].
pub fn report(phases: &[Phase], targets: &[Target], steps: usize) -> String {
    let mut out = String::from(
        "phase | 1 thread (ms) | 2 threads (ms) | speed-up | serial fraction | grows with\n",
    );
    for p in phases {
        out += &format!(
            "{} | {:.1} | {:.1} | {:.2}x | {} | {}\n",
            p.name,
            p.t1_s * 1e3,
            p.t2_s * 1e3,
            p.t1_s / p.t2_s.max(1e-12),
            match p.growth {
                Growth::ShardedGemm => "none (sharded)".to_string(),
                _ => format!("{:.3}", p.serial_fraction()),
            },
            match p.growth {
                Growth::PerParameter => "parameters (fixed)",
                Growth::PerSample => "envs",
                Growth::ShardedGemm => "envs, / (cores x efficiency)",
            }
        );
    }
    out += "cores | envs | collect (s) | learn (s) | of it serial parts (s) | env steps/s\n";
    for t in targets {
        let p = project(phases, t, steps);
        out += &format!(
            "{} | {:.0} | {:.3} | {:.3} | {:.3} | {:.0}\n",
            p.cores, p.envs, p.collect_s, p.learn_s, p.serial_s, p.env_steps_per_s
        );
    }
    if let Some(t) = targets.first() {
        out += &format!(
            "({:.0} envs per core; GEMM efficiency per core {:.2})\n",
            t.envs_per_core, t.gemm_efficiency
        );
    }
    out + ASSUMPTIONS + "\n"
}

#[cfg(test)]
mod tests {
    use super::*;

    fn phase(growth: Growth, t1_s: f64, t2_s: f64) -> Phase {
        Phase {
            name: "p",
            collect: true,
            growth,
            t1_s,
            t2_s,
        }
    }

    fn target(cores: usize, gemm_efficiency: f64) -> Target {
        Target {
            cores,
            envs_measured: 256,
            envs_per_core: 128.0,
            gemm_efficiency,
        }
    }

    #[test]
    fn serial_fraction_fits_both_measurements() {
        assert_eq!(phase(Growth::PerSample, 1.0, 0.5).serial_fraction(), 0.0);
        assert_eq!(phase(Growth::PerSample, 1.0, 1.0).serial_fraction(), 1.0);
        assert!((phase(Growth::PerSample, 1.0, 0.6).serial_fraction() - 0.2).abs() < 1e-12);
        // faster than linear or slower than serial are clamped
        assert_eq!(phase(Growth::PerSample, 1.0, 0.4).serial_fraction(), 0.0);
        assert_eq!(phase(Growth::PerSample, 1.0, 1.3).serial_fraction(), 1.0);
        assert_eq!(phase(Growth::PerSample, 0.0, 0.0).serial_fraction(), 0.0);
    }

    #[test]
    fn projection_reproduces_the_measurements_and_scales_by_amdahl() {
        // at the measured machine (2 cores, 256 envs) every phase gives back t2
        let at2 = Target {
            envs_per_core: 128.0,
            ..target(2, 0.9)
        };
        for g in [Growth::PerSample, Growth::PerParameter] {
            let p = phase(g, 1.0, 0.6);
            assert!((project_phase(&p, &at2) - 0.6).abs() < 1e-12, "{g:?}");
        }
        let gemm = phase(Growth::ShardedGemm, 0.4, 0.4 / 1.8);
        assert!((project_phase(&gemm, &at2) - 0.4 / 1.8).abs() < 1e-12);
        // 16 cores, 2,048 envs (8x the work): s = 0.2
        // per sample: 1.0 x 8 x (0.2 + 0.8 / 16) = 2.0; per parameter: 0.2 + 0.05
        let t16 = target(16, 0.9);
        assert!((project_phase(&phase(Growth::PerSample, 1.0, 0.6), &t16) - 2.0).abs() < 1e-12);
        assert!((project_phase(&phase(Growth::PerParameter, 1.0, 0.6), &t16) - 0.25).abs() < 1e-12);
        // sharded GEMM: 0.4 x 8 / (16 x 0.9): each core's shard keeps its size
        assert!((project_phase(&gemm, &t16) - 0.4 * 8.0 / (16.0 * 0.9)).abs() < 1e-12);
    }

    #[test]
    fn projection_sums_phases_into_an_iteration() {
        let mut learn = phase(Growth::PerParameter, 0.1, 0.1);
        learn.collect = false;
        let phases = [
            phase(Growth::PerSample, 0.5, 0.25), // perfectly parallel collection
            learn,                               // serial Adam
        ];
        let p = project(&phases, &target(64, 1.0), 24);
        // collection: 0.5 x 32 / 64 = 0.25 s; Adam 0.1 s, all of it serial
        assert_eq!(p.envs, 64.0 * 128.0);
        assert!((p.collect_s - 0.25).abs() < 1e-12);
        assert!((p.learn_s - 0.1).abs() < 1e-12);
        assert!((p.serial_s - 0.1).abs() < 1e-12);
        assert!((p.env_steps_per_s - 64.0 * 128.0 * 24.0 / 0.35).abs() < 1e-6);
        let text = report(&phases, &[target(16, 1.0), target(64, 1.0)], 24);
        assert!(text.contains("assumptions:"), "{text}");
        assert_eq!(text.lines().filter(|l| l.starts_with("64 |")).count(), 1);
    }

    #[test]
    fn measured_phases_are_named_once_and_split_collect_from_learn() {
        let one = PhaseTimes {
            physics_s: 0.45,
            gemm_s: 0.3,
            adam_s: 0.01,
            ..Default::default()
        };
        let ph = phases(&one, &one);
        let names: std::collections::HashSet<_> = ph.iter().map(|p| p.name).collect();
        assert_eq!(names.len(), ph.len());
        assert_eq!(ph.iter().filter(|p| p.collect).count(), 5);
        let gemm = ph.iter().find(|p| p.growth == Growth::ShardedGemm).unwrap();
        assert_eq!((gemm.t1_s, gemm.collect), (0.3, false));
    }
}
