//! The store's identity: `manifest.json` beside the store and its copy in
//! the `meta` table, read without opening the store for writing, and
//! checked against the world that opens it.

use std::path::Path;

use redb::ReadableDatabase;

use super::{FORMAT, META, StoreError};
use crate::engine::checkpoint::WorldIdentity;

/// What the manifest records.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Manifest {
    /// The store's format version.
    pub format: u32,
    /// The world.
    pub world: WorldIdentity,
    /// The brickworld version that created the store.
    pub created_by: String,
}

/// `key` of the meta table, read through a read-only handle (None if the
/// file is missing, needs repair after a crash, or lacks the key).
pub(super) fn read_only_meta(path: &Path, key: &str) -> Option<Vec<u8>> {
    if !path.is_file() {
        return None;
    }
    let db = redb::ReadOnlyDatabase::open(path).ok()?;
    let tx = db.begin_read().ok()?;
    let table = tx.open_table(META).ok()?;
    let v = table.get(key).ok()??;
    Some(v.value().to_vec())
}

/// Parse a stored manifest and refuse another format or another world.
pub(super) fn check_manifest(
    path: &Path,
    bytes: &[u8],
    identity: &WorldIdentity,
) -> Result<Manifest, StoreError> {
    let m: Manifest = serde_json::from_slice(bytes).map_err(|e| StoreError::Manifest {
        path: path.to_path_buf(),
        msg: e.to_string(),
    })?;
    if m.format != FORMAT {
        return Err(StoreError::Version {
            path: path.to_path_buf(),
            found: m.format,
        });
    }
    if !m.world.same_world(identity) {
        return Err(StoreError::Foreign {
            path: path.to_path_buf(),
            found: Box::new(m.world),
            expected: Box::new(identity.clone()),
        });
    }
    Ok(m)
}

/// The `manifest.json` beside a store, if it is a regular file of sane size
/// (a FIFO there hung the engine at start; regression).
pub(super) fn read_manifest(path: &Path) -> Option<Vec<u8>> {
    crate::files::read_bounded(path, 1 << 20).ok()
}

/// Replace `path` with `bytes` through a temporary file, synced, then the
/// folder synced.
pub(super) fn write_atomic(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    use std::io::Write;
    // A fresh temporary (`create_new`), never one at a fixed name: a link
    // planted there was written through, a FIFO hung the start (regression,
    // odd-paths probe).
    let (tmp, mut f) = crate::files::fresh_temp_beside(path)?;
    let written = f
        .write_all(bytes)
        .and_then(|_| f.sync_all())
        .and_then(|_| std::fs::rename(&tmp, path));
    if let Err(e) = written {
        // No empty or partial copy is left behind (operator probe).
        let _ = std::fs::remove_file(&tmp);
        return Err(e);
    }
    if let Some(dir) = path.parent()
        && let Ok(d) = std::fs::File::open(dir)
    {
        let _ = d.sync_all();
    }
    Ok(())
}
