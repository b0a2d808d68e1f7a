//! The world store: one [redb](https://www.redb.org) file, `world.redb`, in
//! the state directory, with three tables, plus a human-readable
//! `manifest.json` beside it.
//!
//! | table | key | value |
//! |---|---|---|
//! | `chunks` | [`ChunkKey::to_bytes`] | a chunk blob ([`super::chunk`]) |
//! | `columns` | [`ColumnKey::to_bytes`] | a chunk column blob |
//! | `meta` | `"manifest"`, `"state"` | the manifest JSON; the simulation state blob |
//!
//! Only chunks that differ from what the world's source generates are
//! stored: a procedural world's store grows with its edits, not its size.
//!
//! **Transactions.** [`WorldDb::commit`] writes the dirty chunks, columns
//! and the state blob in one write transaction with redb's default
//! `Durability::Immediate`: when it returns, all of it is on disk, and a
//! `kill -9` or power loss at any moment leaves either the previous commit or
//! this one, never a mix (redb's copy-on-write B-trees and double-buffered
//! commit slots; no recovery code of ours). A failed commit (a full disk)
//! changes nothing on disk, and the caller keeps its dirty set to retry.
//!
//! **Identity.** The manifest names the world (source, size, seed), the
//! config's hash and the store's format version. Opening a store of
//! another world or another format version is refused with a clear error;
//! a changed config hash is reported, not refused (a world may be given new
//! scripts).

use std::path::{Path, PathBuf};
use std::time::Instant;

use redb::{ReadableDatabase, ReadableTable, TableDefinition};
use thiserror::Error;

mod backend;
mod manifest;
mod reader;

use self::backend::open_db;
pub use self::manifest::Manifest;
use self::manifest::{check_manifest, read_manifest, read_only_meta, write_atomic};
pub use self::reader::StoreReader;
use self::reader::{Shared, get_in, with_shared};
use super::chunk::{ChunkKey, ColumnKey};
use crate::engine::checkpoint::WorldIdentity;

/// The store's format version (the layout of tables and blobs).
pub const FORMAT: u32 = 1;
/// redb's page cache (its default is 1 GiB, more than a streamed world's
/// memory budget may allow): the commits of a region and the window's
/// reads fit in it.
pub const STORE_CACHE_BYTES: usize = 64 << 20;
/// The store's file name in the state directory.
pub const DB_FILE: &str = "world.redb";
/// The manifest's file name in the state directory.
pub const MANIFEST_FILE: &str = "manifest.json";

const CHUNKS: TableDefinition<&[u8], &[u8]> = TableDefinition::new("chunks");
const COLUMNS: TableDefinition<&[u8], &[u8]> = TableDefinition::new("columns");
const META: TableDefinition<&str, &[u8]> = TableDefinition::new("meta");

/// Errors of the world store.
#[derive(Debug, Error)]
pub enum StoreError {
    /// The database could not be opened or read.
    #[error("the world store {}: {msg}", path.display())]
    Db {
        /// The store's file.
        path: PathBuf,
        /// What failed.
        msg: String,
    },
    /// The store belongs to another world.
    #[error(
        "the world store {} belongs to another world ({found}); this config describes {expected}: use another --state directory, or the config that made it (`run CFG`; `--world CFG` for export and import)",
        path.display()
    )]
    Foreign {
        /// The store's file.
        path: PathBuf,
        /// The store's world.
        found: Box<WorldIdentity>,
        /// The config's world.
        expected: Box<WorldIdentity>,
    },
    /// The store was written in another format.
    #[error(
        "the world store {} has format version {found}; this brickworld reads version {FORMAT} (export it with the brickworld that wrote it and import the file here)",
        path.display()
    )]
    Version {
        /// The store's file.
        path: PathBuf,
        /// The store's version.
        found: u32,
    },
    /// The manifest is unreadable.
    #[error("the manifest {} is unreadable: {msg}", path.display())]
    Manifest {
        /// The manifest file.
        path: PathBuf,
        /// What is wrong.
        msg: String,
    },
    /// The store is missing, empty or replaced, but the manifest beside it
    /// says this world was stored here: starting afresh would silently
    /// throw the world away.
    #[error(
        "the world store {} is {state}, but {} says this world was stored here: restore the store (or `brickworld import` a backup into a new --state directory), or remove {} to start the world afresh",
        path.display(),
        manifest.display(),
        manifest.display()
    )]
    Lost {
        /// The store's file.
        path: PathBuf,
        /// "missing", "empty" or "not this world's store".
        state: &'static str,
        /// The manifest beside it.
        manifest: PathBuf,
    },
    /// A commit failed; nothing of it is on disk.
    #[error(
        "commit failed (nothing of it was written; the store keeps what it last committed, if anything): {0}"
    )]
    Commit(String),
}

