//! `rall eval race`: the paper's race-track experiment (section V, fig. 4).
//! `agents` robots run `episodes` episodes each on the race course (platform
//! drop, obstacles, rough patches, 100 N pushes throughout); the returns' 0.25 /
//! 0.5 / 0.75 quantiles (worst, middle, best case) per policy and for the meta
//! controller.
//!
//! The meta controller (paper section III-C) runs the risk-neutral policy
//! (RISKY, CVaR_1) and, per robot and step, switches to the risk-averse one
//! (SAFE, CVaR_0.5) while the RISKY critic's IQR is high:
//! RISKY -> SAFE when IQR > threshold; SAFE -> RISKY when IQR < threshold -
//! hysteresis and the robot has been on SAFE for at least `min_safe_steps`.
//! Every robot starts an episode on RISKY.

use anyhow::{bail, Context, Result};
use serde::{Deserialize, Serialize};

use super::cache::{run_jobs_cached, RolloutCache};
use super::policy::Actor;
use super::report::{csv_line, markdown_table};
use super::rollout::{NamedPolicy, ScenarioRun};
use super::scenario::{build_scenario, GroundKind, Load, ScenarioParams, ScenarioSpec};
use crate::env::{EnvConfig, EpisodeEnd, ObsGroup, ACT_DIM};
use crate::learn::relayout_rows;
use crate::stats::{mean, quantile};

/// The meta controller's settings.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MetaConfig {
    pub name: String,
    /// Name of the risk-neutral policy (its critic's IQR drives the switch).
    pub risky: String,
    /// Name of the risk-averse policy.
    pub safe: String,
    pub threshold: f32,
    /// Switch back below `threshold - hysteresis`.
    pub hysteresis: f32,
    /// Least steps on SAFE before switching back.
    pub min_safe_steps: usize,
}

/// The parsed `--meta` argument: policies by path or by `--policy` name.
#[derive(Debug, Clone, PartialEq)]
pub struct MetaArg {
    pub risky: String,
    pub safe: String,
    pub threshold: f32,
    pub hysteresis: f32,
    pub min_safe_steps: usize,
    pub name: String,
}

impl MetaArg {
    /// `RISKY=PATH,SAFE=PATH,THRESHOLD=x[,HYSTERESIS=h][,HOLD=steps][,NAME=label]`
    /// (keys case-insensitive; PATH may also be the NAME of a `--policy`).
    pub fn parse(s: &str) -> Result<MetaArg> {
        let (mut risky, mut safe, mut threshold) = (None, None, None);
        let mut m = MetaArg {
            risky: String::new(),
            safe: String::new(),
            threshold: 0.0,
            hysteresis: 0.0,
            min_safe_steps: 0,
            name: "Meta".into(),
        };
        for part in s.split(',').map(str::trim).filter(|p| !p.is_empty()) {
            let (k, v) = part
                .split_once('=')
                .with_context(|| format!("--meta: {part:?} is not KEY=VALUE"))?;
            let num = |v: &str| -> Result<f32> {
                let x: f32 = v
                    .trim()
                    .parse()
                    .with_context(|| format!("--meta: {k}={v:?} is not a number"))?;
                anyhow::ensure!(x.is_finite() && x >= 0.0, "--meta: {k} must be >= 0");
                Ok(x)
            };
            match k.trim().to_ascii_uppercase().as_str() {
                "RISKY" => risky = Some(v.trim().to_string()),
                "SAFE" => safe = Some(v.trim().to_string()),
                "THRESHOLD" => threshold = Some(num(v)?),
                "HYSTERESIS" => m.hysteresis = num(v)?,
                "HOLD" => {
                    m.min_safe_steps = v
                        .trim()
                        .parse()
                        .with_context(|| format!("--meta: HOLD={v:?} is not a step count"))?
                }
                "NAME" => m.name = v.trim().to_string(),
                other => bail!(
                    "--meta: unknown key {other:?} (RISKY, SAFE, THRESHOLD, HYSTERESIS, HOLD, NAME)"
                ),
            }
        }
        m.risky = risky.context("--meta needs RISKY=PATH")?;
        m.safe = safe.context("--meta needs SAFE=PATH")?;
        m.threshold = threshold.context("--meta needs THRESHOLD=x")?;
        Ok(m)
    }
}

