//! A run's directory: where its checkpoints, metrics and config live, which
//! checkpoint a resume starts from, and the lock that keeps one trainer per run.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result};

use super::checkpoint_kinds::{load_policy, save_policy, Progress};
use crate::config::TrainConfig;
use crate::learn::Learner;

/// Name of the rolling checkpoint in a run directory.
pub const LATEST: &str = "latest.safetensors";

/// What rall writes at the top of a run directory: its files, its folders
/// (`checkpoints/`, RMA's `discarded-adaptation/`) and the final-policy choice
/// of `rall experiment` (`selected.safetensors` and its CSVs). Temp files of
/// these ([`crate::fsio::is_rall_temp`]) and of the lock are rall's too.
pub const RUN_ENTRIES: [&str; 11] = [
    LATEST,
    "config.toml",
    "identity.toml",
    "metrics.csv",
    "adaptation.csv",
    "train.lock",
    "checkpoints",
    "discarded-adaptation",
    "selected.safetensors",
    "selection.csv",
    "teacher-selection.csv",
];

/// Directories no run is written into, nor below: the system's own.
const SYSTEM_TREES: [&str; 17] = [
    "/bin",
    "/boot",
    "/dev",
    "/etc",
    "/lib",
    "/lib32",
    "/lib64",
    "/libx32",
    "/proc",
    "/run",
    "/sbin",
    "/sys",
    "/usr",
    "/var/lib",
    "/var/log",
    "/var/cache",
    "/var/spool",
];

/// Directories no run is written into (what is below them is fine).
const SYSTEM_DIRS: [&str; 9] = [
    "/", "/home", "/root", "/tmp", "/var", "/opt", "/mnt", "/media", "/srv",
];

/// Refuses a directory a new run must not be written into: a system
/// directory (one of [`SYSTEM_DIRS`], or anything within [`SYSTEM_TREES`];
/// symlinks resolved first), and, unless `force`, one that holds files rall
/// did not write (an empty directory, or a run's, is fine).
pub fn check_new_run_folder(path: &Path, force: bool) -> Result<()> {
    let resolved = resolve_symlinks(path)?;
    if is_system_dir(&resolved) {
        anyhow::bail!(
            "--run-dir {} is a system directory ({}): rall writes a run's config, metrics and checkpoints there; choose a folder of your own",
            path.display(),
            resolved.display()
        );
    }
    if force || !resolved.exists() {
        return Ok(());
    }
    anyhow::ensure!(
        resolved.is_dir(),
        "--run-dir {} is not a directory",
        path.display()
    );
    let foreign = foreign_entries(&resolved)?;
    if !foreign.is_empty() {
        let shown: Vec<&str> = foreign.iter().take(3).map(String::as_str).collect();
        anyhow::bail!(
            "--run-dir {} holds files rall did not write ({}{}): a run goes into an empty folder or a run's own; choose another --run-dir, or pass --force to write beside them",
            path.display(),
            shown.join(", "),
            if foreign.len() > 3 {
                format!(" and {} more", foreign.len() - 3)
            } else {
                String::new()
            }
        );
    }
    Ok(())
}

/// `path` with every symlink resolved; for a path that does not exist yet, its
/// nearest existing ancestor resolved and the rest appended.
fn resolve_symlinks(path: &Path) -> Result<PathBuf> {
    let mut rest = Vec::new();
    let mut at = path;
    loop {
        let probe = if at.as_os_str().is_empty() {
            Path::new(".")
        } else {
            at
        };
        if let Ok(real) = std::fs::canonicalize(probe) {
            return Ok(rest.iter().rev().fold(real, |p, c| p.join(c)));
        }
        match (at.file_name(), at.parent()) {
            (Some(name), Some(parent)) => {
                rest.push(name.to_owned());
                at = parent;
            }
            _ => anyhow::bail!("--run-dir {}: no part of it exists", path.display()),
        }
    }
}