/// What one commit wrote.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct CommitStats {
    /// Chunks written.
    pub chunks: usize,
    /// Chunk columns written.
    pub columns: usize,
    /// Blob bytes written (chunks, columns and state).
    pub bytes: usize,
    /// Wall time of the transaction, including the fsync, in ms.
    pub ms: f64,
}

/// `BRICKWORLD_TEST_COMMIT_STALL_MS`: a pause inside each commit's write
/// transaction, after everything is inserted and before it commits, so the
/// crash tests can kill the process in the middle of a commit. Unset in
/// normal use.
fn commit_stall() -> Option<std::time::Duration> {
    std::env::var("BRICKWORLD_TEST_COMMIT_STALL_MS")
        .ok()
        .and_then(|v| v.parse().ok())
        .map(std::time::Duration::from_millis)
}

/// An open world store.
pub struct WorldDb {
    db: Shared,
    path: PathBuf,
    /// A commit failed: redb refuses every later write until the database
    /// is reopened, so the next commit reopens it first.
    failed: bool,
    /// The file's identity (device, inode) when opened: a commit to a file
    /// deleted or replaced since would go nowhere.
    file_id: Option<(u64, u64)>,
}

/// The (device, inode) of the file at `path`, if there is one.
fn file_id(path: &Path) -> Option<(u64, u64)> {
    #[cfg(unix)]
    {
        use std::os::unix::fs::MetadataExt;
        std::fs::metadata(path).ok().map(|m| (m.dev(), m.ino()))
    }
    #[cfg(not(unix))]
    {
        std::fs::metadata(path).ok().map(|_| (0, 0))
    }
}

impl std::fmt::Debug for WorldDb {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("WorldDb").field("path", &self.path).finish()
    }
}