/// Per-robot switching state of the meta controller.
#[derive(Debug, Clone)]
pub struct MetaSwitch {
    threshold: f32,
    hysteresis: f32,
    min_safe_steps: usize,
    on_safe: Vec<bool>,
    safe_for: Vec<usize>,
    /// RISKY -> SAFE switches since creation.
    pub to_safe: u64,
    /// SAFE -> RISKY switches since creation.
    pub to_risky: u64,
    /// Robot-steps run on SAFE / in total.
    pub safe_steps: u64,
    pub steps: u64,
}

impl MetaSwitch {
    pub fn new(n: usize, threshold: f32, hysteresis: f32, min_safe_steps: usize) -> MetaSwitch {
        MetaSwitch {
            threshold,
            hysteresis,
            min_safe_steps,
            on_safe: vec![false; n],
            safe_for: vec![0; n],
            to_safe: 0,
            to_risky: 0,
            safe_steps: 0,
            steps: 0,
        }
    }

    /// Takes this step's IQR of every robot; returns which robots act with SAFE.
    pub fn update(&mut self, iqr: &[f32]) -> &[bool] {
        assert_eq!(iqr.len(), self.on_safe.len(), "one IQR per robot");
        for (i, &x) in iqr.iter().enumerate() {
            if !self.on_safe[i] {
                if x > self.threshold {
                    self.on_safe[i] = true;
                    self.safe_for[i] = 0;
                    self.to_safe += 1;
                }
            } else if x < self.threshold - self.hysteresis
                && self.safe_for[i] >= self.min_safe_steps
            {
                self.on_safe[i] = false;
                self.to_risky += 1;
            }
            if self.on_safe[i] {
                self.safe_for[i] += 1;
                self.safe_steps += 1;
            }
            self.steps += 1;
        }
        &self.on_safe
    }

    /// Robot `i` starts a new episode: back on RISKY (not counted as a switch).
    pub fn reset(&mut self, i: usize) {
        self.on_safe[i] = false;
        self.safe_for[i] = 0;
    }

    pub fn on_safe(&self) -> &[bool] {
        &self.on_safe
    }

    /// Fraction of robot-steps on SAFE.
    pub fn safe_fraction(&self) -> f64 {
        self.safe_steps as f64 / self.steps.max(1) as f64
    }
}

/// What to evaluate.
#[derive(Debug, Clone, Serialize)]
pub struct RaceOptions {
    pub agents: usize,
    pub episodes: usize,
    pub threads: usize,
    /// Env seed (commands, noise, pushes, randomisation).
    pub seed: u64,
    /// Seed of the course (obstacles, rough patches); the same for every policy.
    pub course_seed: u64,
    pub params: ScenarioParams,
}

impl Default for RaceOptions {
    fn default() -> Self {
        let params = ScenarioParams::default();
        RaceOptions {
            agents: 50,
            episodes: 10,
            threads: 1,
            seed: 0,
            course_seed: 0,
            params,
        }
    }
}

/// The meta controller's switching log.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MetaLog {
    pub config: MetaConfig,
    pub switches_to_safe: u64,
    pub switches_to_risky: u64,
    /// Mean RISKY -> SAFE switches per episode.
    pub switches_per_episode: f64,
    /// Fraction of robot-steps acted by SAFE.
    pub safe_fraction: f64,
    /// Robot-steps the controller decided.
    pub robot_steps: u64,
    /// IQR of the RISKY critic over all robot-steps: quantiles 0.25 / 0.5 / 0.75 / 0.95.
    pub iqr_quantiles: [f64; 4],
    /// Where along the course the IQR is high: the RISKY critic's mean IQR and
    /// the fraction of steps on SAFE per 0.5 m of trunk x (bins with steps only).
    pub iqr_by_x: Vec<IqrBin>,
}

