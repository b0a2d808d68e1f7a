//! One checkpoint file: the 40-byte header, the identity block and the
//! LZ4 payload, written atomically and read back only after every checksum
//! and the world hash verify.

use std::fs::{self, File};
use std::io::Write;
use std::path::Path;

use super::payload::{decode, encode};
use super::{
    CheckpointError, HEADER, MAGIC, MAX_LZ4_RATIO, VERSION, WorldIdentity, WorldRef, WorldState,
    io, world_hash,
};

/// What an export may write over: the path is free, or holds an earlier
/// backup of the same world (or an empty file).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum BackupTarget {
    /// Nothing is at the path.
    Free,
    /// An earlier backup of the same world, or an empty file.
    Replaceable,
}

/// Whether a backup of `identity` may be written at `path`: nothing there,
/// an empty file, or a backup of the same world that verifies. Anything
/// else is kept, and the error says why and what to do (regression,
/// newcomer walk and its review: `export notes.txt` replaced the notes,
/// and an export replaced another world's only backup, exit 0).
pub fn backup_target(path: &Path, identity: &WorldIdentity) -> Result<BackupTarget, String> {
    let keep = |what: String| {
        format!("{what}: export would replace it, so name another path or remove it first")
    };
    let meta = match fs::symlink_metadata(path) {
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(BackupTarget::Free),
        Err(e) => return Err(format!("cannot be written ({e})")),
        Ok(m) => m,
    };
    if meta.file_type().is_symlink() {
        return Err(
            "is a symbolic link, which the backup would replace: name the file itself".into(),
        );
    }
    if !meta.is_file() {
        return Err("is not a regular file: name another path".into());
    }
    if meta.len() == 0 {
        return Ok(BackupTarget::Replaceable);
    }
    if meta.len() < MAGIC.len() as u64 {
        return Err(keep("is not a brickworld backup".into()));
    }
    match read_checked(path, false) {
        Ok((_, Some(id))) if id.same_world(identity) => Ok(BackupTarget::Replaceable),
        Ok((_, Some(id))) => Err(keep(format!("is a backup of another world ({id})"))),
        Ok((_, None)) => Err(keep(
            "is a checkpoint that does not say which world it is".into(),
        )),
        Err(CheckpointError::NotACheckpoint { .. }) => {
            Err(keep("is not a brickworld backup".into()))
        }
        Err(CheckpointError::Io { error, .. }) => Err(keep(format!("cannot be read ({error})"))),
        Err(CheckpointError::Corrupt { msg, .. }) => {
            Err(keep(format!("is a damaged backup ({msg})")))
        }
    }
}

/// `brickworld export`'s write: [`write_at`], with the target looked at
/// again just before the backup lands (see [`backup_target`]). Where the
/// path was free, it lands without replacing anything, so a file made
/// there meanwhile is kept. Over an earlier backup, it replaces exactly
/// the file that was checked: [`land_over`] swaps it out atomically and
/// swaps back anything else found there.
pub fn write_backup(
    path: &Path,
    state: WorldRef<'_>,
    identity: &WorldIdentity,
) -> Result<u64, CheckpointError> {
    write_landing(path, state, |tmp| {
        let before = Seen::of(path);
        match backup_target(path, identity) {
            Ok(BackupTarget::Replaceable) => match before {
                // Unchanged while it was checked: that is the file replaced.
                Ok(before) if Seen::of(path).is_ok_and(|after| after == before) => {
                    land_over(tmp, path, &before)
                }
                _ => Err(replaced_meanwhile()),
            },
            Ok(BackupTarget::Free) => land_on_free(tmp, path),
            Err(msg) => Err(std::io::Error::new(std::io::ErrorKind::AlreadyExists, msg)),
        }
    })
    .map_err(|e| match e {
        CheckpointError::Io { error, .. } if error.kind() == std::io::ErrorKind::AlreadyExists => {
            CheckpointError::Io {
                path: path.to_path_buf(),
                error: std::io::Error::new(
                    std::io::ErrorKind::AlreadyExists,
                    format!("{error}; nothing was written"),
                ),
            }
        }
        other => other,
    })
}

