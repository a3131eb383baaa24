//! The experiment file (`experiments/paper.toml`): runs to train and the
//! evaluations of the paper, as data.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use serde::{Deserialize, Serialize};

/// One experiment: what to train, how to evaluate, the paper's numbers to compare with.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ExperimentSpec {
    pub name: String,
    /// Run directories go here (`<runs_dir>/<run name>-s<seed>`).
    pub runs_dir: PathBuf,
    /// Tables, CSV/JSON and figures go here.
    pub results_dir: PathBuf,
    /// Where the runs' latest checkpoints are committed (`--ship` copies them
    /// there; a run missing from `runs_dir` starts from its shipped copy).
    #[serde(default)]
    pub shipped_dir: Option<PathBuf>,
    /// Worker threads for training and evaluation (0 = all cores).
    #[serde(default)]
    pub threads: usize,
    #[serde(rename = "run")]
    pub runs: Vec<RunSpec>,
    pub tracking: TrackingSpec,
    /// How each run's final policy is chosen (`[selection]`); absent: its last checkpoint.
    #[serde(default)]
    pub selection: Option<super::selection::SelectionSpec>,
    pub ttf: TtfSpec,
    pub platform: PlatformSpec,
    pub race: RaceSpec,
    /// One IQR meta controller per pair of seeds (`[[meta]]`; a single `[meta]` table
    /// is one; none: no meta controller on the race).
    #[serde(default, deserialize_with = "one_or_more")]
    pub meta: Vec<MetaSpec>,
    #[serde(default)]
    pub bootstrap: BootstrapSpec,
    #[serde(default)]
    pub paper: PaperNumbers,
    /// Headline numbers over each run's last K checkpoints (`[checkpoints]`); absent:
    /// each run's final policy alone.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub checkpoints: Option<CheckpointsSpec>,
    /// Robustness curves over the severity ladder (`[curves]`); absent: the tables only.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub curves: Option<CurvesSpec>,
    /// What each run's risk penalties marked in training (`[risk_signal]`); absent: not reported.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub risk_signal: Option<super::risk_signal::RiskSignalSpec>,
    /// What each run's critic says before its robots fall (`[critic_tail]`); absent: not reported.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub critic_tail: Option<super::critic_tail::CriticTailSpec>,
    /// Command-space safety maps of the listed runs (`[commands]`), the section of
    /// the built-in benchmark `commands` (`CommandsSpec::of` reads it); absent: none.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub commands: Option<toml::Value>,
    /// The sections of registered benchmarks (`[benchmarks.<name>]`), each read
    /// by its benchmark (`super::benchmark`); absent: none runs.
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub benchmarks: BTreeMap<String, toml::Value>,
    /// Pairs of methods compared rung by rung (`[contrasts]`); absent: none.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub contrasts: Option<super::contrasts::ContrastsSpec>,
    /// The pre-registered primary result and the Holm-adjusted families
    /// (`[verdicts]`); absent: every contrast is exploratory.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub verdicts: Option<super::verdicts::VerdictsSpec>,
    /// A markdown file written by hand that opens the results' README (what the
    /// numbers below answer); `--redraw` takes its current text.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub preface: Option<PathBuf>,
}

/// A run's headline: its last `last` checkpoints, `every` iterations apart.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CheckpointsSpec {
    pub last: usize,
    pub every: usize,
    /// Earlier iterations whose checkpoints `--ship` also keeps (actor-only), so that
    /// the gap between methods can be measured along training; none by default.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub milestones: Vec<usize>,
}

/// Every table's methods on every listed rung of the severity ladder. Rung 0 is
/// the tables themselves; the higher rungs may run fewer robots (their own keys).
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CurvesSpec {
    pub severity: Vec<usize>,
    /// A ladder file (default: the built-in `experiments/severity-ladder.toml`).
    #[serde(default)]
    pub ladder: Option<PathBuf>,
    pub ttf_seeds: usize,
    pub ttf_repeats: usize,
    pub platform_seeds: usize,
    pub platform_repeats: usize,
    pub race_agents: usize,
    pub race_episodes: usize,
}

impl CurvesSpec {
    /// The ladder the curves use.
    pub fn ladder(&self) -> Result<crate::eval::Ladder> {
        match &self.ladder {
            Some(path) => crate::eval::Ladder::from_toml_file(path),
            None => Ok(crate::eval::Ladder::builtin()),
        }
    }