/// Robot-steps whose trunk x fell in [x0, x0 + 0.5).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct IqrBin {
    pub x0_m: f64,
    pub steps: u64,
    pub mean_iqr: f64,
    pub safe_fraction: f64,
}

/// Width of the [`IqrBin`]s (m).
const IQR_BIN_M: f64 = 0.5;

/// Accumulates IQR and SAFE use by trunk x.
#[derive(Debug, Default)]
struct IqrByX {
    /// bin index (floor(x / width)) -> (steps, IQR sum, steps on SAFE)
    bins: std::collections::BTreeMap<i64, (u64, f64, u64)>,
}

impl IqrByX {
    fn add(&mut self, x: f64, iqr: f64, safe: bool) {
        if !x.is_finite() {
            return;
        }
        let b = self.bins.entry((x / IQR_BIN_M).floor() as i64).or_default();
        b.0 += 1;
        b.1 += iqr;
        b.2 += safe as u64;
    }

    fn bins(&self) -> Vec<IqrBin> {
        self.bins
            .iter()
            .map(|(&k, &(n, sum, safe))| IqrBin {
                x0_m: k as f64 * IQR_BIN_M,
                steps: n,
                mean_iqr: sum / n as f64,
                safe_fraction: safe as f64 / n as f64,
            })
            .collect()
    }
}

/// One row: a policy (or the meta controller) over all its episodes.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct RaceRow {
    pub name: String,
    pub episodes: usize,
    /// Returns' 0.25, 0.5, 0.75 quantiles (worst, middle, best case).
    pub q25: f64,
    pub q50: f64,
    pub q75: f64,
    pub mean_return: f64,
    /// Episodes that ended before the time-out.
    pub fall_fraction: f64,
    /// Mean distance from the start at the episode end (m).
    pub mean_distance_m: f64,
    pub returns: Vec<f64>,
    pub meta: Option<MetaLog>,
}

/// One finished race episode.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct RaceEpisode {
    pub total_reward: f64,
    /// Ended before the time-out.
    pub fell: bool,
    /// Distance from the start at the end (m).
    pub distance_m: f64,
}

impl RaceRow {
    fn new(name: &str, eps: &[RaceEpisode], meta: Option<MetaLog>) -> RaceRow {
        let returns: Vec<f64> = eps.iter().map(|e| e.total_reward).collect();
        RaceRow {
            name: name.to_string(),
            episodes: eps.len(),
            q25: quantile(&returns, 0.25),
            q50: quantile(&returns, 0.5),
            q75: quantile(&returns, 0.75),
            mean_return: mean(&returns),
            fall_fraction: eps.iter().filter(|e| e.fell).count() as f64 / eps.len().max(1) as f64,
            mean_distance_m: mean(&eps.iter().map(|e| e.distance_m).collect::<Vec<_>>()),
            returns,
            meta,
        }
    }
}

#[derive(Debug, Clone, Serialize)]
pub struct RaceReport {
    pub options: RaceOptions,
    pub course: Vec<super::ground::Segment>,
    pub rows: Vec<RaceRow>,
}

/// Who acts in a race run.
enum Driver<'a> {
    Single(&'a NamedPolicy),
    Meta {
        risky: &'a NamedPolicy,
        safe: &'a NamedPolicy,
        cfg: MetaConfig,
    },
}

