//! Finished rollouts kept on disk, so that a long evaluation that stops (a
//! machine shut down, Ctrl-C) resumes where it stopped, and one run again only
//! runs what changed.
//!
//! A rollout is found by its key: everything its numbers depend on (the
//! checkpoint's bytes, the env config, the scenario and its parameters, the
//! seed, the number of robots) and the fingerprint of the code that makes the
//! numbers: a hash, taken at build time, of the simulation, task, learner and
//! evaluation sources, the robot model files and `Cargo.lock`. A `rall` built
//! from other physics or evaluation code never reads an older build's rollouts;
//! a change to how results are arranged or drawn keeps them. Each entry is one
//! JSON file holding its full key (compared on reading, so a hash collision is
//! a miss), the seconds the rollout took, and its outputs (floats written so
//! that they read back bit for bit). A rollout whose policy was not loaded from
//! a file has no key and always runs.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Mutex;
use std::time::Instant;

use anyhow::{Context, Result};
use serde::de::DeserializeOwned;
use serde::{Deserialize, Serialize};

use super::jobs::run_jobs;
use crate::hash::fnv1a64;

/// Hash of the sources that decide a rollout's numbers (see the module docs).
pub const CODE_FINGERPRINT: &str = env!("RALL_ROLLOUT_FINGERPRINT");

/// Where finished rollouts are kept, and what this evaluation took from it.
#[derive(Debug, Default)]
pub struct RolloutCache {
    dir: Option<PathBuf>,
    read: AtomicUsize,
    ran: AtomicUsize,
    /// Seconds the rollouts read from disk took when they were run.
    read_seconds: Mutex<f64>,
}

/// What an evaluation took from its cache.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct CacheUse {
    /// Rollouts read from the cache.
    pub read: usize,
    /// Rollouts run (and stored).
    pub ran: usize,
    /// What the rollouts read took when they ran (seconds, summed over rollouts).
    pub read_seconds: f64,
}

impl CacheUse {
    /// One line for a log or `evaluation_time.txt`.
    pub fn show(&self) -> String {
        format!(
            "rollouts: {} run now, {} read from the rollout cache (they took {:.2} rollout-min when run)",
            self.ran,
            self.read,
            self.read_seconds / 60.0
        )
    }
}

/// One stored rollout.
#[derive(Serialize, Deserialize)]
struct Entry<T> {
    key: String,
    seconds: f64,
    value: T,
}

impl RolloutCache {
    /// No cache: every rollout runs.
    pub fn none() -> RolloutCache {
        RolloutCache::default()
    }

    /// Rollouts kept in `dir` (created when the first is stored).
    pub fn at(dir: impl Into<PathBuf>) -> RolloutCache {
        RolloutCache {
            dir: Some(dir.into()),
            ..RolloutCache::default()
        }
    }

    pub fn dir(&self) -> Option<&Path> {
        self.dir.as_deref()
    }

    pub fn usage(&self) -> CacheUse {
        CacheUse {
            read: self.read.load(Ordering::Relaxed),
            ran: self.ran.load(Ordering::Relaxed),
            read_seconds: *self.read_seconds.lock().unwrap_or_else(|e| e.into_inner()),
        }
    }

    fn file(dir: &Path, key: &str) -> PathBuf {
        dir.join(format!("{:016x}.json", fnv1a64(key.bytes())))
    }

    /// The stored outputs of `key`, if any; an unreadable entry is a miss.
    fn lookup<T: DeserializeOwned>(&self, key: &str) -> Option<T> {
        let path = Self::file(self.dir.as_deref()?, key);
        let text = std::fs::read_to_string(&path).ok()?;
        match serde_json::from_str::<Entry<T>>(&text) {
            Ok(e) if e.key == key => {
                self.read.fetch_add(1, Ordering::Relaxed);
                *self.read_seconds.lock().unwrap_or_else(|e| e.into_inner()) += e.seconds;
                Some(e.value)
            }
            Ok(_) => None,
            Err(e) => {
                eprintln!(
                    "note: rollout cache entry {} unreadable ({e}): running it again",
                    path.display()
                );
                None
            }
        }
    }

