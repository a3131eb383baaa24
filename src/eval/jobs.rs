//! Independent evaluations side by side. A benchmark is many small rollouts
//! (a policy, a scenario, a seed: often 10-20 robots); one rollout cannot keep
//! two cores busy, because each policy step waits for the slowest robot and
//! the inference and bookkeeping between steps run on one thread. Giving each
//! rollout one thread and running `threads` rollouts at once keeps every core
//! busy. Every rollout's numbers depend on its seed alone, never on the thread
//! count, so the results are the same bit for bit either way.

use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};

use anyhow::{anyhow, Result};
use indicatif::ProgressBar;

use crate::learn::mat;

/// Stack of each evaluation worker: the main thread's usual 8 MiB (a rollout's
/// MuJoCo calls and the policy's buffers are small; this is headroom).
const WORKER_STACK_BYTES: usize = 8 << 20;

/// Runs `run(job, inner_threads)` for every job on `threads` workers and returns
/// the results in job order. Jobs share the workers: each gets
/// `max(1, threads / jobs)` threads of its own, so a lone job still uses them all.
/// On failure, the error of the first failing job in job order is returned (every
/// job before it has run) and no new job starts.
///
/// The workers are plain threads taking the next job from a counter, not a rayon
/// pool: each job steps its envs on a rayon pool of its own, and a rayon worker
/// that waits for another pool runs its own pool's pending jobs meanwhile, on the
/// same stack. With hundreds of jobs that nesting overflowed the stack.
pub fn run_jobs<J, T>(
    jobs: &[J],
    threads: usize,
    run: impl Fn(&J, usize) -> Result<T> + Sync,
) -> Result<Vec<T>>
where
    J: Sync,
    T: Send,
{
    let threads = threads.max(1);
    if threads == 1 || jobs.len() <= 1 {
        return jobs.iter().map(|j| run(j, threads)).collect();
    }
    let inner = (threads / jobs.len()).max(1);
    let workers = threads.min(jobs.len());
    let next_job = AtomicUsize::new(0);
    let failed = AtomicBool::new(false);
    let bar = rollout_bar(jobs.len());
    // one worker: take the next job until none is left or one has failed
    let work = || {
        let mut done = Vec::new();
        while !failed.load(Ordering::Relaxed) {
            let k = next_job.fetch_add(1, Ordering::Relaxed);
            let Some(job) = jobs.get(k) else { break };
            // each job's inference on its own worker: the products do not fan out again
            let out = mat::serial(|| run(job, inner));
            if out.is_err() {
                failed.store(true, Ordering::Relaxed);
            }
            bar.inc(1);
            done.push((k, out));
        }
        done
    };
    let mut slots: Vec<Option<Result<T>>> = (0..jobs.len()).map(|_| None).collect();
    let mut spawn_error = None;
    std::thread::scope(|scope| {
        let mut handles = Vec::with_capacity(workers);
        for i in 0..workers {
            let spawned = std::thread::Builder::new()
                .name(format!("rall-eval-{i}"))
                .stack_size(WORKER_STACK_BYTES)
                .spawn_scoped(scope, work);
            match spawned {
                Ok(h) => handles.push(h),
                Err(e) => {
                    failed.store(true, Ordering::Relaxed);
                    spawn_error = Some(anyhow!("cannot start evaluation thread {i}: {e}"));
                    break;
                }
            }
        }
        for h in handles {
            match h.join() {
                Ok(done) => done.into_iter().for_each(|(k, out)| slots[k] = Some(out)),
                Err(panic) => std::panic::resume_unwind(panic),
            }
        }
    });
    bar.finish_and_clear();
    if let Some(e) = spawn_error {
        return Err(e);
    }
    // in job order: the first error wins; a job left unrun follows an error
    slots
        .into_iter()
        .map(|slot| slot.unwrap_or_else(|| Err(anyhow!("evaluation stopped early"))))
        .collect()
}

/// A bar on stderr counting finished rollouts (drawn only on a terminal), so that
/// an evaluation of many policies shows how far it is and how long is left.
fn rollout_bar(jobs: usize) -> ProgressBar {
    crate::progress::bar(jobs as u64, "{pos}/{len} rollouts, {eta} left")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn results_come_back_in_job_order_with_the_threads_shared() {
        let jobs: Vec<usize> = (0..37).collect();
        let out = run_jobs(&jobs, 4, |&j, inner| Ok((j * j, inner))).unwrap();
        assert_eq!(out.len(), 37);
        for (j, (sq, inner)) in out.iter().enumerate() {
            assert_eq!(*sq, j * j);
            assert_eq!(*inner, 1);
        }
        let lone = run_jobs(&[5usize], 4, |&j, inner| Ok((j, inner))).unwrap();
        assert_eq!(lone, vec![(5, 4)]);
        let pair = run_jobs(&[1usize, 2], 4, |&j, inner| Ok((j, inner))).unwrap();
        assert_eq!(pair, vec![(1, 2), (2, 2)]);
    }

    /// Every job steps its envs on a rayon pool of its own. A worker waiting for that
    /// pool must not start another job on top of the one it runs: nested jobs grew
    /// the stack until it overflowed (hundreds of rollouts in one call).
    #[test]
    fn a_job_waiting_on_its_own_pool_does_not_start_another_on_its_stack() {
        use rayon::prelude::*;
        use std::cell::Cell;
        use std::sync::atomic::{AtomicUsize, Ordering};
        thread_local!(static DEPTH: Cell<usize> = const { Cell::new(0) });
        let deepest = AtomicUsize::new(0);
        let jobs: Vec<usize> = (0..200).collect();
        let out = run_jobs(&jobs, 2, |&j, _| {
            let depth = DEPTH.with(|d| {
                d.set(d.get() + 1);
                d.get()
            });
            deepest.fetch_max(depth, Ordering::Relaxed);
            let envs = rayon::ThreadPoolBuilder::new()
                .num_threads(1)
                .build()
                .unwrap();
            let sum: u64 = envs.install(|| {
                (0..64u64)
                    .into_par_iter()
                    .map(|i| {
                        std::thread::sleep(std::time::Duration::from_micros(50));
                        i
                    })
                    .sum()
            });
            DEPTH.with(|d| d.set(d.get() - 1));
            Ok(sum + j as u64)
        })
        .unwrap();
        assert_eq!(out, (0..200u64).map(|j| 2016 + j).collect::<Vec<_>>());
        assert_eq!(
            deepest.load(Ordering::Relaxed),
            1,
            "jobs nested on one stack"
        );
    }

    #[test]
    fn a_failure_stops_the_jobs_not_yet_started() {
        use std::sync::atomic::{AtomicUsize, Ordering};
        let started = AtomicUsize::new(0);
        let jobs: Vec<usize> = (0..1000).collect();
        let err = run_jobs(&jobs, 2, |&j, _| {
            started.fetch_add(1, Ordering::Relaxed);
            anyhow::ensure!(j != 3, "job {j} failed");
            Ok(j)
        })
        .unwrap_err();
        assert!(err.to_string().contains("job 3 failed"), "{err}");
        assert!(started.load(Ordering::Relaxed) < 1000);
    }

    #[test]
    fn the_first_failure_is_returned() {
        let jobs: Vec<usize> = (0..8).collect();
        let err = run_jobs(&jobs, 2, |&j, _| {
            anyhow::ensure!(j != 5, "job {j} failed");
            Ok(j)
        })
        .unwrap_err();
        assert!(err.to_string().contains("job 5 failed"), "{err}");
    }
}