/// The meta controller's env: the risky policy's, writing every observation
/// group either policy reads (e.g. an RMA student's history).
fn meta_env(risky: &NamedPolicy, safe: &NamedPolicy) -> Result<EnvConfig> {
    let mut env = risky.env.clone();
    let (ro, so) = (&risky.env.observation, &safe.env.observation);
    for g in &so.groups {
        if !ro.groups.contains(g) {
            env.observation.groups.push(*g);
        }
    }
    let both_history =
        ro.groups.contains(&ObsGroup::History) && so.groups.contains(&ObsGroup::History);
    anyhow::ensure!(
        !both_history || ro.history_steps == so.history_steps,
        "the meta controller's policies keep {} and {} history steps: they cannot share one env",
        ro.history_steps,
        so.history_steps
    );
    if so.groups.contains(&ObsGroup::History) {
        env.observation.history_steps = so.history_steps;
    }
    Ok(env)
}

fn race_spec() -> ScenarioSpec {
    ScenarioSpec::new(Load::None, GroundKind::RaceTrack, true)
}

/// Runs `driver` until every agent has finished `opts.episodes` episodes;
/// returns (return, fell, distance) of each agent's first `episodes` episodes.
fn run_race(driver: &Driver, opts: &RaceOptions) -> Result<(Vec<RaceEpisode>, Option<MetaLog>)> {
    let env_cfg = match driver {
        Driver::Single(p) => p.env.clone(),
        Driver::Meta { risky, safe, .. } => meta_env(risky, safe)?,
    };
    let env_layout = env_cfg.obs_layout();
    let setup = build_scenario(&race_spec(), &env_cfg, &opts.params, opts.course_seed)?;
    let n = opts.agents;
    let mut run = ScenarioRun::new(&setup, n, opts.threads, opts.seed)?;
    let mut done: Vec<Vec<RaceEpisode>> = vec![Vec::new(); n];
    let max_steps = setup.env.max_episode_steps() * opts.episodes + 1;
    let mut switch = match driver {
        Driver::Meta { cfg, .. } => Some(MetaSwitch::new(
            n,
            cfg.threshold,
            cfg.hysteresis,
            cfg.min_safe_steps,
        )),
        Driver::Single(_) => None,
    };
    let mut iqrs: Vec<f64> = Vec::new();
    let mut by_x = IqrByX::default();
    for _ in 0..max_steps {
        let actions = match driver {
            Driver::Single(p) => p.policy.actions(run.obs())?,
            Driver::Meta { risky, safe, .. } => {
                // each policy reads its own groups of the shared observation row
                let risky_obs = relayout_rows(run.obs(), &env_layout, &risky.env.obs_layout())?;
                let iqr = risky.critic()?.iqr(&risky_obs);
                iqrs.extend(iqr.iter().map(|&x| x as f64));
                let sw = switch.as_mut().expect("meta switch");
                let use_safe = sw.update(&iqr).to_vec();
                for (i, (&q, &safe)) in iqr.iter().zip(&use_safe).enumerate() {
                    by_x.add(run.env(i).robot().base_pos_m()[0], q as f64, safe);
                }
                let mut a = risky.policy.actions(&risky_obs)?;
                if use_safe.iter().any(|&s| s) {
                    let safe_obs = relayout_rows(run.obs(), &env_layout, &safe.env.obs_layout())?;
                    let b = safe.policy.actions(&safe_obs)?;
                    for (i, s) in use_safe.iter().enumerate() {
                        if *s {
                            a[i * ACT_DIM..(i + 1) * ACT_DIM]
                                .copy_from_slice(&b[i * ACT_DIM..(i + 1) * ACT_DIM]);
                        }
                    }
                }
                a
            }
        };
        // a single policy's agent that has run its episodes stops; a meta
        // controller's keep walking (their IQR and switches are logged)
        let active: Option<Vec<bool>> = match driver {
            Driver::Single(_) => Some(done.iter().map(|d| d.len() < opts.episodes).collect()),
            Driver::Meta { .. } => None,
        };
        for s in run.step_active(&actions, active.as_deref()) {
            let d = &mut done[s.env_index];
            if d.len() < opts.episodes {
                d.push(RaceEpisode {
                    total_reward: s.total_reward,
                    fell: s.end != EpisodeEnd::TimeOut,
                    distance_m: s.distance_m,
                });
            }
        }
        if let Some(sw) = switch.as_mut() {
            for (i, &d) in run.dones().iter().enumerate() {
                if d {
                    sw.reset(i);
                }
            }
        }
        if done.iter().all(|d| d.len() >= opts.episodes) {
            break;
        }
    }
    let eps: Vec<RaceEpisode> = done.into_iter().flatten().collect();
    let meta = match (driver, switch) {
        (Driver::Meta { cfg, .. }, Some(sw)) => Some(MetaLog {
            config: cfg.clone(),
            switches_to_safe: sw.to_safe,
            switches_to_risky: sw.to_risky,
            switches_per_episode: sw.to_safe as f64 / eps.len().max(1) as f64,
            safe_fraction: sw.safe_fraction(),
            robot_steps: sw.steps,
            iqr_quantiles: [0.25, 0.5, 0.75, 0.95].map(|q| quantile(&iqrs, q)),
            iqr_by_x: by_x.bins(),
        }),
        _ => None,
    };
    Ok((eps, meta))
}

