//! The chunk layout of a `.vox` file, checked before it is parsed.
//!
//! `dot_vox` skips a chunk it cannot read and stops at the first one whose
//! size runs past its parent, so a damaged file loaded as a different
//! model with exit 0: a palette with a huge size gave the default palette,
//! a transform with a huge size dropped the whole scene graph, an `XYZI`
//! whose count was too small drew one voxel of 73 (regression, fuzzing).
//! Here every chunk must fit its parent exactly, the chunks of fixed shape
//! (`SIZE`, `XYZI`, `RGBA`) must have it, and nothing may follow `MAIN`.
//! The pass also counts the scene-graph nodes and models the file holds,
//! so that [`super::parse`] can refuse a file whose node or model chunk
//! had the right size but could not be read (a skipped node shifts every
//! index after it: the file loaded as another scene, found by review).

/// Chunks may nest this deep (files only nest one level under `MAIN`).
const MAX_DEPTH: u32 = 8;

/// What a file's layout holds directly under `MAIN`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Counts {
    /// Scene-graph nodes (`nTRN`, `nGRP`, `nSHP`).
    pub nodes: usize,
    /// Models (an `XYZI` after a `SIZE`).
    pub models: usize,
    /// Whether a `SIZE` came yet.
    sized: bool,
}

/// Check the layout of a file's bytes; the error names the chunk and its
/// byte offset.
pub fn check(b: &[u8]) -> Result<Counts, String> {
    if b.len() < 8 || &b[..4] != b"VOX " {
        return Err("not a MagicaVoxel file (it does not start with 'VOX ')".into());
    }
    let mut counts = Counts::default();
    let end = chunk(b, 8, b.len(), 0, &mut counts)?;
    if end != b.len() {
        return Err(format!(
            "{} bytes follow the MAIN chunk, which ends at byte {end}",
            b.len() - end
        ));
    }
    Ok(counts)
}

fn u32_at(b: &[u8], at: usize) -> Option<usize> {
    let s = b.get(at..at.checked_add(4)?)?;
    Some(u32::from_le_bytes([s[0], s[1], s[2], s[3]]) as usize)
}

/// A chunk id as text: printable ASCII kept, other bytes escaped.
fn name(id: &[u8]) -> String {
    id.iter()
        .map(|&c| {
            if c.is_ascii_graphic() {
                (c as char).to_string()
            } else {
                format!("\\x{c:02x}")
            }
        })
        .collect()
}

