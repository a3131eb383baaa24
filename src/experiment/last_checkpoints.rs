//! A run's headline numbers over its last K checkpoints (`[checkpoints]`), not
//! one: single checkpoints of one run differ by up to 69 points in platform
//! success, more than the methods do. Checkpoint k of every run is evaluated
//! with the benchmark's seeds offset by `k x CHECKPOINT_SEED_STRIDE` on
//! `repeats / K` robots (rounded up), so the K checkpoints together see as many
//! robots as one policy did; the robots are then pooled into the run's cells
//! (the headline is their mean, i.e. the mean over the checkpoints), and each
//! checkpoint's own number is kept as the checkpoint-to-checkpoint spread.

use std::path::PathBuf;

use anyhow::{bail, Result};
use serde::{Deserialize, Serialize};

use super::spec::{CheckpointsSpec, ExperimentSpec, RunSpec};
use super::stats::mean;
use crate::eval::platform::{evaluate_platform_cached, PlatformCell};
use crate::eval::ttf::{evaluate_ttf_cached, time_to_fall, TtfCell};
use crate::eval::{
    NamedPolicy, PlatformOptions, PlatformReport, RolloutCache, TtfOptions, TtfReport,
};
use crate::runner::RunDir;

/// Scenario seeds of checkpoint k start at `first_seed + k x` this.
pub const CHECKPOINT_SEED_STRIDE: u64 = 1000;

/// Iterations of the last `c.last` checkpoints of a run that reaches `target`,
/// newest first.
pub fn headline_iterations(c: &CheckpointsSpec, target: usize) -> Result<Vec<usize>> {
    (0..c.last)
        .map(|k| {
            target.checked_sub(k * c.every).filter(|&it| it > 0).ok_or_else(|| {
                anyhow::anyhow!(
                    "[checkpoints] last = {} every {} reaches before iteration 1 of a {target}-iteration run",
                    c.last,
                    c.every
                )
            })
        })
        .collect()
}

/// The numbered checkpoint `it` of run `r`: in its run directory, else in its
/// shipped copy (`checkpoints/model_<it>.safetensors`, actor and config only).
pub fn checkpoint_path(spec: &ExperimentSpec, r: &RunSpec, it: usize) -> Result<PathBuf> {
    let name = format!("model_{it:06}.safetensors");
    let local = spec.run_dir(r).join("checkpoints").join(&name);
    if local.exists() {
        return Ok(local);
    }
    if let Some(copy) = spec.shipped_copy(r) {
        let p = copy.join("checkpoints").join(&name);
        if p.exists() {
            return Ok(p);
        }
    }
    let stored = RunDir {
        root: spec.run_dir(r),
    }
    .checkpoints_by_iteration()
    .len();
    bail!(
        "run {:?}: [checkpoints] needs its checkpoint of iteration {it} ({}), which neither {} nor the shipped copy holds ({stored} numbered checkpoints stored)",
        r.label,
        name,
        spec.run_dir(r).display()
    )
}

/// Checkpoint `k` (0 = the newest) of each run labelled in `labels`, named by
/// the run's label.
pub fn load_kth_checkpoint(
    spec: &ExperimentSpec,
    c: &CheckpointsSpec,
    labels: &[String],
    k: usize,
) -> Result<Vec<NamedPolicy>> {
    labels
        .iter()
        .map(|l| {
            let r = spec
                .run(l)
                .ok_or_else(|| anyhow::anyhow!("no run labelled {l:?}"))?;
            let target = super::run_target(spec, r)?;
            let it = headline_iterations(c, target)?[k];
            NamedPolicy::load(l, &checkpoint_path(spec, r, it)?)
        })
        .collect()
}

/// The scenario seeds of checkpoint `k`: the benchmark's, offset.
fn checkpoint_seeds(seeds: &[u64], k: usize) -> Vec<u64> {
    seeds
        .iter()
        .map(|s| s + k as u64 * CHECKPOINT_SEED_STRIDE)
        .collect()
}

/// Robots per checkpoint so that K checkpoints see at least `repeats` in all.
pub fn repeats_per_checkpoint(repeats: usize, k: usize) -> usize {
    repeats.div_ceil(k.max(1)).max(1)
}

/// One run's benchmark number at each of its K checkpoints.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct CheckpointSpread {
    pub benchmark: &'static str,
    pub run: String,
    /// Newest first, as `values`.
    pub iterations: Vec<usize>,
    pub values: Vec<f64>,
}

/// [`CheckpointSpread`] as a results file holds it.
#[derive(Deserialize)]
struct CheckpointSpreadFile {
    benchmark: String,
    run: String,
    iterations: Vec<usize>,
    values: Vec<f64>,
}

