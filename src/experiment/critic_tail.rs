//! What each run's critic says before its robots fall (`[critic_tail]`).
//!
//! RALL's claim is about the value distribution's lower tail: rare penalties
//! shape it, and the CVaR_eta actor steers away from states whose tail is low.
//! Here each run's final policy walks in its own training env and the critic's
//! quantiles in the last steps before each fall are set against every other
//! state (`rall eval falls`, one run per job). A scalar critic has one value,
//! V(s), so its "quantiles" are all V: the column to compare against. If the
//! distribution marks danger beyond what the mean already says, its lower tail
//! drops before a fall by more than its median does.

use std::fmt::Write as _;

use anyhow::{bail, Context, Result};
use serde::{Deserialize, Serialize};

use super::final_policy::load_final_policy;
use super::pooled::{methods_of, Method};
use super::spec::ExperimentSpec;
use crate::eval::cache::run_jobs_cached;
use crate::eval::{critic_before_falls, FallReport, NamedPolicy, RolloutCache, FALL_TAUS};
use crate::runner::{load_policy, LoadedPolicy};

/// `[critic_tail]`: which runs, and how long their robots walk.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CriticTailSpec {
    /// Run labels; each run's final policy must hold its critic (a `[selection]`
    /// choice or a full checkpoint, not an actor-only copy).
    pub methods: Vec<String>,
    /// Robots walking at once in the run's training env.
    pub robots: usize,
    /// Policy steps (50 Hz) each robot walks; episodes restart after a fall.
    pub steps: usize,
    /// Steps before a fall that count as "before a fall" (25 = 0.5 s).
    pub window: usize,
    pub seed: u64,
}

impl CriticTailSpec {
    pub fn validate(&self, spec: &ExperimentSpec) -> Result<()> {
        for (key, v) in [
            ("critic_tail.robots", self.robots),
            ("critic_tail.steps", self.steps),
            ("critic_tail.window", self.window),
        ] {
            if v == 0 {
                bail!("{key} must be at least 1");
            }
        }
        if self.window >= self.steps {
            bail!(
                "critic_tail.window = {} must be shorter than critic_tail.steps = {}",
                self.window,
                self.steps
            );
        }
        for m in &self.methods {
            if spec.run(m).is_none() {
                bail!("critic_tail.methods names {m:?}, which is not the label of any [[run]]");
            }
        }
        Ok(())
    }
}

/// One run's critic before falls and elsewhere.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CriticTailRow {
    pub run: String,
    /// The final policy's iteration (`None`: the run's newest checkpoint).
    pub policy_iteration: Option<usize>,
    /// The critic has a value distribution (IQN); `false`: a scalar V.
    pub distribution: bool,
    /// The mean terrain level the run's robots walk at (its curriculum's, stored in
    /// the checkpoint): a run that climbed further falls on harder ground.
    #[serde(default)]
    pub terrain_level: f64,
    pub falls: usize,
    pub states_before_fall: usize,
    pub states_elsewhere: usize,
    /// Mean `Z_tau` at [`FALL_TAUS`] over the states before a fall.
    pub before_fall: [f64; 6],
    pub elsewhere: [f64; 6],
    pub iqr_before_fall: f64,
    pub iqr_elsewhere: f64,
}

const TAIL: usize = 1; // Z_0.05
const MEDIAN: usize = 3; // Z_0.5

impl CriticTailRow {
    fn from_report(
        run: &str,
        policy_iteration: Option<usize>,
        distribution: bool,
        r: &FallReport,
    ) -> Self {
        CriticTailRow {
            run: run.to_string(),
            policy_iteration,
            distribution,
            terrain_level: 0.0,
            falls: r.falls,
            states_before_fall: r.before_fall.states,
            states_elsewhere: r.elsewhere.states,
            before_fall: r.before_fall.quantiles,
            elsewhere: r.elsewhere.quantiles,
            iqr_before_fall: r.before_fall.iqr,
            iqr_elsewhere: r.elsewhere.iqr,
        }
    }

