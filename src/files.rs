//! Files that survive a crash and inputs that cannot hang or exhaust a
//! run: [`write_atomic`] replaces a file only with a complete new one (a
//! kill at any moment leaves the old or the new, never half of either);
//! [`read_text`] reads a regular file up to a size limit (a FIFO, a device
//! or `/dev/zero` is refused before reading); [`create`] and [`write`]
//! never write through a symbolic link; [`OutDir`] is an output folder
//! claimed by one command (locked, never another run's results or an input
//! overwritten unless asked).

use std::io::{self, Read, Write};
use std::path::{Path, PathBuf};

/// Removes a symbolic link at `path` (not what it points to); anything
/// else is left alone. Writers call it first, so that a link planted in an
/// output folder is replaced by the file, never written through.
pub fn remove_link(path: &Path) -> io::Result<()> {
    match std::fs::symlink_metadata(path) {
        Ok(m) if m.file_type().is_symlink() => std::fs::remove_file(path),
        _ => Ok(()),
    }
}

/// Creates (or truncates) the regular file `path` for writing. A symbolic
/// link there is removed first, and the file is opened with `O_NOFOLLOW`:
/// nothing outside the folder is ever written through a link.
pub fn create(path: &Path) -> io::Result<std::fs::File> {
    use std::os::unix::fs::OpenOptionsExt;
    remove_link(path)?;
    std::fs::OpenOptions::new().write(true).create(true).truncate(true).custom_flags(libc::O_NOFOLLOW).open(path)
}

/// Writes `bytes` to the regular file `path` as [`create`] opens it.
pub fn write(path: &Path, bytes: impl AsRef<[u8]>) -> io::Result<()> {
    create(path)?.write_all(bytes.as_ref())
}

/// Writes `bytes` to `path` atomically: to a temporary file beside it,
/// flushed and synced, then renamed over `path`, and the folder synced.
/// A symbolic link at `path` is replaced, not followed.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> io::Result<()> {
    let dir = path.parent().filter(|d| !d.as_os_str().is_empty()).unwrap_or(Path::new("."));
    let name = path.file_name().ok_or_else(|| io::Error::new(io::ErrorKind::InvalidInput, "not a file path"))?;
    let mut tmp_name = name.to_os_string();
    tmp_name.push(".tmp");
    let tmp: PathBuf = dir.join(tmp_name);
    {
        let mut f = create(&tmp)?;
        f.write_all(bytes)?;
        f.flush()?;
        f.sync_all()?;
    }
    std::fs::rename(&tmp, path)?;
    // The rename itself is durable once the folder is synced (not every
    // system can open a folder: best effort).
    if let Ok(d) = std::fs::File::open(dir) {
        let _ = d.sync_all();
    }
    Ok(())
}

/// Why an input file could not be read.
#[derive(Debug, thiserror::Error)]
pub enum ReadError {
    /// The system refused.
    #[error("cannot read {path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The cause.
        source: io::Error,
    },
    /// Not a regular file (a folder, a FIFO, a device).
    #[error("cannot read {path}: not a regular file ({kind})")]
    NotAFile {
        /// The path.
        path: PathBuf,
        /// What it is.
        kind: &'static str,
    },
    /// Larger than the limit for this kind of input.
    #[error("cannot read {path}: {size} bytes, more than the {limit} bytes a {what} may have")]
    TooLarge {
        /// The file.
        path: PathBuf,
        /// Its size (at least).
        size: u64,
        /// The limit.
        limit: u64,
        /// The kind of input.
        what: &'static str,
    },
}

/// The text of the regular file `path`, refused when it is larger than
/// `limit` bytes (`what` names the kind of input in the error) or not UTF-8.
pub fn read_text(path: &Path, limit: u64, what: &'static str) -> Result<String, ReadError> {
    let bytes = read_bytes(path, limit, what)?;
    String::from_utf8(bytes).map_err(|_| ReadError::Io { path: path.to_path_buf(), source: io::Error::new(io::ErrorKind::InvalidData, "not UTF-8 text") })
}