impl<'de> Deserialize<'de> for CheckpointSpread {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<CheckpointSpread, D::Error> {
        let f = CheckpointSpreadFile::deserialize(d)?;
        let name = |n: &str| super::curves::static_name(n).map_err(serde::de::Error::custom);
        Ok(CheckpointSpread {
            benchmark: name(&f.benchmark)?,
            run: f.run,
            iterations: f.iterations,
            values: f.values,
        })
    }
}

impl CheckpointSpread {
    pub fn min(&self) -> f64 {
        self.values.iter().cloned().fold(f64::INFINITY, f64::min)
    }
    pub fn max(&self) -> f64 {
        self.values
            .iter()
            .cloned()
            .fold(f64::NEG_INFINITY, f64::max)
    }
}

/// Each run's number at each checkpoint, by run label.
pub type PerCheckpoint = Vec<(String, Vec<f64>)>;

/// The K checkpoints' TTF reports pooled into one (robots concatenated per cell,
/// checkpoint order), and each run's TTF (mean over its cells) per checkpoint.
pub fn pool_ttf(reports: Vec<TtfReport>) -> Result<(TtfReport, PerCheckpoint)> {
    let mut it = reports.into_iter();
    let Some(mut pooled) = it.next() else {
        bail!("no checkpoint evaluated");
    };
    let mut per_checkpoint: PerCheckpoint = pooled
        .policies
        .iter()
        .map(|p| (p.clone(), vec![run_ttf(&pooled, p)]))
        .collect();
    for rep in it {
        for (p, v) in per_checkpoint.iter_mut() {
            v.push(run_ttf(&rep, p));
        }
        for (cell, more) in pooled.cells.iter_mut().zip(&rep.cells) {
            if (cell.load, &cell.terrain, cell.push, &cell.policy)
                != (more.load, &more.terrain, more.push, &more.policy)
            {
                bail!("checkpoint reports list their cells in different orders");
            }
            merge_ttf_cell(cell, more);
        }
    }
    Ok((pooled, per_checkpoint))
}

/// A run's TTF in a report: the mean over its cells.
fn run_ttf(r: &TtfReport, policy: &str) -> f64 {
    mean(
        &r.cells
            .iter()
            .filter(|c| c.policy == policy)
            .map(|c| c.ttf)
            .collect::<Vec<_>>(),
    )
}

fn merge_ttf_cell(c: &mut TtfCell, more: &TtfCell) {
    let (n0, n1) = (c.robots as f64, more.robots as f64);
    let weighted = |a: f64, b: f64| (a * n0 + b * n1) / (n0 + n1).max(1.0);
    c.walked_ratio = weighted(c.walked_ratio, more.walked_ratio);
    c.progress_ratio = weighted(c.progress_ratio, more.progress_ratio);
    c.steps_per_robot.extend(&more.steps_per_robot);
    c.strict_steps_per_robot
        .extend(&more.strict_steps_per_robot);
    c.ttf_per_seed.extend(&more.ttf_per_seed);
    c.robots += more.robots;
    c.falls += more.falls;
    c.payload_falls += more.payload_falls;
    c.strict_falls += more.strict_falls;
    c.ttf = time_to_fall(&c.steps_per_robot, c.episode_steps);
    c.strict_ttf = time_to_fall(&c.strict_steps_per_robot, c.episode_steps);
    let steps: Vec<f64> = c.steps_per_robot.iter().map(|&s| s as f64).collect();
    c.mean_steps = mean(&steps);
}

/// The K checkpoints' platform reports pooled into one, and each run's success
/// (%) over the heights per checkpoint.
pub fn pool_platform(reports: Vec<PlatformReport>) -> Result<(PlatformReport, PerCheckpoint)> {
    let mut it = reports.into_iter();
    let Some(mut pooled) = it.next() else {
        bail!("no checkpoint evaluated");
    };
    let success = |r: &PlatformReport, p: &str| {
        let all: Vec<f64> = r
            .cells
            .iter()
            .filter(|c| c.policy == p)
            .flat_map(|c| c.success_per_robot.iter().map(|&s| 100.0 * s as u8 as f64))
            .collect();
        mean(&all)
    };
    let names: Vec<String> = pooled.cells.iter().map(|c| c.policy.clone()).collect();
    let mut per_checkpoint: PerCheckpoint = Vec::new();
    for n in names {
        if per_checkpoint.iter().all(|(p, _)| *p != n) {
            per_checkpoint.push((n.clone(), vec![success(&pooled, &n)]));
        }
    }
    for rep in it {
        for (p, v) in per_checkpoint.iter_mut() {
            v.push(success(&rep, p));
        }
        for (cell, more) in pooled.cells.iter_mut().zip(&rep.cells) {
            if (cell.height_m, &cell.policy) != (more.height_m, &more.policy) {
                bail!("checkpoint reports list their cells in different orders");
            }
            let outcomes = cell.robots + more.robots;
            cell.success_per_robot.extend(&more.success_per_robot);
            cell.robots = outcomes;
            cell.success += more.success;
            cell.fell += more.fell;
            cell.not_landed += more.not_landed;
            cell.fell_before_drop += more.fell_before_drop;
            cell.not_reached += more.not_reached;
            cell.success_pct = 100.0 * cell.success as f64 / outcomes.max(1) as f64;
            for (name, n) in &more.ends {
                match cell.ends.iter_mut().find(|(k, _)| k == name) {
                    Some((_, c)) => *c += n,
                    None => cell.ends.push((name.clone(), *n)),
                }
            }
            cell.ends.sort();
        }
    }
    Ok((pooled, per_checkpoint))
}

