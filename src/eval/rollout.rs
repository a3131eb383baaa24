//! Running policies in a scenario: N robots on a [`VecEnv`] (rayon pool) with
//! their [`ScenarioHook`]s, deterministic actions (the policy mean).

use std::path::{Path, PathBuf};

use anyhow::{Context, Result};

use super::policy::{is_onnx, Actor, OnnxPolicy, Policy};
use super::scenario::{ScenarioHook, ScenarioSetup};
use crate::env::{Env, EnvConfig, EpisodeEnd, EpisodeSummary, VecEnv};
use crate::learn::Learner;
use crate::runner::load_policy;

/// A policy under evaluation: a name for the tables, what acts (a checkpoint's
/// networks or an ONNX network), and the env config it was trained with
/// (observation noise, PD, rewards; an ONNX policy's from its sidecar).
pub struct NamedPolicy {
    pub name: String,
    pub policy: Policy,
    pub env: EnvConfig,
    pub path: Option<PathBuf>,
    /// Loaded from an actor-only copy (`rall checkpoint actor-only`): it acts, but
    /// its critic was never trained, so [`NamedPolicy::critic`] refuses it.
    pub actor_only: bool,
    /// FNV-1a of the checkpoint it was loaded from (the rollout cache's key).
    pub file_hash: Option<u64>,
}

/// FNV-1a of a file's bytes; `None` when it cannot be read (the load itself
/// reports why).
fn file_hash(path: &Path) -> Option<u64> {
    std::fs::read(path).ok().map(crate::hash::fnv1a64)
}

impl NamedPolicy {
    /// Loads a checkpoint written by `rall train`, or an ONNX policy (`.onnx`,
    /// its JSON sidecar beside it).
    pub fn load(name: &str, path: &Path) -> Result<NamedPolicy> {
        if is_onnx(path) {
            let p = OnnxPolicy::load(path).with_context(|| format!("policy {name}"))?;
            if !p.defaulted.is_empty() {
                eprintln!(
                    "note: policy {name}: the sidecar has no {}; rall's defaults are used",
                    p.defaulted.join(", ")
                );
            }
            return Ok(NamedPolicy {
                name: name.to_string(),
                env: p.env.clone(),
                policy: Policy::Onnx(Box::new(p)),
                path: Some(path.to_path_buf()),
                actor_only: true,
                // its numbers also depend on the ONNX runtime chosen: never cached
                file_hash: None,
            });
        }
        let p = load_policy(path).with_context(|| format!("policy {name}"))?;
        Ok(NamedPolicy {
            name: name.to_string(),
            policy: Policy::Checkpoint(Box::new(p.learner)),
            env: p.config.env,
            path: Some(path.to_path_buf()),
            actor_only: p.actor_only,
            file_hash: file_hash(path),
        })
    }

    /// What the policy's rollouts depend on, for the rollout cache: the bytes it
    /// was loaded from, the env config it acts in and its robot model's bytes;
    /// `None` when it was not loaded from a checkpoint file.
    pub fn rollout_key(&self) -> Option<String> {
        let h = self.file_hash?;
        let model = file_hash(Path::new(&self.env.robot_mjcf))?;
        Some(format!(
            "policy file {h:016x}\nrobot model {model:016x}\nenv {:?}",
            self.env
        ))
    }

    /// The checkpoint's learner (critic, Gaussian); an ONNX policy has none, and
    /// an actor-only copy's critic was never trained.
    pub fn critic(&self) -> Result<&Learner> {
        let learner = self.policy.learner().with_context(|| {
            format!(
                "policy {} is an ONNX network: it has no critic (only a rall checkpoint has one)",
                self.name
            )
        })?;
        anyhow::ensure!(
            !self.actor_only,
            "policy {} is an actor-only copy ({}): it acts, but it holds no trained critic; give the full checkpoint it was cut from",
            self.name,
            self.path.as_ref().map_or(String::new(), |p| p.display().to_string())
        );
        Ok(learner)
    }

