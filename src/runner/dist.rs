//! The processes of one training run: one alone, or N ranks under an MPI
//! launcher (`mpirun -np N rall train ...`, `srun rall train ...`).
//!
//! MPI is initialised only when a launcher started this process (it sets its
//! own environment variables), so `rall train` alone never touches MPI. Rank 0
//! owns the run directory; every rank steps its own environments and applies
//! the same averaged update ([`crate::learn::Collective`]).

use anyhow::{bail, Result};

use crate::learn::Collective;

/// Environment variables an MPI launcher sets for each process it starts,
/// with the number of processes: Open MPI, MPICH/Hydra and Slurm's PMI, PMIx.
const LAUNCHER_SIZE_VARS: [&str; 4] = [
    "OMPI_COMM_WORLD_SIZE",
    "PMI_SIZE",
    "PMIX_SIZE",
    "SLURM_NTASKS",
];

/// Which launcher variable says this process is one of several, if any.
fn launched_by_mpi() -> Option<(&'static str, usize)> {
    LAUNCHER_SIZE_VARS.iter().find_map(|var| {
        let n = std::env::var(var).ok()?.trim().parse::<usize>().ok()?;
        // `srun` without tasks > 1, or a launcher running one process: one rank
        (n > 1).then_some((*var, n))
    })
}

/// The processes training one policy.
pub enum World {
    /// No launcher: this process alone.
    Single,
    /// One rank of an MPI job.
    #[cfg(feature = "mpi")]
    Mpi(MpiWorld),
}

// without MPI the arms that use the arguments are compiled out
#[cfg_attr(not(feature = "mpi"), allow(unused_variables, clippy::ptr_arg))]
impl World {
    /// MPI when a launcher started this process with more than one rank, else
    /// [`World::Single`]. A build without MPI refuses to run under a launcher
    /// (N independent copies would fight over one run directory).
    pub fn from_env() -> Result<World> {
        let Some((var, n)) = launched_by_mpi() else {
            return Ok(World::Single);
        };
        #[cfg(feature = "mpi")]
        {
            let w = MpiWorld::init()?;
            if w.size() != n && var != "SLURM_NTASKS" {
                bail!(
                    "{var} says {n} processes but MPI reports {}: was rall built against the MPI that launched it?",
                    w.size()
                );
            }
            Ok(World::Mpi(w))
        }
        #[cfg(not(feature = "mpi"))]
        bail!(
            "started as one of {n} processes ({var} is set) but this rall was built without MPI: rebuild with the default features (the `mpi` feature needs libopenmpi-dev) or run it without mpirun/srun"
        )
    }

    pub fn rank(&self) -> usize {
        match self {
            World::Single => 0,
            #[cfg(feature = "mpi")]
            World::Mpi(w) => w.rank(),
        }
    }

    pub fn size(&self) -> usize {
        match self {
            World::Single => 1,
            #[cfg(feature = "mpi")]
            World::Mpi(w) => w.size(),
        }
    }

    /// Rank 0 writes the run directory, logs and recordings.
    pub fn is_root(&self) -> bool {
        self.rank() == 0
    }

    /// Rank 0's `bytes` on every rank (others' contents are replaced).
    pub fn broadcast_bytes(&self, bytes: &mut Vec<u8>) {
        match self {
            World::Single => {}
            #[cfg(feature = "mpi")]
            World::Mpi(w) => w.broadcast_bytes(bytes),
        }
    }

    /// Every rank's `value`, in rank order, on every rank.
    pub fn all_gather_u64(&self, value: u64) -> Vec<u64> {
        match self {
            World::Single => vec![value],
            #[cfg(feature = "mpi")]
            World::Mpi(w) => w.all_gather_u64(value),
        }
    }

    /// Every rank's `mine`, in rank order, on rank 0 (other ranks get nothing).
    pub fn gather_bytes(&self, mine: &[u8]) -> Result<Vec<Vec<u8>>> {
        match self {
            World::Single => Ok(vec![mine.to_vec()]),
            #[cfg(feature = "mpi")]
            World::Mpi(w) => w.gather_bytes(mine),
        }
    }

    /// Ends every process of the job (after an error on one rank, the others
    /// would wait forever for its next sum).
    pub fn abort(&self, code: i32) -> ! {
        match self {
            World::Single => std::process::exit(code),
            #[cfg(feature = "mpi")]
            World::Mpi(w) => w.abort(code),
        }
    }
}

#[cfg_attr(not(feature = "mpi"), allow(unused_variables))]
impl Collective for World {
    fn ranks(&self) -> usize {
        self.size()
    }
    fn sum_f32(&self, v: &mut [f32]) {
        match self {
            World::Single => {}
            #[cfg(feature = "mpi")]
            World::Mpi(w) => w.sum_f32(v),
        }
    }
    fn sum_f64(&self, v: &mut [f64]) {
        match self {
            World::Single => {}
            #[cfg(feature = "mpi")]
            World::Mpi(w) => w.sum_f64(v),
        }
    }
}

/// Rank `rank`'s seed derived from the run's `seed` (rank 0 keeps it, so one
/// process trains exactly as before).
pub fn rank_seed(seed: u64, rank: usize) -> u64 {
    seed ^ (rank as u64).wrapping_mul(0xD1B5_4A32_D192_ED03)
}