    /// "distribution" or "scalar", as the tables print it.
    pub fn critic_kind(&self) -> &'static str {
        if self.distribution {
            "distribution"
        } else {
            "scalar"
        }
    }

    /// How far quantile `k` is lower before a fall than elsewhere (`None` without falls).
    fn drop(&self, k: usize) -> Option<f64> {
        (self.states_before_fall > 0).then(|| self.elsewhere[k] - self.before_fall[k])
    }

    /// The median's drop before a fall as a share of its value elsewhere.
    pub fn median_drop_share(&self) -> Option<f64> {
        let m = self.elsewhere[MEDIAN].abs();
        self.drop(MEDIAN).filter(|_| m > 0.0).map(|d| d / m)
    }

    /// Z_0.05's drop over the median's: above 1, the lower tail marks falls more
    /// sharply than the centre does (exactly 1 for a scalar critic).
    pub fn tail_over_median_drop(&self) -> Option<f64> {
        let (t, m) = (self.drop(TAIL)?, self.drop(MEDIAN)?);
        (m > 0.0).then(|| t / m)
    }

    /// IQR before a fall over IQR elsewhere (`None` for a scalar critic).
    pub fn iqr_ratio(&self) -> Option<f64> {
        (self.distribution && self.states_before_fall > 0 && self.iqr_elsewhere > 0.0)
            .then(|| self.iqr_before_fall / self.iqr_elsewhere)
    }
}

/// The section's results: its settings, the runs grouped into methods, a row per run.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CriticTail {
    pub robots: usize,
    pub steps: usize,
    pub window: usize,
    pub seed: u64,
    pub methods: Vec<Method>,
    pub rows: Vec<CriticTailRow>,
}

/// Every listed run with a checkpoint (`available`), one job per run, each on one
/// thread (so the numbers do not depend on the thread count) and kept in `cache`.
pub fn evaluate_critic_tail(
    spec: &ExperimentSpec,
    s: &CriticTailSpec,
    available: &[String],
    threads: usize,
    cache: &RolloutCache,
) -> Result<CriticTail> {
    let labels: Vec<String> = s
        .methods
        .iter()
        .filter(|m| available.contains(m))
        .cloned()
        .collect();
    let runs = labels
        .iter()
        .map(|label| TailRun::load(spec, label))
        .collect::<Result<Vec<_>>>()?;
    let (robots, steps, window, seed) = (s.robots, s.steps, s.window, s.seed);
    let key = |i: &usize| {
        let own = runs[*i].policy.rollout_key()?;
        Some(format!(
            "critic before falls, sampled actions, training env\n{own}\nrobots {robots} steps {steps} window {window} seed {seed}"
        ))
    };
    let jobs: Vec<usize> = (0..runs.len()).collect();
    let rows = run_jobs_cached(&jobs, threads, cache, key, |&i, _| {
        let run = &runs[i];
        let loaded = &run.loaded;
        let r = crate::learn::mat::serial(|| {
            critic_before_falls(
                &loaded.learner,
                &loaded.config,
                loaded.progress.terrain_levels.as_deref(),
                (robots, steps, window),
                1,
                seed,
            )
        })?;
        Ok(CriticTailRow::from_report(
            &run.policy.name,
            run.iteration,
            run.distribution(),
            &r,
        ))
    })?;
    // not part of the cached rollout: read from the checkpoint each time
    let rows = rows
        .into_iter()
        .zip(&runs)
        .map(|(row, run)| CriticTailRow {
            terrain_level: run.terrain_level(),
            ..row
        })
        .collect();
    Ok(CriticTail {
        robots,
        steps,
        window,
        seed,
        methods: methods_of(spec, &labels),
        rows,
    })
}

/// One listed run as the section reads it: its final policy (named, for the
/// cache key) and the checkpoint's learner, config and curriculum, loaded
/// before the jobs start instead of inside each job.
struct TailRun {
    policy: NamedPolicy,
    loaded: LoadedPolicy,
    iteration: Option<usize>,
}

impl TailRun {
    fn load(spec: &ExperimentSpec, label: &str) -> Result<TailRun> {
        let (policy, iteration) = load_final_policy(spec, label)?;
        policy.critic().with_context(|| {
            format!("critic_tail.methods: run {label:?} (the section reads its critic)")
        })?;
        let path = policy
            .path
            .clone()
            .context("a run's policy comes from a file")?;
        let loaded =
            load_policy(&path).with_context(|| format!("run {label:?}: {}", path.display()))?;
        Ok(TailRun {
            policy,
            loaded,
            iteration,
        })
    }

    /// The critic is a value distribution (IQN), not a scalar.
    fn distribution(&self) -> bool {
        self.loaded.learner.config().critic.has_quantiles()
    }