impl WorldDb {
    /// Open (or create) the store in state directory `dir` for the world
    /// `identity`. Returns the store and warnings (a changed config hash).
    pub fn open(
        dir: &Path,
        identity: &WorldIdentity,
    ) -> Result<(WorldDb, Vec<String>), StoreError> {
        let path = dir.join(DB_FILE);
        let manifest_path = dir.join(MANIFEST_FILE);
        // A FIFO or device named world.redb: one clear line (redb said
        // "Invalid argument").
        if crate::files::is_there_but_not_a_file(&path) {
            return Err(StoreError::Db {
                path: path.clone(),
                msg: "not a regular file: move it away".into(),
            });
        }
        // A manifest.json is written only after the store holds its
        // manifest: with one there, a missing or empty store was lost
        // (regression: the world restarted from tick 0 without a word).
        let recorded = || {
            read_manifest(&manifest_path)
                .is_some_and(|t| serde_json::from_slice::<Manifest>(&t).is_ok())
        };
        let lost = |state| StoreError::Lost {
            path: path.clone(),
            state,
            manifest: manifest_path.clone(),
        };
        match std::fs::metadata(&path) {
            Err(e) if e.kind() == std::io::ErrorKind::NotFound && recorded() => {
                return Err(lost("missing"));
            }
            Ok(m) if m.len() == 0 && recorded() => return Err(lost("empty")),
            _ => {}
        }
        // A store that will be refused is checked read-only first, so the
        // refusal leaves its file exactly as it was.
        if let Some(bytes) = read_only_meta(&path, "manifest") {
            check_manifest(&path, &bytes, identity)?;
        } else if path.is_file()
            && let Some(text) = read_manifest(&manifest_path)
            && serde_json::from_slice::<Manifest>(&text).is_ok()
        {
            // Not readable read-only (after a kill -9 redb must repair it,
            // which writes): the manifest.json kept beside it must be this
            // world's before the store is opened writable. An unreadable
            // manifest.json is only a copy: the stored one is checked next.
            check_manifest(&manifest_path, &text, identity)?;
        }
        let db_err = |e: redb::Error| StoreError::Db {
            path: path.clone(),
            msg: e.to_string(),
        };
        let db = open_db(&path).map_err(db_err)?;
        let this = WorldDb {
            db: std::sync::Arc::new(std::sync::RwLock::new(Some(db))),
            path: path.clone(),
            failed: false,
            file_id: file_id(&path),
        };
        let mut warnings = Vec::new();
        let stored = this.meta("manifest")?;
        let mine = Manifest {
            format: FORMAT,
            world: identity.clone(),
            created_by: format!("brickworld {}", env!("CARGO_PKG_VERSION")),
        };
        let manifest = match &stored {
            Some(bytes) => {
                let m = check_manifest(&path, bytes, identity)?;
                if m.world.config_hash != identity.config_hash {
                    warnings.push(format!(
                        "the world config changed since this world was created ({:#x} → {:#x}): new settings apply from now on",
                        m.world.config_hash, identity.config_hash
                    ));
                }
                Manifest {
                    created_by: m.created_by,
                    ..mine
                }
            }
            None => {
                // A store without a manifest is new: a manifest.json left
                // beside it by another world is refused all the same.
                if let Some(text) =
                    read_manifest(&manifest_path).and_then(|b| String::from_utf8(b).ok())
                    && let Ok(m) = serde_json::from_str::<Manifest>(&text)
                    && !m.world.same_world(identity)
                {
                    return Err(StoreError::Foreign {
                        path: manifest_path,
                        found: Box::new(m.world),
                        expected: Box::new(identity.clone()),
                    });
                }
                // The one refusal decided only after a writable open (a
                // store that needs repair reads as one without a manifest
                // until then); what redb writes on opening is its header.
                if recorded() {
                    return Err(lost("not this world's store (it holds no manifest)"));
                }
                mine
            }
        };
        // Written only when new or changed: opening a store to read it (or
        // to refuse an import) leaves its file as it was.
        let json = serde_json::to_vec_pretty(&manifest).expect("a manifest serialises");
        if stored.as_deref() != Some(&json[..]) {
            this.put_meta("manifest", &json)?;
        }
        // `manifest.json` is a copy for people and tools (the store's own,
        // just checked, is what counts): one that cannot be written is a
        // warning, not a start refused as "unreadable" (regression,
        // operator probe: a deleted copy on a full disk stopped the start).
        if read_manifest(&manifest_path).as_deref() != Some(&json[..])
            && let Err(e) = write_atomic(&manifest_path, &json)
        {
            warnings.push(format!(
                "cannot write {}, the manifest's copy for people and tools: {e} (the store's own manifest is intact; the copy is written again at the next start)",
                manifest_path.display()
            ));
        }
        Ok((this, warnings))
    }

    /// Whether the store in state directory `dir` holds a committed world,
    /// read without opening it for writing (false if it cannot be read so).
    pub fn has_state(dir: &Path) -> bool {
        read_only_meta(&dir.join(DB_FILE), "state").is_some()
    }

    /// Whether the store file in `dir` opens read-only (false while a
    /// running engine holds it, or when it needs repair).
    pub fn readable(dir: &Path) -> bool {
        redb::ReadOnlyDatabase::open(dir.join(DB_FILE)).is_ok()
    }