/// The FNV-1a hash of `values`' bits: ranks compare their parameters by it.
pub fn hash_f32(values: impl IntoIterator<Item = f32>) -> u64 {
    crate::hash::fnv1a64(values.into_iter().flat_map(|v| v.to_bits().to_le_bytes()))
}

/// The ranks whose hash differs from rank 0's.
pub fn diverged_ranks(hashes: &[u64]) -> Vec<usize> {
    let first = hashes.first().copied();
    hashes
        .iter()
        .enumerate()
        .filter(|(_, h)| Some(**h) != first)
        .map(|(r, _)| r)
        .collect()
}

#[cfg(feature = "mpi")]
pub use mpi_world::MpiWorld;

#[cfg(feature = "mpi")]
mod mpi_world {
    use std::cell::RefCell;

    use anyhow::{Context, Result};
    use mpi::collective::SystemOperation;
    use mpi::datatype::PartitionMut;
    use mpi::environment::Universe;
    use mpi::topology::{Communicator, SimpleCommunicator};
    use mpi::traits::*;
    use mpi::Count;
    use mpi::Threading;

    /// MPI_COMM_WORLD of this job; MPI is finalised when it drops.
    pub struct MpiWorld {
        world: SimpleCommunicator,
        /// Send buffers of the sums (MPI reads one buffer and writes another;
        /// kept so that a steady-state sum allocates nothing).
        send_f32: RefCell<Vec<f32>>,
        send_f64: RefCell<Vec<f64>>,
        // dropped last: finalises MPI
        _universe: Universe,
    }

    impl MpiWorld {
        /// `MPI_Init_thread` with `FUNNELED`: only the main thread calls MPI
        /// (rayon's workers never do).
        pub fn init() -> Result<MpiWorld> {
            let (universe, _) = mpi::initialize_with_threading(Threading::Funneled)
                .context("MPI was already initialised in this process")?;
            let world = universe.world();
            Ok(MpiWorld {
                world,
                send_f32: RefCell::default(),
                send_f64: RefCell::default(),
                _universe: universe,
            })
        }

        pub fn rank(&self) -> usize {
            self.world.rank() as usize
        }

        pub fn size(&self) -> usize {
            self.world.size() as usize
        }

        pub fn sum_f32(&self, v: &mut [f32]) {
            self.sum_in_place(&self.send_f32, v);
        }

        pub fn sum_f64(&self, v: &mut [f64]) {
            self.sum_in_place(&self.send_f64, v);
        }

        /// `v <- sum over ranks of v` through the kept send buffer `send`.
        fn sum_in_place<T: Equivalence + Copy>(&self, send: &RefCell<Vec<T>>, v: &mut [T]) {
            let mut send = send.borrow_mut();
            send.clear();
            send.extend_from_slice(v);
            self.world
                .all_reduce_into(&send[..], v, SystemOperation::sum());
        }

        pub fn broadcast_bytes(&self, bytes: &mut Vec<u8>) {
            let root = self.world.process_at_rank(0);
            let mut len = bytes.len() as u64;
            root.broadcast_into(&mut len);
            bytes.resize(len as usize, 0);
            root.broadcast_into(&mut bytes[..]);
        }

        pub fn all_gather_u64(&self, value: u64) -> Vec<u64> {
            let mut out = vec![0u64; self.size()];
            self.world.all_gather_into(&value, &mut out[..]);
            out
        }

        pub fn gather_bytes(&self, mine: &[u8]) -> Result<Vec<Vec<u8>>> {
            let lens = self.all_gather_u64(mine.len() as u64);
            let root = self.world.process_at_rank(0);
            if self.rank() != 0 {
                root.gather_varcount_into(mine);
                return Ok(Vec::new());
            }
            let counts = lens
                .iter()
                .map(|&l| Count::try_from(l))
                .collect::<std::result::Result<Vec<Count>, _>>()
                .context("a rank's state is larger than one MPI message (2 GiB)")?;
            let mut displs = Vec::with_capacity(counts.len());
            let mut total: Count = 0;
            for &c in &counts {
                displs.push(total);
                total = total
                    .checked_add(c)
                    .context("the ranks' states together exceed one MPI message (2 GiB)")?;
            }
            let mut all = vec![0u8; total as usize];
            {
                let mut part = PartitionMut::new(&mut all[..], &counts[..], &displs[..]);
                root.gather_varcount_into_root(mine, &mut part);
            }
            Ok(counts
                .iter()
                .zip(&displs)
                .map(|(&c, &d)| all[d as usize..(d + c) as usize].to_vec())
                .collect())
        }

        pub fn abort(&self, code: i32) -> ! {
            self.world.abort(code)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rank_zero_keeps_the_seed_and_ranks_differ() {
        assert_eq!(rank_seed(7, 0), 7);
        let seeds: std::collections::HashSet<u64> = (0..64).map(|r| rank_seed(7, r)).collect();
        assert_eq!(seeds.len(), 64);
    }

    #[test]
    fn a_one_bit_change_changes_the_hash_and_names_the_rank() {
        let a = hash_f32([1.0, 2.0, 3.0]);
        let b = hash_f32([1.0, 2.0, f32::from_bits(3.0f32.to_bits() ^ 1)]);
        assert_ne!(a, b);
        assert_eq!(diverged_ranks(&[a, a, b, a, b]), vec![2, 4]);
        assert!(diverged_ranks(&[a, a]).is_empty());
    }
}