/// The bytes of the regular file `path`, as [`read_text`].
pub fn read_bytes(path: &Path, limit: u64, what: &'static str) -> Result<Vec<u8>, ReadError> {
    let io = |source| ReadError::Io { path: path.to_path_buf(), source };
    let meta = std::fs::metadata(path).map_err(io)?;
    if !meta.is_file() {
        use std::os::unix::fs::FileTypeExt;
        let t = meta.file_type();
        let kind = if t.is_dir() {
            "a folder"
        } else if t.is_fifo() {
            "a FIFO"
        } else if t.is_char_device() || t.is_block_device() {
            "a device"
        } else if t.is_socket() {
            "a socket"
        } else {
            "not a file"
        };
        return Err(ReadError::NotAFile { path: path.to_path_buf(), kind });
    }
    if meta.len() > limit {
        return Err(ReadError::TooLarge { path: path.to_path_buf(), size: meta.len(), limit, what });
    }
    // The file may grow after the check: read one byte past the limit at most.
    let mut bytes = Vec::with_capacity(meta.len() as usize);
    std::fs::File::open(path).map_err(io)?.take(limit + 1).read_to_end(&mut bytes).map_err(io)?;
    if bytes.len() as u64 > limit {
        return Err(ReadError::TooLarge { path: path.to_path_buf(), size: bytes.len() as u64, limit, what });
    }
    Ok(bytes)
}

/// At most `max` characters of `text`, with `…` when cut (for echoing
/// user values in errors).
pub fn shorten(text: &str, max: usize) -> String {
    match text.char_indices().nth(max) {
        Some((at, _)) => format!("{}…", &text[..at]),
        None => text.to_string(),
    }
}

/// The marker an [`OutDir`] keeps in its folder: which run wrote there and
/// the names it wrote.
const MARKER: &str = ".diffsim-run.json";
/// The lock file of an [`OutDir`].
const LOCK: &str = ".diffsim.lock";

/// Why an output folder cannot be used.
#[derive(Debug, thiserror::Error)]
pub enum OutDirError {
    /// The system refused.
    #[error("cannot write {path}: {source}")]
    Io {
        /// The file or folder.
        path: PathBuf,
        /// The cause.
        source: io::Error,
    },
    /// The path is unusable as a folder (a dangling link, a loop, a file).
    #[error("--out {path}: {reason}")]
    NotAFolder {
        /// The path.
        path: PathBuf,
        /// What it is.
        reason: String,
    },
    /// Another command is writing into the folder now.
    #[error("--out {path}: another diffsim command is writing into this folder ({holder}); wait for it or choose another --out")]
    Busy {
        /// The folder.
        path: PathBuf,
        /// What the lock file says of its holder.
        holder: String,
    },
    /// The folder holds another run's results (or other files).
    #[error("--out {path} holds {what}; {remedy}, or choose another --out")]
    Occupied {
        /// The folder.
        path: PathBuf,
        /// What it holds.
        what: String,
        /// What `--overwrite` would do.
        remedy: &'static str,
    },
    /// A file the command would write is one of its inputs.
    #[error("--out {path}: writing {name} there would overwrite the input {input}; choose another --out")]
    Input {
        /// The folder.
        path: PathBuf,
        /// The output's name.
        name: String,
        /// The input.
        input: PathBuf,
    },
}