    /// The store's file.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Run `f` on the open database (an error if it could not be reopened
    /// after a failed commit).
    fn with_db<R>(
        &self,
        f: impl FnOnce(&redb::Database) -> Result<R, StoreError>,
    ) -> Result<R, StoreError> {
        with_shared(&self.db, &self.path, f)
    }

    /// A read-only handle on the chunks, for other threads: it reads each
    /// chunk as last committed (redb's readers never block the writer).
    pub fn reader(&self) -> StoreReader {
        StoreReader {
            db: self.db.clone(),
            path: self.path.clone(),
        }
    }

    fn err(&self, e: impl Into<redb::Error>) -> StoreError {
        StoreError::Db {
            path: self.path.clone(),
            msg: e.into().to_string(),
        }
    }

    fn meta(&self, key: &str) -> Result<Option<Vec<u8>>, StoreError> {
        self.with_db(|db| {
            let tx = db.begin_read().map_err(|e| self.err(e))?;
            let table = match tx.open_table(META) {
                Ok(t) => t,
                Err(redb::TableError::TableDoesNotExist(_)) => return Ok(None),
                Err(e) => return Err(self.err(e)),
            };
            let v = table.get(key).map_err(|e| self.err(e))?;
            Ok(v.map(|g| g.value().to_vec()))
        })
    }

    fn put_meta(&self, key: &str, value: &[u8]) -> Result<(), StoreError> {
        self.with_db(|db| self.put_meta_in(db, key, value))
    }

    fn put_meta_in(&self, db: &redb::Database, key: &str, value: &[u8]) -> Result<(), StoreError> {
        let mut tx = db.begin_write().map_err(|e| self.err(e))?;
        tx.set_quick_repair(true);
        {
            let mut t = tx.open_table(META).map_err(|e| self.err(e))?;
            t.insert(key, value).map_err(|e| self.err(e))?;
            // Create the other tables, so readers never meet a missing one.
            tx.open_table(CHUNKS).map_err(|e| self.err(e))?;
            tx.open_table(COLUMNS).map_err(|e| self.err(e))?;
        }
        tx.commit().map_err(|e| self.err(e))
    }

    /// The simulation state blob of the last commit (None: never committed).
    pub fn state(&self) -> Result<Option<Vec<u8>>, StoreError> {
        self.meta("state")
    }

    /// Every stored chunk's key, sorted.
    pub fn chunk_keys(&self) -> Result<Vec<ChunkKey>, StoreError> {
        self.keys(CHUNKS, ChunkKey::from_bytes)
    }

    /// Every stored chunk column's key, sorted.
    pub fn column_keys(&self) -> Result<Vec<ColumnKey>, StoreError> {
        self.keys(COLUMNS, ColumnKey::from_bytes)
    }

    fn keys<K>(
        &self,
        def: TableDefinition<&[u8], &[u8]>,
        parse: impl Fn(&[u8]) -> Option<K>,
    ) -> Result<Vec<K>, StoreError> {
        self.with_db(|db| {
            let tx = db.begin_read().map_err(|e| self.err(e))?;
            let table = tx.open_table(def).map_err(|e| self.err(e))?;
            let mut out = Vec::new();
            for entry in table.iter().map_err(|e| self.err(e))? {
                let (k, _) = entry.map_err(|e| self.err(e))?;
                match parse(k.value()) {
                    Some(key) => out.push(key),
                    None => {
                        return Err(StoreError::Db {
                            path: self.path.clone(),
                            msg: format!("a key of {} bytes in table {def}", k.value().len()),
                        });
                    }
                }
            }
            Ok(out)
        })
    }

    /// Chunk `key`'s blob, if stored.
    pub fn chunk(&self, key: ChunkKey) -> Result<Option<Vec<u8>>, StoreError> {
        self.get(CHUNKS, &key.to_bytes())
    }

    /// Chunk column `key`'s blob, if stored.
    pub fn column(&self, key: ColumnKey) -> Result<Option<Vec<u8>>, StoreError> {
        self.get(COLUMNS, &key.to_bytes())
    }

