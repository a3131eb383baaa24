//! `rall eval ttf`: the paper's table I. For each load (ball, frozen arm, moving
//! arm) x terrain (flat, random) x push (off, on), the Time to Fall: the mean
//! episode length over all robots divided by the full episode length, over
//! `seeds x repeats` robots (paper: 3 seeds x 10 repeats).
//!
//! A robot's episode is its first one: it ends with the env's termination (tilt,
//! trunk on the ground), with its payload's base touching the ground, or with
//! the time-out (a full-length episode).

use anyhow::Result;
use serde::Serialize;

use super::cache::{run_jobs_cached, RolloutCache};
use super::report::{csv_line, markdown_table};
use super::rollout::{run_first_episodes, FirstEpisode, NamedPolicy};
use super::scenario::{build_scenario, GroundKind, Load, ScenarioParams, ScenarioSpec};
use crate::stats::mean;

/// What to evaluate.
#[derive(Debug, Clone, Serialize)]
pub struct TtfOptions {
    /// One scene and env seed per trial (the paper: three).
    pub seeds: Vec<u64>,
    /// Robots per seed, one episode each, run in parallel (the paper: 10).
    pub repeats: usize,
    /// Env worker threads.
    pub threads: usize,
    pub loads: Vec<Load>,
    /// Table columns: flat and random (rough) ground ...
    pub terrains: Vec<GroundKind>,
    /// ... each without and with pushes.
    pub pushes: Vec<bool>,
    pub params: ScenarioParams,
}

impl Default for TtfOptions {
    fn default() -> Self {
        TtfOptions {
            seeds: vec![0, 1, 2],
            repeats: 10,
            threads: 1,
            loads: Load::PAYLOADS.to_vec(),
            terrains: vec![GroundKind::Flat, GroundKind::Rough],
            pushes: vec![false, true],
            params: ScenarioParams::default(),
        }
    }
}

/// One cell of the table: a policy in one setup.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct TtfCell {
    pub load: Load,
    /// "flat" or "random".
    pub terrain: String,
    pub push: bool,
    pub policy: String,
    /// Scenario name (see `ScenarioSpec::parse`).
    pub scenario: String,
    /// Time to Fall in [0, 1].
    pub ttf: f64,
    pub ttf_per_seed: Vec<f64>,
    pub robots: usize,
    /// Robots that fell before the time-out (env termination or payload on the ground).
    pub falls: usize,
    /// Of those, falls noticed by the payload touching the ground.
    pub payload_falls: usize,
    pub mean_steps: f64,
    pub episode_steps: usize,
    /// Net displacement from the spawn point / commanded path length, summed over
    /// the robots. Under changing commands even perfect tracking scores well below
    /// 1 (the path turns); `progress_ratio` is the measure to read.
    pub walked_ratio: f64,
    /// Distance made good along the command / commanded path length, summed over
    /// the robots: 1 is perfect tracking, 0 standing still ("robust because it
    /// stands still" shows here).
    pub progress_ratio: f64,
    /// Time to Fall under the strict definition: the episode ends at the first
    /// contact of any non-foot part of the robot (or of its payload's fixed parts)
    /// with the ground.
    pub strict_ttf: f64,
    /// Robots with such a contact before the time-out.
    pub strict_falls: usize,
    /// Policy steps each robot survived, seed-major (for bootstrap intervals).
    pub steps_per_robot: Vec<usize>,
    /// The same under the strict definition.
    pub strict_steps_per_robot: Vec<usize>,
}

/// How the benchmarks define a fall (printed with every table and figure).
pub const FALL_DEFINITION: &str = "A fall: the env's termination (trunk tilted past its limit \
or the trunk on the ground) or a payload part fixed to the trunk (ball container, arm base, \
shoulder, upper arm, elbow) touching the ground; the arm's forearm and wrist and the legs above \
the feet may touch it. Strict: any contact of a non-foot part of the robot or its fixed payload \
with the ground.";

/// All cells, in table order.
#[derive(Debug, Clone, Serialize)]
pub struct TtfReport {
    pub policies: Vec<String>,
    pub options: TtfOptions,
    pub cells: Vec<TtfCell>,
}

/// Time to Fall: mean of `lengths` (policy steps) / `episode_steps`.
pub fn time_to_fall(lengths: &[usize], episode_steps: usize) -> f64 {
    let l: Vec<f64> = lengths.iter().map(|&s| s as f64).collect();
    mean(&l) / episode_steps.max(1) as f64
}