/// Whether `path` (absolute, resolved) is one of [`SYSTEM_DIRS`] or within
/// one of [`SYSTEM_TREES`].
fn is_system_dir(path: &Path) -> bool {
    SYSTEM_DIRS.iter().any(|d| path == Path::new(d))
        || SYSTEM_TREES.iter().any(|t| path.starts_with(t))
}

/// Names at the top of `dir` that rall does not write, sorted.
fn foreign_entries(dir: &Path) -> Result<Vec<String>> {
    let mut foreign = Vec::new();
    for e in std::fs::read_dir(dir).with_context(|| format!("reading {}", dir.display()))? {
        let name = e
            .with_context(|| format!("reading {}", dir.display()))?
            .file_name()
            .to_string_lossy()
            .into_owned();
        if !is_rall_entry(&name) {
            foreign.push(name);
        }
    }
    foreign.sort();
    Ok(foreign)
}

/// Whether a run directory's top-level `name` is one rall writes.
fn is_rall_entry(name: &str) -> bool {
    RUN_ENTRIES.contains(&name)
        || crate::fsio::is_rall_temp(name, false)
        || lock_temp_pid(name).is_some()
}

/// The pid in the name of a lock being taken (`train.lock.<pid>.tmp`).
fn lock_temp_pid(name: &str) -> Option<u32> {
    name.strip_prefix("train.lock.")?
        .strip_suffix(crate::fsio::TMP_SUFFIX)?
        .parse()
        .ok()
}

/// Where a run keeps its files.
pub struct RunDir {
    pub root: PathBuf,
}

impl RunDir {
    pub fn latest(&self) -> PathBuf {
        self.root.join(LATEST)
    }
    pub fn checkpoint(&self, iteration: usize) -> PathBuf {
        self.root
            .join("checkpoints")
            .join(format!("model_{iteration:06}.safetensors"))
    }
    pub fn metrics(&self) -> PathBuf {
        self.root.join("metrics.csv")
    }

    /// Removes the temp files a killed or failed write of rall left behind
    /// (only its own names: a shared folder's other `*.tmp` files stay), and
    /// the lock files of trainers killed while taking the lock.
    pub(super) fn remove_temp_files(&self) {
        for (d, in_checkpoints) in [
            (self.root.clone(), false),
            (self.root.join("checkpoints"), true),
        ] {
            let Ok(entries) = std::fs::read_dir(&d) else {
                continue;
            };
            for e in entries.flatten() {
                let name = e.file_name();
                let ours = name.to_str().is_some_and(|n| {
                    crate::fsio::is_rall_temp(n, in_checkpoints)
                        || (!in_checkpoints && lock_temp_pid(n).is_some_and(|p| !process_alive(p)))
                });
                if ours && e.file_type().is_ok_and(|t| t.is_file()) {
                    let _ = std::fs::remove_file(e.path());
                }
            }
        }
    }

    /// Numbered checkpoints, newest first.
    fn numbered_checkpoints(&self) -> Vec<PathBuf> {
        let mut found = self.checkpoints_by_iteration();
        found.reverse();
        found.into_iter().map(|(_, p)| p).collect()
    }

    /// `checkpoints/model_<iteration>.safetensors`, oldest first, with their iterations.
    pub fn checkpoints_by_iteration(&self) -> Vec<(usize, PathBuf)> {
        let mut found: Vec<(usize, PathBuf)> = std::fs::read_dir(self.root.join("checkpoints"))
            .into_iter()
            .flatten()
            .flatten()
            .filter_map(|e| {
                let name = e.file_name().into_string().ok()?;
                let it = name
                    .strip_prefix("model_")?
                    .strip_suffix(".safetensors")?
                    .parse()
                    .ok()?;
                Some((it, e.path()))
            })
            .collect();
        found.sort_by_key(|f| f.0);
        found
    }

    /// The config of a run stopped before it wrote any checkpoint (nothing to
    /// resume, but the run can start again), or `None` when it has a checkpoint
    /// file or no `config.toml`.
    pub fn config_before_first_checkpoint(&self) -> Result<Option<TrainConfig>> {
        let stored = self.root.join("config.toml");
        if self.latest().exists() || !self.numbered_checkpoints().is_empty() || !stored.exists() {
            return Ok(None);
        }
        TrainConfig::from_toml_file(&stored).map(Some)
    }