/// Makes the folder `path` if missing; a path that is a file, a dangling
/// symbolic link or a loop of links is refused by name.
fn make_folder(path: &Path) -> Result<(), OutDirError> {
    let not_folder = |reason: String| OutDirError::NotAFolder { path: path.to_path_buf(), reason };
    match std::fs::symlink_metadata(path) {
        Ok(m) if m.file_type().is_symlink() => match std::fs::metadata(path) {
            Ok(t) if t.is_dir() => Ok(()),
            Ok(_) => Err(not_folder("is a symbolic link to a file, not a folder".into())),
            Err(e) if e.raw_os_error() == Some(libc::ELOOP) => Err(not_folder("is a symbolic link that loops back on itself".into())),
            Err(_) => {
                let target = std::fs::read_link(path).map(|t| t.display().to_string()).unwrap_or_default();
                Err(not_folder(format!("is a symbolic link to {target}, which does not exist")))
            }
        },
        Ok(m) if !m.is_dir() => Err(not_folder("is a file, not a folder".into())),
        Ok(_) => Ok(()),
        Err(_) => std::fs::create_dir_all(path).map_err(|source| OutDirError::Io { path: path.to_path_buf(), source }),
    }
}

/// The folder's lock, held (an exclusive `flock`, released when the file
/// closes, even at a kill), with `run` and this process written in it for
/// the message of a command that finds it taken.
fn take_lock(path: &Path, run: &str) -> Result<std::fs::File, OutDirError> {
    use std::os::unix::fs::OpenOptionsExt;
    let lock_path = path.join(LOCK);
    let io = |source| OutDirError::Io { path: lock_path.clone(), source };
    remove_link(&lock_path).map_err(io)?;
    let lock = std::fs::OpenOptions::new().read(true).write(true).create(true).truncate(false).custom_flags(libc::O_NOFOLLOW).open(&lock_path).map_err(io)?;
    match lock.try_lock() {
        Ok(()) => {}
        Err(std::fs::TryLockError::WouldBlock) => {
            let holder = std::fs::read_to_string(&lock_path).unwrap_or_default();
            return Err(OutDirError::Busy { path: path.to_path_buf(), holder: shorten(holder.trim(), 200) });
        }
        Err(std::fs::TryLockError::Error(e)) => return Err(io(e)),
    }
    let mut l = &lock;
    let _ = l.set_len(0);
    let _ = writeln!(l, "{} (process {})", shorten(run, 200), std::process::id());
    Ok(lock)
}

/// A command that stops early (an error, or a study that returns before
/// its end) still leaves its files recorded, so that `--overwrite` can
/// remove them later; the marker then says the run is unfinished.
impl Drop for OutDir {
    fn drop(&mut self) {
        self.record_changed();
        let _ = self.save();
    }
}

/// Where a command's outputs go: an [`OutDir`] it claimed, or a plain
/// folder (a sweep's run folder another rank made), each name freed of a
/// planted symbolic link before it is written.
pub trait Outputs {
    /// The path to write the output `name` at.
    fn file(&self, name: &str) -> Result<PathBuf, OutDirError>;
}

impl Outputs for OutDir {
    fn file(&self, name: &str) -> Result<PathBuf, OutDirError> {
        OutDir::file(self, name)
    }
}

impl Outputs for PathBuf {
    fn file(&self, name: &str) -> Result<PathBuf, OutDirError> {
        unlinked(self, name)
    }
}

/// `dir/name`, with a symbolic link planted there removed.
fn unlinked(dir: &Path, name: &str) -> Result<PathBuf, OutDirError> {
    let p = dir.join(name);
    remove_link(&p).map_err(|source| OutDirError::Io { path: p.clone(), source })?;
    Ok(p)
}

/// Whether `name` is an [`OutDir`]'s own bookkeeping (its marker, its
/// lock, a temporary file of an atomic write), not an output.
fn bookkeeping(name: &str) -> bool {
    name == MARKER || name == LOCK || name.ends_with(".tmp")
}

/// What [`OutDir::claim`] does with a folder that holds another run's
/// results, or files no run wrote.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Existing {
    /// Refuses it (the default: an error naming what it holds).
    Refuse,
    /// Removes the other run's recorded files (`--overwrite`); the user's
    /// other files stay.
    Replace,
    /// Continues in it, removing nothing: a resumed run, whose own check
    /// of its saved settings decides (`--resume`).
    Continue,
}

