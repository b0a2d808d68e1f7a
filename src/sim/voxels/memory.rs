//! What a voxel step may allocate, checked before it does: the working
//! set of the bricks it runs on ([`step_fits`]) and what its changed
//! bricks add to the world ([`growth_fits`]). A step that does not fit is
//! rejected like an unstable one (nothing changes; three in a row suspend
//! the script), where the allocation aborted the engine.

use crate::sim::script::VOXEL_CELLS;
use crate::sim::{Rejection, ScriptSpec, SimError};
use crate::world::{BrickStore, Cell};

use super::exec::Working;

/// Refuse a step whose working set would not fit what the process may
/// still allocate: the materials and channels of the candidates and their
/// neighbours (`bricks`), every pass's outputs for the candidates, and the
/// values the step may add to the channel store. The step is rejected like
/// an unstable one (nothing changes; failing steps in a row suspend the
/// script), where it aborted the engine (regression, memory probe: 250
/// voxel channels on a 128 × 64 × 128 world under `ulimit -v`). Checked
/// per step, from the bricks it runs on, because voxel channels are stored
/// only where they hold values: an estimate over the whole box refused
/// ordinary worlds (review: three channels on a 2048 × 256 × 2048 terrain,
/// 28 GiB said, 1.8 GB used).
pub(super) fn step_fits(
    spec: &ScriptSpec,
    channels: usize,
    cands: usize,
    bricks: usize,
) -> Result<(), SimError> {
    use crate::scene::budget::{headroom_bytes, human};
    let chan = (VOXEL_CELLS * 4) as u64;
    let writes = spec.widest_writes() as u64;
    // Per brick in reach: its materials, channels, place and index entry.
    // Per candidate: its materials before the step and after each pass,
    // its 27 neighbours' indices, each pass's channel outputs, and what
    // the step may add to the channel store, each channel's values (the
    // estimate missed `orig` and the neighbours, and the step made an
    // output channel for scripts that write none: growth probe, 3.7 GB
    // for a script that did nothing on a 2048² world).
    let need = (bricks as u64).saturating_mul(VOXEL_CELLS as u64 + channels as u64 * chan + 40)
        + (cands as u64)
            .saturating_mul(2 * VOXEL_CELLS as u64 + 27 * 4 + (writes + channels as u64) * chan);
    // Small steps pass without asking the OS.
    if need < 64 << 20 {
        return Ok(());
    }
    let room = headroom_bytes();
    if need > room {
        return Err(SimError::Unstable {
            script: spec.name.clone(),
            kind: Rejection::Memory,
            msg: format!(
                "its {channels} voxel channels on {cands} bricks (with their neighbours, {bricks}) need about {} for this step; {} is available: fewer channels, or a smaller world or region",
                human(need),
                human(room)
            ),
        });
    }
    Ok(())
}

/// Bytes of the material block a brick of materials `mats` is stored
/// with: none with fewer than two materials, else its header, palette and
/// packed indices at 8 bits (the widest), in 16-byte blocks. An upper
/// bound.
fn block_bytes(mats: &[u8; VOXEL_CELLS]) -> u64 {
    let mut seen = [false; 256];
    let (mut kinds, mut solid) = (0u64, 0u64);
    for &m in mats.iter().filter(|&&m| m != 0) {
        solid += 1;
        if !std::mem::replace(&mut seen[m as usize], true) {
            kinds += 1;
        }
    }
    if kinds >= 2 {
        (3 + kinds + solid).div_ceil(16) * 16
    } else {
        0
    }
}

/// Bytes a new slot of the brick pool holds (mask, metadata, generation).
const SLOT_BYTES: u64 = 64 + 24 + 4;

