//! `rall eval platform`: the paper's table II. The robot starts on a platform
//! (0.40 or 0.45 m) and walks forward off its edge; a drop succeeds when the
//! robot has landed and is still upright (no termination, payload off the
//! ground) a fixed time after the drop.
//!
//! Outcomes per robot ([`DropOutcome`]):
//! - the drop happens at the first step where the trunk is past the edge
//!   (x > edge) or has come down by half the platform height (walked off a side);
//! - `Success`: alive `settle` steps after the drop (or at the time-out, if that
//!   comes first) with the trunk down near the lower ground;
//! - `Fell`: the episode ended (termination, payload on the ground) after the drop;
//! - `NotLanded`: alive but still up at the check (hanging on the edge);
//! - `FellBeforeDrop`: ended on the platform; `NotReached`: never dropped.
//!
//! Only `Success` counts towards the success rate.

use anyhow::Result;
use serde::Serialize;

use super::cache::{run_jobs_cached, RolloutCache};
use super::report::{csv_line, markdown_table};
use super::rollout::{run_first_episodes, FirstEpisode, NamedPolicy};
use super::scenario::{build_scenario, GroundKind, Load, ScenarioParams, ScenarioSpec};

/// How one robot's drop went.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum DropOutcome {
    Success,
    Fell,
    NotLanded,
    FellBeforeDrop,
    NotReached,
}

/// Follows one robot's trunk through its episode and judges the drop.
#[derive(Debug, Clone, PartialEq)]
pub struct DropWatch {
    edge_x_m: f64,
    /// Trunk z on the platform at spawn (m).
    spawn_z_m: f64,
    height_m: f64,
    settle_steps: usize,
    dropped_at: Option<usize>,
    /// Trunk z at the check (drop + settle) or at the last step seen after the drop.
    last_z_after_drop: Option<f64>,
    checked: bool,
}

impl DropWatch {
    pub fn new(edge_x_m: f64, spawn_z_m: f64, height_m: f64, settle_steps: usize) -> DropWatch {
        DropWatch {
            edge_x_m,
            spawn_z_m,
            height_m,
            settle_steps,
            dropped_at: None,
            last_z_after_drop: None,
            checked: false,
        }
    }

    /// The trunk position after `step` (1-based) of an episode that goes on.
    pub fn observe(&mut self, step: usize, trunk_x_m: f64, trunk_z_m: f64) {
        if self.checked {
            return;
        }
        let down = trunk_z_m < self.spawn_z_m - self.height_m / 2.0;
        match self.dropped_at {
            None if trunk_x_m > self.edge_x_m || down => {
                self.dropped_at = Some(step);
                self.last_z_after_drop = Some(trunk_z_m);
            }
            None => {}
            Some(d) => {
                self.last_z_after_drop = Some(trunk_z_m);
                if step >= d + self.settle_steps {
                    self.checked = true;
                }
            }
        }
    }

    /// Step of the drop, if any.
    pub fn dropped_at(&self) -> Option<usize> {
        self.dropped_at
    }

    /// The verdict, given how the episode ended.
    pub fn outcome(&self, episode: &FirstEpisode) -> DropOutcome {
        let Some(_) = self.dropped_at else {
            return if episode.fell() {
                DropOutcome::FellBeforeDrop
            } else {
                DropOutcome::NotReached
            };
        };
        if !self.checked && episode.fell() {
            return DropOutcome::Fell;
        }
        let landed = self
            .last_z_after_drop
            .is_some_and(|z| z < self.spawn_z_m - self.height_m / 2.0);
        if landed {
            DropOutcome::Success
        } else {
            DropOutcome::NotLanded
        }
    }
}

/// What to evaluate.
#[derive(Debug, Clone, Serialize)]
pub struct PlatformOptions {
    pub heights_m: Vec<f64>,
    pub seeds: Vec<u64>,
    /// Robots per seed (in parallel).
    pub repeats: usize,
    pub threads: usize,
    /// Time after the drop at which the robot must still be up (s).
    pub settle_s: f64,
    /// Payload carried (default none).
    pub load: Load,
    pub params: ScenarioParams,
}

impl Default for PlatformOptions {
    fn default() -> Self {
        PlatformOptions {
            heights_m: vec![0.40, 0.45],
            seeds: vec![0, 1, 2],
            repeats: 50,
            threads: 1,
            settle_s: 2.0,
            load: Load::None,
            params: ScenarioParams::default(),
        }
    }
}

