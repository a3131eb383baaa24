//! Checkpoints as safetensors files (`f32` tensors, little endian, plus `u8`
//! byte tensors for state kept bit for bit) with a caller-supplied
//! `__metadata__` string map (the runner stores config TOML, observation layout
//! and version there: `runner::checkpoint_kinds`). Writes are atomic: `<path>.tmp`,
//! fsync, rename.
//!
//! Integrity: every file carries a SHA-256 of each tensor (its name, dtype,
//! shape and bytes) under the metadata key `sha256.<tensor>`, and one of the
//! rest of the metadata under `sha256.__metadata__`. Loading verifies them all:
//! a corrupt file is refused naming the tensor (or the metadata). Files written
//! before checksums existed (no `sha256.` key at all) still load, unverified
//! ([`Checkpoint::verified`] is false).

use anyhow::{bail, Context, Result};
use safetensors::tensor::{Dtype, SafeTensors, TensorView};
use sha2::{Digest, Sha256};
use std::collections::HashMap;
use std::path::Path;

/// One named `f32` tensor of the learner state (row-major).
#[derive(Clone, Debug, PartialEq)]
pub struct NamedTensor {
    pub name: String,
    pub shape: Vec<usize>,
    pub data: Vec<f32>,
}

/// Prefix of the checksum keys in the metadata.
pub const CHECKSUM_PREFIX: &str = "sha256.";
/// The checksum key of the metadata itself.
const METADATA_CHECKSUM: &str = "sha256.__metadata__";

/// A checkpoint read back: `f32` tensors and byte tensors in file order, the
/// metadata without its checksum keys, and whether checksums were verified.
#[derive(Debug, Clone, PartialEq)]
pub struct Checkpoint {
    pub tensors: Vec<NamedTensor>,
    /// `u8` tensors: state stored as bytes (RNG states, counters, env state).
    pub blobs: Vec<(String, Vec<u8>)>,
    pub metadata: HashMap<String, String>,
    /// The file carried checksums and every one matched (false: an older file
    /// without checksums, loaded unverified).
    pub verified: bool,
}

fn tensor_digest(name: &str, dtype: Dtype, shape: &[usize], data: &[u8]) -> String {
    let mut h = Sha256::new();
    h.update(name.as_bytes());
    h.update([0]);
    h.update(format!("{dtype:?}{shape:?}").as_bytes());
    h.update([0]);
    h.update(data);
    hex(&h.finalize())
}

/// Digest of every metadata entry but the checksums, in key order.
fn metadata_digest(meta: &HashMap<String, String>) -> String {
    let mut keys: Vec<&String> = meta
        .keys()
        .filter(|k| !k.starts_with(CHECKSUM_PREFIX))
        .collect();
    keys.sort();
    let mut h = Sha256::new();
    for k in keys {
        for part in [k.as_bytes(), meta[k].as_bytes()] {
            h.update((part.len() as u64).to_le_bytes());
            h.update(part);
        }
    }
    hex(&h.finalize())
}

fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

/// Writes `tensors` and `metadata` to `path` atomically, with checksums.
pub fn save_checkpoint(
    path: &Path,
    tensors: &[NamedTensor],
    metadata: &HashMap<String, String>,
) -> Result<()> {
    save_checkpoint_with(path, tensors, &[], metadata)
}

/// [`save_checkpoint`] with byte tensors (`u8`) beside the `f32` ones.
pub fn save_checkpoint_with(
    path: &Path,
    tensors: &[NamedTensor],
    blobs: &[(String, Vec<u8>)],
    metadata: &HashMap<String, String>,
) -> Result<()> {
    let buf = serialize_checkpoint(tensors, blobs, metadata)
        .with_context(|| format!("serialising checkpoint {}", path.display()))?;
    crate::fsio::write_atomic_io(path, &buf)
        .with_context(|| format!("writing checkpoint {}", path.display()))
}