/// Refuse a step whose changed bricks could not be stored: past the brick
/// pool's material arena (`limit`, [`ARENA_LIMIT`](crate::world::ARENA_LIMIT)
/// in the engine), or past what the process may still allocate for them
/// (twice, for the renderer's copy, and an array of the pool moved to a
/// larger capacity, with [`GROWTH_MARGIN`] to spare). A voxel script that
/// filled a 4096² world with many materials grew it until the arena's
/// limit panicked the engine, with nothing said before (regression,
/// growth probe). The step is rejected like one out of memory: nothing
/// changes, and three in a row suspend the script, the engine going on.
/// What is counted is the net growth: a brick replaced frees its slot and
/// block (review: every changed brick was counted new, and a compacted
/// arena, full to its capacity, asked for twice itself at every step).
pub(super) fn growth_fits(
    spec: &ScriptSpec,
    store: &BrickStore,
    work: &Working,
    limit: u64,
) -> Result<(), SimError> {
    let pool = store.pool();
    let (mut blocks, mut freed, mut slots, mut bricks) = (0u64, 0u64, 0u64, 0u64);
    for ci in work.changed_mats() {
        bricks += 1;
        let new = block_bytes(&work.mats[ci]);
        blocks += new;
        match store.cell(work.cands[ci]) {
            Cell::Mixed(id) => {
                freed += pool
                    .arena_block(id.index())
                    .map_or(0, |(_, len)| len as u64);
            }
            // A brick of one material (or none) needs no slot.
            Cell::Empty | Cell::Uniform(_) => {
                let first = work.mats[ci][0];
                if work.mats[ci].iter().any(|&m| m != first) {
                    slots += 1;
                }
            }
        }
    }
    if bricks == 0 {
        return Ok(());
    }
    let net_blocks = blocks.saturating_sub(freed);
    let growth = Growth {
        bricks,
        blocks: net_blocks,
        bytes: net_blocks + slots * SLOT_BYTES,
        reserve: pool.growth_reserve(slots as usize, net_blocks as usize),
        arena: pool.arena_len() as u64,
    };
    match growth.refusal(limit, crate::scene::budget::headroom_bytes) {
        None => Ok(()),
        Some(msg) => Err(SimError::Unstable {
            script: spec.name.clone(),
            kind: Rejection::Memory,
            msg,
        }),
    }
}

/// Memory kept free beside a step's growth, for commits, frames and the
/// next step's working set.
const GROWTH_MARGIN: u64 = 64 << 20;

/// Growth below this asks the OS nothing: a pool's array that moves to a
/// larger capacity (the allocation that aborted) is always asked about.
const SMALL_GROWTH: u64 = 16 << 20;

/// What a step's changed bricks may add to the world.
struct Growth {
    bricks: u64,
    /// Net bytes of material blocks added.
    blocks: u64,
    /// Net bytes added in all (blocks and slots).
    bytes: u64,
    /// Bytes of the pool's arrays moved to a larger capacity, if any.
    reserve: u64,
    /// The material arena's bytes now.
    arena: u64,
}

impl Growth {
    /// Why it cannot be stored, if it cannot: past `limit` bytes of arena,
    /// or past the `room` the process has (asked only once the arena fits,
    /// and the growth is not small).
    fn refusal(&self, limit: u64, room: impl FnOnce() -> u64) -> Option<String> {
        use crate::scene::budget::human;
        if self.arena + self.blocks > limit {
            return Some(format!(
                "its {} changed bricks could take the world's material arena (many-material bricks) from {} past its {} limit: fewer materials per brick, or a smaller world or region",
                self.bricks,
                human(self.arena),
                human(limit)
            ));
        }
        let need = self.bytes.saturating_mul(2) + self.reserve;
        if need < SMALL_GROWTH {
            return None;
        }
        let room = room();
        if need + GROWTH_MARGIN > room {
            return Some(format!(
                "its {} changed bricks need up to {} to store (twice over, for the renderer's copy, and {} for the brick pool's arrays to grow), and {} to spare; {} is available: fewer materials per brick, or a smaller world or region",
                self.bricks,
                human(self.bytes * 2),
                human(self.reserve),
                human(GROWTH_MARGIN),
                human(room)
            ));
        }
        None
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Regression (growth probe): the arena's limit and the memory left
    /// are checked before a step's bricks are stored; small growth asks
    /// the OS nothing.
    #[test]
    fn a_step_past_the_arena_or_the_memory_left_is_refused_naming_both() {
        let g = Growth {
            bricks: 3,
            blocks: 3 * 720,
            bytes: 3 * 808,
            reserve: 32 << 20,
            arena: 10_000,
        };
        assert_eq!(g.refusal(20_000, || u64::MAX), None);
        let e = g
            .refusal(12_000, || panic!("the arena decides first"))
            .unwrap();
        assert!(
            e.starts_with("its 3 changed bricks could take the world's material arena"),
            "{e}"
        );
        let need = 2 * 3 * 808 + (32 << 20) + GROWTH_MARGIN;
        assert_eq!(g.refusal(20_000, || need), None);
        let e = g.refusal(20_000, || need - 1).unwrap();
        assert!(
            e.contains("and 32 MiB for the brick pool's arrays to grow"),
            "{e}"
        );
        let small = Growth { reserve: 0, ..g };
        assert_eq!(
            small.refusal(20_000, || panic!("small: the OS is not asked")),
            None
        );
    }

    #[test]
    fn a_bricks_block_is_counted_only_with_two_materials() {
        let mut mats = [0u8; VOXEL_CELLS];
        assert_eq!(block_bytes(&mats), 0);
        mats[..100].fill(7);
        assert_eq!(block_bytes(&mats), 0, "one material: no block");
        mats[100] = 9;
        // 3 header bytes + 2 palette entries + 101 solid voxels, in 16s.
        assert_eq!(block_bytes(&mats), 112);
    }
}