/// What tells one file from another that took its place: the same inode,
/// with the same size and modification time.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
struct Seen {
    dev: u64,
    ino: u64,
    len: u64,
    mtime: (i64, i64),
}

impl Seen {
    fn of(path: &Path) -> std::io::Result<Seen> {
        use std::os::unix::fs::MetadataExt;
        let m = fs::symlink_metadata(path)?;
        Ok(Seen {
            dev: m.dev(),
            ino: m.ino(),
            len: m.len(),
            mtime: (m.mtime(), m.mtime_nsec()),
        })
    }
}

fn replaced_meanwhile() -> std::io::Error {
    std::io::Error::new(
        std::io::ErrorKind::AlreadyExists,
        "the earlier backup there was replaced or changed while this one was made",
    )
}

/// `NAME.kept-PID` beside `path`: where another's file goes when the
/// backup has taken its place and it cannot go back.
fn kept_name(path: &Path) -> std::path::PathBuf {
    let mut name = path.file_name().unwrap_or_default().to_os_string();
    name.push(format!(".kept-{}", std::process::id()));
    path.with_file_name(name)
}

/// A failed swap back left another's file at the temporary path, or moved
/// it beside: [`write_landing`] must not remove the temporary.
#[derive(Debug)]
struct AnothersFile(String);

impl std::fmt::Display for AnothersFile {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.0)
    }
}

impl std::error::Error for AnothersFile {}

/// Move `tmp` over `path`, replacing only the file `checked` saw there.
/// Where the system can swap two names atomically (`renameat2` with
/// `RENAME_EXCHANGE`), the backup swaps places with what is at `path`,
/// which is then looked at: the checked file is removed; anything else (a
/// file put there since the check) is swapped back and kept, and nothing
/// is written. Elsewhere a plain rename follows the last look.
fn land_over(tmp: &Path, path: &Path, checked: &Seen) -> std::io::Result<()> {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        use nix::fcntl::{AT_FDCWD, RenameFlags, renameat2};
        let swap = || renameat2(AT_FDCWD, tmp, AT_FDCWD, path, RenameFlags::RENAME_EXCHANGE);
        // From the swap on, `tmp` may name another's file: an interrupt
        // waits until it is settled, and then must not remove it (review: a
        // Ctrl-C just after the swap did).
        let _landing = crate::files::landing();
        crate::files::temp_landed(tmp);
        match swap() {
            Ok(()) => {
                // `tmp` now names what was at `path`.
                if Seen::of(tmp).is_ok_and(|s| s == *checked) {
                    let _ = fs::remove_file(tmp);
                    return Ok(());
                }
                // Another file: give it its name back; `tmp` is the
                // backup again, which the caller removes.
                if swap().is_ok() {
                    crate::files::temp_writing(tmp);
                    return Err(replaced_meanwhile());
                }
                // The backup has gone from `path` since: theirs goes back.
                if land_on_free(tmp, path).is_ok() {
                    return Err(replaced_meanwhile());
                }
                // The backup is at `path`, and theirs cannot go back: it
                // is kept under a name no sweep of temporaries takes
                // (review: it stayed at the temporary's name, which the
                // next export to this path removed).
                let kept = kept_name(path);
                let at = match land_on_free(tmp, &kept) {
                    Ok(()) => format!("it is kept as {}", kept.display()),
                    Err(_) => format!(
                        "it is kept at {} (a temporary's name, which a later export to this path removes: move it)",
                        tmp.display()
                    ),
                };
                return Err(std::io::Error::other(AnothersFile(format!(
                    "a file was put at {0} while the backup was made, and could not be put back: {at}; the backup is at {0}",
                    path.display()
                ))));
            }
            // The checked file has gone: the path is free.
            Err(nix::errno::Errno::ENOENT) => {
                crate::files::temp_writing(tmp);
                return land_on_free(tmp, path);
            }
            // No atomic swap here: the last look stands.
            Err(_) => crate::files::temp_writing(tmp),
        }
    }
    match Seen::of(path) {
        Ok(s) if s == *checked => fs::rename(tmp, path),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => land_on_free(tmp, path),
        _ => Err(replaced_meanwhile()),
    }
}