/// What a run recorded of itself in its folder.
#[derive(Debug, Default, serde::Serialize, serde::Deserialize)]
struct Marker {
    /// The command and what it ran (`run /abs/scene.toml`).
    run: String,
    /// Whether it finished.
    complete: bool,
    /// The files and folders (`run-0001/`) it wrote, relative to the folder
    /// (a set: a sweep records tens of thousands of folders).
    files: std::collections::BTreeSet<String>,
}

/// An output folder claimed by one command: created if missing, locked
/// for the command's lifetime (a second command writing there at the same
/// time is refused), and holding another run's results or files of the
/// user's as [`Existing`] says. Runs are told apart by the string the
/// command gives (a scene's path and a hash of its text, an experiment's
/// flags): the same run again, by any command, writes beside its earlier
/// results. Outputs named through [`OutDir::file`] are refused when one is
/// an input, and a symbolic link planted at the name is removed; the names
/// are recorded in the folder's marker (those written by path, when the
/// `OutDir` is finished or dropped), so that a replaced run leaves no
/// stale file beside the new ones.
#[derive(Debug)]
pub struct OutDir {
    path: PathBuf,
    /// When it was claimed: what changed since is this run's.
    started: std::time::SystemTime,
    inputs: Vec<PathBuf>,
    marker: std::cell::RefCell<Marker>,
    /// Held open: the lock lasts as long as the `OutDir`.
    _lock: std::fs::File,
}

impl OutDir {
    /// Claims `path` for the run described by `run`, never writing over
    /// any of `inputs`; what it finds there is handled as `existing` says.
    pub fn claim(path: &Path, run: &str, inputs: &[&Path], existing: Existing) -> Result<OutDir, OutDirError> {
        let overwrite = existing != Existing::Refuse;
        let io_at = |p: &Path| {
            let p = p.to_path_buf();
            move |source| OutDirError::Io { path: p, source }
        };
        make_folder(path)?;
        let lock = take_lock(path, run)?;
        let inputs: Vec<PathBuf> = inputs.iter().filter_map(|p| std::fs::canonicalize(p).ok()).collect();
        let marker_path = path.join(MARKER);
        let earlier: Option<Marker> = read_text(&marker_path, 1 << 24, "run marker").ok().and_then(|t| serde_json::from_str(&t).ok());
        // What else the folder holds (beside the marker and the lock).
        let others: Vec<String> = std::fs::read_dir(path)
            .map_err(io_at(path))?
            .filter_map(|e| e.ok())
            .map(|e| e.file_name().to_string_lossy().into_owned())
            .filter(|n| !bookkeeping(n))
            .collect();
        let listed = |names: &[String]| {
            let shown: Vec<&str> = names.iter().take(4).map(String::as_str).collect();
            format!("{}{}", shown.join(", "), if names.len() > 4 { format!(" and {} more", names.len() - 4) } else { String::new() })
        };
        match &earlier {
            Some(m) if m.run != run && !overwrite => {
                return Err(OutDirError::Occupied {
                    path: path.to_path_buf(),
                    what: format!("the results of another run (`{}`{})", shorten(&m.run, 120), if m.complete { "" } else { ", unfinished" }),
                    remedy: "--overwrite replaces them",
                });
            }
            _ => {}
        }
        // Without a marker, whatever the folder holds is no run's (the
        // same run again owns what it finds: a resumed study's parts).
        let mut strangers = if earlier.is_some() { Vec::new() } else { others };
        strangers.sort();
        if !strangers.is_empty() && !overwrite {
            return Err(OutDirError::Occupied {
                path: path.to_path_buf(),
                what: format!("files that no diffsim run wrote ({})", listed(&strangers)),
                remedy: "--overwrite writes beside them (over any of the same name)",
            });
        }
        // The same run again (another command on the same input) adds to
        // its files; another run's own files go, so that none stays beside
        // the new ones (the user's other files stay, under --overwrite).
        // A resumed run continues what it finds (its own check of the
        // settings decides), removing nothing.
        let same = existing == Existing::Continue || earlier.as_ref().is_some_and(|m| m.run == run);
        let kept = if same { earlier.as_ref().map(|m| m.files.clone()).unwrap_or_default() } else { Default::default() };
        if let Some(m) = earlier.as_ref().filter(|_| !same) {
            for f in &m.files {
                let name = f.trim_end_matches('/');
                if name.is_empty() || name.contains("..") || Path::new(name).is_absolute() {
                    continue;
                }
                let p = path.join(name);
                if inputs.iter().any(|i| std::fs::canonicalize(&p).is_ok_and(|c| &c == i)) {
                    continue;
                }
                match std::fs::symlink_metadata(&p) {
                    Ok(md) if md.is_dir() => std::fs::remove_dir_all(&p).map_err(io_at(&p))?,
                    Ok(_) => std::fs::remove_file(&p).map_err(io_at(&p))?,
                    Err(_) => {}
                }
            }
        }
        let out = OutDir {
            path: path.to_path_buf(),
            started: std::time::SystemTime::now(),
            inputs,
            marker: std::cell::RefCell::new(Marker { run: run.to_string(), complete: false, files: kept }),
            _lock: lock,
        };
        out.save()?;
        Ok(out)
    }