/// The paper's column label of a terrain.
pub fn terrain_label(g: &GroundKind) -> &'static str {
    match g {
        GroundKind::Flat => "Flat",
        GroundKind::Rough => "Random",
        GroundKind::Platform { .. } => "Platform",
        GroundKind::RaceTrack => "Race",
    }
}

/// A cell from the first episodes of each seed's robots.
pub fn ttf_cell(
    spec: &ScenarioSpec,
    policy: &str,
    per_seed: &[Vec<FirstEpisode>],
    episode_steps: usize,
) -> TtfCell {
    let all: Vec<FirstEpisode> = per_seed.iter().flatten().copied().collect();
    let lengths: Vec<usize> = all.iter().map(|e| e.steps).collect();
    let strict: Vec<usize> = all.iter().map(|e| e.strict_steps).collect();
    TtfCell {
        load: spec.load,
        terrain: terrain_label(&spec.ground).to_lowercase(),
        push: spec.push,
        policy: policy.to_string(),
        scenario: spec.name(),
        ttf: time_to_fall(&lengths, episode_steps),
        ttf_per_seed: per_seed
            .iter()
            .map(|s| {
                time_to_fall(
                    &s.iter().map(|e| e.steps).collect::<Vec<_>>(),
                    episode_steps,
                )
            })
            .collect(),
        robots: all.len(),
        falls: all.iter().filter(|e| e.fell()).count(),
        payload_falls: all.iter().filter(|e| e.end.is_none()).count(),
        mean_steps: mean(&lengths.iter().map(|&s| s as f64).collect::<Vec<_>>()),
        episode_steps,
        walked_ratio: all.iter().map(|e| e.walked_m).sum::<f64>()
            / all.iter().map(|e| e.commanded_m).sum::<f64>(),
        progress_ratio: all.iter().map(|e| e.progress_m).sum::<f64>()
            / all.iter().map(|e| e.commanded_m).sum::<f64>(),
        strict_ttf: time_to_fall(&strict, episode_steps),
        strict_falls: strict.iter().filter(|&&s| s < episode_steps).count(),
        steps_per_robot: lengths,
        strict_steps_per_robot: strict,
    }
}

/// Runs every policy in every setup of `opts`. `progress` gets a line per cell.
pub fn evaluate_ttf(
    policies: &[NamedPolicy],
    opts: &TtfOptions,
    progress: impl FnMut(&TtfCell),
) -> Result<TtfReport> {
    evaluate_ttf_cached(policies, opts, &RolloutCache::none(), progress)
}

/// [`evaluate_ttf`], reading and storing its rollouts in `cache`.
pub fn evaluate_ttf_cached(
    policies: &[NamedPolicy],
    opts: &TtfOptions,
    cache: &RolloutCache,
    mut progress: impl FnMut(&TtfCell),
) -> Result<TtfReport> {
    anyhow::ensure!(!policies.is_empty(), "no policy to evaluate");
    anyhow::ensure!(
        opts.repeats > 0 && !opts.seeds.is_empty(),
        "need at least one seed and one repeat"
    );
    // every (setup, policy, seed) is its own rollout; they run side by side
    let mut jobs = Vec::new();
    for &load in &opts.loads {
        for terrain in &opts.terrains {
            for &push in &opts.pushes {
                let spec = ScenarioSpec::new(load, *terrain, push);
                for p in policies {
                    for &seed in &opts.seeds {
                        jobs.push((spec, p, seed));
                    }
                }
            }
        }
    }
    let key = |(spec, p, seed): &(ScenarioSpec, &NamedPolicy, u64)| {
        let (params, robots) = (&opts.params, opts.repeats);
        p.rollout_key().map(|k| {
            format!("time to fall\n{spec:?}\n{params:?}\nseed {seed}\nrobots {robots}\n{k}")
        })
    };
    let rollouts = run_jobs_cached(
        &jobs,
        opts.threads,
        cache,
        key,
        |(spec, p, seed), threads| {
            let setup = build_scenario(spec, &p.env, &opts.params, *seed)?;
            let first = run_first_episodes(
                &p.policy,
                &setup,
                opts.repeats,
                threads,
                *seed,
                |_, _, _| {},
            )?;
            Ok((first, setup.env.max_episode_steps()))
        },
    )?;
    let (firsts, episode_steps): (Vec<Vec<FirstEpisode>>, Vec<usize>) =
        rollouts.into_iter().unzip();
    let mut cells = Vec::new();
    for ((cell_jobs, per_seed), steps) in jobs
        .chunks(opts.seeds.len())
        .zip(firsts.chunks(opts.seeds.len()))
        .zip(episode_steps.chunks(opts.seeds.len()))
    {
        let (spec, p, _) = cell_jobs[0];
        let cell = ttf_cell(&spec, &p.name, per_seed, steps[steps.len() - 1]);
        progress(&cell);
        cells.push(cell);
    }
    Ok(TtfReport {
        policies: policies.iter().map(|p| p.name.clone()).collect(),
        options: opts.clone(),
        cells,
    })
}