    /// `NAME=PATH` -> (name, path).
    pub fn parse_arg(arg: &str) -> Result<(String, PathBuf)> {
        let (name, path) = arg
            .split_once('=')
            .with_context(|| format!("--policy {arg:?}: expected NAME=PATH"))?;
        anyhow::ensure!(
            !name.trim().is_empty() && !path.trim().is_empty(),
            "--policy {arg:?}: expected NAME=PATH"
        );
        Ok((name.trim().to_string(), PathBuf::from(path.trim())))
    }
}

/// N robots of one scenario, stepped together; hooks run around every step and
/// after every (auto-)reset.
pub struct ScenarioRun {
    pub venv: VecEnv,
    pub hooks: Vec<ScenarioHook>,
    obs: Vec<f32>,
    dones: Vec<bool>,
}

impl ScenarioRun {
    pub fn new(setup: &ScenarioSetup, n: usize, threads: usize, seed: u64) -> Result<ScenarioRun> {
        let (venv, hooks) = setup.vec_env(n, threads, seed)?;
        let obs = venv.batch().obs.clone();
        Ok(ScenarioRun {
            venv,
            hooks,
            obs,
            dones: vec![false; n],
        })
    }

    pub fn num_envs(&self) -> usize {
        self.dones.len()
    }
    /// Current observations, `n x OBS_DIM` (first of a new episode after a done).
    pub fn obs(&self) -> &[f32] {
        &self.obs
    }
    /// Which robots ended an episode in the last step (they have been reset).
    pub fn dones(&self) -> &[bool] {
        &self.dones
    }
    pub fn env(&self, i: usize) -> &Env {
        &self.venv.envs()[i]
    }

    /// One policy step of every robot; returns the episodes that ended.
    pub fn step(&mut self, actions: &[f32]) -> Vec<EpisodeSummary> {
        self.step_active(actions, None)
    }

    /// One policy step of the robots whose `active` entry is true (every robot with
    /// `None`); the others stand still ([`VecEnv::step_active`]). A robot's numbers
    /// depend on its own seed alone, so leaving out robots whose episodes are no
    /// longer counted changes nothing but the time.
    pub fn step_active(&mut self, actions: &[f32], active: Option<&[bool]>) -> Vec<EpisodeSummary> {
        for (i, (h, e)) in self.hooks.iter_mut().zip(self.venv.envs_mut()).enumerate() {
            if active.is_none_or(|m| m[i]) {
                h.before_step(e);
            }
        }
        let b = self.venv.step_active(actions, active);
        self.obs.copy_from_slice(&b.obs);
        self.dones.copy_from_slice(&b.dones);
        for ((h, e), &d) in self
            .hooks
            .iter_mut()
            .zip(self.venv.envs_mut())
            .zip(&self.dones)
        {
            if d {
                h.on_reset(e);
            }
        }
        self.venv.drain_episodes().collect()
    }

    /// Whether robot `i`'s payload (container, arm base) touches the ground.
    pub fn payload_on_ground(&self, i: usize) -> bool {
        self.hooks[i].payload_on_ground(&self.venv.envs()[i])
    }
}

/// How a robot's first episode ended.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct FirstEpisode {
    /// Policy steps survived (the full length on a time-out).
    pub steps: usize,
    /// The env's reason; `None` when the payload touched the ground first.
    pub end: Option<EpisodeEnd>,
    /// Horizontal distance from the spawn point at the end (m).
    pub walked_m: f64,
    /// Integral of the commanded planar speed over the episode (m).
    pub commanded_m: f64,
    /// Distance made good along the command: the integral of v . c/|c| (body-frame
    /// planar velocity and command) over the episode (m). Over `commanded_m`, 1 is
    /// perfect tracking, 0 standing still, whatever the command's turns.
    pub progress_m: f64,
    /// Policy steps until any part of the robot but a foot (or of what is fixed to
    /// it) first touched the ground: the strict fall definition; the full length
    /// when that never happened.
    pub strict_steps: usize,
}

impl FirstEpisode {
    /// Fell (terminated, or the payload on the ground) before the time-out.
    pub fn fell(&self) -> bool {
        self.end != Some(EpisodeEnd::TimeOut)
    }
}

