//! `rall eval falls`: what the critic says before a robot falls. Robots walk
//! in the checkpoint's own training env (terrain at its stored curriculum
//! levels, pushes, randomisation) with sampled actions; every state's value
//! quantiles are logged, and the states of the last `window` steps before a
//! fall are compared with all others. If the value distribution tells danger
//! apart, its lower tail and its IQR move in the states before a fall.

use std::collections::VecDeque;
use std::sync::Arc;

use anyhow::Result;
use rand::SeedableRng;

use crate::config::TrainConfig;
use crate::env::{build_scene, VecEnv};
use crate::learn::Learner;

/// The quantile levels reported; the IQR is `Z_0.75 - Z_0.25`.
pub const FALL_TAUS: [f32; 6] = [0.01, 0.05, 0.25, 0.5, 0.75, 0.95];

/// Means over a set of states of the critic's quantiles at [`FALL_TAUS`] and IQR.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct QuantileMeans {
    pub states: usize,
    pub quantiles: [f64; 6],
    pub iqr: f64,
}

impl QuantileMeans {
    fn add(&mut self, z: &[f32]) {
        self.states += 1;
        for (m, q) in self.quantiles.iter_mut().zip(z) {
            *m += *q as f64;
        }
        self.iqr += (z[4] - z[2]) as f64;
    }

    fn finish(mut self) -> QuantileMeans {
        let n = self.states.max(1) as f64;
        self.quantiles.iter_mut().for_each(|q| *q /= n);
        self.iqr /= n;
        self
    }
}

/// The critic's quantiles before falls against everywhere else.
#[derive(Debug, Clone, PartialEq)]
pub struct FallReport {
    pub robots: usize,
    pub steps: usize,
    pub window: usize,
    pub falls: usize,
    /// States of the last `window` steps of episodes that ended in a fall.
    pub before_fall: QuantileMeans,
    /// Every other state.
    pub elsewhere: QuantileMeans,
}

/// `robots` envs of `cfg`'s training env, on the terrain curriculum at the
/// checkpoint's stored `terrain_levels` (shared out round-robin).
pub fn training_envs(
    cfg: &TrainConfig,
    terrain_levels: Option<&[usize]>,
    robots: usize,
    threads: usize,
    seed: u64,
) -> Result<VecEnv> {
    let scene = build_scene(&cfg.env, cfg.runner.seed)?;
    let mut envs = VecEnv::new(
        Arc::new(cfg.env.clone()),
        &scene.model,
        scene.terrain.clone(),
        robots,
        threads,
        seed,
    )?;
    if let Some(levels) = terrain_levels.filter(|l| !l.is_empty()) {
        let mine: Vec<usize> = (0..robots).map(|i| levels[i % levels.len()]).collect();
        envs.restore_terrain_levels(&mine)?;
    }
    Ok(envs)
}

/// Runs `robots` robots for `steps` policy steps in `cfg`'s training env.
pub fn critic_before_falls(
    learner: &Learner,
    cfg: &TrainConfig,
    terrain_levels: Option<&[usize]>,
    (robots, steps, window): (usize, usize, usize),
    threads: usize,
    seed: u64,
) -> Result<FallReport> {
    let mut envs = training_envs(cfg, terrain_levels, robots, threads, seed)?;
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let mut obs = envs.batch().obs.clone();
    let k = FALL_TAUS.len();
    let mut recent: Vec<VecDeque<Vec<f32>>> = vec![VecDeque::new(); robots];
    let (mut before, mut elsewhere) = (QuantileMeans::default(), QuantileMeans::default());
    let mut falls = 0;
    for _ in 0..steps {
        let z = learner.value_quantiles(&obs, &FALL_TAUS);
        let b = envs.step(&learner.act(&obs, &mut rng).actions);
        for (i, window_i) in recent.iter_mut().enumerate() {
            window_i.push_back(z[i * k..(i + 1) * k].to_vec());
            let fell = b.dones[i] && !b.time_outs[i];
            falls += fell as usize;
            if b.dones[i] {
                let sink = if fell { &mut before } else { &mut elsewhere };
                window_i.drain(..).for_each(|q| sink.add(&q));
            } else if window_i.len() > window {
                let q = window_i.pop_front().expect("non-empty");
                elsewhere.add(&q);
            }
        }
        obs.copy_from_slice(&b.obs);
    }
    // states still in the windows at the end did not precede a fall (yet)
    recent.iter().flatten().for_each(|q| elsewhere.add(q));
    Ok(FallReport {
        robots,
        steps,
        window,
        falls,
        before_fall: before.finish(),
        elsewhere: elsewhere.finish(),
    })
}
