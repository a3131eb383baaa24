//! Benchmarks of `rall experiment` as a trait: a benchmark reads its section of
//! the experiment file, evaluates the runs it lists (one stage of the
//! evaluation) and reports what it measured: its CSV files, its section of the
//! results' README, its figures, its entry of `results.json` and any contrasts
//! `[verdicts]` may name. The command map (`[commands]`) is built in; code
//! outside the crate adds a benchmark with [`register_benchmark`], and its
//! section is then `[benchmarks.<name>]`.

use std::any::Any;
use std::fmt;
use std::path::Path;
use std::sync::{Arc, RwLock};

use anyhow::{bail, ensure, Context, Result};
use serde::de::{DeserializeOwned, IgnoredAny, MapAccess, SeqAccess, Visitor};
use serde::ser::{SerializeMap, SerializeSeq};
use serde::{Deserialize, Deserializer, Serialize, Serializer};

use super::clock::PhaseClock;
use super::contrasts::Contrast;
use super::final_policy::load_final_policy;
use super::pooled::{methods_of, Method};
use super::spec::ExperimentSpec;
use crate::eval::{NamedPolicy, RolloutCache};

/// What a benchmark's evaluation may use.
pub struct BenchmarkContext<'a> {
    pub spec: &'a ExperimentSpec,
    /// Labels of the runs that have a checkpoint (with `--allow-unfinished`, the
    /// others are left out).
    pub available: &'a [String],
    /// Worker threads for the rollouts.
    pub threads: usize,
    /// The experiment's rollout cache (off with `--fresh-rollouts`).
    pub cache: &'a RolloutCache,
}

impl BenchmarkContext<'_> {
    /// The labels of `wanted` whose runs have a checkpoint, in `wanted`'s order.
    pub fn available_runs(&self, wanted: &[String]) -> Vec<String> {
        let mut out = wanted.to_vec();
        out.retain(|l| self.available.contains(l));
        out
    }

    /// `labels` grouped into methods: the runs of one `name` are its seeds.
    pub fn methods(&self, labels: &[String]) -> Vec<Method> {
        methods_of(self.spec, labels)
    }

    /// Run `label`'s final policy (the `[selection]` choice with its iteration,
    /// else its newest checkpoint).
    pub fn final_policy(&self, label: &str) -> Result<(NamedPolicy, Option<usize>)> {
        load_final_policy(self.spec, label)
    }
}

/// What a benchmark measured, and its contrasts for `[verdicts]` (rung 0).
pub struct Evaluated<O> {
    pub output: O,
    pub contrasts: Vec<Contrast>,
}

/// A number of a benchmark's contrasts (one per seed) that `[verdicts]` may
/// name; it has no severity rung.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BenchmarkMetric {
    /// Its name: the `metric` of its contrasts and of a verdict.
    pub name: &'static str,
    /// Its title in the verdicts' table (`command map safe share`).
    pub title: &'static str,
    /// Its title in the README's contrast tables (`command map: safe share`).
    pub contrast_title: &'static str,
    /// Decimals of its differences.
    pub decimals: usize,
    /// Lower is safer: a method is ahead with a negative difference.
    pub lower_is_safer: bool,
}

/// One figure of a benchmark: its file name in `figures/` and what it shows
/// (the README's list of figures).
#[derive(Debug, Clone, PartialEq)]
pub struct FigureEntry {
    pub file: String,
    pub shows: String,
}

/// A benchmark's results as `results.json` keeps them: everything its tables,
/// README section and figures are written from, so `--redraw` rebuilds them.
pub trait BenchmarkOutput:
    Serialize + DeserializeOwned + Clone + fmt::Debug + Send + Sync + 'static
{
    /// Its CSV files: (file name, text).
    fn csv_files(&self) -> Vec<(String, String)>;

    /// Its section of the results' README, on the first page after the preface.
    fn markdown(&self, s: &mut String);

    /// Its figures, listed in the README after every other; none by default.
    fn figures(&self) -> Vec<FigureEntry> {
        Vec::new()
    }

    /// Draws its figure `file` (one of [`BenchmarkOutput::figures`]) to `path`.
    fn draw(&self, file: &str, path: &Path) -> Result<()> {
        bail!("no figure {file:?} to draw at {}", path.display())
    }
}