    fn validate(&self) -> Result<()> {
        let ladder = self.ladder()?;
        if self.severity.is_empty() {
            bail!("curves.severity lists no rung");
        }
        for &s in &self.severity {
            ladder.rung(s).context("curves.severity")?;
        }
        for (key, v) in [
            ("curves.ttf_seeds", self.ttf_seeds),
            ("curves.ttf_repeats", self.ttf_repeats),
            ("curves.platform_seeds", self.platform_seeds),
            ("curves.platform_repeats", self.platform_repeats),
            ("curves.race_agents", self.race_agents),
            ("curves.race_episodes", self.race_episodes),
        ] {
            if v == 0 {
                bail!("{key} must be at least 1");
            }
        }
        Ok(())
    }
}

/// `[[meta]]` tables, or one `[meta]` table (experiment files before two seeds).
fn one_or_more<'de, D: serde::Deserializer<'de>>(d: D) -> Result<Vec<MetaSpec>, D::Error> {
    use serde::de::Error;
    match toml::Value::deserialize(d)? {
        v @ toml::Value::Array(_) => Vec::<MetaSpec>::deserialize(v).map_err(D::Error::custom),
        v => MetaSpec::deserialize(v)
            .map(|m| vec![m])
            .map_err(D::Error::custom),
    }
}

/// One training run: a method config, a seed and a budget.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RunSpec {
    /// Directory name stem (`<name>-s<seed>`).
    pub name: String,
    /// Row label in the tables (the paper's method names).
    pub label: String,
    pub config: PathBuf,
    pub seed: u64,
    /// PPO iterations (RMA's phase 2 comes on top, from its config).
    pub iterations: usize,
    /// This run's shipped copy, when it is not `<shipped_dir>/<name>-s<seed>`: a run
    /// another experiment trained and shipped with the same config, reused as it is.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub shipped: Option<PathBuf>,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TrackingSpec {
    pub episodes: usize,
    pub seed: u64,
    /// Run configs whose [env.randomization] every policy is also judged under
    /// (`rall eval tracking --randomization-from`), one path or a list: the same ground
    /// for all methods, beside each under its own training draws.
    #[serde(default, deserialize_with = "one_or_many_paths")]
    pub randomization_from: Vec<PathBuf>,
}

/// `key = "a.toml"` or `key = ["a.toml", "b.toml"]`.
fn one_or_many_paths<'de, D: serde::Deserializer<'de>>(d: D) -> Result<Vec<PathBuf>, D::Error> {
    #[derive(Deserialize)]
    #[serde(untagged, expecting = "a config path or a list of config paths")]
    enum OneOrMany {
        One(PathBuf),
        Many(Vec<PathBuf>),
    }
    Ok(match OneOrMany::deserialize(d)? {
        OneOrMany::One(p) => vec![p],
        OneOrMany::Many(v) => v,
    })
}

/// Refuses a run name that is not a plain directory name: empty, `.` or `..`,
/// containing a path separator, a NUL, a control character, or longer than
/// 200 bytes (a run directory is `<runs_dir>/<name>-s<seed>` and must stay there).
pub fn check_run_name(name: &str) -> Result<()> {
    if name.is_empty() || name == "." || name == ".." || name.contains("..") {
        bail!("run name {name:?} must be a plain directory name (not empty, no \"..\")");
    }
    if let Some(c) = name
        .chars()
        .find(|c| matches!(c, '/' | '\\') || c.is_control())
    {
        bail!("run name {name:?} must be a plain directory name: it contains {c:?}");
    }
    if name.len() > 200 || name.starts_with('-') {
        bail!("run name {name:?} must be at most 200 bytes and not start with '-'");
    }
    Ok(())
}

/// The name of a common randomisation in results (`runs.csv` column prefixes): its
/// config's file stem (`configs/dr.toml` -> `dr`), other characters than [A-Za-z0-9_] as `_`.
pub fn common_ground_name(config: &Path) -> String {
    config
        .file_stem()
        .unwrap_or(config.as_os_str())
        .to_string_lossy()
        .chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || c == '_' {
                c
            } else {
                '_'
            }
        })
        .collect()
}

/// Table I: TTF per load x terrain x push.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TtfSpec {
    /// Labels of the runs to evaluate.
    pub methods: Vec<String>,
    pub seeds: usize,
    pub repeats: usize,
    #[serde(default)]
    pub first_seed: u64,
    /// Loads (default: ball, frozen_arm, moving_arm).
    #[serde(default = "all_loads")]
    pub loads: Vec<String>,
}