/// Move `tmp` to the free path `path` without replacing a file that
/// appeared there since: a rename that refuses to replace where the
/// system has one, else a hard link (made only where nothing is), else,
/// on a file system with neither, a plain rename.
fn land_on_free(tmp: &Path, path: &Path) -> std::io::Result<()> {
    let appeared = || {
        std::io::Error::new(
            std::io::ErrorKind::AlreadyExists,
            "a file appeared there while the backup was made",
        )
    };
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        use nix::fcntl::{AT_FDCWD, RenameFlags, renameat2};
        match renameat2(AT_FDCWD, tmp, AT_FDCWD, path, RenameFlags::RENAME_NOREPLACE) {
            Ok(()) => return Ok(()),
            Err(nix::errno::Errno::EEXIST) => return Err(appeared()),
            // Not supported here: try a hard link.
            Err(_) => {}
        }
    }
    match fs::hard_link(tmp, path) {
        Ok(()) => {
            let _ = fs::remove_file(tmp);
            Ok(())
        }
        Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => Err(appeared()),
        Err(_) => fs::rename(tmp, path),
    }
}

/// Write a checkpoint file at `path` (atomically: a temp file beside it,
/// fsynced, renamed, the directory fsynced). Returns the world hash.
pub fn write_at(path: &Path, state: WorldRef<'_>) -> Result<u64, CheckpointError> {
    write_landing(path, state, |tmp| fs::rename(tmp, path))
}

/// [`write_at`], landing the fsynced temporary file with `land`.
fn write_landing(
    path: &Path,
    state: WorldRef<'_>,
    land: impl FnOnce(&Path) -> std::io::Result<()>,
) -> Result<u64, CheckpointError> {
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => Path::new("."),
    };
    let hash = world_hash(state.store, state.channels);
    let payload = lz4_flex::compress_prepend_size(&encode(state));
    let mut header = Vec::with_capacity(HEADER);
    header.extend_from_slice(MAGIC);
    header.extend_from_slice(&VERSION.to_le_bytes());
    header.extend_from_slice(&state.tick.to_le_bytes());
    header.extend_from_slice(&hash.to_le_bytes());
    header.extend_from_slice(&(payload.len() as u64).to_le_bytes());
    header.extend_from_slice(&crc32fast::hash(&payload).to_le_bytes());
    let hcrc = crc32fast::hash(&header);
    header.extend_from_slice(&hcrc.to_le_bytes());
    let id = serde_json::to_vec(&state.identity).unwrap_or_else(|_| b"null".to_vec());
    header.extend_from_slice(&(id.len() as u32).to_le_bytes());
    header.extend_from_slice(&id);
    header.extend_from_slice(&crc32fast::hash(&id).to_le_bytes());
    // A fresh temp name: a file already there is never reused or removed
    // (regression: export overwrote a user's `.NAME.tmp`).
    let (tmp, mut f) = crate::files::fresh_temp_beside(path).map_err(|e| io(path, e))?;
    let result = (|| -> std::io::Result<()> {
        f.write_all(&header)?;
        f.write_all(&payload)?;
        f.sync_all()?;
        land(&tmp)?;
        crate::files::temp_landed(&tmp);
        Ok(())
    })();
    if let Err(e) = result {
        // Another's file may be all the temporary holds now (see
        // [`land_over`]): that one is kept.
        if !e.get_ref().is_some_and(|inner| inner.is::<AnothersFile>()) {
            let _ = fs::remove_file(&tmp);
        }
        return Err(io(path, e));
    }
    // The file has landed under its final name: it is this checkpoint, and
    // retention must count it even if the directory's fsync fails (out of
    // descriptors, say; regression: such files were orphaned for ever).
    if let Err(e) = File::open(dir).and_then(|d| d.sync_all()) {
        crate::say!(
            "warning: checkpoint {} written, but syncing its directory failed: {e}",
            path.display()
        );
    }
    Ok(hash)
}