/// A benchmark of `rall experiment`, run as one stage of the evaluation when
/// the experiment file has its section.
pub trait Benchmark: Send + Sync + 'static {
    /// Its section of the experiment file.
    type Section: DeserializeOwned;
    /// What it measured.
    type Output: BenchmarkOutput;

    /// Its name: its section `[benchmarks.<name>]` and its key in `results.json`
    /// (lowercase letters, digits, `-` and `_`).
    fn name(&self) -> &'static str;

    /// The title of its stage in the evaluation's progress and timing.
    fn stage(&self) -> &'static str;

    /// Refuses a section that cannot run, naming the key at fault.
    fn validate(&self, section: &Self::Section, spec: &ExperimentSpec) -> Result<()>;

    /// Evaluates the section's runs.
    fn evaluate(
        &self,
        section: &Self::Section,
        cx: &BenchmarkContext,
    ) -> Result<Evaluated<Self::Output>>;

    /// The metrics of its contrasts that `[verdicts]` may name; none by default.
    fn metrics(&self) -> Vec<BenchmarkMetric> {
        Vec::new()
    }

    /// Whether the section evaluates some run of `label`'s method, as a verdict
    /// on one of its metrics needs; by default every run.
    fn compares(&self, section: &Self::Section, spec: &ExperimentSpec, label: &str) -> bool {
        let _ = (section, spec, label);
        true
    }
}

/// A benchmark with its section and output as values (the registry's entries).
trait AnyBenchmark: Send + Sync {
    fn name(&self) -> &'static str;
    fn stage(&self) -> &'static str;
    fn validate(&self, section: &toml::Value, spec: &ExperimentSpec) -> Result<()>;
    fn evaluate(&self, section: &toml::Value, cx: &BenchmarkContext) -> Result<Measured>;
    fn decode(&self, json: &Json) -> Result<Box<dyn AnyOutput>>;
    fn metrics(&self) -> Vec<BenchmarkMetric>;
    fn compares(&self, section: &toml::Value, spec: &ExperimentSpec, label: &str) -> Result<bool>;
}

/// One benchmark's output and contrasts.
type Measured = (Box<dyn AnyOutput>, Vec<Contrast>);

/// `[commands]` for the command map, `[benchmarks.<name>]` for every other.
pub fn section_title(name: &str) -> String {
    if name == super::commands::BENCHMARK {
        format!("[{name}]")
    } else {
        format!("[benchmarks.{name}]")
    }
}

/// Benchmark `b`'s section parsed from `value`, refused with its title.
fn parse_section<B: Benchmark>(b: &B, value: &toml::Value) -> Result<B::Section> {
    B::Section::deserialize(value.clone()).with_context(|| section_title(b.name()))
}

impl<B: Benchmark> AnyBenchmark for B {
    fn name(&self) -> &'static str {
        Benchmark::name(self)
    }
    fn stage(&self) -> &'static str {
        Benchmark::stage(self)
    }
    fn validate(&self, section: &toml::Value, spec: &ExperimentSpec) -> Result<()> {
        Benchmark::validate(self, &parse_section(self, section)?, spec)
    }
    fn evaluate(&self, section: &toml::Value, cx: &BenchmarkContext) -> Result<Measured> {
        let e = Benchmark::evaluate(self, &parse_section(self, section)?, cx)?;
        Ok((Box::new(e.output), e.contrasts))
    }
    fn decode(&self, json: &Json) -> Result<Box<dyn AnyOutput>> {
        let output: B::Output = json.decode().with_context(|| {
            format!(
                "results.json: the {:?} entry is not this version's",
                Benchmark::name(self)
            )
        })?;
        Ok(Box::new(output))
    }
    fn metrics(&self) -> Vec<BenchmarkMetric> {
        Benchmark::metrics(self)
    }
    fn compares(&self, section: &toml::Value, spec: &ExperimentSpec, label: &str) -> Result<bool> {
        let section = parse_section(self, section)?;
        Ok(Benchmark::compares(self, &section, spec, label))
    }
}