    /// The checkpoint to resume from: `latest`, or when it is missing,
    /// unreadable or corrupt the newest numbered checkpoint that loads intact.
    /// Says nothing (see [`RunDir::resume_point_noting`]).
    pub fn resume_point(&self) -> Result<(PathBuf, crate::runner::LoadedPolicy)> {
        self.find_resume_point().map(|f| (f.path, f.loaded))
    }

    fn find_resume_point(&self) -> Result<Found> {
        let latest = self.latest();
        let resumable = |path: &Path| {
            load_policy(path).and_then(|loaded| {
                if loaded.actor_only {
                    anyhow::bail!(
                        "{} holds the actor alone (an evaluation copy): it cannot be resumed",
                        path.display()
                    )
                }
                if loaded.evaluation_only {
                    anyhow::bail!(
                        "{} is an evaluation file (no optimiser or environment state): it cannot be resumed",
                        path.display()
                    )
                }
                Ok(loaded)
            })
        };
        let latest_err = match resumable(&latest) {
            Ok(loaded) => {
                return Ok(Found {
                    path: latest,
                    loaded,
                    passed_over: Vec::new(),
                })
            }
            Err(e) => e,
        };
        let mut passed_over = vec![(latest, format!("{latest_err:#}"))];
        for path in self.numbered_checkpoints() {
            match resumable(&path) {
                Ok(loaded) => {
                    return Ok(Found {
                        path,
                        loaded,
                        passed_over,
                    })
                }
                Err(e) => passed_over.push((path, format!("{e:#}"))),
            }
        }
        Err(latest_err).with_context(|| {
            format!(
                "cannot resume {}: no readable checkpoint (latest or checkpoints/model_*)",
                self.root.display()
            )
        })
    }

    /// [`RunDir::resume_point`] for the run about to resume: says once which
    /// checkpoint it falls back to and why, and moves the unreadable numbered
    /// checkpoints it passed over aside (`<name>.corrupt`), so that nothing
    /// picks them up later.
    pub(super) fn resume_point_noting(&self) -> Result<(PathBuf, crate::runner::LoadedPolicy)> {
        let found = self.find_resume_point()?;
        if let Some((first, why)) = found.passed_over.first() {
            let mut note = format!(
                "note: {} is unusable ({why}); resuming from {}",
                first.display(),
                found.path.display()
            );
            for (p, _) in &found.passed_over[1..] {
                let mut aside = p.as_os_str().to_owned();
                aside.push(".corrupt");
                if std::fs::rename(p, &aside).is_ok() {
                    note.push_str(&format!(
                        "; unreadable {} moved to {}",
                        p.display(),
                        Path::new(&aside).display()
                    ));
                }
            }
            eprintln!("{note}");
        }
        Ok((found.path, found.loaded))
    }
}

/// A resume point and the unusable checkpoints passed over on the way (path, why).
struct Found {
    path: PathBuf,
    loaded: crate::runner::LoadedPolicy,
    passed_over: Vec<(PathBuf, String)>,
}

/// Held while a process trains in a run directory: `train.lock` with its pid.
/// A lock whose process is gone (killed) is taken over.
///
/// The lock appears whole: the pid is written and synced to a file of this
/// process's own (`train.lock.<pid>.tmp`), which is then hard-linked as
/// `train.lock`; the link fails when the lock exists, so of two trainers
/// starting together exactly one gets it, and nobody ever reads a lock without
/// its pid. A dead holder's lock is removed under an exclusive `flock` on it,
/// so two processes taking it over at once cannot both win.
pub struct RunLock {
    path: PathBuf,
}

/// `RALL_FAULT_LOCK_DELAY_MS=<ms>`: sleep this long between preparing the lock
/// and making it visible (widens the window two starting trainers race in).
const LOCK_DELAY_VAR: &str = "RALL_FAULT_LOCK_DELAY_MS";