/// One row: a policy at one height.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct PlatformCell {
    pub height_m: f64,
    pub policy: String,
    pub robots: usize,
    pub success: usize,
    pub fell: usize,
    pub not_landed: usize,
    pub fell_before_drop: usize,
    pub not_reached: usize,
    /// success / robots, in percent.
    pub success_pct: f64,
    /// How the episodes ended (env reason, or "payload_on_ground"), with counts.
    pub ends: Vec<(String, usize)>,
    /// Whether each robot succeeded, seed-major (for bootstrap intervals).
    pub success_per_robot: Vec<bool>,
}

impl PlatformCell {
    pub fn from_outcomes(height_m: f64, policy: &str, outcomes: &[DropOutcome]) -> PlatformCell {
        let count = |o: DropOutcome| outcomes.iter().filter(|&&x| x == o).count();
        let success = count(DropOutcome::Success);
        PlatformCell {
            height_m,
            policy: policy.to_string(),
            robots: outcomes.len(),
            success,
            fell: count(DropOutcome::Fell),
            not_landed: count(DropOutcome::NotLanded),
            fell_before_drop: count(DropOutcome::FellBeforeDrop),
            not_reached: count(DropOutcome::NotReached),
            success_pct: 100.0 * success as f64 / outcomes.len().max(1) as f64,
            ends: Vec::new(),
            success_per_robot: outcomes
                .iter()
                .map(|&o| o == DropOutcome::Success)
                .collect(),
        }
    }

    /// Adds the count of each way the episodes ended.
    pub fn with_ends(mut self, episodes: &[FirstEpisode]) -> PlatformCell {
        let mut ends: Vec<(String, usize)> = Vec::new();
        for e in episodes {
            let k = e
                .end
                .map_or("payload_on_ground".to_string(), |x| format!("{x:?}"));
            match ends.iter_mut().find(|(n, _)| *n == k) {
                Some((_, c)) => *c += 1,
                None => ends.push((k, 1)),
            }
        }
        ends.sort();
        self.ends = ends;
        self
    }
}

#[derive(Debug, Clone, Serialize)]
pub struct PlatformReport {
    pub policies: Vec<String>,
    pub options: PlatformOptions,
    pub cells: Vec<PlatformCell>,
}

/// Runs `n` robots of the platform scenario and judges each drop (with how
/// each episode ended).
pub fn platform_outcomes(
    policy: &dyn super::policy::Actor,
    setup: &super::scenario::ScenarioSetup,
    n: usize,
    threads: usize,
    seed: u64,
    settle_s: f64,
) -> Result<Vec<(DropOutcome, FirstEpisode)>> {
    let geo = setup
        .platform
        .ok_or_else(|| anyhow::anyhow!("scenario {} has no platform", setup.spec.name()))?;
    let settle = (settle_s / setup.env.control.policy_dt_s()).round() as usize;
    let mut watches = vec![DropWatch::new(geo.edge_x_m, setup.spawn_m[2], geo.height_m, settle); n];
    let first = run_first_episodes(policy, setup, n, threads, seed, |i, env, step| {
        let p = env.robot().base_pos_m();
        watches[i].observe(step, p[0], p[2]);
    })?;
    Ok(watches
        .iter()
        .zip(&first)
        .map(|(w, e)| (w.outcome(e), *e))
        .collect())
}

/// Runs every policy at every height.
pub fn evaluate_platform(
    policies: &[NamedPolicy],
    opts: &PlatformOptions,
    progress: impl FnMut(&PlatformCell),
) -> Result<PlatformReport> {
    evaluate_platform_cached(policies, opts, &RolloutCache::none(), progress)
}