    fn get(
        &self,
        def: TableDefinition<&[u8], &[u8]>,
        key: &[u8],
    ) -> Result<Option<Vec<u8>>, StoreError> {
        self.with_db(|db| get_in(db, &self.path, def, key))
    }

    /// Write `chunks`, `columns` and the `state` blob in one durable
    /// transaction: all of it or (on error) none of it.
    ///
    /// After a failed commit (a full disk) redb refuses every write until
    /// the database is reopened; this commit reopens it first, so writing
    /// resumes as soon as there is room again.
    pub fn commit(
        &mut self,
        chunks: &[(ChunkKey, Vec<u8>)],
        columns: &[(ColumnKey, Vec<u8>)],
        state: &[u8],
    ) -> Result<CommitStats, StoreError> {
        // The file deleted (or its state directory) or replaced while the
        // engine runs: redb would go on writing to the unlinked file, and
        // every commit "succeeded" into nothing (regression, hostile probe).
        if self.file_id.is_some() && file_id(&self.path) != self.file_id {
            return Err(StoreError::Commit(format!(
                "{} was deleted or replaced while the engine runs, so nothing can be committed to it: stop the engine and restore the state directory (what changed since the last commit is only in memory and will be lost)",
                self.path.display()
            )));
        }
        if self.failed {
            let mut slot = self.db.write().unwrap_or_else(|p| p.into_inner());
            *slot = None; // closes the file before it is opened again
            *slot = Some(open_db(&self.path).map_err(|e| StoreError::Commit(e.to_string()))?);
            self.failed = false;
        }
        let r = self.try_commit(chunks, columns, state);
        self.failed = r.is_err();
        r
    }

    fn try_commit(
        &self,
        chunks: &[(ChunkKey, Vec<u8>)],
        columns: &[(ColumnKey, Vec<u8>)],
        state: &[u8],
    ) -> Result<CommitStats, StoreError> {
        self.with_db(|db| self.commit_in(db, chunks, columns, state))
    }

    fn commit_in(
        &self,
        db: &redb::Database,
        chunks: &[(ChunkKey, Vec<u8>)],
        columns: &[(ColumnKey, Vec<u8>)],
        state: &[u8],
    ) -> Result<CommitStats, StoreError> {
        let t = Instant::now();
        let fail = |e: redb::Error| StoreError::Commit(e.to_string());
        let mut tx = db.begin_write().map_err(|e| fail(e.into()))?;
        // Quick repair: one more fsync per commit, and reopening after a
        // crash reads the allocator state instead of scanning the whole file
        // (2–9 ms instead of 70–240 ms for a 263 MB store; tools/store-compare).
        tx.set_quick_repair(true);
        let mut bytes = state.len();
        {
            let mut ct = tx.open_table(CHUNKS).map_err(|e| fail(e.into()))?;
            for (k, blob) in chunks {
                ct.insert(&k.to_bytes()[..], &blob[..])
                    .map_err(|e| fail(e.into()))?;
                bytes += blob.len();
            }
            let mut colt = tx.open_table(COLUMNS).map_err(|e| fail(e.into()))?;
            for (k, blob) in columns {
                colt.insert(&k.to_bytes()[..], &blob[..])
                    .map_err(|e| fail(e.into()))?;
                bytes += blob.len();
            }
            let mut mt = tx.open_table(META).map_err(|e| fail(e.into()))?;
            mt.insert("state", state).map_err(|e| fail(e.into()))?;
        }
        if let Some(stall) = commit_stall() {
            crate::say!("test hook: a commit is stalled inside its transaction");
            std::thread::sleep(stall);
        }
        tx.commit().map_err(|e| fail(e.into()))?;
        Ok(CommitStats {
            chunks: chunks.len(),
            columns: columns.len(),
            bytes,
            ms: t.elapsed().as_secs_f64() * 1e3,
        })
    }

    /// The store file's size in bytes.
    pub fn file_bytes(&self) -> u64 {
        std::fs::metadata(&self.path).map_or(0, |m| m.len())
    }
}