    /// Mean terrain level of the run's robots when the checkpoint was written.
    fn terrain_level(&self) -> f64 {
        mean_level(
            self.loaded
                .progress
                .terrain_levels
                .as_deref()
                .unwrap_or_default(),
        )
    }
}

fn mean_level(levels: &[usize]) -> f64 {
    if levels.is_empty() {
        return 0.0;
    }
    levels.iter().sum::<usize>() as f64 / levels.len() as f64
}

fn opt(v: Option<f64>, digits: usize) -> String {
    v.map_or(String::new(), |v| format!("{v:.digits$}"))
}

/// `critic_tail.csv`: every run's quantiles before a fall and elsewhere.
pub fn tail_csv(t: &CriticTail) -> String {
    let taus: Vec<String> = FALL_TAUS.iter().map(|t| format!("{t}")).collect();
    let mut s = String::from(
        "run,policy_iteration,critic,terrain_level,falls,states_before_fall,states_elsewhere",
    );
    for side in ["before_fall", "elsewhere"] {
        for t in &taus {
            let _ = write!(s, ",z{t}_{side}");
        }
        let _ = write!(s, ",iqr_{side}");
    }
    s.push_str(",median_drop_share,tail_over_median_drop,iqr_ratio\n");
    for r in &t.rows {
        let _ = write!(
            s,
            "{},{},{},{:.3},{},{},{}",
            r.run,
            r.policy_iteration.map_or(String::new(), |i| i.to_string()),
            r.critic_kind(),
            r.terrain_level,
            r.falls,
            r.states_before_fall,
            r.states_elsewhere
        );
        for (q, iqr) in [
            (&r.before_fall, r.iqr_before_fall),
            (&r.elsewhere, r.iqr_elsewhere),
        ] {
            for v in q {
                let _ = write!(s, ",{v:.6}");
            }
            let _ = write!(s, ",{iqr:.6}");
        }
        let _ = writeln!(
            s,
            ",{},{},{}",
            opt(r.median_drop_share(), 4),
            opt(r.tail_over_median_drop(), 4),
            opt(r.iqr_ratio(), 4)
        );
    }
    s
}

/// The mean over a method's seeds of `f` (seeds without a value left out).
fn seed_mean(rows: &[&CriticTailRow], f: impl Fn(&CriticTailRow) -> Option<f64>) -> Option<f64> {
    let v: Vec<f64> = rows.iter().filter_map(|r| f(r)).collect();
    (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64)
}

