//! What a rall checkpoint holds and its three kinds: the full run state (learner
//! state + runner state + metadata: config, observation layout, version), which
//! training resumes from; actor-only files; evaluation-only files. Saving each
//! kind, telling them apart, and loading any of them into a policy, refusing a
//! file this build cannot read. The safetensors container with its checksums
//! and atomic writes is `learn::checkpoint`.

use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};
use std::sync::Mutex;

use anyhow::{bail, Context, Result};

use super::identity::RunIdentity;
use crate::config::TrainConfig;
use crate::env::observation::layout_string;
use crate::env::{ACT_DIM, OBS_DIM};
use crate::learn::{
    decode_checkpoint, read_checkpoint, save_checkpoint_with, Checkpoint, LatentSource, Learner,
    NamedTensor, ObsLayout, CHECKSUM_PREFIX,
};

/// Bumped when the file layout changes incompatibly.
pub const FORMAT_VERSION: &str = "1";

/// Runner progress stored next to the learner state.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Progress {
    /// Iterations completed.
    pub iteration: usize,
    pub total_env_steps: u64,
    pub wall_s: f64,
    /// Action-sampling RNG: seed and position in its stream.
    pub rng_seed: u64,
    pub rng_word_pos: u128,
    /// Every env's terrain-curriculum level (rough ground; `None` on flat).
    pub terrain_levels: Option<Vec<usize>>,
    /// Each MPI rank's runner state (its envs' episodes and RNGs, observations,
    /// last episode statistics; see `train`), rank 0 first: what a resume needs
    /// to continue bit for bit. Empty in checkpoints written before it existed.
    pub rank_states: Vec<Vec<u8>>,
    /// The run this state belongs to (`None` in checkpoints written before
    /// identities existed).
    pub identity: Option<RunIdentity>,
}

/// Byte tensor of the learner's exact state ([`Learner::exact_state`]).
const LEARNER_EXACT: &str = "learner.exact";
/// Prefix of the byte tensors of the ranks' runner states.
const RANK_STATE_PREFIX: &str = "runner.rank.";

/// Writes `learner` + `progress` + `cfg` to `path` (temp file + rename).
pub fn save_policy(
    path: &Path,
    learner: &Learner,
    cfg: &TrainConfig,
    progress: &Progress,
) -> Result<()> {
    let mut meta = HashMap::new();
    meta.insert("format".into(), "rall-checkpoint".into());
    meta.insert("format_version".into(), FORMAT_VERSION.into());
    meta.insert("rall_version".into(), env!("CARGO_PKG_VERSION").into());
    meta.insert("config_toml".into(), cfg.to_toml());
    meta.insert("obs_layout".into(), layout_string());
    meta.insert("obs_dim".into(), OBS_DIM.to_string());
    meta.insert("act_dim".into(), ACT_DIM.to_string());
    meta.insert("obs_groups".into(), cfg.env.obs_layout().to_meta());
    let o = &cfg.env.observation;
    for g in &o.groups {
        meta.insert(
            format!("obs_group.{}", g.name()),
            g.fields_string(o.history_steps),
        );
    }
    let source = match learner.latent_source() {
        LatentSource::Encoder => "encoder",
        LatentSource::Adaptation => "adaptation",
    };
    meta.insert("latent_source".into(), source.into());
    meta.insert("iteration".into(), progress.iteration.to_string());
    meta.insert(
        "total_env_steps".into(),
        progress.total_env_steps.to_string(),
    );
    meta.insert("wall_s".into(), format!("{:.3}", progress.wall_s));
    meta.insert("rng_seed".into(), progress.rng_seed.to_string());
    meta.insert("rng_word_pos".into(), progress.rng_word_pos.to_string());
    if let Some(identity) = &progress.identity {
        identity.to_meta(&mut meta);
    }
    if let Some(levels) = &progress.terrain_levels {
        let text: Vec<String> = levels.iter().map(|l| l.to_string()).collect();
        meta.insert("terrain_levels".into(), text.join(","));
    }
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    }
    let mut blobs = vec![(LEARNER_EXACT.to_string(), learner.exact_state())];
    for (rank, bytes) in progress.rank_states.iter().enumerate() {
        blobs.push((format!("{RANK_STATE_PREFIX}{rank}"), bytes.clone()));
    }
    save_checkpoint_with(path, &learner.state(), &blobs, &meta)
}

