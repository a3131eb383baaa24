//! Whole-file writes that never leave a half-written file behind:
//! [`write_atomic`] writes `<path>.tmp`, syncs it, renames it over `path` and
//! syncs the directory, so a reader (or a run killed mid-write) sees the old
//! file or the new one, never a mix. [`is_rall_temp`] names the temp files rall
//! itself leaves when killed mid-write: the only ones it ever removes.
//! [`append_whole`] appends a record (a CSV row) whole or not at all.
//!
//! Fault injection for the tests: `RALL_FAULT_DISK_FULL=<file name>:<n>` makes
//! the `n`-th append (1-based) to every file of that name write half its bytes
//! and then fail as a full disk does.

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

/// Appends `bytes` to `file` (opened for appending; `path` names it in errors)
/// whole or not at all: on a failure (a full disk mid-row) the file is cut back
/// to its length before the call, so it never ends in half a record.
pub fn append_whole(file: &mut std::fs::File, path: &Path, bytes: &[u8]) -> Result<()> {
    let before = file
        .metadata()
        .with_context(|| format!("appending to {}", path.display()))?
        .len();
    let written = write_or_fail_as_injected(file, path, bytes).and_then(|()| file.flush());
    written.map_err(|e| {
        let restored = file.set_len(before);
        let what = match restored {
            Ok(()) => format!("appending to {} failed; the file is as it was", path.display()),
            Err(r) => format!(
                "appending to {} failed, and cutting it back to its {before} bytes failed too ({r})",
                path.display()
            ),
        };
        anyhow::Error::new(e).context(what)
    })
}

/// `file.write_all(bytes)`, unless `RALL_FAULT_DISK_FULL` asks this append to
/// fail after half its bytes.
fn write_or_fail_as_injected(
    file: &mut std::fs::File,
    path: &Path,
    bytes: &[u8],
) -> std::io::Result<()> {
    if injected_disk_full(path) {
        file.write_all(&bytes[..bytes.len() / 2])?;
        return Err(std::io::Error::from_raw_os_error(libc::ENOSPC));
    }
    file.write_all(bytes)
}

/// Whether this append to `path` is the one `RALL_FAULT_DISK_FULL` fails.
fn injected_disk_full(path: &Path) -> bool {
    use std::sync::atomic::{AtomicUsize, Ordering};
    static APPENDS: AtomicUsize = AtomicUsize::new(0);
    let Ok(spec) = std::env::var("RALL_FAULT_DISK_FULL") else {
        return false;
    };
    let Some((name, n)) = spec.split_once(':') else {
        return false;
    };
    if path.file_name().and_then(|f| f.to_str()) != Some(name) {
        return false;
    }
    let count = APPENDS.fetch_add(1, Ordering::SeqCst) + 1;
    n.parse::<usize>().is_ok_and(|n| n == count)
}

/// Copies `from` over `to` as [`write_atomic`] writes.
pub fn copy_atomic(from: &Path, to: &Path) -> Result<()> {
    let bytes = std::fs::read(from).with_context(|| format!("reading {}", from.display()))?;
    write_atomic(to, &bytes)
}

/// Files of a run directory rall writes through a temp file.
const RUN_FILES: [&str; 5] = [
    "latest.safetensors",
    "metrics.csv",
    "adaptation.csv",
    "config.toml",
    "identity.toml",
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
    fn append_whole_appends_and_names_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("rows.csv");
        let mut f = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(&p)
            .unwrap();
        append_whole(&mut f, &p, b"a,b\n").unwrap();
        append_whole(&mut f, &p, b"1,2\n").unwrap();
        assert_eq!(std::fs::read(&p).unwrap(), b"a,b\n1,2\n");
        // /dev/full fails every write as a full disk does
        let full = Path::new("/dev/full");
        let mut f = std::fs::OpenOptions::new().append(true).open(full).unwrap();
        let e = format!("{:#}", append_whole(&mut f, full, b"1,2\n").unwrap_err());
        assert!(
            e.contains("/dev/full") && e.contains("No space left"),
            "{e}"
        );
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