/// A benchmark's output behind a pointer.
trait AnyOutput: Send + Sync {
    fn json(&self) -> Result<Json>;
    fn csv_files(&self) -> Vec<(String, String)>;
    fn markdown(&self, s: &mut String);
    fn figures(&self) -> Vec<FigureEntry>;
    fn draw(&self, file: &str, path: &Path) -> Result<()>;
    fn clone_box(&self) -> Box<dyn AnyOutput>;
    fn debug(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result;
    fn as_any(&self) -> &dyn Any;
}

impl<O: BenchmarkOutput> AnyOutput for O {
    fn json(&self) -> Result<Json> {
        Json::encode(self)
    }
    fn csv_files(&self) -> Vec<(String, String)> {
        BenchmarkOutput::csv_files(self)
    }
    fn markdown(&self, s: &mut String) {
        BenchmarkOutput::markdown(self, s)
    }
    fn figures(&self) -> Vec<FigureEntry> {
        BenchmarkOutput::figures(self)
    }
    fn draw(&self, file: &str, path: &Path) -> Result<()> {
        BenchmarkOutput::draw(self, file, path)
    }
    fn clone_box(&self) -> Box<dyn AnyOutput> {
        Box::new(self.clone())
    }
    fn debug(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        fmt::Debug::fmt(self, f)
    }
    fn as_any(&self) -> &dyn Any {
        self
    }
}

/// The benchmarks registered from outside the crate.
static REGISTERED: RwLock<Vec<Arc<dyn AnyBenchmark>>> = RwLock::new(Vec::new());

/// The other entries of `results.json` (the fields of `ExperimentResults` it
/// writes): no benchmark may take one of these names, as its entry sits beside them.
const RESULT_KEYS: [&str; 16] = [
    "name",
    "confidence",
    "runs",
    "common_randomization",
    "ttf",
    "platform",
    "race",
    "meta",
    "methods",
    "curves",
    "ladder",
    "checkpoint_spread",
    "curve_paper",
    "risk_signal",
    "critic_tail",
    "contrasts",
];

/// Every benchmark in stage order: the built-in command map, then the
/// registered ones in the order they were registered.
fn all_benchmarks() -> Vec<Arc<dyn AnyBenchmark>> {
    let registered = REGISTERED.read().unwrap_or_else(|e| e.into_inner());
    let built_in: Arc<dyn AnyBenchmark> = Arc::new(super::commands::CommandMap);
    std::iter::once(built_in)
        .chain(registered.iter().cloned())
        .collect()
}

fn find(name: &str) -> Option<Arc<dyn AnyBenchmark>> {
    all_benchmarks().into_iter().find(|b| b.name() == name)
}

/// Adds a benchmark to `rall experiment`: an experiment file with its section
/// `[benchmarks.<name>]` runs it. Refuses a name already taken (by a benchmark
/// or a key of `results.json`) and one that is not lowercase letters, digits,
/// `-` and `_`.
pub fn register_benchmark<B: Benchmark>(benchmark: B) -> Result<()> {
    let name = Benchmark::name(&benchmark);
    ensure!(
        !name.is_empty()
            && name
                .bytes()
                .all(|b| b.is_ascii_lowercase() || b.is_ascii_digit() || b == b'-' || b == b'_'),
        "benchmark name {name:?}: use lowercase letters, digits, '-' and '_'"
    );
    let mut registered = REGISTERED.write().unwrap_or_else(|e| e.into_inner());
    let taken = RESULT_KEYS.contains(&name)
        || name == super::commands::BENCHMARK
        || registered.iter().any(|b| b.name() == name);
    ensure!(
        !taken,
        "benchmark name {name:?} is already taken: register the benchmark under another name"
    );
    registered.push(Arc::new(benchmark));
    Ok(())
}

/// The section of benchmark `name` in `spec`: `[benchmarks.<name>]`, or the
/// command map's own `[commands]`.
pub fn section<'a>(spec: &'a ExperimentSpec, name: &str) -> Option<&'a toml::Value> {
    match name {
        super::commands::BENCHMARK => spec.commands.as_ref().or(spec.benchmarks.get(name)),
        _ => spec.benchmarks.get(name),
    }
}

