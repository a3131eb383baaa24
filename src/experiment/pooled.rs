//! Each method over its training seeds. Runs that share a `name` in the experiment
//! file (`rall-eta0.5` seeds 1-3) are one method; its number weights every seed
//! equally (the mean of the seeds' means; the race: quantiles of the seeds' returns
//! pooled), with a bootstrap that resamples robots within each seed: a description of
//! these trained policies, which does not cover what another seed would do. The seeds'
//! own values travel with it, so the spread between seeds stays visible; whether two
//! methods differ is decided on those values, one per seed (`contrasts`, `verdicts`).

use serde::{Deserialize, Serialize};

use super::spec::ExperimentSpec;
use super::stats::{bootstrap_strata, cell_seed, mean, quantile, Estimate};
use crate::eval::{PlatformReport, RaceReport, TtfReport};

/// One method: the labels of its seeds' runs, in the experiment file's order.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Method {
    /// The first seed's label (the paper's method name; its numbers are looked up by it).
    pub label: String,
    pub seeds: Vec<String>,
}

impl Method {
    /// `RALL (2 seeds)`, or the label alone for one seed.
    pub fn display(&self) -> String {
        match self.seeds.len() {
            1 => self.label.clone(),
            n => format!("{} ({n} seeds)", self.label),
        }
    }
}

/// Groups `labels` (one table's evaluated runs, in table order) into methods: labels of
/// runs with the same `name` go together, and so do meta controllers switching between
/// runs of the same two names (seed 1's pair, seed 2's pair).
pub fn methods_of(spec: &ExperimentSpec, labels: &[String]) -> Vec<Method> {
    let name = |label: &str| spec.run(label).map(|r| r.name.clone());
    let key = |label: &str| {
        if let Some(n) = name(label) {
            return format!("run:{n}");
        }
        match spec.meta.iter().find(|m| m.label == label) {
            Some(m) => format!(
                "meta:{}+{}",
                name(&m.risky).unwrap_or_default(),
                name(&m.safe).unwrap_or_default()
            ),
            None => format!("label:{label}"),
        }
    };
    let mut out: Vec<(String, Method)> = Vec::new();
    for l in labels {
        let k = key(l);
        match out.iter_mut().find(|(kk, _)| *kk == k) {
            Some((_, m)) => {
                if !m.seeds.contains(l) {
                    m.seeds.push(l.clone())
                }
            }
            None => out.push((
                k,
                Method {
                    label: l.clone(),
                    seeds: vec![l.clone()],
                },
            )),
        }
    }
    // seeds in the experiment file's order; the first names the method
    let order = |l: &String| {
        spec.runs
            .iter()
            .position(|r| &r.label == l)
            .or_else(|| {
                spec.meta
                    .iter()
                    .position(|m| &m.label == l)
                    .map(|i| spec.runs.len() + i)
            })
            .unwrap_or(usize::MAX)
    };
    out.into_iter()
        .map(|(_, mut m)| {
            m.seeds.sort_by_key(order);
            m.label = m.seeds[0].clone();
            m
        })
        .collect()
}

/// The bootstrap seed of a method's cell, `cell(label)` naming it: a one-seed method uses
/// its run's cell name, so its interval is the per-run table's to the digit.
fn pooled_seed(base: u64, m: &Method, cell: impl Fn(&str) -> String) -> u64 {
    if m.seeds.len() == 1 {
        cell_seed(base, &cell(&m.label))
    } else {
        cell_seed(base, &format!("seeds:{}", cell(&m.seeds.join("+"))))
    }
}