    /// The path to write the output `name` (relative, `run-0001/smoke.npy`
    /// allowed) at: recorded as this run's, refused when it is one of the
    /// inputs, and freed of a symbolic link planted there.
    pub fn file(&self, name: &str) -> Result<PathBuf, OutDirError> {
        if let Ok(c) = std::fs::canonicalize(self.path.join(name))
            && let Some(input) = self.inputs.iter().find(|i| **i == c)
        {
            return Err(OutDirError::Input { path: self.path.clone(), name: name.to_string(), input: input.clone() });
        }
        let p = unlinked(&self.path, name)?;
        if self.note(name) {
            self.save()?;
        }
        Ok(p)
    }

    /// The subfolders `names`, created (a symbolic link at a name is
    /// replaced by a folder) and recorded as this run's, the marker saved
    /// once for all of them.
    pub fn folders(&self, names: impl IntoIterator<Item = String>) -> Result<(), OutDirError> {
        for name in names {
            let p = unlinked(&self.path, &name)?;
            std::fs::create_dir_all(&p).map_err(|source| OutDirError::Io { path: p.clone(), source })?;
            self.note(&format!("{name}/"));
        }
        self.save()
    }

    /// Records `name` (its first component: `run-0001/x.npy` is
    /// `run-0001/`) as this run's; whether it is new.
    fn note(&self, name: &str) -> bool {
        let top = match name.split_once('/') {
            Some((dir, _)) => format!("{dir}/"),
            None => name.to_string(),
        };
        self.marker.borrow_mut().files.insert(top)
    }

    /// Marks the run finished, recording as its own every entry of the
    /// folder written since the claim (for commands that write by path
    /// rather than through [`OutDir::file`]).
    pub fn finish(self) -> Result<(), OutDirError> {
        self.record_changed();
        self.marker.borrow_mut().complete = true;
        self.save()
    }

    /// Records every entry of the folder written since the claim.
    fn record_changed(&self) {
        let Ok(entries) = std::fs::read_dir(&self.path) else { return };
        for entry in entries.filter_map(|e| e.ok()) {
            let name = entry.file_name().to_string_lossy().into_owned();
            let changed = entry.metadata().and_then(|m| m.modified()).is_ok_and(|t| t >= self.started);
            if changed && !bookkeeping(&name) {
                self.note(&if entry.file_type().is_ok_and(|t| t.is_dir()) { format!("{name}/") } else { name });
            }
        }
    }

    fn save(&self) -> Result<(), OutDirError> {
        let p = self.path.join(MARKER);
        let text = serde_json::to_string_pretty(&*self.marker.borrow()).map_err(|e| OutDirError::Io { path: p.clone(), source: io::Error::other(e) })?;
        write_atomic(&p, text.as_bytes()).map_err(|source| OutDirError::Io { path: p, source })
    }
}