impl RunLock {
    pub fn acquire(root: &Path) -> Result<RunLock> {
        let path = root.join("train.lock");
        let mine = write_pid_file(root)?;
        let taken = (|| {
            injected_lock_delay()?;
            for _ in 0..3 {
                match std::fs::hard_link(&mine, &path) {
                    Ok(()) => return Ok(RunLock { path: path.clone() }),
                    Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => {
                        refuse_if_held(root, &path)?;
                        remove_dead_lock(&path);
                    }
                    Err(e) => {
                        return Err(e).with_context(|| format!("creating {}", path.display()))
                    }
                }
            }
            anyhow::bail!("could not take {}", path.display())
        })();
        let _ = std::fs::remove_file(&mine);
        taken
    }
}

/// This process's pid in `<root>/train.lock.<pid>.tmp`, synced: the lock to be.
fn write_pid_file(root: &Path) -> Result<PathBuf> {
    use std::io::Write as _;
    let pid = std::process::id();
    let tmp = root.join(format!("train.lock.{pid}.tmp"));
    let write = || -> std::io::Result<()> {
        let mut f = std::fs::File::create(&tmp)?;
        writeln!(f, "{pid}")?;
        f.sync_all()
    };
    write().with_context(|| format!("writing {}", tmp.display()))?;
    Ok(tmp)
}

/// The delay of [`LOCK_DELAY_VAR`], if set (a malformed value is an error).
fn injected_lock_delay() -> Result<()> {
    let Ok(v) = std::env::var(LOCK_DELAY_VAR) else {
        return Ok(());
    };
    let ms: u64 = v
        .parse()
        .map_err(|_| anyhow::anyhow!("{LOCK_DELAY_VAR}={v:?}: expected milliseconds"))?;
    std::thread::sleep(std::time::Duration::from_millis(ms));
    Ok(())
}

/// The pid a lock file holds, if it holds one.
fn lock_holder(path: &Path) -> Option<u32> {
    std::fs::read_to_string(path)
        .ok()
        .and_then(|t| t.trim().parse::<u32>().ok())
}

/// Refuses when the lock at `path` belongs to a live process.
fn refuse_if_held(root: &Path, path: &Path) -> Result<()> {
    if let Some(pid) = lock_holder(path).filter(|pid| process_alive(*pid)) {
        anyhow::bail!(
            "{} is being trained by process {pid} ({} holds its pid): wait for it or stop it; remove the file only if that process is not rall",
            root.display(),
            path.display()
        );
    }
    Ok(())
}

/// Removes the lock at `path` if it is still the dead holder's: under an
/// exclusive `flock` on it, and only when `path` is still that very file and
/// names no live process (another trainer may have replaced it meanwhile).
fn remove_dead_lock(path: &Path) {
    use std::os::unix::fs::MetadataExt as _;
    let Ok(f) = std::fs::File::open(path) else {
        return; // gone already: the next link attempt decides
    };
    if f.try_lock().is_err() {
        return; // another process is removing it
    }
    let same_file = match (f.metadata(), std::fs::metadata(path)) {
        (Ok(held), Ok(now)) => held.ino() == now.ino() && held.dev() == now.dev(),
        _ => false,
    };
    if same_file && !lock_holder(path).is_some_and(process_alive) {
        let _ = std::fs::remove_file(path);
    }
}

impl Drop for RunLock {
    fn drop(&mut self) {
        let _ = std::fs::remove_file(&self.path);
    }
}

/// Whether process `pid` exists and has not exited (Linux /proc; a zombie,
/// e.g. an MPI rank whose launcher is gone and not yet reaped, is dead).
fn process_alive(pid: u32) -> bool {
    match std::fs::read_to_string(format!("/proc/{pid}/stat")) {
        // "pid (comm) S ...": the state follows the last ')'
        Ok(stat) => stat
            .rsplit_once(')')
            .and_then(|(_, rest)| rest.split_whitespace().next())
            .is_some_and(|state| state != "Z" && state != "X"),
        Err(_) => false,
    }
}

