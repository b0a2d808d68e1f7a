//! Ray-guided streaming: which bricks the GPU pool holds. After each frame
//! the requests rays recorded are served within the upload budget; a full
//! pool evicts the least recently seen bricks; edits invalidate pointers.
//! A CPU-side [`BrickPool`] mirrors the GPU pool so that slot and material
//! block allocation reuse its free lists and size classes.

use glam::IVec3;
use rustc_hash::FxHashMap;

use super::tracer::{GpuBrickmap, STATE_MASK, UNLOADED, lod565, occupancy_words};
use super::{GpuContext, GpuError};
use crate::world::{BRICK_VOXELS, BrickContent, BrickGrid, BrickPool, Palette, UNIFORM};

/// Sizes of the streaming pool.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct StreamConfig {
    /// Brick slots in the GPU pool.
    pub pool_slots: u32,
    /// Bytes of material data in the GPU pool.
    pub arena_bytes: u32,
    /// Requests the feedback buffer holds per frame.
    pub feedback_capacity: u32,
    /// Most bricks uploaded per frame.
    pub uploads_per_frame: u32,
}

impl Default for StreamConfig {
    fn default() -> Self {
        StreamConfig {
            pool_slots: 65_536,
            arena_bytes: 65_536 * 96,
            feedback_capacity: 4096,
            uploads_per_frame: 256,
        }
    }
}

/// What one streamed frame did.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct FrameStats {
    /// Distinct bricks requested by rays this frame (recorded).
    pub requests: u32,
    /// Requests lost to feedback overflow (asked again later).
    pub overflowed: u32,
    /// Bricks uploaded after the frame.
    pub uploads: u32,
    /// Bricks evicted to make room.
    pub evictions: u32,
    /// Bricks resident after the frame.
    pub resident: u32,
    /// Bytes uploaded after the frame.
    pub upload_bytes: u64,
    /// Material bytes the uploads would have needed without culling the
    /// materials of voxels hidden on all six sides.
    pub unculled_material_bytes: u64,
    /// Material bytes actually uploaded.
    pub material_bytes: u64,
}

/// Residency bookkeeping of a streaming pool.
pub(super) struct Residency {
    pub(super) mirror: BrickPool,
    /// Grid index of the brick in each GPU slot.
    pub(super) owner: FxHashMap<u32, u32>,
    /// GPU slot (as a mirror id) of each resident grid index.
    pub(super) slot_of: FxHashMap<u32, crate::world::BrickId>,
    /// LOD colour (RGB565, from the world's palette) of each resident grid index.
    pub(super) lod_of: FxHashMap<u32, u32>,
    pub(super) last_seen: Vec<u32>,
    pub(super) cfg: StreamConfig,
}

/// Bytes of per-voxel material data a brick needs in the pool's arena
/// (header, local palette and packed indices, rounded to the 16-byte class).
fn material_bytes(b: &crate::world::Brick) -> u64 {
    if b.local_palette().len() <= 1 {
        return 0;
    }
    let len =
        3 + b.local_palette().len() + (b.solid_voxels() as usize * b.bits() as usize).div_ceil(8);
    len.div_ceil(16) as u64 * 16
}

/// Give voxels hidden on all six sides (within the brick) the brick's most
/// common visible material: rays from outside never see them, and fewer
/// distinct materials mean a smaller palette and fewer index bits (the
/// thesis culls hidden voxels' colours the same way, §4.2). The mask is
/// untouched, so traversal is exact. Neighbours in other bricks count as
/// open, so no visible voxel is ever changed.
fn cull_hidden_materials(dense: &mut [u8; BRICK_VOXELS]) {
    let at = |d: &[u8; BRICK_VOXELS], x: i32, y: i32, z: i32| -> bool {
        (0..8).contains(&x)
            && (0..8).contains(&y)
            && (0..8).contains(&z)
            && d[(x | (y << 3) | (z << 6)) as usize] != 0
    };
    let mut hidden = [false; BRICK_VOXELS];
    let mut counts = [0u32; 256];
    for i in 0..BRICK_VOXELS {
        if dense[i] == 0 {
            continue;
        }
        let (x, y, z) = ((i & 7) as i32, ((i >> 3) & 7) as i32, (i >> 6) as i32);
        hidden[i] = at(dense, x - 1, y, z)
            && at(dense, x + 1, y, z)
            && at(dense, x, y - 1, z)
            && at(dense, x, y + 1, z)
            && at(dense, x, y, z - 1)
            && at(dense, x, y, z + 1);
        if !hidden[i] {
            counts[dense[i] as usize] += 1;
        }
    }
    let Some(common) = (1..256)
        .max_by_key(|&m| (counts[m], std::cmp::Reverse(m)))
        .filter(|&m| counts[m] > 0)
    else {
        return;
    };
    for i in 0..BRICK_VOXELS {
        if hidden[i] {
            dense[i] = common as u8;
        }
    }
}