/// The file's bytes: tensors, blobs and metadata with fresh checksums (any
/// `sha256.` keys in `metadata` are replaced).
pub fn serialize_checkpoint(
    tensors: &[NamedTensor],
    blobs: &[(String, Vec<u8>)],
    metadata: &HashMap<String, String>,
) -> Result<Vec<u8>> {
    let bytes: Vec<Vec<u8>> = tensors
        .iter()
        .map(|t| t.data.iter().flat_map(|v| v.to_le_bytes()).collect())
        .collect();
    let mut meta: HashMap<String, String> = metadata
        .iter()
        .filter(|(k, _)| !k.starts_with(CHECKSUM_PREFIX))
        .map(|(k, v)| (k.clone(), v.clone()))
        .collect();
    let digest = metadata_digest(&meta);
    meta.insert(METADATA_CHECKSUM.into(), digest);
    let mut views = Vec::with_capacity(tensors.len() + blobs.len());
    let items = tensors
        .iter()
        .zip(&bytes)
        .map(|(t, b)| (&t.name, Dtype::F32, t.shape.clone(), b))
        .chain(blobs.iter().map(|(n, b)| (n, Dtype::U8, vec![b.len()], b)));
    for (name, dtype, shape, data) in items {
        let key = format!("{CHECKSUM_PREFIX}{name}");
        anyhow::ensure!(!meta.contains_key(&key), "two tensors are called `{name}`");
        meta.insert(key, tensor_digest(name, dtype, &shape, data));
        let view = TensorView::new(dtype, shape.clone(), data)
            .with_context(|| format!("tensor `{name}` with shape {shape:?}"))?;
        views.push((name.clone(), view));
    }
    let buf = safetensors::serialize(views, Some(meta)).map_err(|e| anyhow::anyhow!("{e:?}"))?;
    canonical_header(buf)
}

/// The same file with its header's keys in sorted order. The format writes its
/// metadata map in no fixed order, so the same checkpoint serialised twice gave
/// different bytes; sorted, the same contents are the same bytes (identical
/// files cost nothing more in a repository, and a rewrite changes nothing).
fn canonical_header(mut buf: Vec<u8>) -> Result<Vec<u8>> {
    use std::collections::BTreeMap;
    let n = u64::from_le_bytes(buf[..8].try_into().expect("8 bytes")) as usize;
    let header: BTreeMap<String, serde_json::Value> = serde_json::from_slice(&buf[8..8 + n])?;
    let sorted: BTreeMap<String, serde_json::Value> = header
        .into_iter()
        .map(|(k, v)| match v {
            serde_json::Value::Object(m) => {
                let entries: BTreeMap<String, serde_json::Value> = m.into_iter().collect();
                Ok((k, serde_json::to_value(entries)?))
            }
            v => Ok((k, v)),
        })
        .collect::<Result<_>>()?;
    let text = serde_json::to_string(&sorted)?;
    // the same entries in another order: the same length, padded as before
    anyhow::ensure!(
        text.len() <= n,
        "re-ordering the checkpoint header changed its length"
    );
    buf[8..8 + text.len()].copy_from_slice(text.as_bytes());
    buf[8 + text.len()..8 + n].fill(b' ');
    Ok(buf)
}

/// Reads a checkpoint written by [`save_checkpoint`]: tensors (in file order) and
/// metadata. Any malformed, truncated or corrupt file is an error naming the path.
pub fn load_checkpoint(path: &Path) -> Result<(Vec<NamedTensor>, HashMap<String, String>)> {
    read_checkpoint(path).map(|c| (c.tensors, c.metadata))
}

/// [`load_checkpoint`] of a file's bytes already in memory (`path` names it in errors).
pub fn parse_checkpoint(
    bytes: &[u8],
    path: &Path,
) -> Result<(Vec<NamedTensor>, HashMap<String, String>)> {
    decode_checkpoint(bytes, path).map(|c| (c.tensors, c.metadata))
}

/// The whole checkpoint at `path` (byte tensors and verification included).
pub fn read_checkpoint(path: &Path) -> Result<Checkpoint> {
    let bytes =
        std::fs::read(path).with_context(|| format!("reading checkpoint {}", path.display()))?;
    decode_checkpoint(&bytes, path)
}

/// [`read_checkpoint`] of bytes in memory.
pub fn decode_checkpoint(bytes: &[u8], path: &Path) -> Result<Checkpoint> {
    let st = SafeTensors::deserialize(bytes)
        .map_err(|e| anyhow::anyhow!("{e:?}"))
        .with_context(|| {
            format!(
                "checkpoint {} is not a valid safetensors file",
                path.display()
            )
        })?;
    let (_, header) = SafeTensors::read_metadata(bytes)
        .map_err(|e| anyhow::anyhow!("{e:?}"))
        .with_context(|| format!("checkpoint {}: bad header", path.display()))?;
    let mut metadata = header.metadata().clone().unwrap_or_default();
    let sums: HashMap<String, String> = metadata
        .iter()
        .filter(|(k, _)| k.starts_with(CHECKSUM_PREFIX))
        .map(|(k, v)| (k.clone(), v.clone()))
        .collect();
    metadata.retain(|k, _| !k.starts_with(CHECKSUM_PREFIX));
    let verified = !sums.is_empty();
    let mut out = Checkpoint {
        tensors: Vec::new(),
        blobs: Vec::new(),
        metadata,
        verified,
    };
    let mut checked = 0;
    for name in header.offset_keys() {
        let view = st
            .tensor(&name)
            .map_err(|e| anyhow::anyhow!("{e:?}"))
            .with_context(|| format!("checkpoint {}: tensor `{name}`", path.display()))?;
        if verified {
            verify_tensor(&sums, &name, &view, path)?;
            checked += 1;
        }
        push_tensor(&mut out, name, &view, path)?;
    }
    if verified {
        verify_metadata(&sums, &out.metadata, checked, path)?;
    }
    Ok(out)
}