/// Table I on the runs `labels`: their final policies, or with `[checkpoints]`
/// their last K checkpoints pooled (and the spread between them).
pub fn evaluate_ttf_runs(
    spec: &ExperimentSpec,
    labels: &[String],
    opts: &TtfOptions,
    cache: &RolloutCache,
    mut progress: impl FnMut(&TtfCell),
) -> Result<(TtfReport, Vec<CheckpointSpread>)> {
    let Some(c) = &spec.checkpoints else {
        let report = evaluate_ttf_cached(
            &super::final_policy::load_runs(spec, labels)?,
            opts,
            cache,
            progress,
        )?;
        return Ok((report, Vec::new()));
    };
    let mut reports = Vec::new();
    for k in 0..c.last {
        let opts_k = TtfOptions {
            seeds: checkpoint_seeds(&opts.seeds, k),
            repeats: repeats_per_checkpoint(opts.repeats, c.last),
            ..opts.clone()
        };
        reports.push(evaluate_ttf_cached(
            &load_kth_checkpoint(spec, c, labels, k)?,
            &opts_k,
            cache,
            &mut progress,
        )?);
    }
    let (pooled, per) = pool_ttf(reports)?;
    Ok((pooled, checkpoint_spreads(spec, c, "ttf", per)?))
}

/// Table II on the runs `labels`, as [`evaluate_ttf_runs`].
pub fn evaluate_platform_runs(
    spec: &ExperimentSpec,
    labels: &[String],
    opts: &PlatformOptions,
    cache: &RolloutCache,
    mut progress: impl FnMut(&PlatformCell),
) -> Result<(PlatformReport, Vec<CheckpointSpread>)> {
    let Some(c) = &spec.checkpoints else {
        let report = evaluate_platform_cached(
            &super::final_policy::load_runs(spec, labels)?,
            opts,
            cache,
            progress,
        )?;
        return Ok((report, Vec::new()));
    };
    let mut reports = Vec::new();
    for k in 0..c.last {
        let opts_k = PlatformOptions {
            seeds: checkpoint_seeds(&opts.seeds, k),
            repeats: repeats_per_checkpoint(opts.repeats, c.last),
            ..opts.clone()
        };
        reports.push(evaluate_platform_cached(
            &load_kth_checkpoint(spec, c, labels, k)?,
            &opts_k,
            cache,
            &mut progress,
        )?);
    }
    let (pooled, per) = pool_platform(reports)?;
    Ok((pooled, checkpoint_spreads(spec, c, "platform", per)?))
}

fn checkpoint_spreads(
    spec: &ExperimentSpec,
    c: &CheckpointsSpec,
    benchmark: &'static str,
    per: PerCheckpoint,
) -> Result<Vec<CheckpointSpread>> {
    per.into_iter()
        .map(|(run, values)| {
            let r = spec
                .run(&run)
                .ok_or_else(|| anyhow::anyhow!("no run labelled {run:?}"))?;
            let target = super::run_target(spec, r)?;
            Ok(CheckpointSpread {
                benchmark,
                run,
                iterations: headline_iterations(c, target)?,
                values,
            })
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_last_checkpoints_step_back_from_the_target() {
        let c = CheckpointsSpec {
            last: 5,
            every: 100,
            milestones: vec![1500],
        };
        assert_eq!(
            headline_iterations(&c, 4500).unwrap(),
            vec![4500, 4400, 4300, 4200, 4100]
        );
        assert!(headline_iterations(&c, 400).is_err());
        assert_eq!(repeats_per_checkpoint(10, 5), 2);
        assert_eq!(repeats_per_checkpoint(50, 5), 10);
        assert_eq!(repeats_per_checkpoint(3, 5), 1);
    }
}