impl GpuBrickmap {
    /// Upload up to the per-frame budget of requested bricks; put the rest
    /// back to unloaded so that rays ask again.
    pub(super) fn serve(
        &mut self,
        ctx: &GpuContext,
        requests: &[u32],
        grid: &BrickGrid,
        pool: &BrickPool,
        stats: &mut FrameStats,
    ) -> Result<(), GpuError> {
        let budget = self
            .residency
            .as_ref()
            .map_or(0, |r| r.cfg.uploads_per_frame) as usize;
        let mut dense = [0u8; BRICK_VOXELS];
        for (k, &i) in requests.iter().enumerate() {
            let p = self.shadow[i as usize];
            let unloaded = (p & !STATE_MASK) | UNLOADED;
            if k >= budget {
                self.set_pointer(ctx, i, unloaded);
                continue;
            }
            let l = grid.local_of_index(i as usize);
            let wp = grid.pointer(l);
            let Some(brick) = (wp != 0 && wp & UNIFORM == 0)
                .then(|| pool.slot(wp - 1))
                .flatten()
            else {
                // The world changed under the request: re-encode the pointer.
                let np = Self::unloaded_pointer(wp, pool);
                self.set_pointer(ctx, i, np);
                continue;
            };
            brick.to_dense(&mut dense);
            let lod = lod565(brick.lod_rgb());
            if let BrickContent::Mixed(full) =
                BrickContent::from_dense(&dense, &Palette::grey_ramp())
            {
                stats.unculled_material_bytes += material_bytes(&full);
            }
            cull_hidden_materials(&mut dense);
            let BrickContent::Mixed(b) = BrickContent::from_dense(&dense, &Palette::grey_ramp())
            else {
                continue;
            };
            stats.material_bytes += material_bytes(&b);
            if let Some(res) = self.residency.as_mut() {
                res.lod_of.insert(i, lod);
            }
            let Some(slot) = self.admit(ctx, i, b, stats)? else {
                if let Some(res) = self.residency.as_mut() {
                    res.lod_of.remove(&i);
                }
                self.set_pointer(ctx, i, unloaded);
                continue;
            };
            self.set_pointer(ctx, i, slot + 1);
        }
        Ok(())
    }

    /// Put a brick into the pool (evicting least recently seen bricks if
    /// needed) and upload it. `None` if nothing could be evicted.
    fn admit(
        &mut self,
        ctx: &GpuContext,
        index: u32,
        brick: crate::world::Brick,
        stats: &mut FrameStats,
    ) -> Result<Option<u32>, GpuError> {
        for _attempt in 0..2 {
            let frame_no = self.frame_no;
            let res = self.residency.as_mut().expect("streaming");
            let full = res.mirror.len() as u32 >= res.cfg.pool_slots;
            if !full {
                let id = res.mirror.insert(brick.clone());
                let cap = res.cfg.arena_bytes as usize;
                let fits = id.index() < res.cfg.pool_slots
                    && res
                        .mirror
                        .arena_block(id.index())
                        .is_none_or(|(off, len)| off + len <= cap);
                if fits {
                    let slot = id.index();
                    res.owner.insert(slot, index);
                    res.slot_of.insert(index, id);
                    let (masks, meta, arena) = res.mirror.raw();
                    let mask_words: Vec<u32> = masks[slot as usize]
                        .iter()
                        .flat_map(|w| [*w as u32, (*w >> 32) as u32])
                        .collect();
                    ctx.queue.write_buffer(
                        &self.masks,
                        slot as u64 * 64,
                        bytemuck::cast_slice(&mask_words),
                    );
                    ctx.queue.write_buffer(
                        &self.meta,
                        slot as u64 * 8,
                        bytemuck::cast_slice(&meta[slot as usize]),
                    );
                    stats.upload_bytes += 72;
                    if let Some((off, len)) = res.mirror.arena_block(slot) {
                        // Arena writes must be 4-byte aligned: blocks are 16-byte aligned.
                        ctx.queue
                            .write_buffer(&self.arena, off as u64, &arena[off..off + len]);
                        stats.upload_bytes += len as u64;
                    }
                    stats.uploads += 1;
                    return Ok(Some(slot));
                }
                res.mirror.remove(id);
            }
            // Evict the least recently seen resident brick not seen this frame.
            let victim = res
                .owner
                .iter()
                .filter(|(slot, _)| res.last_seen[**slot as usize] < frame_no)
                .min_by_key(|(slot, _)| (res.last_seen[**slot as usize], **slot))
                .map(|(s, i)| (*s, *i));
            let Some((_, victim_index)) = victim else {
                return Ok(None);
            };
            self.evict(ctx, victim_index);
            stats.evictions += 1;
        }
        Ok(None)
    }

    /// Drop grid index `i`'s brick from the pool; its pointer becomes unloaded.
    fn evict(&mut self, ctx: &GpuContext, i: u32) {
        let Some(res) = self.residency.as_mut() else {
            return;
        };
        if let Some(id) = res.slot_of.remove(&i) {
            let lod = res.lod_of.remove(&i).unwrap_or(0);
            res.owner.remove(&id.index());
            res.mirror.remove(id);
            self.set_pointer(ctx, i, UNLOADED | lod);
        }
    }

    /// Apply the world's edits to bricks `changed` (world brick coordinates,
    /// duplicates allowed): pointers go back to unloaded with their new LOD
    /// colour (or empty / uniform), freed slots return to the pool, and the
    /// occupancy layer is refreshed. Only meaningful when streaming.
    pub fn apply_edits(
        &mut self,
        ctx: &GpuContext,
        grid: &BrickGrid,
        pool: &BrickPool,
        changed: &[IVec3],
    ) {
        let mut seen = rustc_hash::FxHashSet::default();
        for &b in changed {
            let l = b - grid.origin();
            let Some(i) = grid.cell_index(l) else {
                continue;
            };
            if !seen.insert(l) {
                continue;
            }
            let i = i as u32;
            if let Some(res) = self.residency.as_mut()
                && let Some(id) = res.slot_of.remove(&i)
            {
                res.lod_of.remove(&i);
                res.owner.remove(&id.index());
                res.mirror.remove(id);
            }
            let p = Self::unloaded_pointer(grid.pointer(l), pool);
            self.set_pointer(ctx, i, p);
        }
        ctx.queue
            .write_buffer(&self.occ, 0, bytemuck::cast_slice(&occupancy_words(grid)));
    }
}
