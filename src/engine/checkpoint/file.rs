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

/// Write a checkpoint file at `path` (atomically: a temp file beside it,
/// fsynced, renamed, the directory fsynced). Returns the world hash.
pub fn write_at(path: &Path, state: WorldRef<'_>) -> Result<u64, CheckpointError> {
    write_landing(path, state, |tmp| fs::rename(tmp, path))
}

/// [`write_at`], landing the fsynced temporary file with `land`.
pub(super) fn write_landing(
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
        // `landing::land_over`): that one is kept.
        if !e
            .get_ref()
            .is_some_and(|inner| inner.is::<super::landing::AnothersFile>())
        {
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
