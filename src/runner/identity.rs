//! Which run a checkpoint belongs to: an id made when the run starts, the
//! run's seed and the hash of the config it started with. Every checkpoint
//! carries it in its metadata, the run directory keeps it in `identity.toml`,
//! and `rall train --resume` refuses a checkpoint of another run. Checkpoints
//! written before identities existed carry none: they are of an unknown run
//! and are accepted.

use std::collections::HashMap;
use std::path::Path;

use anyhow::{Context, Result};
use serde::{Deserialize, Serialize};

use crate::config::TrainConfig;

/// The file of a run directory holding its identity.
pub const IDENTITY_FILE: &str = "identity.toml";

/// Metadata keys of a checkpoint's identity.
const META_RUN_ID: &str = "run_id";
const META_SEED: &str = "run_seed";
const META_CONFIG_HASH: &str = "run_config_hash";

/// The identity of one training run.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RunIdentity {
    /// Made when the run starts (16 hex digits): two runs never share one, a
    /// run folder copied elsewhere keeps it.
    pub run_id: String,
    /// `runner.seed`.
    pub seed: u64,
    /// FNV-1a of the config the run started with, as TOML (16 hex digits).
    pub config_hash: String,
}

impl RunIdentity {
    /// A new run's identity: an id from the clock, the process and the config.
    pub fn new(cfg: &TrainConfig) -> RunIdentity {
        let nanos = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_nanos());
        let config_hash = config_hash(cfg);
        let seed_text = format!("{nanos}:{}:{config_hash}", std::process::id());
        RunIdentity {
            run_id: format!("{:016x}", crate::hash::fnv1a64(seed_text.bytes())),
            seed: cfg.runner.seed,
            config_hash,
        }
    }

    /// One line: `run <id> (seed <s>, config <hash>)`.
    pub fn describe(&self) -> String {
        format!(
            "run {} (seed {}, config {})",
            self.run_id, self.seed, self.config_hash
        )
    }

    /// Adds the identity to checkpoint metadata.
    pub fn to_meta(&self, meta: &mut HashMap<String, String>) {
        meta.insert(META_RUN_ID.into(), self.run_id.clone());
        meta.insert(META_SEED.into(), self.seed.to_string());
        meta.insert(META_CONFIG_HASH.into(), self.config_hash.clone());
    }

    /// The identity in checkpoint metadata (`None`: written before identities
    /// existed); `path` names the file in errors.
    pub fn from_meta(meta: &HashMap<String, String>, path: &Path) -> Result<Option<RunIdentity>> {
        let Some(run_id) = meta.get(META_RUN_ID) else {
            return Ok(None);
        };
        let get = |key: &str| {
            meta.get(key).with_context(|| {
                format!(
                    "{}: metadata `{META_RUN_ID}` is set but `{key}` is missing",
                    path.display()
                )
            })
        };
        let seed_text = get(META_SEED)?;
        let seed = seed_text.parse().map_err(|_| {
            anyhow::anyhow!(
                "{}: metadata `{META_SEED}` = {seed_text:?} is not a seed",
                path.display()
            )
        })?;
        Ok(Some(RunIdentity {
            run_id: run_id.clone(),
            seed,
            config_hash: get(META_CONFIG_HASH)?.clone(),
        }))
    }

    /// The identity stored in run directory `dir` (`None`: the directory has
    /// no `identity.toml`, e.g. a run started before identities existed).
    pub fn read(dir: &Path) -> Result<Option<RunIdentity>> {
        let path = dir.join(IDENTITY_FILE);
        let text = match std::fs::read_to_string(&path) {
            Ok(text) => text,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
            Err(e) => return Err(e).with_context(|| format!("reading {}", path.display())),
        };
        toml::from_str(&text)
            .map(Some)
            .map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))
    }

    /// Writes `identity.toml` into run directory `dir` (atomically).
    pub fn write(&self, dir: &Path) -> Result<()> {
        let body = toml::to_string(self).context("serialising the run identity")?;
        let text = format!(
            "# The run this folder holds. Every checkpoint rall writes here carries this\n\
             # identity, and `rall train --resume` refuses a checkpoint of another run.\n{body}"
        );
        crate::fsio::write_atomic(&dir.join(IDENTITY_FILE), text.as_bytes())
    }
}

/// FNV-1a of `cfg` as TOML, 16 hex digits.
pub fn config_hash(cfg: &TrainConfig) -> String {
    format!("{:016x}", crate::hash::fnv1a64(cfg.to_toml().bytes()))
}

/// The identity a resumed run goes on under: the run directory's, else the
/// checkpoint's, else a new one (both unknown: written before identities).
/// Refuses a checkpoint whose identity is another run's, naming both.
pub fn resumed_identity(
    dir: &Path,
    stored: Option<RunIdentity>,
    checkpoint: Option<&RunIdentity>,
    checkpoint_path: &Path,
    cfg: &TrainConfig,
) -> Result<RunIdentity> {
    match (stored, checkpoint) {
        (Some(run), Some(ckpt)) if run.run_id != ckpt.run_id => anyhow::bail!(
            "{} is a checkpoint of another run: it belongs to {}, but {} holds {} ({}). \
             A resume continues its own run: move the file away, or resume the folder of the \
             run it belongs to (a run folder copied elsewhere resumes as that run)",
            checkpoint_path.display(),
            ckpt.describe(),
            dir.display(),
            run.describe(),
            dir.join(IDENTITY_FILE).display()
        ),
        (Some(run), _) => Ok(run),
        (None, Some(ckpt)) => Ok(ckpt.clone()),
        (None, None) => Ok(RunIdentity::new(cfg)),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn identities_round_trip_and_another_runs_checkpoint_is_refused() {
        let cfg = TrainConfig::default();
        let (a, b) = (RunIdentity::new(&cfg), RunIdentity::new(&cfg));
        assert_ne!(a.run_id, b.run_id, "two runs never share an id");
        let mut meta = HashMap::new();
        assert_eq!(RunIdentity::from_meta(&meta, Path::new("x")).unwrap(), None);
        a.to_meta(&mut meta);
        let back = RunIdentity::from_meta(&meta, Path::new("x")).unwrap();
        assert_eq!(back.as_ref(), Some(&a));
        let dir = tempfile::tempdir().unwrap();
        assert_eq!(RunIdentity::read(dir.path()).unwrap(), None);
        a.write(dir.path()).unwrap();
        assert_eq!(RunIdentity::read(dir.path()).unwrap(), Some(a.clone()));
        let ckpt = Path::new("latest.safetensors");
        let e = resumed_identity(dir.path(), Some(a.clone()), Some(&b), ckpt, &cfg);
        let e = format!("{:#}", e.unwrap_err());
        assert!(e.contains(&a.run_id) && e.contains(&b.run_id), "{e}");
        // unknown on either side: accepted
        let same = resumed_identity(dir.path(), Some(a.clone()), None, ckpt, &cfg).unwrap();
        assert_eq!(same, a);
        let adopted = resumed_identity(dir.path(), None, Some(&b), ckpt, &cfg).unwrap();
        assert_eq!(adopted, b);
    }
}