/// Refuses a `[benchmarks.<name>]` of no registered benchmark, the command map
/// given twice, and every section its benchmark refuses.
pub(super) fn validate_sections(spec: &ExperimentSpec) -> Result<()> {
    let known = all_benchmarks();
    for name in spec.benchmarks.keys() {
        if !known.iter().any(|b| b.name() == name) {
            let names: Vec<&str> = known.iter().map(|b| b.name()).collect();
            bail!(
                "[benchmarks.{name}]: no benchmark is registered as {name:?} (known: {})",
                names.join(", ")
            );
        }
    }
    ensure!(
        !(spec.commands.is_some() && spec.benchmarks.contains_key(super::commands::BENCHMARK)),
        "the command map has two sections, [commands] and [benchmarks.commands]: keep one"
    );
    for b in &known {
        if let Some(s) = section(spec, b.name()) {
            b.validate(s, spec)?;
        }
    }
    Ok(())
}

/// Every benchmark's metrics with its name, in stage order.
pub fn metrics() -> Vec<(&'static str, BenchmarkMetric)> {
    let mut out = Vec::new();
    for b in all_benchmarks() {
        out.extend(b.metrics().into_iter().map(|m| (b.name(), m)));
    }
    out
}

/// The benchmark whose contrasts have metric `name`, and the metric.
pub fn metric(name: &str) -> Option<(&'static str, BenchmarkMetric)> {
    metrics().into_iter().find(|(_, m)| m.name == name)
}

/// Refuses a verdict at `at` on benchmark metric `metric` between the methods of
/// `labels` unless the experiment has the benchmark's section and it evaluates a
/// run of each.
pub(super) fn check_compared(
    spec: &ExperimentSpec,
    metric: &str,
    labels: [&str; 2],
    at: &str,
) -> Result<()> {
    let Some(b) = self::metric(metric).and_then(|(name, _)| find(name)) else {
        bail!("{at}.metric is {metric:?}, the metric of no benchmark");
    };
    let title = section_title(b.name());
    let Some(s) = section(spec, b.name()) else {
        bail!(
            "{at}.metric is {metric:?}, a metric of the benchmark {}, but the experiment file has no {title} section",
            b.name()
        );
    };
    for label in labels {
        if !b.compares(s, spec, label)? {
            bail!("{at}.metric is {metric:?}, but {title} lists no run of {label:?}'s method");
        }
    }
    Ok(())
}

/// How many benchmarks `spec` runs (one stage each).
pub(super) fn stage_count(spec: &ExperimentSpec) -> usize {
    all_benchmarks()
        .iter()
        .filter(|b| section(spec, b.name()).is_some())
        .count()
}

/// Runs every benchmark with a section in `spec`, one stage each in registry
/// order; returns their outputs and their contrasts, in that order.
pub(super) fn evaluate_benchmarks(
    cx: &BenchmarkContext,
    clock: &mut PhaseClock,
) -> Result<(BenchmarkOutputs, Vec<Contrast>)> {
    let mut outputs = BenchmarkOutputs::default();
    let mut contrasts = Vec::new();
    for b in all_benchmarks() {
        let Some(s) = section(cx.spec, b.name()) else {
            continue;
        };
        clock.next(b.stage());
        let (output, more) = b.evaluate(s, cx)?;
        outputs.0.push((b.name().to_string(), output));
        contrasts.extend(more);
    }
    Ok((outputs, contrasts))
}

/// Each benchmark's output, in the order the benchmarks ran; in `results.json`
/// one entry per benchmark, keyed by its name.
#[derive(Default)]
pub struct BenchmarkOutputs(Vec<(String, Box<dyn AnyOutput>)>);

impl BenchmarkOutputs {
    pub fn is_empty(&self) -> bool {
        self.0.is_empty()
    }

    /// The names of the benchmarks with an output, in order.
    pub fn names(&self) -> Vec<&str> {
        self.0.iter().map(|(n, _)| n.as_str()).collect()
    }

    /// Benchmark `name`'s output as its type `O` (`None` without it, or of another type).
    pub fn get<O: BenchmarkOutput>(&self, name: &str) -> Option<&O> {
        let (_, o) = self.0.iter().find(|(n, _)| n == name)?;
        o.as_any().downcast_ref()
    }

    /// Every benchmark's CSV files.
    pub fn csv_files(&self) -> Vec<(String, String)> {
        self.0.iter().flat_map(|(_, o)| o.csv_files()).collect()
    }

    /// Every benchmark's README section.
    pub fn markdown(&self, s: &mut String) {
        for (_, o) in &self.0 {
            o.markdown(s);
        }
    }