/// [`evaluate_platform`], reading and storing its rollouts in `cache`.
pub fn evaluate_platform_cached(
    policies: &[NamedPolicy],
    opts: &PlatformOptions,
    cache: &RolloutCache,
    mut progress: impl FnMut(&PlatformCell),
) -> Result<PlatformReport> {
    anyhow::ensure!(!policies.is_empty(), "no policy to evaluate");
    anyhow::ensure!(
        opts.repeats > 0 && !opts.seeds.is_empty(),
        "need at least one seed and one repeat"
    );
    // every (height, policy, seed) is its own rollout; they run side by side
    let mut jobs = Vec::new();
    for &h in &opts.heights_m {
        let spec = ScenarioSpec::new(opts.load, GroundKind::Platform { height_m: h }, false);
        for p in policies {
            for &seed in &opts.seeds {
                jobs.push((h, spec, p, seed));
            }
        }
    }
    let key = |(_, spec, p, seed): &(f64, ScenarioSpec, &NamedPolicy, u64)| {
        let (params, robots, settle_s) = (&opts.params, opts.repeats, opts.settle_s);
        p.rollout_key().map(|k| {
            format!("platform\n{spec:?}\n{params:?}\nseed {seed}\nrobots {robots}\nsettle {settle_s:?} s\n{k}")
        })
    };
    let rollouts = run_jobs_cached(
        &jobs,
        opts.threads,
        cache,
        key,
        |(_, spec, p, seed), threads| {
            let setup = build_scenario(spec, &p.env, &opts.params, *seed)?;
            platform_outcomes(
                &p.policy,
                &setup,
                opts.repeats,
                threads,
                *seed,
                opts.settle_s,
            )
        },
    )?;
    let mut cells = Vec::new();
    for (cell_jobs, cell_rollouts) in jobs
        .chunks(opts.seeds.len())
        .zip(rollouts.chunks(opts.seeds.len()))
    {
        let (h, _, p, _) = cell_jobs[0];
        let (o, e): (Vec<DropOutcome>, Vec<FirstEpisode>) =
            cell_rollouts.iter().flatten().copied().unzip();
        let cell = PlatformCell::from_outcomes(h, &p.name, &o).with_ends(&e);
        progress(&cell);
        cells.push(cell);
    }
    Ok(PlatformReport {
        policies: policies.iter().map(|p| p.name.clone()).collect(),
        options: opts.clone(),
        cells,
    })
}

impl PlatformReport {
    /// The paper's table II (plus how the failures happened).
    pub fn markdown(&self) -> String {
        let header = [
            "Height",
            "Policy",
            "Success %",
            "Fell %",
            "Not landed %",
            "Fell before edge %",
            "Not reached %",
            "Robots",
        ]
        .map(String::from);
        let right = [false, false, true, true, true, true, true, true];
        let mut rows = Vec::new();
        let pct = |k: usize, n: usize| format!("{:.1}", 100.0 * k as f64 / n.max(1) as f64);
        for &h in &self.options.heights_m {
            let best = self
                .cells
                .iter()
                .filter(|c| c.height_m == h)
                .map(|c| c.success_pct)
                .fold(f64::NEG_INFINITY, f64::max);
            let mut first = true;
            for c in self.cells.iter().filter(|c| c.height_m == h) {
                let s = format!("{:.1}", c.success_pct);
                rows.push(vec![
                    if first {
                        format!("{h:.2} m")
                    } else {
                        String::new()
                    },
                    c.policy.clone(),
                    if self.policies.len() > 1 && c.success_pct == best {
                        format!("**{s}**")
                    } else {
                        s
                    },
                    pct(c.fell, c.robots),
                    pct(c.not_landed, c.robots),
                    pct(c.fell_before_drop, c.robots),
                    pct(c.not_reached, c.robots),
                    c.robots.to_string(),
                ]);
                first = false;
            }
        }
        let o = &self.options;
        format!(
            "Platform drop success (walk off at {} m/s; success = landed and up {} s after the drop; \
             {} seeds x {} robots)\n\n{}",
            o.params.forward_mps,
            o.settle_s,
            o.seeds.len(),
            o.repeats,
            markdown_table(&header, &right, &rows)
        )
    }

    pub fn csv(&self) -> String {
        let mut s = csv_line(
            &[
                "height_m",
                "policy",
                "robots",
                "success",
                "fell",
                "not_landed",
                "fell_before_drop",
                "not_reached",
                "success_pct",
            ]
            .map(String::from),
        );
        for c in &self.cells {
            s.push_str(&csv_line(&[
                format!("{:.3}", c.height_m),
                c.policy.clone(),
                c.robots.to_string(),
                c.success.to_string(),
                c.fell.to_string(),
                c.not_landed.to_string(),
                c.fell_before_drop.to_string(),
                c.not_reached.to_string(),
                format!("{:.2}", c.success_pct),
            ]));
        }
        s
    }

    pub fn json(&self) -> serde_json::Value {
        serde_json::to_value(self).unwrap_or(serde_json::Value::Null)
    }
}