/// Runs every policy, then each meta controller (`metas`: their settings with the
/// names of their RISKY and SAFE policies in `policies`).
pub fn evaluate_race(
    policies: &[NamedPolicy],
    metas: &[MetaConfig],
    opts: &RaceOptions,
    progress: impl FnMut(&RaceRow),
) -> Result<RaceReport> {
    evaluate_race_cached(policies, metas, opts, &RolloutCache::none(), progress)
}

/// [`evaluate_race`], reading and storing its rollouts in `cache`.
pub fn evaluate_race_cached(
    policies: &[NamedPolicy],
    metas: &[MetaConfig],
    opts: &RaceOptions,
    cache: &RolloutCache,
    mut progress: impl FnMut(&RaceRow),
) -> Result<RaceReport> {
    anyhow::ensure!(
        opts.agents > 0 && opts.episodes > 0,
        "need at least one agent and one episode"
    );
    let find = |n: &str| {
        policies
            .iter()
            .find(|p| p.name == n)
            .with_context(|| format!("meta controller: no policy named {n:?}"))
    };
    // every policy's race, then every meta controller's; they run side by side
    let mut drivers: Vec<(String, Driver)> = policies
        .iter()
        .map(|p| (p.name.clone(), Driver::Single(p)))
        .collect();
    for cfg in metas {
        let (risky, safe) = (find(&cfg.risky)?, find(&cfg.safe)?);
        let meta = Driver::Meta {
            risky,
            safe,
            cfg: cfg.clone(),
        };
        drivers.push((cfg.name.clone(), meta));
    }
    let key = |(_, driver): &(String, Driver)| {
        let o = opts;
        let race = format!(
            "race\n{:?}\nagents {} episodes {} seed {} course {}",
            o.params, o.agents, o.episodes, o.seed, o.course_seed
        );
        match driver {
            Driver::Single(p) => Some(format!("{race}\n{}", p.rollout_key()?)),
            Driver::Meta { risky, safe, cfg } => Some(format!(
                "{race}\nmeta {cfg:?}\nrisky {}\nsafe {}",
                risky.rollout_key()?,
                safe.rollout_key()?
            )),
        }
    };
    let raced = run_jobs_cached(
        &drivers,
        opts.threads,
        cache,
        key,
        |(_, driver), threads| {
            run_race(
                driver,
                &RaceOptions {
                    threads,
                    ..opts.clone()
                },
            )
        },
    )?;
    let mut rows = Vec::new();
    for ((name, _), (eps, log)) in drivers.iter().zip(raced) {
        let row = RaceRow::new(name, &eps, log);
        progress(&row);
        rows.push(row);
    }
    let course = super::ground::Ground::race_track(&opts.params.race, opts.course_seed)
        .segments()
        .to_vec();
    Ok(RaceReport {
        options: opts.clone(),
        course,
        rows,
    })
}