/// Every method's cells: for each cell of its first seed, the same cell (`same`) of each
/// of its seeds, in seed order. `policy` names the run a cell belongs to.
fn cells_by_method<'a, C>(
    spec: &ExperimentSpec,
    cells: &'a [C],
    policy: impl Fn(&C) -> &str,
    same: impl Fn(&C, &C) -> bool,
) -> Vec<(Method, &'a C, Vec<&'a C>)> {
    let labels: Vec<String> = cells.iter().map(|c| policy(c).to_string()).collect();
    let mut out = Vec::new();
    for m in methods_of(spec, &labels) {
        for c in cells.iter().filter(|c| policy(c) == m.label) {
            let seeds = m
                .seeds
                .iter()
                .filter_map(|s| cells.iter().find(|o| policy(o) == s && same(o, c)))
                .collect();
            out.push((m.clone(), c, seeds));
        }
    }
    out
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct MethodTtfRow {
    pub method: Method,
    pub load: String,
    pub terrain: String,
    pub push: bool,
    pub ttf: Estimate,
    /// Each seed's TTF, in `method.seeds` order.
    pub per_seed: Vec<f64>,
    pub robots: usize,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct MethodPlatformRow {
    pub method: Method,
    pub height_m: f64,
    pub success_pct: Estimate,
    pub per_seed: Vec<f64>,
    pub robots: usize,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct MethodRaceRow {
    pub method: Method,
    pub q25: Estimate,
    pub q50: Estimate,
    pub q75: Estimate,
    /// Each seed's (q0.25, q0.5, q0.75).
    pub per_seed: Vec<[f64; 3]>,
    pub fall_fraction: f64,
    pub episodes: usize,
}

/// The three tables, one row per method.
#[derive(Debug, Clone, Default, Serialize, Deserialize)]
pub struct MethodTables {
    pub ttf: Vec<MethodTtfRow>,
    pub platform: Vec<MethodPlatformRow>,
    pub race: Vec<MethodRaceRow>,
}

/// Mean over strata of each stratum's mean.
fn mean_of_means(strata: &[Vec<f64>]) -> f64 {
    mean(&strata.iter().map(|s| mean(s)).collect::<Vec<_>>())
}

impl MethodTables {
    pub fn new(
        spec: &ExperimentSpec,
        ttf: Option<&TtfReport>,
        platform: Option<&PlatformReport>,
        race: Option<&RaceReport>,
    ) -> MethodTables {
        let b = &spec.bootstrap;
        let ci = |strata: &[Vec<f64>], stat: &dyn Fn(&[Vec<f64>]) -> f64, seed: u64| {
            bootstrap_strata(strata, stat, b.resamples, b.level, seed)
        };
        let mut out = MethodTables::default();
        let ttf_cells = ttf.map_or(&[][..], |t| &t.cells);
        for (m, c, cells) in cells_by_method(
            spec,
            ttf_cells,
            |c| &c.policy,
            |o, c| o.load == c.load && o.terrain == c.terrain && o.push == c.push,
        ) {
            // every seed's cell has the same episode length (the same scenario)
            let len = c.episode_steps.max(1) as f64;
            let strata: Vec<Vec<f64>> = cells
                .iter()
                .map(|o| o.steps_per_robot.iter().map(|&s| s as f64).collect())
                .collect();
            let seed = pooled_seed(b.seed, &m, |label| {
                format!("ttf/{label}/{}/{}/{}", c.load.name(), c.terrain, c.push)
            });
            out.ttf.push(MethodTtfRow {
                load: c.load.name().to_string(),
                terrain: c.terrain.clone(),
                push: c.push,
                ttf: ci(&strata, &|s| mean_of_means(s) / len, seed),
                per_seed: strata.iter().map(|s| mean(s) / len).collect(),
                robots: cells.iter().map(|o| o.robots).sum(),
                method: m,
            });
        }
        let platform_cells = platform.map_or(&[][..], |p| &p.cells);
        for (m, c, cells) in cells_by_method(
            spec,
            platform_cells,
            |c| &c.policy,
            |o, c| o.height_m == c.height_m,
        ) {
            let strata: Vec<Vec<f64>> = cells
                .iter()
                .map(|o| {
                    o.success_per_robot
                        .iter()
                        .map(|&s| if s { 100.0 } else { 0.0 })
                        .collect()
                })
                .collect();
            let seed = pooled_seed(b.seed, &m, |label| {
                format!("platform/{label}/{}", c.height_m)
            });
            out.platform.push(MethodPlatformRow {
                height_m: c.height_m,
                success_pct: ci(&strata, &mean_of_means, seed),
                per_seed: strata.iter().map(|s| mean(s)).collect(),
                robots: cells.iter().map(|o| o.robots).sum(),
                method: m,
            });
        }
        let per_agent = race.map_or(1, |r| r.options.episodes.max(1));
        let race_rows = race.map_or(&[][..], |r| &r.rows);
        for (m, _, rows) in cells_by_method(spec, race_rows, |r| &r.name, |_, _| true) {
            // agents are the units: each keeps its episodes together
            let strata: Vec<Vec<Vec<f64>>> = rows
                .iter()
                .map(|o| o.returns.chunks(per_agent).map(|c| c.to_vec()).collect())
                .collect();
            let est = |q: f64, name: &str| {
                let pooled = move |s: &[Vec<Vec<f64>>]| {
                    let all: Vec<f64> = s.iter().flatten().flatten().copied().collect();
                    quantile(&all, q)
                };
                let seed = pooled_seed(b.seed, &m, |label| format!("race/{label}/{name}"));
                bootstrap_strata(&strata, pooled, b.resamples, b.level, seed)
            };
            let episodes: usize = rows.iter().map(|o| o.episodes).sum();
            out.race.push(MethodRaceRow {
                q25: est(0.25, "q25"),
                q50: est(0.5, "q50"),
                q75: est(0.75, "q75"),
                per_seed: rows.iter().map(|o| [o.q25, o.q50, o.q75]).collect(),
                fall_fraction: rows
                    .iter()
                    .map(|o| o.fall_fraction * o.episodes as f64)
                    .sum::<f64>()
                    / episodes.max(1) as f64,
                episodes,
                method: m,
            });
        }
        out
    }
}

/// `0.930 [0.85, 0.99] {0.93, 1.00}`: the estimate, its interval and each seed's value.
pub fn show_with_seeds(e: &Estimate, per_seed: &[f64], digits: usize) -> String {
    if per_seed.len() < 2 {
        return e.show(digits);
    }
    let seeds: Vec<String> = per_seed
        .iter()
        .map(|v| format!("{v:.d$}", d = digits))
        .collect();
    format!("{} {{{}}}", e.show(digits), seeds.join(", "))
}