    /// Every benchmark's figures, each with its benchmark's name.
    pub fn figures(&self) -> Vec<(String, FigureEntry)> {
        let mut out = Vec::new();
        for (n, o) in &self.0 {
            out.extend(o.figures().into_iter().map(|f| (n.clone(), f)));
        }
        out
    }

    /// Draws figure `file` of benchmark `name` to `path`.
    pub fn draw(&self, name: &str, file: &str, path: &Path) -> Result<()> {
        match self.0.iter().find(|(n, _)| n == name) {
            Some((_, o)) => o.draw(file, path),
            None => bail!("no output of benchmark {name:?} to draw {file:?} from"),
        }
    }
}

impl Clone for BenchmarkOutputs {
    fn clone(&self) -> Self {
        BenchmarkOutputs(
            self.0
                .iter()
                .map(|(n, o)| (n.clone(), o.clone_box()))
                .collect(),
        )
    }
}

impl fmt::Debug for BenchmarkOutputs {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let mut m = f.debug_map();
        for (n, o) in &self.0 {
            m.entry(n, &DebugOutput(o.as_ref()));
        }
        m.finish()
    }
}

/// A boxed output's `Debug`.
struct DebugOutput<'a>(&'a dyn AnyOutput);

impl fmt::Debug for DebugOutput<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        self.0.debug(f)
    }
}

impl Serialize for BenchmarkOutputs {
    fn serialize<S: Serializer>(&self, s: S) -> std::result::Result<S::Ok, S::Error> {
        use serde::ser::Error;
        let mut map = s.serialize_map(Some(self.0.len()))?;
        for (n, o) in &self.0 {
            map.serialize_entry(n, &o.json().map_err(S::Error::custom)?)?;
        }
        map.end()
    }
}

impl<'de> Deserialize<'de> for BenchmarkOutputs {
    /// The entries of registered benchmarks; any other key is left alone.
    fn deserialize<D: Deserializer<'de>>(d: D) -> std::result::Result<Self, D::Error> {
        d.deserialize_map(OutputsVisitor)
    }
}

struct OutputsVisitor;

impl<'de> Visitor<'de> for OutputsVisitor {
    type Value = BenchmarkOutputs;

    fn expecting(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str("the benchmarks' outputs")
    }

    fn visit_map<A: MapAccess<'de>>(
        self,
        mut map: A,
    ) -> std::result::Result<Self::Value, A::Error> {
        use serde::de::Error;
        let mut out = BenchmarkOutputs::default();
        while let Some(name) = map.next_key::<String>()? {
            match find(&name) {
                Some(b) => {
                    let json: Json = map.next_value()?;
                    let output = b
                        .decode(&json)
                        .map_err(|e| A::Error::custom(format!("{e:#}")))?;
                    out.0.push((name, output));
                }
                None => {
                    map.next_value::<IgnoredAny>()?;
                }
            }
        }
        Ok(out)
    }
}

/// A JSON value whose objects keep their keys' order, so that a benchmark's
/// output reads back, and is written, as its own type writes it.
#[derive(Debug, Clone, PartialEq)]
pub enum Json {
    Null,
    Bool(bool),
    Number(serde_json::Number),
    String(String),
    Array(Vec<Json>),
    Object(Vec<(String, Json)>),
}

impl Json {
    /// `value` as JSON (numbers exactly as `serde_json` writes them).
    pub fn encode<T: Serialize>(value: &T) -> Result<Json> {
        Ok(serde_json::from_str(&serde_json::to_string(value)?)?)
    }

    /// This JSON read as a `T`.
    pub fn decode<T: DeserializeOwned>(&self) -> Result<T> {
        Ok(serde_json::from_str(&serde_json::to_string(self)?)?)
    }
}

impl Serialize for Json {
    fn serialize<S: Serializer>(&self, s: S) -> std::result::Result<S::Ok, S::Error> {
        match self {
            Json::Null => s.serialize_unit(),
            Json::Bool(b) => s.serialize_bool(*b),
            Json::Number(n) => n.serialize(s),
            Json::String(t) => s.serialize_str(t),
            Json::Array(v) => {
                let mut seq = s.serialize_seq(Some(v.len()))?;
                for x in v {
                    seq.serialize_element(x)?;
                }
                seq.end()
            }
            Json::Object(entries) => {
                let mut map = s.serialize_map(Some(entries.len()))?;
                for (k, v) in entries {
                    map.serialize_entry(k, v)?;
                }
                map.end()
            }
        }
    }
}

