//! Whole-file writes that never leave a half-written file behind:
//! [`write_atomic`] writes `<path>.tmp`, syncs it, renames it over `path` and
//! syncs the directory, so a reader (or a run killed mid-write) sees the old
//! file or the new one, never a mix. [`is_rall_temp`] names the temp files rall
//! itself leaves when killed mid-write: the only ones it ever removes.

use std::io::Write;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result};

/// Suffix of the temp file of a write in progress.
pub const TMP_SUFFIX: &str = ".tmp";

/// `<path>.tmp`.
pub fn tmp_path(path: &Path) -> PathBuf {
    let mut s = path.as_os_str().to_owned();
    s.push(TMP_SUFFIX);
    PathBuf::from(s)
}

/// Replaces `path` with `bytes` atomically (temp file, fsync, rename, fsync of
/// the directory). The parent directory must exist. On failure the temp file
/// is removed and `path` is unchanged.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    write_atomic_io(path, bytes).with_context(|| format!("writing {}", path.display()))
}

/// [`write_atomic`] with the bare I/O error, for callers that name the file
/// themselves.
pub fn write_atomic_io(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    let tmp = tmp_path(path);
    let write = || -> std::io::Result<()> {
        let mut f = std::fs::File::create(&tmp)?;
        f.write_all(bytes)?;
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
    write().inspect_err(|_| {
        // a failed write must not leave its temp file filling the disk
        let _ = std::fs::remove_file(&tmp);
    })
}

/// Copies `from` over `to` as [`write_atomic`] writes.
pub fn copy_atomic(from: &Path, to: &Path) -> Result<()> {
    let bytes = std::fs::read(from).with_context(|| format!("reading {}", from.display()))?;
    write_atomic(to, &bytes)
}

/// Files of a run directory rall writes through a temp file.
const RUN_FILES: [&str; 4] = [
    "latest.safetensors",
    "metrics.csv",
    "adaptation.csv",
    "config.toml",
];

/// Whether `name` (a file name in a run directory, or in its `checkpoints/`
/// when `in_checkpoints`) is the temp file of one of rall's own writes:
/// `<rall file>.tmp`, nothing else (a shared folder's other `*.tmp` stay).
pub fn is_rall_temp(name: &str, in_checkpoints: bool) -> bool {
    let Some(base) = name.strip_suffix(TMP_SUFFIX) else {
        return false;
    };
    if in_checkpoints {
        base.strip_prefix("model_")
            .and_then(|b| b.strip_suffix(".safetensors"))
            .is_some_and(|n| !n.is_empty() && n.bytes().all(|c| c.is_ascii_digit()))
    } else {
        RUN_FILES.contains(&base)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_rall_temp_names_are_rall_temps() {
        assert!(is_rall_temp("latest.safetensors.tmp", false));
        assert!(is_rall_temp("config.toml.tmp", false));
        assert!(is_rall_temp("model_000050.safetensors.tmp", true));
        assert!(!is_rall_temp("model_000050.safetensors.tmp", false));
        assert!(!is_rall_temp("notes.tmp", false));
        assert!(!is_rall_temp("model_x.safetensors.tmp", true));
        assert!(!is_rall_temp("latest.safetensors", false));
    }

    #[test]
    fn write_atomic_replaces_and_leaves_no_temp() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("config.toml");
        write_atomic(&p, b"a").unwrap();
        write_atomic(&p, b"bb").unwrap();
        assert_eq!(std::fs::read(&p).unwrap(), b"bb");
        assert!(!tmp_path(&p).exists());
        let missing = dir.path().join("no/such/dir/x");
        assert!(write_atomic(&missing, b"x").is_err());
    }
}
