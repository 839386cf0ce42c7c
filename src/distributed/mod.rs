//! Processes working together over MPI: the world of ranks a run was
//! started in (`mpirun -np K diffsim …`) and the collectives diffsim uses,
//! each with a result that does not depend on timing. One process started
//! without a launcher is a world of one, with no MPI call made.
//!
//! MPI comes from the `mpi` cargo feature (on by default; Open MPI through
//! rsmpi, installed by `scripts/system-packages`). A build without it
//! refuses to run as one of several processes, instead of running K
//! copies that each believe they are alone.

mod model;

pub use model::ScalingModel;
use thiserror::Error;

/// Why the processes of a run cannot work together.
#[derive(Debug, Error)]
pub enum DistributedError {
    /// Started by a launcher as one of several processes, without MPI.
    #[error(
        "this diffsim was built without MPI (the `mpi` cargo feature) but was started by mpirun as one of {size} processes, which would each run alone; build it with the default features (`cargo build --release --bin diffsim`, after scripts/system-packages) or run it without mpirun"
    )]
    BuiltWithoutMpi {
        /// The processes the launcher started.
        size: usize,
    },
    /// The ranks of a run no longer hold the same state.
    #[error(
        "the ranks diverged: rank {rank}'s {what} differ from rank 0's after {after} (a rank computed something the others did not; the run stops instead of going on inconsistent)"
    )]
    Diverged {
        /// What differs (`parameters and optimizer state`).
        what: &'static str,
        /// The first rank that differs from rank 0.
        rank: usize,
        /// When (`iteration 40`).
        after: String,
    },
    /// A command that runs in one process only was started as several.
    #[error("`diffsim {command}` runs in one process; it was started by mpirun as {size} processes (run it without mpirun)")]
    OneProcessOnly {
        /// The command.
        command: &'static str,
        /// The processes the launcher started.
        size: usize,
    },
}

/// Where each rank's part starts in a gathered buffer: the running sums of
/// `counts`.
#[cfg(feature = "mpi")]
fn offsets(counts: &[i32]) -> Vec<i32> {
    counts.iter().scan(0, |acc, &c| Some(std::mem::replace(acc, *acc + c))).collect()
}

/// The number of processes a launcher started this one among (Open MPI's
/// `OMPI_COMM_WORLD_SIZE`, or PMI's `PMI_SIZE` for MPICH and others);
/// `None` when no launcher started it.
pub fn launched_size() -> Option<usize> {
    launched_size_in(|k| std::env::var(k).ok())
}

/// [`launched_size`] reading the environment through `var`.
pub fn launched_size_in(var: impl Fn(&str) -> Option<String>) -> Option<usize> {
    ["OMPI_COMM_WORLD_SIZE", "PMI_SIZE"].iter().find_map(|k| var(k)?.trim().parse().ok())
}

/// The ranks of a run: this process's rank and their number, and MPI's
/// communicator when there is more than this process. MPI is finalised
/// when the world is dropped.
pub struct World {
    rank: usize,
    size: usize,
    #[cfg(feature = "mpi")]
    mpi: Option<(mpi::environment::Universe, mpi::topology::SimpleCommunicator)>,
}

impl std::fmt::Debug for World {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("World").field("rank", &self.rank).field("size", &self.size).finish()
    }
}

impl Drop for World {
    /// A panic that unwinds past the world stops every rank: finalising
    /// MPI here would wait for ranks that wait in an exchange for this one.
    fn drop(&mut self) {
        if self.size > 1 && std::thread::panicking() {
            eprintln!("diffsim rank {} of {}: panicked (the message is above); stopping every rank", self.rank, self.size);
            self.abort(101);
        }
    }
}

impl World {
    /// This process alone.
    pub fn single() -> Self {
        Self {
            rank: 0,
            size: 1,
            #[cfg(feature = "mpi")]
            mpi: None,
        }
    }

    /// The world this process was started in: MPI's when a launcher
    /// started it, else a world of one.
    pub fn from_launch() -> Result<Self, DistributedError> {
        let Some(size) = launched_size() else {
            return Ok(Self::single());
        };
        #[cfg(feature = "mpi")]
        {
            use mpi::traits::Communicator;
            let _ = size;
            let Some(universe) = mpi::initialize() else {
                return Ok(Self::single());
            };
            let comm = universe.world();
            let (rank, size) = (comm.rank() as usize, comm.size() as usize);
            Ok(Self { rank, size, mpi: Some((universe, comm)) })
        }
        #[cfg(not(feature = "mpi"))]
        {
            if size > 1 { Err(DistributedError::BuiltWithoutMpi { size }) } else { Ok(Self::single()) }
        }
    }