impl<'de> Deserialize<'de> for Json {
    fn deserialize<D: Deserializer<'de>>(d: D) -> std::result::Result<Self, D::Error> {
        d.deserialize_any(JsonVisitor)
    }
}

struct JsonVisitor;

impl<'de> Visitor<'de> for JsonVisitor {
    type Value = Json;

    fn expecting(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str("a JSON value")
    }
    fn visit_unit<E>(self) -> std::result::Result<Json, E> {
        Ok(Json::Null)
    }
    fn visit_none<E>(self) -> std::result::Result<Json, E> {
        Ok(Json::Null)
    }
    fn visit_some<D: Deserializer<'de>>(self, d: D) -> std::result::Result<Json, D::Error> {
        Json::deserialize(d)
    }
    fn visit_bool<E>(self, b: bool) -> std::result::Result<Json, E> {
        Ok(Json::Bool(b))
    }
    fn visit_u64<E>(self, n: u64) -> std::result::Result<Json, E> {
        Ok(Json::Number(n.into()))
    }
    fn visit_i64<E>(self, n: i64) -> std::result::Result<Json, E> {
        Ok(Json::Number(n.into()))
    }
    fn visit_f64<E>(self, x: f64) -> std::result::Result<Json, E> {
        Ok(serde_json::Number::from_f64(x).map_or(Json::Null, Json::Number))
    }
    fn visit_str<E>(self, t: &str) -> std::result::Result<Json, E> {
        Ok(Json::String(t.to_string()))
    }
    fn visit_string<E>(self, t: String) -> std::result::Result<Json, E> {
        Ok(Json::String(t))
    }
    fn visit_seq<A: SeqAccess<'de>>(self, mut seq: A) -> std::result::Result<Json, A::Error> {
        let mut v = Vec::new();
        while let Some(x) = seq.next_element()? {
            v.push(x);
        }
        Ok(Json::Array(v))
    }
    fn visit_map<A: MapAccess<'de>>(self, mut map: A) -> std::result::Result<Json, A::Error> {
        let mut entries = Vec::new();
        while let Some(k) = map.next_key::<String>()? {
            entries.push((k, map.next_value()?));
        }
        Ok(Json::Object(entries))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
    struct Out {
        zeta: f64,
        alpha: Option<f64>,
        n: u64,
        k: i64,
        list: Vec<f32>,
    }

    #[test]
    fn json_keeps_key_order_and_numbers_as_written() {
        let o = Out {
            zeta: 0.1 + 0.2,
            alpha: None,
            n: u64::MAX,
            k: -3,
            list: vec![0.1, 1e-7],
        };
        let json = Json::encode(&o).unwrap();
        assert_eq!(
            serde_json::to_string_pretty(&json).unwrap(),
            serde_json::to_string_pretty(&o).unwrap()
        );
        assert_eq!(json.decode::<Out>().unwrap(), o);
    }

    #[test]
    fn names_of_results_keys_and_odd_names_are_refused() {
        struct Named(&'static str);
        impl Benchmark for Named {
            type Section = toml::Value;
            type Output = NoOutput;
            fn name(&self) -> &'static str {
                self.0
            }
            fn stage(&self) -> &'static str {
                "nothing"
            }
            fn validate(&self, _: &toml::Value, _: &ExperimentSpec) -> Result<()> {
                Ok(())
            }
            fn evaluate(
                &self,
                _: &toml::Value,
                _: &BenchmarkContext,
            ) -> Result<Evaluated<NoOutput>> {
                bail!("never run")
            }
        }
        #[derive(Debug, Clone, Serialize, Deserialize)]
        struct NoOutput;
        impl BenchmarkOutput for NoOutput {
            fn csv_files(&self) -> Vec<(String, String)> {
                Vec::new()
            }
            fn markdown(&self, _: &mut String) {}
        }
        for name in ["ttf", "commands", "Upper", "a b", ""] {
            assert!(register_benchmark(Named(name)).is_err(), "{name:?}");
        }
    }
}
