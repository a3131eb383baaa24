//! Running a policy (deterministic mean action) for the viewer, with or without a
//! recording. A scenario is just another [`EnvConfig`] (and so another scene).

use std::sync::Arc;

use anyhow::{Context, Result};

use super::episode::{EpisodeLogger, HeightGrid};
use super::value::{ValueProbe, DEFAULT_NUM_BARS};
use crate::env::terrain::Terrain;
use crate::env::{build_scene, Env, EnvConfig, EpisodeEnd, Scene};
use crate::eval::{build_named_scenario, ScenarioHook};
use crate::learn::Learner;

/// What to run.
#[derive(Debug, Clone)]
pub struct PlayOptions {
    pub episodes: usize,
    /// Seed of the env (commands, randomisation, noise, pushes).
    pub seed: u64,
    /// Seed of the terrain (use the training run's seed to see its terrain).
    pub scene_seed: u64,
    /// Stop an episode after this many policy steps (default: the env's episode length).
    pub max_steps: Option<usize>,
    /// Terrain level of every episode (rough terrain); the type cycles with the episode.
    pub terrain_level: usize,
    /// Bars of the quantile chart.
    pub num_bars: usize,
    /// Steps buffered before the recording gets them.
    pub flush_steps: usize,
    /// The critic (value chart, mean/CVaR, IQR) is read and logged every this many
    /// frames (1: every policy step).
    pub value_every_frames: usize,
    /// An evaluation scenario by name (`rall eval`'s names, e.g. `ball+rough+push`)
    /// instead of the env config's own scene.
    pub scenario: Option<String>,
}

impl Default for PlayOptions {
    fn default() -> Self {
        PlayOptions {
            episodes: 1,
            seed: 0,
            scene_seed: 1,
            max_steps: None,
            terrain_level: 0,
            num_bars: DEFAULT_NUM_BARS,
            flush_steps: super::episode::DEFAULT_FLUSH_STEPS,
            value_every_frames: super::episode::VALUE_EVERY_FRAMES,
            scenario: None,
        }
    }
}

/// How one episode went.
#[derive(Debug, Clone, PartialEq)]
pub struct PlayedEpisode {
    pub steps: usize,
    pub total_reward: f64,
    /// `None` when cut at `max_steps` before the env ended it.
    pub end: Option<EpisodeEnd>,
    pub risk_penalties: usize,
    pub pushes: usize,
}

/// What a play run did.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct PlayReport {
    pub episodes: Vec<PlayedEpisode>,
    pub policy_steps: usize,
    pub sim_time_s: f64,
}

/// One env for the viewer: the scene of `cfg` (or of a named evaluation
/// scenario) and an [`Env`] on it.
pub struct ViewerEnv {
    pub env: Env,
    /// The training terrain (rough ground), for the logger and the curriculum cells.
    pub terrain: Option<Arc<Terrain>>,
    /// What the logger draws as ground: the terrain or the scenario's heightfield.
    pub ground: Option<Arc<dyn HeightGrid>>,
    /// The scenario's per-step logic (moving arm, payload), when playing one.
    pub hook: Option<ScenarioHook>,
    source: Source,
}

enum Source {
    Scene { scene: Scene, cfg: Arc<EnvConfig> },
    Scenario(Box<crate::eval::ScenarioSetup>),
}

impl ViewerEnv {
    pub fn new(cfg: &EnvConfig, scene_seed: u64, env_seed: u64) -> Result<ViewerEnv> {
        let scene = build_scene(cfg, scene_seed).context("building the scene")?;
        let terrain = scene.terrain.clone();
        let cfg = Arc::new(cfg.clone());
        let env = Env::new(cfg.clone(), &scene.model, terrain.clone(), env_seed, 0)
            .context("creating the env")?;
        Ok(ViewerEnv {
            env,
            ground: terrain.clone().map(|t| t as Arc<dyn HeightGrid>),
            terrain,
            hook: None,
            source: Source::Scene { scene, cfg },
        })
    }

    /// The evaluation scenario `name` (e.g. `moving_arm+rough+push`, see
    /// `rall eval --help`) built on `cfg` (the checkpoint's noise, PD, rewards).
    pub fn scenario(
        name: &str,
        cfg: &EnvConfig,
        scene_seed: u64,
        env_seed: u64,
    ) -> Result<ViewerEnv> {
        let setup = build_named_scenario(name, cfg, scene_seed)
            .with_context(|| format!("building scenario {name:?}"))?;
        let (env, hook) = setup.single_env(env_seed)?;
        Ok(ViewerEnv {
            env,
            terrain: None,
            ground: setup.ground.clone().map(|g| g as Arc<dyn HeightGrid>),
            hook: Some(hook),
            source: Source::Scenario(Box::new(setup)),
        })
    }