    /// This process's rank, `0..size`.
    pub fn rank(&self) -> usize {
        self.rank
    }

    /// The number of ranks.
    pub fn size(&self) -> usize {
        self.size
    }

    /// Whether this is rank 0 (the one that writes a run's outputs).
    pub fn is_root(&self) -> bool {
        self.rank == 0
    }

    /// Refuses a command that runs in one process when there are several.
    pub fn one_process(&self, command: &'static str) -> Result<(), DistributedError> {
        if self.size > 1 { Err(DistributedError::OneProcessOnly { command, size: self.size }) } else { Ok(()) }
    }

    /// Every rank's `mine` (lengths may differ), concatenated in rank
    /// order, on every rank: the exchange behind sums taken in a fixed
    /// order (each rank then adds the parts in rank order itself).
    pub fn all_gather(&self, mine: &[f64]) -> Vec<f64> {
        #[cfg(feature = "mpi")]
        if let Some((_, comm)) = &self.mpi {
            use mpi::datatype::PartitionMut;
            use mpi::traits::CommunicatorCollectives;
            let mut counts = vec![0i32; self.size];
            comm.all_gather_into(&(mine.len() as i32), &mut counts[..]);
            let displs = offsets(&counts);
            let mut all = vec![0.0; counts.iter().map(|&c| c as usize).sum()];
            let mut parts = PartitionMut::new(&mut all[..], counts, displs);
            comm.all_gather_varcount_into(mine, &mut parts);
            return all;
        }
        mine.to_vec()
    }

    /// The contiguous share of `n` items (samples of a batch, runs of a
    /// sweep) this rank owns: rank `r` of `K` owns `r·n/K .. (r+1)·n/K`, so
    /// the shares in rank order are the items in order.
    pub fn share(&self, n: usize) -> std::ops::Range<usize> {
        self.share_of(self.rank, n)
    }

    /// The share of `n` items rank `rank` owns (see [`World::share`]).
    pub fn share_of(&self, rank: usize, n: usize) -> std::ops::Range<usize> {
        rank * n / self.size..(rank + 1) * n / self.size
    }

    /// Every rank's `mine` concatenated in rank order on rank 0 (`Some`
    /// there, `None` elsewhere): what only rank 0 works on, such as the
    /// batch Jacobian it decomposes.
    pub fn gather(&self, mine: &[f64]) -> Option<Vec<f64>> {
        self.gather_parts(mine).map(|parts| parts.concat())
    }

    /// Every rank's `mine` on rank 0, one entry per rank in rank order
    /// (`None` on the other ranks): results described in bytes (JSON).
    pub fn gather_bytes(&self, mine: &[u8]) -> Option<Vec<Vec<u8>>> {
        self.gather_parts(mine)
    }

    #[cfg(feature = "mpi")]
    fn gather_parts<T: mpi::datatype::Equivalence + Default + Clone>(&self, mine: &[T]) -> Option<Vec<Vec<T>>> {
        let Some((_, comm)) = &self.mpi else { return Some(vec![mine.to_vec()]) };
        use mpi::datatype::PartitionMut;
        use mpi::traits::{Communicator, Root};
        let root = comm.process_at_rank(0);
        let count = mine.len() as i32;
        if !self.is_root() {
            root.gather_into(&count);
            root.gather_varcount_into(mine);
            return None;
        }
        let mut counts = vec![0i32; self.size];
        root.gather_into_root(&count, &mut counts[..]);
        let displs = offsets(&counts);
        let mut all = vec![T::default(); counts.iter().map(|&c| c as usize).sum()];
        let mut parts = PartitionMut::new(&mut all[..], &counts[..], &displs[..]);
        root.gather_varcount_into_root(mine, &mut parts);
        Some(counts.iter().zip(&displs).map(|(&c, &d)| all[d as usize..(d + c) as usize].to_vec()).collect())
    }

    #[cfg(not(feature = "mpi"))]
    fn gather_parts<T: Clone>(&self, mine: &[T]) -> Option<Vec<Vec<T>>> {
        Some(vec![mine.to_vec()])
    }