impl TtfReport {
    fn columns(&self) -> Vec<(String, bool)> {
        let mut cols = Vec::new();
        for t in &self.options.terrains {
            for &p in &self.options.pushes {
                cols.push((terrain_label(t).to_lowercase(), p));
            }
        }
        cols
    }

    fn cell(&self, load: Load, policy: &str, terrain: &str, push: bool) -> Option<&TtfCell> {
        self.cells.iter().find(|c| {
            c.load == load && c.policy == policy && c.terrain == terrain && c.push == push
        })
    }

    /// The paper's table: rows load x policy, columns terrain x push; the best
    /// policy of each load and column in bold.
    pub fn markdown(&self) -> String {
        let cols = self.columns();
        let mut header = vec!["Load type".to_string(), "Policy".to_string()];
        for (t, p) in &cols {
            let t = if t == "flat" { "Flat" } else { "Random" };
            header.push(format!("{t}, push {}", if *p { "True" } else { "False" }));
        }
        let mut right = vec![false, false];
        right.extend(cols.iter().map(|_| true));
        let mut rows = Vec::new();
        for &load in &self.options.loads {
            let best: Vec<f64> = cols
                .iter()
                .map(|(t, p)| {
                    self.policies
                        .iter()
                        .filter_map(|n| self.cell(load, n, t, *p).map(|c| c.ttf))
                        .fold(f64::NEG_INFINITY, f64::max)
                })
                .collect();
            for (i, name) in self.policies.iter().enumerate() {
                let mut row = vec![
                    if i == 0 {
                        load.label().to_string()
                    } else {
                        String::new()
                    },
                    name.clone(),
                ];
                for (k, (t, p)) in cols.iter().enumerate() {
                    row.push(match self.cell(load, name, t, *p) {
                        Some(c) if self.policies.len() > 1 && c.ttf == best[k] => {
                            format!("**{:.3}**", c.ttf)
                        }
                        Some(c) => format!("{:.3}", c.ttf),
                        None => "-".into(),
                    });
                }
                rows.push(row);
            }
        }
        let o = &self.options;
        let steps = self.cells.first().map_or(0, |c| c.episode_steps);
        format!(
            "Time to Fall (mean episode length / {steps} steps; {} seeds x {} robots per cell; \
             pushes {} N every {} steps for {})\n\n{}\n{FALL_DEFINITION} Strict TTF, progress \
             along the command and falls per cell: ttf.csv.\n",
            o.seeds.len(),
            o.repeats,
            o.params.push_force_n,
            o.params.push_every_steps,
            o.params.push_hold_steps,
            markdown_table(&header, &right, &rows)
        )
    }

    /// One line per cell.
    pub fn csv(&self) -> String {
        let mut s = csv_line(
            &[
                "load",
                "terrain",
                "push",
                "policy",
                "ttf",
                "robots",
                "falls",
                "payload_falls",
                "mean_steps",
                "episode_steps",
                "walked_ratio",
                "ttf_per_seed",
                "progress_ratio",
                "strict_ttf",
                "strict_falls",
            ]
            .map(String::from),
        );
        for c in &self.cells {
            let per_seed: Vec<String> = c.ttf_per_seed.iter().map(|x| format!("{x:.4}")).collect();
            s.push_str(&csv_line(&[
                c.load.name().into(),
                c.terrain.clone(),
                c.push.to_string(),
                c.policy.clone(),
                format!("{:.4}", c.ttf),
                c.robots.to_string(),
                c.falls.to_string(),
                c.payload_falls.to_string(),
                format!("{:.1}", c.mean_steps),
                c.episode_steps.to_string(),
                format!("{:.3}", c.walked_ratio),
                per_seed.join(";"),
                format!("{:.3}", c.progress_ratio),
                format!("{:.4}", c.strict_ttf),
                c.strict_falls.to_string(),
            ]));
        }
        s
    }

    pub fn json(&self) -> serde_json::Value {
        serde_json::to_value(self).unwrap_or(serde_json::Value::Null)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ttf_is_mean_length_over_full_length() {
        assert!((time_to_fall(&[100, 50, 150], 200) - 0.5).abs() < 1e-12);
        assert_eq!(time_to_fall(&[200, 200], 200), 1.0);
    }
}