    fn store<T: Serialize>(&self, key: &str, seconds: f64, value: &T) -> Result<()> {
        self.ran.fetch_add(1, Ordering::Relaxed);
        let Some(dir) = &self.dir else { return Ok(()) };
        let entry = Entry {
            key: key.to_string(),
            seconds,
            value,
        };
        let text = serde_json::to_string(&entry).context("encoding a rollout for the cache")?;
        let path = Self::file(dir, key);
        std::fs::create_dir_all(dir)
            .and_then(|()| crate::fsio::write_atomic_io(&path, text.as_bytes()))
            .with_context(|| format!("storing a rollout in {}", path.display()))
    }
}

/// [`run_jobs`] through `cache`: a job whose key (`key(job)`, `None`: not
/// cacheable) is stored is read, the others run on `threads` workers and are
/// stored as each finishes, so an evaluation stopped half way keeps what it
/// ran. Results come back in job order, the same bit for bit as without a cache.
pub fn run_jobs_cached<J, T>(
    jobs: &[J],
    threads: usize,
    cache: &RolloutCache,
    key: impl Fn(&J) -> Option<String>,
    run: impl Fn(&J, usize) -> Result<T> + Sync,
) -> Result<Vec<T>>
where
    J: Sync,
    T: Send + Serialize + DeserializeOwned,
{
    let keys: Vec<Option<String>> = jobs
        .iter()
        .map(|j| key(j).map(|k| format!("rall rollout\ncode {CODE_FINGERPRINT}\n{k}")))
        .collect();
    let mut found: Vec<Option<T>> = keys
        .iter()
        .map(|k| k.as_deref().and_then(|k| cache.lookup(k)))
        .collect();
    let todo: Vec<usize> = (0..jobs.len()).filter(|&i| found[i].is_none()).collect();
    let ran = run_jobs(&todo, threads, |&i, inner| {
        let start = Instant::now();
        let out = run(&jobs[i], inner)?;
        match &keys[i] {
            Some(k) => cache.store(k, start.elapsed().as_secs_f64(), &out)?,
            None => {
                cache.ran.fetch_add(1, Ordering::Relaxed);
            }
        }
        Ok(out)
    })?;
    for (i, out) in todo.into_iter().zip(ran) {
        found[i] = Some(out);
    }
    Ok(found.into_iter().flatten().collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_stored_rollout_is_read_back_bit_for_bit_and_not_run_again() {
        let dir = std::env::temp_dir().join(format!("rall-cache-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let jobs: Vec<u64> = (0..6).collect();
        let value = |j: u64| (j as f64 * 0.1).sin() / 3.0;
        let key = |j: &u64| (*j != 5).then(|| format!("job {j}"));
        let first = RolloutCache::at(&dir);
        let a = run_jobs_cached(&jobs, 2, &first, key, |&j, _| Ok(value(j))).unwrap();
        assert_eq!(first.usage().ran, 6);
        assert_eq!(first.usage().read, 0);
        let again = RolloutCache::at(&dir);
        let runs = AtomicUsize::new(0);
        let b = run_jobs_cached(&jobs, 2, &again, key, |&j, _| {
            runs.fetch_add(1, Ordering::Relaxed);
            Ok(value(j))
        })
        .unwrap();
        assert_eq!(runs.load(Ordering::Relaxed), 1, "only the keyless job runs");
        assert_eq!(again.usage().read, 5);
        let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&a), bits(&b));
        // another key (other code, seed or checkpoint) is a miss
        let other = RolloutCache::at(&dir);
        run_jobs_cached(
            &jobs,
            1,
            &other,
            |j| Some(format!("other {j}")),
            |&j, _| Ok(value(j)),
        )
        .unwrap();
        assert_eq!(other.usage().read, 0);
        // an entry cut short is run again, not trusted
        let k = format!("rall rollout\ncode {CODE_FINGERPRINT}\njob 0");
        std::fs::write(RolloutCache::file(&dir, &k), "{\"key\":").unwrap();
        let mended = RolloutCache::at(&dir);
        let c = run_jobs_cached(&jobs, 1, &mended, key, |&j, _| Ok(value(j))).unwrap();
        assert_eq!(mended.usage().read, 4);
        assert_eq!(bits(&a), bits(&c));
        let _ = std::fs::remove_dir_all(&dir);
    }
}