/// Header, identity and payload checksum; with `full`, also decode and the
/// world hash. Returns the state (when `full`) and the identity.
///
/// Nothing is allocated for the payload before the header has verified and
/// the file's size agrees with it; the payload checksum of a cheap check is
/// streamed; a full read needs the payload and its claimed decompressed
/// size to fit in the memory the OS says is available.
pub(super) fn read_checked(
    path: &Path,
    full: bool,
) -> Result<(Option<WorldState>, Option<WorldIdentity>), CheckpointError> {
    use std::io::Read;
    let corrupt = |msg: String| CheckpointError::Corrupt {
        path: path.to_path_buf(),
        msg,
    };
    let meta = fs::metadata(path).map_err(|e| io(path, e))?;
    if !meta.is_file() {
        return Err(corrupt("not a regular file".into()));
    }
    let mut f = File::open(path).map_err(|e| io(path, e))?;
    // The header and the identity block (at most 64 KiB) first.
    let mut head = Vec::with_capacity(HEADER + 8);
    (&mut f)
        .take(HEADER as u64 + 4)
        .read_to_end(&mut head)
        .map_err(|e| io(path, e))?;
    if head.len() >= MAGIC.len() && head[..MAGIC.len()] != MAGIC[..] {
        return Err(CheckpointError::NotACheckpoint {
            path: path.to_path_buf(),
        });
    }
    let (version, payload_len) = check_header(&head).map_err(corrupt)?;
    let mut id_block = Vec::new();
    if version >= 2 {
        let n = u32::from_le_bytes(head[HEADER..HEADER + 4].try_into().expect("4")) as u64;
        if n > 64 << 10 {
            return Err(corrupt(format!("identity block of {n} bytes is too large")));
        }
        (&mut f)
            .take(n + 4)
            .read_to_end(&mut id_block)
            .map_err(|e| io(path, e))?;
    } else {
        head.truncate(HEADER);
    }
    let prefix = head.len() as u64 + id_block.len() as u64;
    if meta.len() != prefix + payload_len {
        return Err(corrupt(format!(
            "the file is {} bytes, its header says {}",
            meta.len(),
            prefix + payload_len
        )));
    }
    if !full {
        let mut head_and_id = head.clone();
        head_and_id.extend_from_slice(&id_block);
        let (_, identity) = parse_prefix(&head_and_id).map_err(corrupt)?;
        let want = u32::from_le_bytes(head[32..36].try_into().expect("4"));
        let mut crc = crc32fast::Hasher::new();
        let mut buf = vec![0u8; 1 << 20];
        loop {
            let n = f.read(&mut buf).map_err(|e| io(path, e))?;
            if n == 0 {
                break;
            }
            crc.update(&buf[..n]);
        }
        if crc.finalize() != want {
            return Err(corrupt("payload checksum mismatch".into()));
        }
        return Ok((None, identity));
    }
    let have = crate::scene::budget::available_bytes();
    if payload_len > have / 2 {
        return Err(corrupt(format!(
            "a {payload_len}-byte payload does not fit in the {have} bytes available"
        )));
    }
    let mut bytes = head;
    bytes.extend_from_slice(&id_block);
    f.read_to_end(&mut bytes).map_err(|e| io(path, e))?;
    parse(&bytes, true).map_err(corrupt)
}

/// Verify the fixed header; returns (version, payload length).
fn check_header(h: &[u8]) -> Result<(u32, u64), String> {
    if h.len() < HEADER {
        return Err(format!("{} bytes is shorter than the header", h.len()));
    }
    if &h[0..4] != MAGIC {
        return Err("not a brickworld checkpoint (bad magic)".into());
    }
    if crc32fast::hash(&h[..36]) != u32::from_le_bytes(h[36..40].try_into().expect("4")) {
        return Err("header checksum mismatch".into());
    }
    let version = u32::from_le_bytes(h[4..8].try_into().expect("4"));
    if !(1..=VERSION).contains(&version) {
        return Err(format!(
            "format version {version}, this build reads 1 to {VERSION}"
        ));
    }
    if version >= 2 && h.len() < HEADER + 4 {
        return Err("the identity block is missing".into());
    }
    Ok((
        version,
        u64::from_le_bytes(h[24..32].try_into().expect("8")),
    ))
}