    /// Replaces the env by a fresh one seeded `env_seed` (same draws as the first
    /// time with that seed: evaluation episodes stay comparable).
    pub fn reseed(&mut self, env_seed: u64) -> Result<()> {
        match &self.source {
            Source::Scene { scene, cfg } => {
                self.env = Env::new(cfg.clone(), &scene.model, self.terrain.clone(), env_seed, 0)
                    .context("creating the env")?;
            }
            Source::Scenario(setup) => {
                let (env, hook) = setup.single_env(env_seed)?;
                self.env = env;
                self.hook = Some(hook);
            }
        }
        Ok(())
    }
}

/// Runs one episode of `learner`'s mean action in `env`, logging every step when a
/// logger is given (the critic is only evaluated then, by the logger).
pub fn run_episode(
    learner: &Learner,
    env: &mut Env,
    mut hook: Option<&mut ScenarioHook>,
    mut logger: Option<&mut EpisodeLogger>,
    max_steps: Option<usize>,
    label: &str,
) -> Result<PlayedEpisode> {
    let mut obs = vec![0.0f32; env.obs_width()];
    let mut final_obs = vec![0.0f32; env.obs_width()];
    env.reset(&mut obs).context("resetting the env")?;
    if let Some(h) = hook.as_deref_mut() {
        h.on_reset(env);
    }
    let dt = env.config().control.policy_dt_s();
    if let Some(l) = logger.as_deref_mut() {
        l.begin_episode(learner, env, label, &obs)?;
    }
    let limit = max_steps.unwrap_or(usize::MAX).min(env.max_steps());
    let mut ep = PlayedEpisode {
        steps: 0,
        total_reward: 0.0,
        end: None,
        risk_penalties: 0,
        pushes: 0,
    };
    while ep.steps < limit {
        let action = learner.act_mean(&obs);
        if let Some(h) = hook.as_deref_mut() {
            h.before_step(env);
        }
        let r = env.step(&action, &mut obs, &mut final_obs);
        ep.steps += 1;
        ep.total_reward += r.reward;
        ep.risk_penalties += r.risk.fired.iter().filter(|f| **f).count();
        ep.pushes += r.pushed as usize;
        if let Some(l) = logger.as_deref_mut() {
            l.log_step(env, &r, &obs, dt)?;
        }
        if r.done {
            ep.end = env.take_summary().map(|s| s.end);
            break;
        }
    }
    if ep.end.is_none() {
        if let Some(l) = logger {
            l.event(
                rerun::TextLogLevel::INFO,
                format!("episode cut after {} steps", ep.steps),
            )?;
        }
    }
    Ok(ep)
}

/// Plays `opts.episodes` episodes of `learner` in `cfg`; logs them when `rec` is given
/// (the blueprint is the caller's: see [`super::open_recording`]). Returns the report
/// and the recording, flushed.
pub fn play(
    learner: &Learner,
    cfg: &EnvConfig,
    opts: &PlayOptions,
    rec: Option<rerun::RecordingStream>,
) -> Result<(PlayReport, Option<rerun::RecordingStream>)> {
    let mut venv = match &opts.scenario {
        Some(name) => ViewerEnv::scenario(name, cfg, opts.scene_seed, opts.seed)?,
        None => ViewerEnv::new(cfg, opts.scene_seed, opts.seed)?,
    };
    let terrain = venv.terrain.clone();
    let num_types = terrain.as_ref().map_or(1, |t| t.num_types());
    let level = terrain
        .as_ref()
        .map_or(0, |t| opts.terrain_level.min(t.num_levels() - 1));
    let mut logger = match rec {
        Some(rec) => {
            let probe = ValueProbe::new(learner, opts.num_bars);
            let mut l = EpisodeLogger::new(rec, venv.env.robot(), venv.ground.clone(), probe)?;
            l.set_flush_steps(opts.flush_steps);
            l.set_value_every_frames(opts.value_every_frames);
            Some(l)
        }
        None => None,
    };
    let mut report = PlayReport::default();
    let dt = cfg.control.policy_dt_s();
    for e in 0..opts.episodes {
        venv.env.set_terrain_cell(level, e % num_types);
        let label = format!("episode {}/{}", e + 1, opts.episodes);
        let ep = run_episode(
            learner,
            &mut venv.env,
            venv.hook.as_mut(),
            logger.as_mut(),
            opts.max_steps,
            &label,
        )?;
        report.policy_steps += ep.steps;
        report.sim_time_s += ep.steps as f64 * dt;
        report.episodes.push(ep);
    }
    let rec = match logger {
        Some(l) => Some(l.finish()?),
        None => None,
    };
    Ok((report, rec))
}
