//! Processes working together over MPI: the world of ranks a run was
//! started in (`mpirun -np K diffsim …`) and the collectives diffsim uses,
//! each with a result that does not depend on timing. One process started
//! without a launcher is a world of one, with no MPI call made.
//!
//! MPI comes from the `mpi` cargo feature (on by default; Open MPI through
//! rsmpi, installed by `scripts/system-packages`). A build without it
//! refuses to run as one of several processes, instead of running K
//! copies that each believe they are alone.

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
    /// A command that runs in one process only was started as several.
    #[error("`diffsim {command}` runs in one process; it was started by mpirun as {size} processes (run it without mpirun)")]
    OneProcessOnly {
        /// The command.
        command: &'static str,
        /// The processes the launcher started.
        size: usize,
    },
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
            let displs: Vec<i32> = counts.iter().scan(0, |acc, &c| Some(std::mem::replace(acc, *acc + c))).collect();
            let mut all = vec![0.0; counts.iter().map(|&c| c as usize).sum()];
            let mut parts = PartitionMut::new(&mut all[..], counts, displs);
            comm.all_gather_varcount_into(mine, &mut parts);
            return all;
        }
        mine.to_vec()
    }

    /// The MPI library this build runs on (`None` without MPI).
    pub fn library() -> Option<String> {
        #[cfg(feature = "mpi")]
        if let Ok(v) = mpi::environment::library_version() {
            return Some(v.lines().next().unwrap_or("").trim().trim_end_matches(',').trim_end().to_string());
        }
        None
    }
}