/// The header and identity block at the start of `bytes`: returns the
/// prefix length and the identity.
fn parse_prefix(bytes: &[u8]) -> Result<(usize, Option<WorldIdentity>), String> {
    let (version, _) = check_header(bytes)?;
    if version < 2 {
        return Ok((HEADER, None));
    }
    let rest = &bytes[HEADER..];
    let n = u32::from_le_bytes(rest[..4].try_into().expect("4")) as usize;
    if n > 64 << 10 || rest.len() < 8 + n {
        return Err(format!("identity block of {n} bytes does not fit"));
    }
    let id = &rest[4..4 + n];
    let icrc = u32::from_le_bytes(rest[4 + n..8 + n].try_into().expect("4"));
    if crc32fast::hash(id) != icrc {
        return Err("identity checksum mismatch".into());
    }
    let identity = serde_json::from_slice::<Option<WorldIdentity>>(id)
        .map_err(|e| format!("identity: {e}"))?;
    Ok((HEADER + 8 + n, identity))
}

/// Parse a whole checkpoint file from bytes (the fuzz target): never panics
/// and never allocates more than the bytes justify.
pub fn parse(
    bytes: &[u8],
    full: bool,
) -> Result<(Option<WorldState>, Option<WorldIdentity>), String> {
    let (version, len) = check_header(bytes)?;
    let h = &bytes[..HEADER];
    let tick = u64::from_le_bytes(h[8..16].try_into().expect("8"));
    let hash = u64::from_le_bytes(h[16..24].try_into().expect("8"));
    let crc = u32::from_le_bytes(h[32..36].try_into().expect("4"));
    let (prefix, identity) = parse_prefix(bytes)?;
    let payload = &bytes[prefix..];
    if payload.len() as u64 != len {
        return Err(format!(
            "payload is {} bytes, the header says {len}",
            payload.len()
        ));
    }
    if crc32fast::hash(payload) != crc {
        return Err("payload checksum mismatch".into());
    }
    if !full {
        return Ok((None, identity));
    }
    let claimed = payload
        .get(..4)
        .map(|b| u32::from_le_bytes(b.try_into().expect("4")) as usize)
        .ok_or("the payload has no size prefix")?;
    if claimed > payload.len().saturating_mul(MAX_LZ4_RATIO) + 64 {
        return Err(format!(
            "the payload claims {claimed} bytes uncompressed, more than {} compressed bytes can hold",
            payload.len()
        ));
    }
    let have = crate::scene::budget::available_bytes();
    if claimed as u64 > have / 2 {
        return Err(format!(
            "the payload claims {claimed} bytes uncompressed; only {have} bytes are available"
        ));
    }
    let raw = lz4_flex::decompress_size_prepended(payload).map_err(|e| format!("LZ4: {e}"))?;
    let mut state = decode(tick, version, &raw)?;
    // Version 4 files may hold either hash: builds of one session wrote
    // the hash by name before the version became 5 (review).
    let got = if version >= 6 {
        world_hash(&state.store, &state.channels)
    } else if version == 5 {
        super::world_hash_v5(&state.store, &state.channels)
    } else {
        match super::world_hash_by_id(&state.store, &state.channels) {
            by_id if by_id != hash && version == 4 => {
                super::world_hash_v5(&state.store, &state.channels)
            }
            by_id => by_id,
        }
    };
    if got != hash {
        return Err(format!(
            "world hash {got:#x} differs from the recorded {hash:#x}"
        ));
    }
    state.identity = identity.clone();
    Ok((Some(state), identity))
}