/// Writes the numbered checkpoint and the rolling `latest` one.
pub(super) fn save_both(
    dir: &RunDir,
    learner: &Learner,
    cfg: &TrainConfig,
    progress: &Progress,
) -> Result<PathBuf> {
    let numbered = dir.checkpoint(progress.iteration);
    save_policy(&numbered, learner, cfg, progress)?;
    save_policy(&dir.latest(), learner, cfg, progress)?;
    Ok(numbered)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_dead_trainers_lock_in_the_making_is_removed_a_live_ones_kept() {
        let dir = tempfile::tempdir().unwrap();
        let (dead, live) = (
            "train.lock.4294967295.tmp".to_string(),
            format!("train.lock.{}.tmp", std::process::id()),
        );
        for n in [&dead, &live] {
            std::fs::write(dir.path().join(n), "").unwrap();
        }
        RunDir {
            root: dir.path().to_path_buf(),
        }
        .remove_temp_files();
        assert!(!dir.path().join(&dead).exists());
        assert!(dir.path().join(&live).exists());
    }

    #[test]
    fn system_and_foreign_folders_are_refused() {
        for dir in [
            "/",
            "/etc",
            "/etc/ssh",
            "/usr/local/share",
            "/proc/self",
            "/home",
        ] {
            let e = format!(
                "{:#}",
                check_new_run_folder(Path::new(dir), true).unwrap_err()
            );
            assert!(e.contains("system directory"), "{dir}: {e}");
        }
        let tmp = tempfile::tempdir().unwrap();
        // a symlink to a system directory is that directory
        let link = tmp.path().join("link");
        std::os::unix::fs::symlink("/etc", &link).unwrap();
        let e = format!("{:#}", check_new_run_folder(&link, true).unwrap_err());
        assert!(e.contains("system directory") && e.contains("/etc"), "{e}");
        let e = format!(
            "{:#}",
            check_new_run_folder(&link.join("new/run"), true).unwrap_err()
        );
        assert!(e.contains("/etc/new/run"), "{e}");
        // empty, new, or a run's own: fine; someone else's files: refused unless forced
        let run = tmp.path().join("run");
        check_new_run_folder(&run, false).unwrap();
        std::fs::create_dir_all(run.join("checkpoints")).unwrap();
        for f in ["config.toml", "metrics.csv.tmp", "train.lock.42.tmp"] {
            std::fs::write(run.join(f), "").unwrap();
        }
        check_new_run_folder(&run, false).unwrap();
        std::fs::write(run.join("notes.txt"), "mine").unwrap();
        let e = format!("{:#}", check_new_run_folder(&run, false).unwrap_err());
        assert!(e.contains("notes.txt") && e.contains("--force"), "{e}");
        check_new_run_folder(&run, true).unwrap();
    }

    #[test]
    fn one_trainer_per_run_directory_and_dead_holders_are_taken_over() {
        let dir = tempfile::tempdir().unwrap();
        let lock = RunLock::acquire(dir.path()).unwrap();
        let e = format!("{:#}", RunLock::acquire(dir.path()).err().unwrap());
        assert!(e.contains(&std::process::id().to_string()), "{e}");
        drop(lock);
        assert!(!dir.path().join("train.lock").exists());
        // a pid above any pid_max: its holder is gone
        std::fs::write(dir.path().join("train.lock"), "4294967295\n").unwrap();
        let again = RunLock::acquire(dir.path()).unwrap();
        // the lock holds our pid, and its temp file is gone
        let held = std::fs::read_to_string(dir.path().join("train.lock")).unwrap();
        assert_eq!(held.trim(), std::process::id().to_string());
        drop(again);
        // a lock without a pid (not rall's: rall's never appears empty) is taken over
        std::fs::write(dir.path().join("train.lock"), "").unwrap();
        let _third = RunLock::acquire(dir.path()).unwrap();
        let names: Vec<String> = std::fs::read_dir(dir.path())
            .unwrap()
            .map(|e| e.unwrap().file_name().into_string().unwrap())
            .collect();
        assert_eq!(names, ["train.lock"]);
    }
}