/// Runs `n` robots of `setup` for one episode each under `policy`'s mean action.
/// A robot's episode ends with the env's own episode or when its payload touches
/// the ground. `observe(i, env, step)` sees every robot after each step of its
/// first episode that did not end it.
pub fn run_first_episodes(
    policy: &dyn Actor,
    setup: &ScenarioSetup,
    n: usize,
    threads: usize,
    seed: u64,
    mut observe: impl FnMut(usize, &Env, usize),
) -> Result<Vec<FirstEpisode>> {
    let mut run = ScenarioRun::new(setup, n, threads, seed)?;
    let max_steps = setup.env.max_episode_steps();
    let dt = setup.env.control.policy_dt_s();
    let mut first: Vec<Option<FirstEpisode>> = vec![None; n];
    let mut commanded = vec![0.0f64; n];
    let mut progress = vec![0.0f64; n];
    let mut strict: Vec<Option<usize>> = vec![None; n];
    let walked = |env: &Env| {
        let p = env.robot().base_pos_m();
        (p[0] - setup.spawn_m[0]).hypot(p[1] - setup.spawn_m[1])
    };
    for step in 1..=max_steps {
        let commands: Vec<[f64; 3]> = (0..n).map(|i| run.env(i).command()).collect();
        for (c, cmd) in commanded.iter_mut().zip(&commands) {
            *c += cmd[0].hypot(cmd[1]) * dt;
        }
        let actions = policy.actions(run.obs())?;
        // robots whose first episode has ended stand still from here on
        let active: Vec<bool> = first.iter().map(Option::is_none).collect();
        for s in run.step_active(&actions, Some(&active)) {
            let i = s.env_index;
            if first[i].is_none() {
                first[i] = Some(FirstEpisode {
                    steps: s.steps,
                    end: Some(s.end),
                    walked_m: s.distance_m,
                    commanded_m: s.commanded_distance_m,
                    progress_m: progress[i],
                    strict_steps: strict[i].unwrap_or(s.steps).min(s.steps),
                });
            }
        }
        for i in 0..n {
            if first[i].is_some() {
                continue;
            }
            progress[i] += progress_along_command_mps(run.env(i), commands[i]) * dt;
            if strict[i].is_none() && run.hooks[i].non_foot_on_ground(run.env(i)) {
                strict[i] = Some(step);
            }
            if run.payload_on_ground(i) {
                first[i] = Some(FirstEpisode {
                    steps: step,
                    end: None,
                    walked_m: walked(run.env(i)),
                    commanded_m: commanded[i],
                    progress_m: progress[i],
                    strict_steps: strict[i].unwrap_or(step).min(step),
                });
            } else {
                observe(i, run.env(i), step);
            }
        }
        if first.iter().all(Option::is_some) {
            break;
        }
    }
    Ok(first
        .into_iter()
        .enumerate()
        .map(|(i, f)| {
            f.unwrap_or_else(|| FirstEpisode {
                steps: max_steps,
                end: Some(EpisodeEnd::TimeOut),
                walked_m: walked(run.env(i)),
                commanded_m: commanded[i],
                progress_m: progress[i],
                strict_steps: strict[i].unwrap_or(max_steps),
            })
        })
        .collect())
}

/// The body-frame planar velocity along the planar command's direction (m/s);
/// 0 under a zero planar command.
fn progress_along_command_mps(env: &Env, command: [f64; 3]) -> f64 {
    let norm = command[0].hypot(command[1]);
    if norm == 0.0 {
        return 0.0;
    }
    let v = env.state().base_lin_vel_body_mps;
    (v[0] * command[0] + v[1] * command[1]) / norm
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn policy_args_split_on_the_first_equals() {
        let (n, p) = NamedPolicy::parse_arg("RALL=runs/a=b.safetensors").unwrap();
        assert_eq!(n, "RALL");
        assert_eq!(p, PathBuf::from("runs/a=b.safetensors"));
        assert!(NamedPolicy::parse_arg("nopath").is_err());
        assert!(NamedPolicy::parse_arg("=x").is_err());
    }
}