/// A loaded checkpoint: the learner (weights, optimiser, lr), its config and progress.
pub struct LoadedPolicy {
    pub learner: Learner,
    pub config: TrainConfig,
    pub progress: Progress,
    /// The checkpoint holds everything a bit-identical resume needs (the
    /// learner's RNG and step counts, every rank's runner state).
    pub exact: bool,
    /// The file holds the actor alone ([`save_actor_only`]): it acts, but its
    /// critic and optimiser are fresh, so it is never resumed.
    pub actor_only: bool,
    /// The file holds what evaluation reads ([`save_evaluation_only`]): actor,
    /// critic and normaliser as trained, but no optimiser or environment state,
    /// so it evaluates and analyses the critic but is never resumed.
    pub evaluation_only: bool,
}

impl LoadedPolicy {
    /// Whether training can continue from this file (a full run state).
    pub fn resumable(&self) -> bool {
        !self.actor_only && !self.evaluation_only
    }
}

/// Metadata `contents` of a file written by [`save_actor_only`].
const ACTOR_ONLY: &str = "actor-only";

/// Whether checkpoint metadata `meta` marks a file written by [`save_actor_only`].
pub fn is_actor_only(meta: &HashMap<String, String>) -> bool {
    meta.get("contents").map(String::as_str) == Some(ACTOR_ONLY)
}

/// Metadata `contents` of a file written by [`save_evaluation_only`].
const EVALUATION_ONLY: &str = "evaluation";

/// Whether checkpoint metadata `meta` marks a file written by [`save_evaluation_only`].
pub fn is_evaluation_only(meta: &HashMap<String, String>) -> bool {
    meta.get("contents").map(String::as_str) == Some(EVALUATION_ONLY)
}

/// Whether checkpoint metadata `meta` marks a full run state (neither an
/// actor-only nor an evaluation file): what training can continue from.
pub fn is_run_state(meta: &HashMap<String, String>) -> bool {
    !is_actor_only(meta) && !is_evaluation_only(meta)
}

/// Whether a tensor is optimiser state (Adam's moments and step counts, the
/// adaptation module's too): what training needs and evaluation never reads.
fn is_optimiser_state(name: &str) -> bool {
    name.starts_with("adam.") || name.starts_with("adapt_adam.")
}

/// Writes what evaluation reads of checkpoint `src` to `path`: actor, critic,
/// observation normaliser, config and progress, without the optimiser's moments
/// or the environments' state (a PPO run state of 5.4 MB becomes about 1.8 MB).
/// Evaluating it gives the very numbers the full file gives; it never resumes.
/// Refuses an actor-only source (it has no trained critic to keep).
pub fn save_evaluation_only(src: &Path, path: &Path) -> Result<()> {
    let ckpt = read_checkpoint(src)?;
    if is_actor_only(&ckpt.metadata) {
        bail!(
            "{} holds the actor alone: an evaluation file needs the trained critic; cut it from the full checkpoint",
            src.display()
        );
    }
    let tensors: Vec<_> = ckpt
        .tensors
        .into_iter()
        .filter(|t| !is_optimiser_state(&t.name))
        .collect();
    let mut meta = ckpt.metadata;
    meta.insert("contents".into(), EVALUATION_ONLY.into());
    if holds_already(path, &tensors, &meta) {
        return Ok(());
    }
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    }
    save_checkpoint_with(path, &tensors, &[], &meta)
}

/// Whether a tensor belongs to what acts: the actor's weights (with RMA's encoder
/// or adaptation module) and the observation normaliser.
fn acts(name: &str) -> bool {
    name.starts_with("actor.") || name.starts_with("obs_norm.")
}