fn verify_tensor(
    sums: &HashMap<String, String>,
    name: &str,
    view: &TensorView,
    path: &Path,
) -> Result<()> {
    let Some(expected) = sums.get(&format!("{CHECKSUM_PREFIX}{name}")) else {
        bail!(
            "checkpoint {} is corrupt: tensor `{name}` has no checksum while the others have",
            path.display()
        );
    };
    if *expected != tensor_digest(name, view.dtype(), view.shape(), view.data()) {
        bail!(
            "checkpoint {} is corrupt: tensor `{name}` does not match its checksum",
            path.display()
        );
    }
    Ok(())
}

fn verify_metadata(
    sums: &HashMap<String, String>,
    metadata: &HashMap<String, String>,
    tensors_checked: usize,
    path: &Path,
) -> Result<()> {
    if sums.get(METADATA_CHECKSUM) != Some(&metadata_digest(metadata)) {
        bail!(
            "checkpoint {} is corrupt: its metadata (config, progress) does not match its checksum",
            path.display()
        );
    }
    // every checksum but the metadata's belongs to a tensor that was checked
    if sums.len() != tensors_checked + 1 {
        bail!(
            "checkpoint {} is corrupt: it has {} tensor checksums for {tensors_checked} tensors",
            path.display(),
            sums.len() - 1
        );
    }
    Ok(())
}

fn push_tensor(out: &mut Checkpoint, name: String, view: &TensorView, path: &Path) -> Result<()> {
    match view.dtype() {
        Dtype::F32 => {
            let data = view
                .data()
                .chunks_exact(4)
                .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
                .collect();
            out.tensors.push(NamedTensor {
                name,
                shape: view.shape().to_vec(),
                data,
            });
        }
        Dtype::U8 => out.blobs.push((name, view.data().to_vec())),
        other => bail!(
            "checkpoint {}: tensor `{name}` has dtype {other:?}, expected F32 (or U8 state)",
            path.display()
        ),
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn contents() -> (Vec<NamedTensor>, HashMap<String, String>) {
        let tensors = ["actor.0.weight", "critic.0.bias", "actor.0.bias", "a"]
            .iter()
            .enumerate()
            .map(|(i, n)| NamedTensor {
                name: n.to_string(),
                shape: vec![2, i + 1],
                data: (0..2 * (i + 1))
                    .map(|v| v as f32 * 0.5 - i as f32)
                    .collect(),
            })
            .collect();
        let meta = (0..40)
            .map(|i| (format!("key{i}"), format!("value {i} \"quoted\"")))
            .collect();
        (tensors, meta)
    }

    #[test]
    fn the_same_contents_serialise_to_the_same_bytes() {
        let (tensors, meta) = contents();
        let blobs = vec![("state".to_string(), vec![1u8, 2, 3])];
        let first = serialize_checkpoint(&tensors, &blobs, &meta).unwrap();
        for _ in 0..8 {
            // a map built again iterates in another order
            let again: HashMap<String, String> =
                meta.iter().map(|(k, v)| (k.clone(), v.clone())).collect();
            assert_eq!(
                serialize_checkpoint(&tensors, &blobs, &again).unwrap(),
                first
            );
        }
        let back = decode_checkpoint(&first, Path::new("mem")).unwrap();
        assert!(back.verified);
        // the file keeps tensors in its own (offset) order
        let by_name = |mut v: Vec<NamedTensor>| {
            v.sort_by(|a, b| a.name.cmp(&b.name));
            v
        };
        assert_eq!(by_name(back.tensors), by_name(tensors));
        assert_eq!(back.blobs, blobs);
        for (k, v) in &meta {
            assert_eq!(back.metadata.get(k), Some(v), "{k}");
        }
    }
}
