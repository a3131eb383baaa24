//! Checkpoints as safetensors files (`f32`, little endian) with a caller-supplied
//! `__metadata__` string map (the runner stores config JSON, observation layout
//! and version there). Writes are atomic: `<path>.tmp`, fsync, rename.

use super::learner::NamedTensor;
use anyhow::{bail, Context, Result};
use safetensors::tensor::{Dtype, SafeTensors, TensorView};
use std::collections::HashMap;
use std::io::Write;
use std::path::{Path, PathBuf};

fn tmp_path(path: &Path) -> PathBuf {
    let mut s = path.as_os_str().to_owned();
    s.push(".tmp");
    PathBuf::from(s)
}

/// Writes `tensors` and `metadata` to `path` atomically.
pub fn save_checkpoint(
    path: &Path,
    tensors: &[NamedTensor],
    metadata: &HashMap<String, String>,
) -> Result<()> {
    let bytes: Vec<Vec<u8>> = tensors
        .iter()
        .map(|t| t.data.iter().flat_map(|v| v.to_le_bytes()).collect())
        .collect();
    let views = tensors
        .iter()
        .zip(&bytes)
        .map(|(t, b)| {
            TensorView::new(Dtype::F32, t.shape.clone(), b)
                .map(|v| (t.name.clone(), v))
                .with_context(|| format!("tensor `{}` with shape {:?}", t.name, t.shape))
        })
        .collect::<Result<Vec<_>>>()?;
    let buf = safetensors::serialize(views, Some(metadata.clone()))
        .with_context(|| format!("serialising checkpoint {}", path.display()))?;
    let tmp = tmp_path(path);
    let write = || -> std::io::Result<()> {
        let mut f = std::fs::File::create(&tmp)?;
        f.write_all(&buf)?;
        f.sync_all()?;
        std::fs::rename(&tmp, path)?;
        // persist the rename (best effort: not every platform can fsync a directory)
        if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
            if let Ok(d) = std::fs::File::open(dir) {
                let _ = d.sync_all();
            }
        }
        Ok(())
    };
    write().with_context(|| {
        // a failed write must not leave its temp file filling the disk
        let _ = std::fs::remove_file(&tmp);
        format!("writing checkpoint {}", path.display())
    })
}

/// Reads a checkpoint written by [`save_checkpoint`]: tensors (in file order) and
/// metadata. Any malformed or truncated file is an error naming the path.
pub fn load_checkpoint(path: &Path) -> Result<(Vec<NamedTensor>, HashMap<String, String>)> {
    let bytes =
        std::fs::read(path).with_context(|| format!("reading checkpoint {}", path.display()))?;
    parse_checkpoint(&bytes, path)
}

/// [`load_checkpoint`] of a file's bytes already in memory (`path` names it in errors).
pub fn parse_checkpoint(
    bytes: &[u8],
    path: &Path,
) -> Result<(Vec<NamedTensor>, HashMap<String, String>)> {
    let st = SafeTensors::deserialize(bytes)
        .map_err(|e| anyhow::anyhow!("{e:?}"))
        .with_context(|| {
            format!(
                "checkpoint {} is not a valid safetensors file",
                path.display()
            )
        })?;
    let (_, meta) = SafeTensors::read_metadata(bytes)
        .map_err(|e| anyhow::anyhow!("{e:?}"))
        .with_context(|| format!("checkpoint {}: bad header", path.display()))?;
    let metadata = meta.metadata().clone().unwrap_or_default();
    let mut tensors = Vec::new();
    for name in meta.offset_keys() {
        let view = st
            .tensor(&name)
            .map_err(|e| anyhow::anyhow!("{e:?}"))
            .with_context(|| format!("checkpoint {}: tensor `{name}`", path.display()))?;
        if view.dtype() != Dtype::F32 {
            bail!(
                "checkpoint {}: tensor `{name}` has dtype {:?}, expected F32",
                path.display(),
                view.dtype()
            );
        }
        let data = view
            .data()
            .chunks_exact(4)
            .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
            .collect();
        tensors.push(NamedTensor {
            name,
            shape: view.shape().to_vec(),
            data,
        });
    }
    Ok((tensors, metadata))
}