/// Writes the acting part of checkpoint `src` to `path` (config and progress
/// kept, critic and optimiser left out, about a sixth of the size): enough to
/// evaluate the policy, never to resume it.
pub fn save_actor_only(src: &Path, path: &Path) -> Result<()> {
    let ckpt = read_checkpoint(src)?;
    let tensors: Vec<_> = ckpt.tensors.into_iter().filter(|t| acts(&t.name)).collect();
    let mut meta = ckpt.metadata;
    meta.insert("contents".into(), ACTOR_ONLY.into());
    if holds_already(path, &tensors, &meta) {
        return Ok(());
    }
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    }
    save_checkpoint_with(path, &tensors, &[], &meta)
}

/// Whether `path` already holds exactly `tensors` and `meta` (checksums aside).
/// Leaving such a file alone keeps re-shipping a finished run from rewriting its
/// files, including those written before headers were sorted (the same contents
/// in other bytes).
fn holds_already(path: &Path, tensors: &[NamedTensor], meta: &HashMap<String, String>) -> bool {
    let Ok(old) = read_checkpoint(path) else {
        return false;
    };
    let entries = |m: &HashMap<String, String>| -> BTreeMap<String, String> {
        m.iter()
            .filter(|(k, _)| !k.starts_with(CHECKSUM_PREFIX))
            .map(|(k, v)| (k.clone(), v.clone()))
            .collect()
    };
    old.verified
        && old.blobs.is_empty()
        && old.tensors == tensors
        && entries(&old.metadata) == entries(meta)
}

fn meta_value<'a>(meta: &'a HashMap<String, String>, key: &str, path: &Path) -> Result<&'a str> {
    meta.get(key).map(String::as_str).with_context(|| {
        format!(
            "{} is not a rall checkpoint: metadata `{key}` is missing",
            path.display()
        )
    })
}

fn meta_parse<T: std::str::FromStr>(
    meta: &HashMap<String, String>,
    key: &str,
    path: &Path,
) -> Result<T> {
    let v = meta_value(meta, key, path)?;
    v.parse().map_err(|_| {
        anyhow::anyhow!(
            "{}: metadata `{key}` = {v:?} is not a valid number",
            path.display()
        )
    })
}

/// Loads a checkpoint, refusing one whose format, observation layout or
/// tensor shapes do not match this build.
pub fn load_policy(path: &Path) -> Result<LoadedPolicy> {
    let ckpt = read_checkpoint(path)?;
    if !ckpt.verified {
        note_unverified(path);
    }
    policy_from_parts(ckpt, path)
}

/// [`load_policy`] of a checkpoint file's bytes (e.g. broadcast from MPI rank
/// 0, which has already said whether the file carries checksums).
pub fn load_policy_bytes(bytes: &[u8], path: &Path) -> Result<LoadedPolicy> {
    policy_from_parts(decode_checkpoint(bytes, path)?, path)
}

/// Says once per file and process that `path` has no checksums to verify.
fn note_unverified(path: &Path) {
    static SEEN: Mutex<Vec<PathBuf>> = Mutex::new(Vec::new());
    let mut seen = SEEN.lock().unwrap_or_else(|e| e.into_inner());
    if !seen.iter().any(|p| p == path) {
        seen.push(path.to_path_buf());
        eprintln!(
            "note: {} has no checksums (written by an older rall): loaded unverified",
            path.display()
        );
    }
}