fn all_loads() -> Vec<String> {
    vec!["ball".into(), "frozen_arm".into(), "moving_arm".into()]
}

/// Table II: platform drops.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PlatformSpec {
    pub methods: Vec<String>,
    pub heights_m: Vec<f64>,
    pub seeds: usize,
    pub repeats: usize,
    #[serde(default)]
    pub first_seed: u64,
}

/// The race track: return quantiles per method and for the meta controller.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RaceSpec {
    pub methods: Vec<String>,
    pub agents: usize,
    pub episodes: usize,
    #[serde(default)]
    pub seed: u64,
    #[serde(default)]
    pub course_seed: u64,
}

/// The IQR meta controller and the rule that fixes its threshold before the race.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MetaSpec {
    pub label: String,
    /// Label of the risk-neutral (CVaR_1) run; its critic's IQR drives the switch.
    pub risky: String,
    /// Label of the risk-averse (CVaR_0.5) run.
    pub safe: String,
    /// Threshold = this quantile of the risky critic's IQR over `calibration_robots`
    /// robots walking one episode on flat ground under random commands.
    pub threshold_quantile: f64,
    pub calibration_robots: usize,
    #[serde(default)]
    pub calibration_seed: u64,
    /// Switch back below threshold x (1 - hysteresis_fraction).
    pub hysteresis_fraction: f32,
    pub min_safe_steps: usize,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct BootstrapSpec {
    pub resamples: usize,
    pub seed: u64,
    /// Two-sided confidence level.
    pub level: f64,
}

impl Default for BootstrapSpec {
    fn default() -> Self {
        BootstrapSpec {
            resamples: 1000,
            seed: 0,
            level: 0.95,
        }
    }
}

/// The paper's published numbers, printed beside ours.
#[derive(Debug, Clone, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct PaperNumbers {
    pub ttf: Vec<PaperTtfRow>,
    pub platform: Vec<PaperPlatformRow>,
}

/// One row of table I: TTF of a method with a load, in the column order
/// flat/no push, flat/push, random/no push, random/push.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PaperTtfRow {
    pub load: String,
    pub method: String,
    pub ttf: [f64; 4],
}

#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PaperPlatformRow {
    pub height_m: f64,
    pub method: String,
    pub success_pct: f64,
}

impl ExperimentSpec {
    /// Reads and checks an experiment file; relative paths are taken from the
    /// current directory (run it from the repository root).
    pub fn from_file(path: &Path) -> Result<ExperimentSpec> {
        let text = std::fs::read_to_string(path)
            .with_context(|| format!("reading experiment file {}", path.display()))?;
        let spec: ExperimentSpec = toml::from_str(&text)
            .with_context(|| format!("parsing experiment file {}", path.display()))?;
        spec.validate()
            .with_context(|| format!("experiment file {}", path.display()))?;
        Ok(spec)
    }

