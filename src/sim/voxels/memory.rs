//! What a voxel step may allocate, checked before it does: the working
//! set of the bricks it runs on ([`step_fits`]) and what its changed
//! bricks add to the world ([`growth_fits`]). A step that does not fit is
//! rejected like an unstable one (nothing changes; three in a row suspend
//! the script), where the allocation aborted the engine.

use crate::sim::script::VOXEL_CELLS;
use crate::sim::{Rejection, ScriptSpec, SimError};
use crate::world::BrickStore;

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
    // its 27 neighbours' indices, and each pass's channel outputs (the
    // estimate missed `orig` and the neighbours, and the step made an
    // output channel for scripts that write none: growth probe, 3.7 GB
    // for a script that did nothing on a 2048² world).
    let need = (bricks as u64).saturating_mul(VOXEL_CELLS as u64 + channels as u64 * chan + 40)
        + (cands as u64).saturating_mul(2 * VOXEL_CELLS as u64 + 27 * 4 + writes * chan);
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

/// Most bytes a brick of materials `mats` can add to a world's brick pool
/// when stored: its mask, slot and, with two materials or more, its
/// palette and packed indices at 8 bits (the widest) in 16-byte blocks.
fn brick_growth(mats: &[u8; VOXEL_CELLS]) -> (u64, u64) {
    let mut seen = [false; 256];
    let (mut kinds, mut solid) = (0u64, 0u64);
    for &m in mats.iter().filter(|&&m| m != 0) {
        solid += 1;
        if !std::mem::replace(&mut seen[m as usize], true) {
            kinds += 1;
        }
    }
    let block = if kinds >= 2 {
        (3 + kinds + solid).div_ceil(16) * 16
    } else {
        0
    };
    (block, 64 + 24 + block)
}

/// Refuse a step whose changed bricks could not be stored: past the brick
/// pool's material arena ([`ARENA_LIMIT`](crate::world::ARENA_LIMIT)), or
/// past what the process may still allocate for them twice over (the world
/// and the renderer's copy) with [`GROWTH_MARGIN`] to spare. A voxel script
/// that filled a 4096² world with many materials grew it until the arena's
/// limit panicked the engine, with nothing said before (regression, growth
/// probe). The step is rejected like one out of memory: nothing changes,
/// and three in a row suspend the script, the engine going on.
pub(super) fn growth_fits(
    spec: &ScriptSpec,
    store: &BrickStore,
    work: &Working,
) -> Result<(), SimError> {
    let (mut blocks, mut bytes, mut bricks) = (0u64, 0u64, 0u64);
    for ci in work.changed_mats() {
        let (block, all) = brick_growth(&work.mats[ci]);
        blocks += block;
        bytes += all;
        bricks += 1;
    }
    if bricks == 0 {
        return Ok(());
    }
    let growth = Growth {
        bricks,
        blocks,
        bytes: bytes
            + store
                .pool()
                .growth_reserve(bricks as usize, blocks as usize),
        arena: store.pool().arena_len() as u64,
    };
    match growth.refusal(
        crate::world::ARENA_LIMIT,
        crate::scene::budget::headroom_bytes,
    ) {
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

/// What a step's changed bricks may add to the world.
struct Growth {
    bricks: u64,
    /// Bytes of material blocks.
    blocks: u64,
    /// Bytes in all (blocks, masks and slots, and the pool's arrays
    /// moved to a larger capacity).
    bytes: u64,
    /// The material arena's bytes now.
    arena: u64,
}

impl Growth {
    /// Why it cannot be stored, if it cannot: past `limit` bytes of arena,
    /// or past the `room` the process has (asked only once the arena fits).
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
        let room = room();
        if self.bytes.saturating_mul(2) + GROWTH_MARGIN > room {
            return Some(format!(
                "its {} changed bricks need up to {} to store, twice over (the world and the renderer's copy), and {} to spare; {} is available: fewer materials per brick, or a smaller world or region",
                self.bricks,
                human(self.bytes),
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
    /// are checked before a step's bricks are stored.
    #[test]
    fn a_step_past_the_arena_or_the_memory_left_is_refused_naming_both() {
        let g = Growth {
            bricks: 3,
            blocks: 3 * 720,
            bytes: 3 * 808,
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
        assert_eq!(g.refusal(20_000, || GROWTH_MARGIN + 2 * 3 * 808), None);
        let e = g
            .refusal(20_000, || GROWTH_MARGIN + 2 * 3 * 808 - 1)
            .unwrap();
        assert!(e.contains("need up to 2 KiB to store, twice over"), "{e}");
    }

    #[test]
    fn a_bricks_growth_counts_its_block_only_with_two_materials() {
        let mut mats = [0u8; VOXEL_CELLS];
        assert_eq!(brick_growth(&mats), (0, 88));
        mats[..100].fill(7);
        assert_eq!(brick_growth(&mats), (0, 88), "one material: no block");
        mats[100] = 9;
        // 3 header bytes + 2 palette entries + 101 solid voxels, in 16s.
        assert_eq!(brick_growth(&mats), (112, 88 + 112));
    }
}