fn policy_from_parts(ckpt: Checkpoint, path: &Path) -> Result<LoadedPolicy> {
    let Checkpoint {
        tensors,
        blobs,
        metadata: meta,
        ..
    } = ckpt;
    let format = meta_value(&meta, "format", path)?;
    if format != "rall-checkpoint" {
        bail!(
            "{} is not a rall checkpoint (format {format:?})",
            path.display()
        );
    }
    let version = meta_value(&meta, "format_version", path)?;
    if version != FORMAT_VERSION {
        bail!(
            "{}: checkpoint format {version} but this rall reads format {FORMAT_VERSION}",
            path.display()
        );
    }
    let layout = meta_value(&meta, "obs_layout", path)?;
    if layout != layout_string() {
        bail!(
            "{}: observation layout mismatch: the checkpoint was trained on [{layout}] but this rall observes [{}]",
            path.display(),
            layout_string()
        );
    }
    let (obs_dim, act_dim): (usize, usize) = (
        meta_parse(&meta, "obs_dim", path)?,
        meta_parse(&meta, "act_dim", path)?,
    );
    if obs_dim != OBS_DIM || act_dim != ACT_DIM {
        bail!(
            "{}: checkpoint has obs {obs_dim} / actions {act_dim}, this rall needs {OBS_DIM} / {ACT_DIM}",
            path.display()
        );
    }
    let config = TrainConfig::from_toml_str(meta_value(&meta, "config_toml", path)?)
        .with_context(|| format!("{}: the stored config", path.display()))?;
    let progress = Progress {
        iteration: meta_parse(&meta, "iteration", path)?,
        total_env_steps: meta_parse(&meta, "total_env_steps", path)?,
        wall_s: meta_parse(&meta, "wall_s", path)?,
        rng_seed: meta_parse(&meta, "rng_seed", path)?,
        rng_word_pos: meta_parse(&meta, "rng_word_pos", path)?,
        terrain_levels: meta
            .get("terrain_levels")
            .map(|text| {
                text.split(',')
                    .map(|v| v.parse::<usize>())
                    .collect::<std::result::Result<Vec<_>, _>>()
                    .map_err(|_| {
                        anyhow::anyhow!(
                            "{}: metadata `terrain_levels` is not a list of levels",
                            path.display()
                        )
                    })
            })
            .transpose()?,
        rank_states: rank_states(&blobs),
        identity: RunIdentity::from_meta(&meta, path)?,
    };
    // the row's groups: stored since groups exist, else the policy group alone
    let stored_layout = match meta.get("obs_groups") {
        Some(text) => ObsLayout::parse_meta(text)
            .with_context(|| format!("{}: metadata `obs_groups`", path.display()))?,
        None => ObsLayout::policy_only(OBS_DIM),
    };
    let layout = config.env.obs_layout();
    stored_layout.check_same(&layout, &path.display().to_string())?;
    let o = &config.env.observation;
    for g in &o.groups {
        let key = format!("obs_group.{}", g.name());
        let here = g.fields_string(o.history_steps);
        if let Some(stored) = meta.get(&key).filter(|s| **s != here) {
            bail!(
                "{}: observation group {:?} holds [{stored}] in the checkpoint but [{here}] in this build",
                path.display(),
                g.name()
            );
        }
    }
    let mut learner = Learner::with_layout(&layout, ACT_DIM, &config.learner, config.runner.seed)?;
    if meta.get("latent_source").map(String::as_str) == Some("adaptation") {
        learner.set_latent_source(LatentSource::Adaptation);
    }
    let actor_only = is_actor_only(&meta);
    let evaluation_only = is_evaluation_only(&meta);
    let loaded = if actor_only {
        learner.load_state_keeping(&tensors, |name| !acts(name))
    } else if evaluation_only {
        learner.load_state_keeping(&tensors, is_optimiser_state)
    } else {
        learner.load_state(&tensors)
    };
    loaded.with_context(|| {
        format!(
            "{} does not match the network in its own config",
            path.display()
        )
    })?;
    let exact_learner = blobs.iter().find(|(n, _)| n == LEARNER_EXACT);
    if let Some((_, bytes)) = exact_learner {
        learner
            .load_exact_state(bytes)
            .with_context(|| format!("{}: the learner's exact state", path.display()))?;
    }
    let exact = exact_learner.is_some() && !progress.rank_states.is_empty();
    Ok(LoadedPolicy {
        learner,
        config,
        progress,
        exact: exact && !actor_only && !evaluation_only,
        actor_only,
        evaluation_only,
    })
}

/// The ranks' runner states `runner.rank.0`, `runner.rank.1`, ... (stops at
/// the first rank missing).
fn rank_states(blobs: &[(String, Vec<u8>)]) -> Vec<Vec<u8>> {
    (0..)
        .map_while(|rank| {
            let name = format!("{RANK_STATE_PREFIX}{rank}");
            blobs
                .iter()
                .find(|(n, _)| *n == name)
                .map(|(_, b)| b.clone())
        })
        .collect()
}
