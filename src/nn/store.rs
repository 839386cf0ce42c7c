//! One flat, named parameter store, saved as JSON.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

/// One tensor of a [`ParamStore`].
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct ParamEntry {
    /// Its name (`sol.0.conv1d.weight`).
    pub name: String,
    /// Its shape.
    pub shape: Vec<usize>,
    /// Where it starts in the flat values.
    pub offset: usize,
}

impl ParamEntry {
    /// Number of values.
    pub fn len(&self) -> usize {
        self.shape.iter().product()
    }

    /// Its name and shape for a message, each cut to a readable length
    /// (both come from files).
    pub fn describe(&self) -> String {
        format!("`{}` {}", crate::files::shorten(&self.name, 80), crate::files::shorten(&format!("{:?}", self.shape), 80))
    }

    /// Whether the tensor is empty.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// All trainable parameters in one flat vector, each tensor named.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct ParamStore {
    /// The tensors, in order.
    pub entries: Vec<ParamEntry>,
    /// The values.
    pub values: Vec<f64>,
}

/// A store that cannot be saved, loaded or matched.
#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    /// Reading or writing failed.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The cause.
        source: std::io::Error,
    },
    /// The file could not be read (missing, not a regular file, too large).
    #[error(transparent)]
    Read(#[from] crate::files::ReadError),
    /// The file is not a parameter store.
    #[error("{path}: not a parameter file: {reason}")]
    Format {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        reason: String,
    },
    /// The stored tensors do not match the network's.
    #[error("the parameters do not fit: {0}")]
    Mismatch(String),
}

impl ParamStore {
    /// An empty store.
    pub fn new() -> Self {
        Self::default()
    }

    /// Appends the tensors `names` (name, shape) with `values` under
    /// `prefix`; returns their range in the flat values.
    ///
    /// # Panics
    /// If `values` does not hold exactly the tensors' sizes.
    pub fn add(&mut self, prefix: &str, names: &[(String, Vec<usize>)], values: &[f64]) -> std::ops::Range<usize> {
        let start = self.values.len();
        let mut at = start;
        for (name, shape) in names {
            let e = ParamEntry { name: format!("{prefix}{name}"), shape: shape.clone(), offset: at };
            at += e.len();
            self.entries.push(e);
        }
        assert_eq!(at - start, values.len(), "ParamStore::add: values do not match the shapes");
        self.values.extend_from_slice(values);
        start..at
    }

    /// The values of tensor `name`.
    pub fn get(&self, name: &str) -> Option<&[f64]> {
        self.entries.iter().find(|e| e.name == name).map(|e| &self.values[e.offset..e.offset + e.len()])
    }

    /// Checks that `other` has the same tensors (names, shapes, order).
    pub fn check_layout(&self, other: &ParamStore) -> Result<(), StoreError> {
        if self.entries.len() != other.entries.len() {
            return Err(StoreError::Mismatch(format!("{} tensors expected, the file has {}", self.entries.len(), other.entries.len())));
        }
        for (a, b) in self.entries.iter().zip(&other.entries) {
            if a.name != b.name || a.shape != b.shape {
                return Err(StoreError::Mismatch(format!("expected {}, the file has {}", a.describe(), b.describe())));
            }
            // Same name and shape at another place in the flat values (an
            // edited file): say so, not "expected [16], found [16]".
            if a.offset != b.offset {
                return Err(StoreError::Mismatch(format!(
                    "{} starts at value {} in the file, expected {} (the file was altered)",
                    a.describe(),
                    b.offset,
                    a.offset
                )));
            }
        }
        Ok(())
    }

    /// Writes the store as JSON, atomically (a kill leaves the old file or
    /// the new one).
    pub fn save(&self, path: &Path) -> Result<(), StoreError> {
        let text = serde_json::to_string(self).map_err(|e| StoreError::Format { path: path.to_path_buf(), reason: e.to_string() })?;
        crate::files::write_atomic(path, text.as_bytes()).map_err(|source| StoreError::Io { path: path.to_path_buf(), source })
    }

    /// Reads a store written by [`ParamStore::save`], checking it (a
    /// regular file of at most 1 GiB).
    pub fn load(path: &Path) -> Result<ParamStore, StoreError> {
        let text = crate::files::read_text(path, 1 << 30, "parameter file")?;
        Self::parse(&text).map_err(|reason| StoreError::Format { path: path.to_path_buf(), reason })
    }

    /// A store from the JSON text [`ParamStore::save`] writes, checked.
    pub fn parse(text: &str) -> Result<ParamStore, String> {
        let store: ParamStore = serde_json::from_str(text).map_err(|e| crate::files::shorten(&e.to_string(), 200))?;
        store.validate()?;
        Ok(store)
    }

    /// Entries tile the values in order and every value is finite.
    pub fn validate(&self) -> Result<(), String> {
        let mut at: usize = 0;
        for e in &self.entries {
            if e.offset != at {
                return Err(format!("{} starts at {}, expected {at}", e.describe(), e.offset));
            }
            at = e
                .shape
                .iter()
                .try_fold(1usize, |n, &d| n.checked_mul(d))
                .and_then(|n| at.checked_add(n))
                .ok_or_else(|| format!("{}: the sizes overflow", e.describe()))?;
        }
        if at != self.values.len() {
            return Err(format!("the tensors hold {at} values, the file {}", self.values.len()));
        }
        if let Some(i) = self.values.iter().position(|v| !v.is_finite()) {
            return Err(format!("value {i} is {}", self.values[i]));
        }
        Ok(())
    }
}
