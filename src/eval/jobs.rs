//! Independent evaluations side by side. A benchmark is many small rollouts
//! (a policy, a scenario, a seed: often 10-20 robots); one rollout cannot keep
//! two cores busy, because each policy step waits for the slowest robot and
//! the inference and bookkeeping between steps run on one thread. Giving each
//! rollout one thread and running `threads` rollouts at once keeps every core
//! busy. Every rollout's numbers depend on its seed alone, never on the thread
//! count, so the results are the same bit for bit either way.

use anyhow::{Context, Result};
use rayon::prelude::*;

use crate::learn::mat;

/// Runs `run(job, inner_threads)` for every job on `threads` workers and returns
/// the results in job order. Jobs share the workers: each gets
/// `max(1, threads / jobs)` threads of its own, so a lone job still uses them all.
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
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(workers)
        .thread_name(|i| format!("rall-eval-{i}"))
        .build()
        .with_context(|| format!("cannot start {workers} evaluation threads"))?;
    // each job's inference on its own worker: the products do not fan out again
    pool.install(|| {
        jobs.par_iter()
            .map(|j| mat::serial(|| run(j, inner)))
            .collect()
    })
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