impl RaceReport {
    pub fn markdown(&self) -> String {
        let header = [
            "Policy",
            "Return q0.25 (worst)",
            "q0.5 (middle)",
            "q0.75 (best)",
            "Mean",
            "Falls %",
            "Distance m",
            "Episodes",
        ]
        .map(String::from);
        let right = [false, true, true, true, true, true, true, true];
        let best =
            |f: fn(&RaceRow) -> f64| self.rows.iter().map(f).fold(f64::NEG_INFINITY, f64::max);
        let (b25, b50, b75) = (best(|r| r.q25), best(|r| r.q50), best(|r| r.q75));
        let bold = |x: f64, b: f64| {
            if self.rows.len() > 1 && x == b {
                format!("**{x:.3}**")
            } else {
                format!("{x:.3}")
            }
        };
        let rows: Vec<Vec<String>> = self
            .rows
            .iter()
            .map(|r| {
                vec![
                    r.name.clone(),
                    bold(r.q25, b25),
                    bold(r.q50, b50),
                    bold(r.q75, b75),
                    format!("{:.3}", r.mean_return),
                    format!("{:.1}", 100.0 * r.fall_fraction),
                    format!("{:.2}", r.mean_distance_m),
                    r.episodes.to_string(),
                ]
            })
            .collect();
        let o = &self.options;
        let mut s = format!(
            "Race track returns ({} agents x {} episodes, forward {} m/s, pushes {} N every {} steps for {})\n\n{}",
            o.agents,
            o.episodes,
            o.params.forward_mps,
            o.params.push_force_n,
            o.params.push_every_steps,
            o.params.push_hold_steps,
            markdown_table(&header, &right, &rows)
        );
        for r in &self.rows {
            if let Some(m) = &r.meta {
                s.push_str(&format!(
                    "\n{}: RISKY {} -> SAFE {} above IQR {} (back below {}, after >= {} steps): \
                     {} switches to SAFE ({:.2} per episode), {} back; {:.1}% of steps on SAFE; \
                     IQR q0.25/0.5/0.75/0.95 = {:.3}/{:.3}/{:.3}/{:.3}\n",
                    r.name,
                    m.config.risky,
                    m.config.safe,
                    m.config.threshold,
                    m.config.threshold - m.config.hysteresis,
                    m.config.min_safe_steps,
                    m.switches_to_safe,
                    m.switches_per_episode,
                    m.switches_to_risky,
                    100.0 * m.safe_fraction,
                    m.iqr_quantiles[0],
                    m.iqr_quantiles[1],
                    m.iqr_quantiles[2],
                    m.iqr_quantiles[3],
                ));
            }
        }
        s
    }

    pub fn csv(&self) -> String {
        let mut s = csv_line(
            &[
                "policy",
                "episodes",
                "q25",
                "q50",
                "q75",
                "mean_return",
                "fall_fraction",
                "mean_distance_m",
                "switches_to_safe",
                "safe_fraction",
            ]
            .map(String::from),
        );
        for r in &self.rows {
            s.push_str(&csv_line(&[
                r.name.clone(),
                r.episodes.to_string(),
                format!("{:.4}", r.q25),
                format!("{:.4}", r.q50),
                format!("{:.4}", r.q75),
                format!("{:.4}", r.mean_return),
                format!("{:.4}", r.fall_fraction),
                format!("{:.3}", r.mean_distance_m),
                r.meta
                    .as_ref()
                    .map_or(String::new(), |m| m.switches_to_safe.to_string()),
                r.meta
                    .as_ref()
                    .map_or(String::new(), |m| format!("{:.4}", m.safe_fraction)),
            ]));
        }
        s
    }

    pub fn json(&self) -> serde_json::Value {
        serde_json::to_value(self).unwrap_or(serde_json::Value::Null)
    }
}
