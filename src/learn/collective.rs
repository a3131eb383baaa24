//! What a data-parallel update needs from the other processes of a run: sums
//! across ranks. The learner knows nothing of MPI; the runner hands it an
//! implementation (`runner::dist::World`) or [`SingleProcess`].

/// Element-wise sums over every rank of a data-parallel run. Every rank calls
/// each method in the same order with buffers of the same length, and every
/// rank receives the same result.
pub trait Collective {
    /// Number of processes training this policy (1 without MPI).
    fn ranks(&self) -> usize;
    /// `v <- sum over ranks of v`, in place.
    fn sum_f32(&self, v: &mut [f32]);
    /// `v <- sum over ranks of v`, in place.
    fn sum_f64(&self, v: &mut [f64]);
}

/// One process: sums are the identity.
#[derive(Clone, Copy, Debug, Default)]
pub struct SingleProcess;

impl Collective for SingleProcess {
    fn ranks(&self) -> usize {
        1
    }
    fn sum_f32(&self, _v: &mut [f32]) {}
    fn sum_f64(&self, _v: &mut [f64]) {}
}

/// Sums between ranks simulated by threads of one process, for tests: `n`
/// [`ThreadRanks`] handles meet at a barrier for every sum.
pub mod threads {
    use super::Collective;
    use std::sync::{Arc, Barrier, Mutex};

    struct Shared {
        barrier: Barrier,
        acc: Mutex<Vec<f64>>,
    }

    /// One rank's handle; make them with [`ThreadRanks::group`].
    pub struct ThreadRanks {
        n: usize,
        shared: Arc<Shared>,
    }

    impl ThreadRanks {
        /// `n` handles to give to `n` threads.
        pub fn group(n: usize) -> Vec<ThreadRanks> {
            let shared = Arc::new(Shared {
                barrier: Barrier::new(n),
                acc: Mutex::new(Vec::new()),
            });
            (0..n)
                .map(|_| ThreadRanks {
                    n,
                    shared: shared.clone(),
                })
                .collect()
        }

        fn sum(&self, v: &mut [f64]) {
            let s = &self.shared;
            if s.barrier.wait().is_leader() {
                *s.acc.lock().expect("lock") = vec![0.0; v.len()];
            }
            s.barrier.wait();
            {
                let mut acc = s.acc.lock().expect("lock");
                for (a, x) in acc.iter_mut().zip(v.iter()) {
                    *a += *x;
                }
            }
            s.barrier.wait();
            v.copy_from_slice(&s.acc.lock().expect("lock"));
            s.barrier.wait();
        }
    }

    impl Collective for ThreadRanks {
        fn ranks(&self) -> usize {
            self.n
        }
        fn sum_f32(&self, v: &mut [f32]) {
            let mut w: Vec<f64> = v.iter().map(|x| *x as f64).collect();
            self.sum(&mut w);
            v.iter_mut().zip(&w).for_each(|(x, s)| *x = *s as f32);
        }
        fn sum_f64(&self, v: &mut [f64]) {
            self.sum(v);
        }
    }
}