/// Check the chunk at `at`, which must end by `limit`; returns its end.
/// Childless chunks directly under `MAIN` are counted into `counts`.
fn chunk(
    b: &[u8],
    at: usize,
    limit: usize,
    depth: u32,
    counts: &mut Counts,
) -> Result<usize, String> {
    let short = || format!("the file ends inside a chunk header at byte {at}");
    let id = b.get(at..at + 4).ok_or_else(short)?;
    let content = u32_at(b, at + 4).ok_or_else(short)?;
    let children = u32_at(b, at + 8).ok_or_else(short)?;
    let id_text = name(id);
    let start = at + 12;
    let end = start
        .checked_add(content)
        .and_then(|e| e.checked_add(children))
        .filter(|&e| e <= limit)
        .ok_or_else(|| {
            format!(
                "chunk '{id_text}' at byte {at} claims {content} + {children} bytes, past the end of {}",
                if depth == 0 { "the file" } else { "its parent" }
            )
        })?;
    // A palette may list fewer than 256 colours (`dot_vox` writes as many
    // as it has; found by review).
    if id == b"RGBA" && (content == 0 || content % 4 != 0 || content > 1024) {
        return Err(format!(
            "chunk 'RGBA' at byte {at} holds {content} bytes, not 1 to 256 colours of 4"
        ));
    }
    let fixed = match id {
        b"SIZE" => Some(12),
        b"XYZI" => {
            let n = u32_at(b, start).filter(|_| content >= 4).ok_or_else(|| {
                format!("chunk 'XYZI' at byte {at} is too short for its voxel count")
            })?;
            Some(
                n.checked_mul(4)
                    .and_then(|v| v.checked_add(4))
                    .unwrap_or(usize::MAX),
            )
        }
        _ => None,
    };
    if let Some(want) = fixed
        && content != want
    {
        return Err(format!(
            "chunk '{id_text}' at byte {at} holds {content} bytes where its contents need {want}"
        ));
    }
    if depth == 0 && id != b"MAIN" {
        return Err(format!("the first chunk is '{id_text}', not 'MAIN'"));
    }
    let mut c = start + content;
    if children > 0 && depth >= MAX_DEPTH {
        return Err(format!(
            "chunks nest deeper than {MAX_DEPTH} levels at byte {at}"
        ));
    }
    while c < end {
        c = chunk(b, c, end, depth + 1, counts)?;
    }
    if depth == 1 && children == 0 {
        match id {
            b"nTRN" | b"nGRP" | b"nSHP" => counts.nodes += 1,
            b"SIZE" => counts.sized = true,
            b"XYZI" if counts.sized => counts.models += 1,
            _ => {}
        }
    }
    Ok(end)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn chunk_bytes(id: &[u8; 4], content: &[u8], children: &[u8]) -> Vec<u8> {
        let mut v = id.to_vec();
        v.extend((content.len() as u32).to_le_bytes());
        v.extend((children.len() as u32).to_le_bytes());
        v.extend(content);
        v.extend(children);
        v
    }

    fn file(children: &[u8]) -> Vec<u8> {
        let mut v = b"VOX ".to_vec();
        v.extend(150u32.to_le_bytes());
        v.extend(chunk_bytes(b"MAIN", &[], children));
        v
    }

    fn model(count: u32, voxels: u32) -> Vec<u8> {
        let mut kids = chunk_bytes(b"SIZE", &[8, 0, 0, 0, 8, 0, 0, 0, 8, 0, 0, 0], &[]);
        let mut xyzi = count.to_le_bytes().to_vec();
        xyzi.extend((0..voxels).flat_map(|i| [i as u8, 0, 0, 1]));
        kids.extend(chunk_bytes(b"XYZI", &xyzi, &[]));
        kids
    }

    #[test]
    fn a_well_formed_file_passes_and_so_does_what_dot_vox_writes() {
        let counts = check(&file(&model(3, 3))).unwrap();
        assert_eq!((counts.nodes, counts.models), (0, 1));
        let data = dot_vox::DotVoxData {
            version: 150,
            index_map: Vec::new(),
            models: vec![dot_vox::Model {
                size: dot_vox::Size { x: 2, y: 2, z: 2 },
                voxels: vec![dot_vox::Voxel {
                    x: 1,
                    y: 0,
                    z: 1,
                    i: 4,
                }],
            }],
            palette: dot_vox::DEFAULT_PALETTE.to_vec(),
            materials: Vec::new(),
            scenes: Vec::new(),
            layers: Vec::new(),
        };
        let mut bytes = Vec::new();
        data.write_vox(&mut bytes).unwrap();
        assert!(check(&bytes).is_ok());
        // A palette of fewer than 256 colours, as `dot_vox` writes one
        // (regression, review: it was refused).
        let short = dot_vox::DotVoxData {
            palette: dot_vox::DEFAULT_PALETTE[..16].to_vec(),
            ..data
        };
        let mut bytes = Vec::new();
        short.write_vox(&mut bytes).unwrap();
        assert!(check(&bytes).is_ok(), "{:?}", check(&bytes));
    }

    /// Regression (review): a node chunk of the right size whose contents
    /// could not be read was skipped by the parser, so the file loaded as
    /// another scene with exit 0.
    #[test]
    fn a_node_chunk_that_cannot_be_read_is_refused() {
        let mut kids = model(1, 1);
        // A transform node claiming 99 dictionary entries it does not hold.
        kids.extend(chunk_bytes(b"nTRN", &[0, 0, 0, 0, 99, 0, 0, 0], &[]));
        let bytes = file(&kids);
        assert_eq!(check(&bytes).map(|c| c.nodes), Ok(1));
        let e = super::super::parse(&bytes).unwrap_err();
        assert!(e.contains("1 of the file's 1 scene-graph chunks"), "{e}");
    }

    #[test]
    fn damaged_layouts_are_refused_naming_the_chunk() {
        // An XYZI count that disagrees with its bytes.
        let e = check(&file(&model(1, 3))).unwrap_err();
        assert!(e.contains("'XYZI' at byte") && e.contains("need 8"), "{e}");
        // A palette whose size runs past the file.
        let mut rgba = chunk_bytes(b"RGBA", &[0; 1024], &[]);
        rgba[4..8].copy_from_slice(&0x8000_0000u32.to_le_bytes());
        let mut kids = model(2, 2);
        kids.extend(&rgba);
        let e = check(&file(&kids)).unwrap_err();
        assert!(e.contains("'RGBA'") && e.contains("past the end"), "{e}");
        // Bytes after MAIN, a first chunk that is not MAIN, odd ids escaped.
        let mut extra = file(&model(1, 1));
        extra.extend([0; 5]);
        assert!(check(&extra).unwrap_err().contains("5 bytes follow"));
        let mut not_main = file(&model(1, 1));
        not_main[8..12].copy_from_slice(b"M\xffIN");
        assert!(check(&not_main).unwrap_err().contains("'M\\xffIN'"));
        // Truncated anywhere: refused, never a panic.
        let whole = file(&model(4, 4));
        for n in 0..whole.len() {
            assert!(check(&whole[..n]).is_err(), "cut at {n}");
        }
    }
}
