//! How the store's file is opened: redb's file backend with the page cache
//! capped, or, under the `BRICKWORLD_TEST_DISK_LIMIT` test hook, a backend
//! whose file cannot grow past a limit, as on a full disk.

use std::path::Path;

use super::STORE_CACHE_BYTES;

/// Where the test disk's size comes from.
#[derive(Debug)]
enum Limit {
    /// A fixed number of bytes.
    Bytes(u64),
    /// The number of bytes written in this file, read at every write, so a
    /// test can make room while the engine runs (unreadable: no limit).
    File(std::path::PathBuf),
}

impl Limit {
    fn bytes(&self) -> u64 {
        match self {
            Limit::Bytes(b) => *b,
            Limit::File(p) => std::fs::read_to_string(p)
                .ok()
                .and_then(|t| t.trim().parse().ok())
                .unwrap_or(u64::MAX),
        }
    }
}

/// `BRICKWORLD_TEST_DISK_LIMIT`: the store's file cannot grow past this many
/// bytes (or, given as `@FILE`, the number FILE holds at each write), as on
/// a full disk (writes past it fail with "No space left on device"), so the
/// tests can fill the disk without filling the machine's, and make room
/// again. Unset in normal use.
fn disk_limit() -> Option<Limit> {
    let v = std::env::var("BRICKWORLD_TEST_DISK_LIMIT").ok()?;
    match v.strip_prefix('@') {
        Some(file) => Some(Limit::File(file.into())),
        None => v.parse().ok().map(Limit::Bytes),
    }
}

/// Open (or create) the database file, on a limited disk under the test
/// hook.
pub(super) fn open_db(path: &Path) -> Result<redb::Database, redb::Error> {
    match disk_limit() {
        None => Ok(redb::Builder::new()
            .set_cache_size(STORE_CACHE_BYTES)
            .create(path)?),
        Some(limit) => {
            let file = std::fs::OpenOptions::new()
                .read(true)
                .write(true)
                .create(true)
                .truncate(false)
                .open(path)?;
            let inner = redb::backends::FileBackend::new(file)?;
            Ok(redb::Builder::new()
                .set_cache_size(STORE_CACHE_BYTES)
                .create_with_backend(DiskLimit { inner, limit })?)
        }
    }
}

/// A file backend on a disk with `limit` bytes for this file.
#[derive(Debug)]
struct DiskLimit {
    inner: redb::backends::FileBackend,
    limit: Limit,
}

impl DiskLimit {
    fn check(&self, end: u64) -> std::io::Result<()> {
        if end > self.limit.bytes() {
            return Err(std::io::Error::new(
                std::io::ErrorKind::StorageFull,
                "No space left on device (test disk limit)",
            ));
        }
        Ok(())
    }
}

impl redb::StorageBackend for DiskLimit {
    fn len(&self) -> std::io::Result<u64> {
        self.inner.len()
    }
    fn read(&self, offset: u64, out: &mut [u8]) -> std::io::Result<()> {
        self.inner.read(offset, out)
    }
    fn set_len(&self, len: u64) -> std::io::Result<()> {
        self.check(len)?;
        self.inner.set_len(len)
    }
    fn sync_data(&self) -> std::io::Result<()> {
        self.inner.sync_data()
    }
    fn write(&self, offset: u64, data: &[u8]) -> std::io::Result<()> {
        self.check(offset + data.len() as u64)?;
        self.inner.write(offset, data)
    }
    fn close(&self) -> std::io::Result<()> {
        self.inner.close()
    }
    fn try_lock_range(
        &self,
        start: std::ops::Bound<u64>,
        end: std::ops::Bound<u64>,
    ) -> Result<bool, redb::BackendError> {
        self.inner.try_lock_range(start, end)
    }
    fn try_lock_shared_range(
        &self,
        start: std::ops::Bound<u64>,
        end: std::ops::Bound<u64>,
    ) -> Result<bool, redb::BackendError> {
        self.inner.try_lock_shared_range(start, end)
    }
    fn lock_range(
        &self,
        start: std::ops::Bound<u64>,
        end: std::ops::Bound<u64>,
    ) -> Result<(), redb::BackendError> {
        self.inner.lock_range(start, end)
    }
    fn lock_shared_range(
        &self,
        start: std::ops::Bound<u64>,
        end: std::ops::Bound<u64>,
    ) -> Result<(), redb::BackendError> {
        self.inner.lock_shared_range(start, end)
    }
    fn unlock_range(
        &self,
        start: std::ops::Bound<u64>,
        end: std::ops::Bound<u64>,
    ) -> Result<(), redb::BackendError> {
        self.inner.unlock_range(start, end)
    }
    fn query_lock_range(
        &self,
        start: std::ops::Bound<u64>,
        end: std::ops::Bound<u64>,
    ) -> Result<bool, redb::BackendError> {
        self.inner.query_lock_range(start, end)
    }
}