    /// Rank 0's `values` on every rank (the others' argument is ignored).
    pub fn broadcast(&self, values: Vec<f64>) -> Vec<f64> {
        if self.size == 1 {
            return values;
        }
        let bytes = values.iter().flat_map(|v| v.to_le_bytes()).collect();
        self.broadcast_bytes(bytes).as_chunks::<8>().0.iter().map(|c| f64::from_le_bytes(*c)).collect()
    }

    /// Waits until every rank is here.
    pub fn barrier(&self) {
        #[cfg(feature = "mpi")]
        if let Some((_, comm)) = &self.mpi {
            use mpi::traits::CommunicatorCollectives;
            comm.barrier();
        }
    }

    /// Whether any rank's `flag` is set (on every rank): a decision all
    /// ranks take together, such as stopping at Ctrl-C.
    pub fn any(&self, flag: bool) -> bool {
        if self.size == 1 {
            return flag;
        }
        self.all_gather(&[if flag { 1.0 } else { 0.0 }]).iter().any(|&v| v != 0.0)
    }

    /// Rank 0's `bytes` on every rank (the other ranks' argument is
    /// ignored): a starting state rank 0 read or made, sent to all.
    pub fn broadcast_bytes(&self, bytes: Vec<u8>) -> Vec<u8> {
        #[cfg(feature = "mpi")]
        if let Some((_, comm)) = &self.mpi {
            use mpi::traits::{Communicator, Root};
            let root = comm.process_at_rank(0);
            let mut len = bytes.len() as u64;
            root.broadcast_into(&mut len);
            let mut buf = if self.is_root() { bytes } else { vec![0u8; len as usize] };
            root.broadcast_into(&mut buf[..]);
            return buf;
        }
        bytes
    }

    /// Rank 0's value of `make()` on every rank: rank 0 calls `make` (reads
    /// a checkpoint, draws parameters) and sends the result, exactly (JSON
    /// with round-trip floats), to the others, which do not call it. An
    /// error on rank 0 is returned there (the caller stops the run).
    pub fn from_root<T, E>(&self, make: impl FnOnce() -> Result<T, E>) -> Result<T, E>
    where
        T: serde::Serialize + serde::de::DeserializeOwned,
    {
        if self.size == 1 {
            return make();
        }
        let bytes = if self.is_root() { serde_json::to_vec(&make()?).expect("plain data serialises") } else { Vec::new() };
        let bytes = self.broadcast_bytes(bytes);
        Ok(serde_json::from_slice(&bytes).expect("rank 0 sent what this build writes"))
    }

    /// Checks that every rank holds the same `state` (hashed, FNV-1a over
    /// its bytes): the first rank that differs from rank 0 is
    /// [`DistributedError::Diverged`], on every rank. Costs one exchange of
    /// two numbers per rank.
    pub fn check_same(&self, what: &'static str, after: impl FnOnce() -> String, state: &[&[f64]]) -> Result<(), DistributedError> {
        if self.size == 1 {
            return Ok(());
        }
        let mut h: u64 = 0xcbf2_9ce4_8422_2325;
        for part in state {
            for v in *part {
                for b in v.to_bits().to_le_bytes() {
                    h = (h ^ b as u64).wrapping_mul(0x0100_0000_01b3);
                }
            }
        }
        // Two exact halves (an f64 holds any 32-bit integer).
        let all = self.all_gather(&[(h >> 32) as f64, (h & 0xffff_ffff) as f64]);
        match all.chunks(2).position(|c| c != &all[..2]) {
            Some(rank) => Err(DistributedError::Diverged { what, rank, after: after() }),
            None => Ok(()),
        }
    }

    /// Stops every rank of the run at once (MPI_Abort) after this rank
    /// printed why: the way out of an error that the other ranks, waiting
    /// in an exchange, do not share. Exits with `code` in a world of one.
    pub fn abort(&self, code: i32) -> ! {
        #[cfg(feature = "mpi")]
        if let Some((_, comm)) = &self.mpi {
            use mpi::traits::Communicator;
            comm.abort(code);
        }
        std::process::exit(code)
    }

    /// The MPI library this build runs on (`None` without MPI).
    pub fn library() -> Option<String> {
        #[cfg(feature = "mpi")]
        if let Ok(v) = mpi::environment::library_version() {
            // The C library's buffer may end in NUL bytes.
            let v = v.replace('\0', "");
            return Some(v.lines().next().unwrap_or("").trim().trim_end_matches(',').trim_end().to_string());
        }
        None
    }
}