/// The section of the results' README: methods over their seeds, then every run.
pub fn tail_markdown(t: Option<&CriticTail>, s: &mut String) {
    let Some(t) = t.filter(|t| !t.rows.is_empty()) else {
        return;
    };
    let _ = writeln!(s, "\n## What the critics saw before falls\n");
    let _ = writeln!(
        s,
        "Each run's final policy walks {} robots for {} policy steps in its own training env (terrain at the run's curriculum levels, pushes, randomisation, sampled actions), seed {}; the critic's value quantiles over the last {} steps ({:.1} s) before each fall against every other state (`critic_tail.csv` has every quantile). A scalar critic has one value, V, so its quantiles are all V. A distribution that marks danger beyond what its mean says drops its lower tail (Z_0.05) before a fall by more than its median (Z_0.5): tail / median drop above 1. Each run walks at its own curriculum's terrain level and its states before a fall are its own, so compare the drops, not the values or the fall counts.\n",
        t.robots,
        t.steps,
        t.seed,
        t.window,
        t.window as f64 * 0.02
    );
    let _ = writeln!(
        s,
        "| Method | seeds | terrain level | falls per run | median drop (share of its value elsewhere) | tail / median drop | IQR before a fall / elsewhere |"
    );
    let _ = writeln!(s, "|---|---:|---:|---:|---:|---:|---:|");
    for m in &t.methods {
        let rows: Vec<&CriticTailRow> =
            t.rows.iter().filter(|r| m.seeds.contains(&r.run)).collect();
        let _ = writeln!(
            s,
            "| {} | {} | {} | {} | {} | {} | {} |",
            m.label,
            rows.len(),
            seed_mean(&rows, |r| Some(r.terrain_level)).map_or("-".into(), |v| format!("{v:.2}")),
            seed_mean(&rows, |r| Some(r.falls as f64)).map_or("-".into(), |v| format!("{v:.1}")),
            seed_mean(&rows, |r| r.median_drop_share())
                .map_or("-".into(), |v| format!("{:.0}%", 100.0 * v)),
            seed_mean(&rows, |r| r.tail_over_median_drop())
                .map_or("-".into(), |v| format!("{v:.2}")),
            seed_mean(&rows, |r| r.iqr_ratio()).map_or("-".into(), |v| format!("{v:.1}x")),
        );
    }
    let _ = writeln!(s, "\nEvery run (before a fall / elsewhere):\n");
    let _ = writeln!(
        s,
        "| Run | policy | critic | terrain level | falls | Z_0.5 | Z_0.05 | IQR | tail / median drop |"
    );
    let _ = writeln!(s, "|---|---:|---|---:|---:|---|---|---|---:|");
    for r in &t.rows {
        let pair = |a: f64, b: f64| {
            if r.states_before_fall == 0 {
                format!("- / {b:.2}")
            } else {
                format!("{a:.2} / {b:.2}")
            }
        };
        let _ = writeln!(
            s,
            "| {} | {} | {} | {:.2} | {} | {} | {} | {} | {} |",
            r.run,
            r.policy_iteration
                .map_or("newest".into(), |i| i.to_string()),
            r.critic_kind(),
            r.terrain_level,
            r.falls,
            pair(r.before_fall[MEDIAN], r.elsewhere[MEDIAN]),
            pair(r.before_fall[TAIL], r.elsewhere[TAIL]),
            if r.distribution {
                pair(r.iqr_before_fall, r.iqr_elsewhere)
            } else {
                "-".into()
            },
            r.tail_over_median_drop()
                .map_or("-".into(), |v| format!("{v:.2}")),
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn row(
        distribution: bool,
        before: [f64; 6],
        elsewhere: [f64; 6],
        iqr: (f64, f64),
    ) -> CriticTailRow {
        CriticTailRow {
            run: "r".into(),
            policy_iteration: Some(100),
            distribution,
            terrain_level: 4.5,
            falls: 3,
            states_before_fall: 75,
            states_elsewhere: 1000,
            before_fall: before,
            elsewhere,
            iqr_before_fall: iqr.0,
            iqr_elsewhere: iqr.1,
        }
    }

    #[test]
    fn drops_compare_the_tail_with_the_median() {
        // the tail falls by 6, the median by 2
        let r = row(
            true,
            [0.0, 2.0, 5.0, 6.0, 7.0, 8.0],
            [7.0, 8.0, 8.0, 8.0, 8.5, 9.0],
            (2.0, 0.5),
        );
        assert!((r.tail_over_median_drop().unwrap() - 3.0).abs() < 1e-12);
        assert!((r.median_drop_share().unwrap() - 0.25).abs() < 1e-12);
        assert!((r.iqr_ratio().unwrap() - 4.0).abs() < 1e-12);
        // a scalar critic: every quantile is V, the ratio is 1 and there is no IQR
        let v = row(false, [5.0; 6], [9.0; 6], (0.0, 0.0));
        assert_eq!(v.tail_over_median_drop(), Some(1.0));
        assert_eq!(v.iqr_ratio(), None);
        // no fall: nothing to compare
        let none = CriticTailRow {
            states_before_fall: 0,
            falls: 0,
            ..r.clone()
        };
        assert_eq!(none.tail_over_median_drop(), None);
        assert_eq!(none.median_drop_share(), None);
        assert_eq!(none.iqr_ratio(), None);
    }

    #[test]
    fn the_csv_has_a_column_per_quantile_and_side() {
        let t = CriticTail {
            robots: 2,
            steps: 10,
            window: 2,
            seed: 1,
            methods: vec![Method {
                label: "r".into(),
                seeds: vec!["r".into()],
            }],
            rows: vec![row(true, [1.0; 6], [2.0; 6], (0.5, 0.25))],
        };
        let csv = tail_csv(&t);
        let lines: Vec<&str> = csv.lines().collect();
        assert_eq!(lines.len(), 2);
        let width = lines[0].split(',').count();
        assert_eq!(width, 7 + 2 * 7 + 3);
        assert_eq!(lines[1].split(',').count(), width);
        let mut md = String::new();
        tail_markdown(Some(&t), &mut md);
        assert!(md.contains("## What the critics saw before falls"), "{md}");
        assert!(md.contains("| r | 1 | 4.50 | 3.0 |"), "{md}");
    }
}
