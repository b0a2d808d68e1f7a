//! Reads of a [`super::WorldDb`]'s tables through its shared handle, for
//! the store itself and for [`StoreReader`]s on other threads (the render
//! window's fetchers).

use std::path::{Path, PathBuf};

use redb::{ReadableDatabase, TableDefinition};

use super::{CHUNKS, StoreError};
use crate::persist::chunk::ChunkKey;

/// The database handle, shared with [`StoreReader`]s (the render window's
/// fetcher threads): `None` only after a failed commit whose reopen failed
/// too. The lock is taken for writing only to reopen after a failure.
pub(super) type Shared = std::sync::Arc<std::sync::RwLock<Option<redb::Database>>>;

/// Run `f` on the shared database, or fail if a failed commit left none.
pub(super) fn with_shared<R>(
    db: &Shared,
    path: &Path,
    f: impl FnOnce(&redb::Database) -> Result<R, StoreError>,
) -> Result<R, StoreError> {
    let slot = db.read().unwrap_or_else(|p| p.into_inner());
    match slot.as_ref() {
        Some(db) => f(db),
        None => Err(StoreError::Db {
            path: path.to_path_buf(),
            msg: "the database could not be reopened after a failed commit".into(),
        }),
    }
}

/// `key`'s value in table `def`, in its own read transaction.
pub(super) fn get_in(
    db: &redb::Database,
    path: &Path,
    def: TableDefinition<&[u8], &[u8]>,
    key: &[u8],
) -> Result<Option<Vec<u8>>, StoreError> {
    let err = |e: redb::Error| StoreError::Db {
        path: path.to_path_buf(),
        msg: e.to_string(),
    };
    let tx = db.begin_read().map_err(|e| err(e.into()))?;
    let table = tx.open_table(def).map_err(|e| err(e.into()))?;
    let v = table.get(key).map_err(|e| err(e.into()))?;
    Ok(v.map(|g| g.value().to_vec()))
}

/// A read-only handle on a [`WorldDb`](super::WorldDb)'s chunks for another
/// thread (see [`WorldDb::reader`](super::WorldDb::reader)). Cheap to clone.
#[derive(Clone)]
pub struct StoreReader {
    pub(super) db: Shared,
    pub(super) path: PathBuf,
}

impl std::fmt::Debug for StoreReader {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("StoreReader")
            .field("path", &self.path)
            .finish()
    }
}

impl StoreReader {
    /// Chunk `key`'s blob as last committed, if stored.
    pub fn chunk(&self, key: ChunkKey) -> Result<Option<Vec<u8>>, StoreError> {
        with_shared(&self.db, &self.path, |db| {
            get_in(db, &self.path, CHUNKS, &key.to_bytes())
        })
    }
}