    pub fn validate(&self) -> Result<()> {
        if self.runs.is_empty() {
            bail!("no [[run]]");
        }
        if let Some(c) = &self.curves {
            c.validate()?;
        }
        if self.risk_signal.as_ref().is_some_and(|r| r.window == 0) {
            bail!("risk_signal.window must be at least 1 iteration");
        }
        if let Some(c) = &self.checkpoints {
            if c.last == 0 || c.every == 0 {
                bail!("checkpoints.last and checkpoints.every must be at least 1");
            }
            if c.last > 50 {
                bail!("checkpoints.last = {} is more than 50", c.last);
            }
        }
        for (i, r) in self.runs.iter().enumerate() {
            check_run_name(&r.name).with_context(|| format!("run {:?}", r.label))?;
            if self.runs[..i].iter().any(|o| o.label == r.label) {
                bail!("two runs are labelled {:?}", r.label);
            }
            if self.runs[..i]
                .iter()
                .any(|o| o.name == r.name && o.seed == r.seed)
            {
                bail!("two runs are named {:?} with seed {}", r.name, r.seed);
            }
            if r.iterations == 0 {
                bail!("run {:?}: iterations must be at least 1", r.label);
            }
        }
        let known = |label: &str, key: &str| -> Result<()> {
            if self.run(label).is_none() {
                bail!(
                    "{key} names {label:?}, which is not the label of any [[run]] ({})",
                    self.runs
                        .iter()
                        .map(|r| r.label.as_str())
                        .collect::<Vec<_>>()
                        .join(", ")
                );
            }
            Ok(())
        };
        for m in &self.ttf.methods {
            known(m, "ttf.methods")?;
        }
        for m in &self.platform.methods {
            known(m, "platform.methods")?;
        }
        for m in &self.race.methods {
            known(m, "race.methods")?;
        }
        for (i, m) in self.meta.iter().enumerate() {
            known(&m.risky, "meta.risky")?;
            known(&m.safe, "meta.safe")?;
            if !(0.0..=1.0).contains(&m.threshold_quantile) {
                bail!("meta {:?}: threshold_quantile must be in [0, 1]", m.label);
            }
            if self.run(&m.label).is_some() || self.meta[..i].iter().any(|o| o.label == m.label) {
                bail!(
                    "meta label {:?} is already taken by a run or another [[meta]]",
                    m.label
                );
            }
        }
        for (i, p) in self.tracking.randomization_from.iter().enumerate() {
            crate::config::TrainConfig::from_toml_file(p)
                .with_context(|| format!("tracking.randomization_from = {:?}", p.display()))?;
            // results/runs.csv names each one's columns after it
            let name = common_ground_name(p);
            if self.tracking.randomization_from[..i]
                .iter()
                .any(|q| common_ground_name(q) == name)
            {
                bail!(
                    "tracking.randomization_from: two configs named {name:?} (the result columns are named after the file)"
                );
            }
        }
        if let Some(sel) = &self.selection {
            sel.validate(self.tracking.seed)?;
        }
        super::benchmark::validate_sections(self)?;
        if let Some(v) = &self.verdicts {
            v.validate(self)?;
        }
        if let Some(c) = &self.contrasts {
            c.validate(self)?;
        }
        if let Some(c) = &self.critic_tail {
            c.validate(self)?;
        }
        self.preface_text()?;
        if !(0.5..1.0).contains(&self.bootstrap.level) || self.bootstrap.resamples < 10 {
            bail!("bootstrap: level must be in [0.5, 1) and resamples at least 10");
        }
        if self.ttf.seeds == 0 || self.ttf.repeats == 0 {
            bail!("ttf: seeds and repeats must be at least 1");
        }
        if self.platform.seeds == 0
            || self.platform.repeats == 0
            || self.platform.heights_m.is_empty()
        {
            bail!("platform: heights, seeds and repeats must not be empty or 0");
        }
        if self.race.agents == 0 || self.race.episodes == 0 {
            bail!("race: agents and episodes must be at least 1");
        }
        Ok(())
    }

    /// The text of the `preface` file (`None` without one); an unreadable file is
    /// refused, naming it.
    pub fn preface_text(&self) -> Result<Option<String>> {
        let Some(p) = &self.preface else {
            return Ok(None);
        };
        let text = std::fs::read_to_string(p)
            .with_context(|| format!("preface = {:?}: reading it", p.display()))?;
        Ok(Some(text))
    }

    pub fn run(&self, label: &str) -> Option<&RunSpec> {
        self.runs.iter().find(|r| r.label == label)
    }

    /// `<name>-s<seed>`.
    pub fn run_dir_name(&self, r: &RunSpec) -> String {
        format!("{}-s{}", r.name, r.seed)
    }

    /// `<runs_dir>/<name>-s<seed>`.
    pub fn run_dir(&self, r: &RunSpec) -> PathBuf {
        self.runs_dir.join(self.run_dir_name(r))
    }

    /// Where run `r` is shipped: its own `shipped` folder, else
    /// `<shipped_dir>/<name>-s<seed>`; `None` when neither is set.
    pub fn shipped_copy(&self, r: &RunSpec) -> Option<PathBuf> {
        r.shipped
            .clone()
            .or_else(|| Some(self.shipped_dir.as_ref()?.join(self.run_dir_name(r))))
    }
}

#[cfg(test)]
mod tests {
    use super::common_ground_name;
    use std::path::Path;

    #[test]
    fn common_ground_names_are_the_sanitised_file_stem() {
        assert_eq!(common_ground_name(Path::new("configs/dr.toml")), "dr");
        // two different files that would name the same CSV columns
        assert_eq!(
            common_ground_name(Path::new("a/wide-dr.toml")),
            common_ground_name(Path::new("b/wide.dr.toml"))
        );
    }
}