/// Read and verify one checkpoint file.
pub fn read(path: &Path) -> Result<WorldState, CheckpointError> {
    let (state, _) = read_checked(path, true)?;
    Ok(state.expect("full read returns the state"))
}

#[cfg(test)]
mod tests {
    use super::{Seen, land_on_free, land_over};

    /// Over an earlier backup, only the file that was checked is replaced:
    /// one put in its place since, or changed in place, is kept and the
    /// backup stays in its temporary (gap: the look just before a plain
    /// rename was the last check); the checked file, unchanged, is
    /// replaced and leaves nothing behind; gone, the path is free.
    #[test]
    fn landing_over_a_backup_replaces_only_the_file_that_was_checked() {
        let dir = std::env::temp_dir().join(format!("bw-over-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        let (tmp, path) = (dir.join(".b.tmp"), dir.join("b.bwc"));
        let read = |p: &std::path::Path| std::fs::read_to_string(p).unwrap();
        std::fs::write(&tmp, "new backup").unwrap();
        std::fs::write(&path, "old backup").unwrap();
        // Another file renamed into its place.
        let checked = Seen::of(&path).unwrap();
        std::fs::write(dir.join("other"), "put there meanwhile").unwrap();
        std::fs::rename(dir.join("other"), &path).unwrap();
        let e = land_over(&tmp, &path, &checked).unwrap_err();
        assert_eq!(e.kind(), std::io::ErrorKind::AlreadyExists, "{e}");
        assert_eq!(read(&path), "put there meanwhile");
        assert_eq!(read(&tmp), "new backup");
        // The same file, changed in place.
        let checked = Seen::of(&path).unwrap();
        std::fs::write(&path, "put there meanwhile, then edited").unwrap();
        assert!(land_over(&tmp, &path, &checked).is_err());
        assert_eq!(read(&path), "put there meanwhile, then edited");
        assert_eq!(read(&tmp), "new backup");
        // Unchanged since the check: replaced, and nothing is left over.
        let checked = Seen::of(&path).unwrap();
        land_over(&tmp, &path, &checked).unwrap();
        assert_eq!(read(&path), "new backup");
        let names: Vec<_> = std::fs::read_dir(&dir)
            .unwrap()
            .map(|e| e.unwrap().file_name())
            .collect();
        assert_eq!(names, vec![std::ffi::OsString::from("b.bwc")]);
        // Gone since the check: the backup lands on the free path.
        std::fs::write(&tmp, "newer backup").unwrap();
        let checked = Seen::of(&path).unwrap();
        std::fs::remove_file(&path).unwrap();
        land_over(&tmp, &path, &checked).unwrap();
        assert_eq!(read(&path), "newer backup");
        assert!(!tmp.exists());
        let _ = std::fs::remove_dir_all(&dir);
    }

    /// A file made at the export's path while the backup was being made
    /// is kept, and the backup stays in its temporary (review: it was
    /// replaced, exit 0); where the path is still free, the backup lands.
    #[test]
    fn landing_on_a_free_path_never_replaces_a_file_made_meanwhile() {
        let dir = std::env::temp_dir().join(format!("bw-land-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        let (tmp, path) = (dir.join(".b.tmp"), dir.join("b.bwc"));
        std::fs::write(&tmp, "backup").unwrap();
        std::fs::write(&path, "notes made meanwhile").unwrap();
        let e = land_on_free(&tmp, &path).unwrap_err();
        assert_eq!(e.kind(), std::io::ErrorKind::AlreadyExists, "{e}");
        assert_eq!(
            std::fs::read_to_string(&path).unwrap(),
            "notes made meanwhile"
        );
        assert_eq!(std::fs::read_to_string(&tmp).unwrap(), "backup");
        std::fs::remove_file(&path).unwrap();
        land_on_free(&tmp, &path).unwrap();
        assert_eq!(std::fs::read_to_string(&path).unwrap(), "backup");
        assert!(!tmp.exists());
        let _ = std::fs::remove_dir_all(&dir);
    }
}
