//! Env throughput against the physics limit, shared by `rall bench env` and
//! `benches/env.rs`: the same robots stepped (a) through [`VecEnv`] and (b) as
//! bare `mj_step` x decimation with the same PD law on the raw FFI, interleaved
//! in rounds so both see the same machine load.

use std::sync::Arc;
use std::time::{Duration, Instant};

use rand::{Rng, SeedableRng};
use rayon::prelude::*;

use super::config::{EnvConfig, PushConfig};
use super::observation::ACT_DIM;
use super::scene::build_scene;
use super::vec_env::VecEnv;
use crate::robot::{ControlConfig, RobotLayout, NUM_JOINTS};
use crate::sim::raw_bench::{raw_pd_steps, RawPd};
use crate::sim::{Data, Model, Result, SimError};

/// What one benchmark run measured.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EnvBenchReport {
    pub envs: usize,
    pub threads: usize,
    /// Policy steps per second through VecEnv (observation, reward, risk, resets).
    pub env_steps_per_s: f64,
    /// Policy-step equivalents (decimation x mj_step with PD) per second on the raw FFI.
    pub raw_steps_per_s: f64,
}

impl EnvBenchReport {
    /// env / raw: 1.0 means the env layer costs nothing over the physics.
    pub fn ratio(&self) -> f64 {
        self.env_steps_per_s / self.raw_steps_per_s
    }
}

/// A raw robot: its own model copy (holding its env's randomisation) and
/// state, and what its PD law needs.
struct RawRobot {
    model: Model,
    data: Data,
    layout: RobotLayout,
    control: ControlConfig,
    default_q_rad: [f64; NUM_JOINTS],
    limits: [f64; NUM_JOINTS],
}

/// The bench's env config: the given one with random actions in mind — no pushes
/// and long episodes, so both sides simulate the same kind of motion.
pub fn bench_config(base: &EnvConfig) -> EnvConfig {
    let mut cfg = base.clone();
    cfg.randomization.push = PushConfig::None;
    cfg.episode.length_s = 1e4;
    cfg
}

/// Runs both loops for about `seconds` in total with `envs` robots on `threads` threads.
pub fn bench_env(
    cfg: &EnvConfig,
    envs: usize,
    threads: usize,
    seconds: f64,
    seed: u64,
) -> Result<EnvBenchReport> {
    let cfg = Arc::new(bench_config(cfg));
    let scene = build_scene(&cfg, seed)?;
    let mut vec = VecEnv::new(
        cfg.clone(),
        &scene.model,
        scene.terrain.clone(),
        envs,
        threads,
        seed,
    )?;
    // Raw robots start from the envs' own (randomised, spawned) states.
    let mut raw: Vec<RawRobot> = vec
        .envs()
        .iter()
        .map(|e| {
            let src = e.robot();
            let model = src.model_copy()?;
            let mut data = Data::new(&model)?;
            data.qpos_mut().copy_from_slice(src.data().qpos());
            data.qvel_mut().copy_from_slice(src.data().qvel());
            data.forward(&model)?;
            let limits = std::array::from_fn(|i| src.control.torque_limit_nm(i));
            Ok(RawRobot {
                model,
                data,
                layout: src.layout.clone(),
                control: src.control.clone(),
                default_q_rad: src.default_q_rad,
                limits,
            })
        })
        .collect::<Result<_>>()?;
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads.max(1))
        .build()
        .map_err(|e| SimError::Invalid(e.to_string()))?;
    // A fixed table of random actions, U[-0.5, 0.5], cycled by both loops.
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let table: Vec<Vec<f32>> = (0..64)
        .map(|_| {
            (0..envs * ACT_DIM)
                .map(|_| rng.gen_range(-0.5..0.5))
                .collect()
        })
        .collect();
    let decimation = cfg.control.decimation;
    let round_steps = 50;
    let (mut t_env, mut t_raw, mut steps) = (Duration::ZERO, Duration::ZERO, 0usize);
    let deadline = Instant::now() + Duration::from_secs_f64(seconds.max(0.1));
    let mut k = 0;
    while Instant::now() < deadline || steps == 0 {
        let t = Instant::now();
        for _ in 0..round_steps {
            vec.step(&table[k % table.len()]);
            vec.drain_episodes().for_each(drop);
            k += 1;
        }
        t_env += t.elapsed();
        // Both loops start each round from the same robot states (not timed), so
        // the raw robots see the envs' resets instead of lying where they fell.
        for (r, e) in raw.iter_mut().zip(vec.envs()) {
            r.data.qpos_mut().copy_from_slice(e.robot().data().qpos());
            r.data.qvel_mut().copy_from_slice(e.robot().data().qvel());
        }
        let t = Instant::now();
        for j in 0..round_steps {
            let actions = &table[(k - round_steps + j) % table.len()];
            pool.install(|| {
                raw.par_iter_mut()
                    .zip(actions.par_chunks(ACT_DIM))
                    .try_for_each(|(r, a)| {
                        let target = r.control.joint_targets(&r.default_q_rad, a);
                        let pd = RawPd {
                            qpos_adr: &r.layout.qpos_adr,
                            dof_adr: &r.layout.dof_adr,
                            actuator: &r.layout.actuator_ids,
                            target_rad: &target,
                            kp: r.control.kp_nm_per_rad,
                            kd: r.control.kd_nm_s_per_rad,
                            limit_nm: &r.limits,
                        };
                        // A raw robot that failed starts over (as an env would).
                        match raw_pd_steps(&r.model, &mut r.data, decimation, &pd) {
                            Ok(()) => Ok(()),
                            Err(_) => r.data.reset(&r.model),
                        }
                    })
            })?;
        }
        t_raw += t.elapsed();
        steps += round_steps;
    }
    let total = (steps * envs) as f64;
    Ok(EnvBenchReport {
        envs,
        threads,
        env_steps_per_s: total / t_env.as_secs_f64(),
        raw_steps_per_s: total / t_raw.as_secs_f64(),
    })
}
