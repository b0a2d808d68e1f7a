//! Ray-guided streaming: which bricks the GPU pool holds. After each frame
//! the requests rays recorded are served within the upload budget; a full
//! pool evicts the least recently seen bricks; edits invalidate pointers.
//! A CPU-side [`BrickPool`] mirrors the GPU pool so that slot and material
//! block allocation reuse its free lists and size classes.

use glam::IVec3;
use rustc_hash::FxHashMap;

use super::tracer::{GpuBrickmap, META_BYTES, STATE_MASK, UNLOADED, coarse_words, unloaded_bits};
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
    /// The pool doubles (slots and arena together) when a frame needs
    /// more than it holds, up to this many slots (and the device's
    /// storage-buffer limit).
    pub max_pool_slots: u32,
}

/// The default cap of a growing pool: 2²⁰ slots, 64 MiB of masks and 96
/// MiB of arena at the default arena share.
pub const MAX_POOL_SLOTS: u32 = 1 << 20;

impl Default for StreamConfig {
    fn default() -> Self {
        StreamConfig {
            pool_slots: 65_536,
            arena_bytes: 65_536 * 96,
            feedback_capacity: 4096,
            uploads_per_frame: 256,
            max_pool_slots: MAX_POOL_SLOTS,
        }
    }
}

/// `cfg` shrunk to a device whose storage buffers hold at most `limit`
/// bytes, with a warning giving the figures if it had to shrink.
pub fn fit_pool(mut cfg: StreamConfig, limit: u64) -> (StreamConfig, Option<String>) {
    let slots = (limit / 64).min(u32::MAX as u64) as u32;
    let arena = (limit.min(u32::MAX as u64) / 16 * 16) as u32;
    if cfg.pool_slots <= slots && cfg.arena_bytes <= arena {
        return (cfg, None);
    }
    let asked = (cfg.pool_slots, cfg.arena_bytes);
    cfg.pool_slots = cfg.pool_slots.min(slots);
    cfg.arena_bytes = cfg.arena_bytes.min(arena);
    let warning = format!(
        "the GPU's storage buffers hold at most {limit} bytes: the brick pool has {} slots and {} arena bytes instead of the {} and {} asked for",
        cfg.pool_slots, cfg.arena_bytes, asked.0, asked.1
    );
    (cfg, Some(warning))
}

/// What one streamed frame did.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
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
    /// Times the pool doubled this frame.
    pub grown: u32,
    /// Times the pool's material arena was compacted this frame (its
    /// holes dropped, the arena and metadata uploaded whole).
    pub compactions: u32,
    /// The tracer's passes on the device (beam starts and trace), ms, from
    /// timestamp queries; `None` where the device has none.
    pub gpu_ms: Option<f64>,
    /// Of which the beam-start pass, ms (with beams on).
    pub beam_ms: Option<f64>,
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
            let lod = unloaded_bits(&brick);
            let BrickContent::Mixed(full) = BrickContent::from_dense(&dense, &Palette::grey_ramp())
            else {
                // A pool slot holds a mixed brick; were it not, its pointer
                // is re-encoded rather than left requested.
                let np = Self::unloaded_pointer(wp, pool);
                self.set_pointer(ctx, i, np);
                continue;
            };
            stats.unculled_material_bytes += material_bytes(&full);
            cull_hidden_materials(&mut dense);
            // Hiding a solid brick's inside can leave one material (a full
            // brick whose surface is all one material): it is uploaded whole
            // then. Skipping it left its pointer requested for ever, drawn
            // in its average colour (regression, world review).
            let b = match BrickContent::from_dense(&dense, &Palette::grey_ramp()) {
                BrickContent::Mixed(b) => b,
                _ => full,
            };
            // Hidden voxels were recoloured; from afar it must still look
            // like the world's brick.
            let b = b.with_lod(brick.lod());
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
    /// needed) and upload it. `None` if nothing could be evicted, or four
    /// evictions did not make room.
    ///
    /// Freed material blocks serve only their own size class, so an arena
    /// full of other sizes' holes cannot take a brick (regression test
    /// `an_arena_full_of_another_sizes_holes_is_compacted`: every admit
    /// evicted four bricks and failed). When the arena is what is short,
    /// and evicting bricks not seen this frame can free a quarter of it,
    /// the least recently seen of those that hold material blocks are
    /// evicted until a quarter of it (below the GPU's size) is holes, and
    /// it is compacted once: each compaction reclaims a quarter of the
    /// arena, so its cost is O(1) a freed byte. Otherwise, as for slots,
    /// four evictions at most.
    fn admit(
        &mut self,
        ctx: &GpuContext,
        index: u32,
        brick: crate::world::Brick,
        stats: &mut FrameStats,
    ) -> Result<Option<u32>, GpuError> {
        let (mut evicted, mut compacted) = (0, false);
        // Whether evictions can reach a compaction; decided once.
        let mut reachable: Option<bool> = None;
        loop {
            let frame_no = self.frame_no;
            let res = self.residency.as_mut().expect("streaming");
            let full = res.mirror.len() as u32 >= res.cfg.pool_slots;
            let mut arena_short = false;
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
                    // Requested by this frame's rays: as needed as a brick
                    // they saw, so later admits of the same frame evict
                    // neither it nor each other, and a pool that this
                    // frame's bricks fill grows (regression: a small pool
                    // thrashed on its own uploads and stopped growing, so
                    // `bench stream --pool 1` failed now and then).
                    res.last_seen[slot as usize] = frame_no;
                    // The GPU's copy too: the next frame's readback
                    // replaces the CPU's stamps with the GPU's, and a slot
                    // no ray touches then would take its previous
                    // occupant's stamp (regression test
                    // `a_fresh_upload_keeps_its_stamp_through_a_frame_that_does_not_see_it`).
                    ctx.queue.write_buffer(
                        &self.last_seen,
                        slot as u64 * 4,
                        bytemuck::bytes_of(&frame_no),
                    );
                    res.owner.insert(slot, index);
                    res.slot_of.insert(index, id);
                    let (mask, meta, block) = res.mirror.raw_slot(slot).expect("inserted above");
                    let mut mask_words = [0u32; 16];
                    for (k, w) in mask.iter().enumerate() {
                        mask_words[2 * k] = *w as u32;
                        mask_words[2 * k + 1] = (*w >> 32) as u32;
                    }
                    ctx.queue.write_buffer(
                        &self.masks,
                        slot as u64 * 64,
                        bytemuck::cast_slice(&mask_words),
                    );
                    ctx.queue.write_buffer(
                        &self.meta,
                        slot as u64 * META_BYTES,
                        bytemuck::cast_slice(&meta),
                    );
                    stats.upload_bytes += 64 + META_BYTES;
                    if let Some((off, len)) = res.mirror.arena_block(slot) {
                        // Arena writes must be 4-byte aligned: blocks are 16-byte aligned.
                        ctx.queue.write_buffer(&self.arena, off as u64, block);
                        stats.upload_bytes += len as u64;
                    }
                    stats.uploads += 1;
                    return Ok(Some(slot));
                }
                let len = res.mirror.arena_block(id.index()).map_or(0, |(_, l)| l);
                res.mirror.remove(id);
                arena_short = id.index() < res.cfg.pool_slots;
                if arena_short && !compacted {
                    // Only holes inside the GPU's arena count (a failed
                    // insert leaves its block past it).
                    let (target, holes) = ((cap / 4).max(len), res.mirror.arena_holes_below(cap));
                    if holes >= target {
                        self.compact_arena(ctx, stats);
                        compacted = true;
                        continue;
                    }
                    let mirror = &res.mirror;
                    reachable.get_or_insert_with(|| {
                        let evictable: usize = (res.owner.keys())
                            .filter(|s| res.last_seen[**s as usize] < frame_no)
                            .filter_map(|s| mirror.arena_block(*s))
                            .map(|(_, l)| l)
                            .sum();
                        holes + evictable >= target
                    });
                }
            }
            let chasing = arena_short && !compacted && reachable == Some(true);
            // Evict the least recently seen resident brick not seen this
            // frame; towards a compaction, one that holds a material block.
            let victim = res
                .owner
                .iter()
                .filter(|(slot, _)| res.last_seen[**slot as usize] < frame_no)
                .filter(|(slot, _)| !chasing || res.mirror.arena_block(**slot).is_some())
                .min_by_key(|(slot, _)| (res.last_seen[**slot as usize], **slot))
                .map(|(s, i)| (*s, *i));
            let Some((_, victim_index)) = victim else {
                // Every resident brick was seen this frame: the view needs
                // a larger pool.
                if self.grow(ctx) {
                    stats.grown += 1;
                    continue;
                }
                return Ok(None);
            };
            self.evict(ctx, victim_index);
            stats.evictions += 1;
            evicted += 1;
            // Past four evictions, go on only towards a compaction.
            if evicted >= 4 && !chasing {
                return Ok(None);
            }
        }
    }

    /// Drop the mirror's arena holes and upload its arena and every
    /// slot's metadata (whose offsets moved) whole.
    fn compact_arena(&mut self, ctx: &GpuContext, stats: &mut FrameStats) {
        let Some(res) = self.residency.as_mut() else {
            return;
        };
        res.mirror.compact_arena();
        let (_, meta, arena) = res.mirror.raw();
        // Never more slots than the GPU's (an insert past them is removed
        // at once, and its slot reused first); bounded all the same.
        let meta = &meta[..meta.len().min(res.cfg.pool_slots as usize)];
        ctx.queue
            .write_buffer(&self.meta, 0, bytemuck::cast_slice(meta));
        // Blocks are whole 16-byte classes, so the length is aligned; the
        // live blocks each fitted the GPU's arena, so together they do.
        ctx.queue.write_buffer(&self.arena, 0, arena);
        stats.upload_bytes += (meta.len() * META_BYTES as usize + arena.len()) as u64;
        stats.compactions += 1;
    }

    /// Double the pool's slots and arena (up to the configured cap and the
    /// device's limit), copying what is resident; false if it cannot grow.
    fn grow(&mut self, ctx: &GpuContext) -> bool {
        let Some(res) = self.residency.as_mut() else {
            return false;
        };
        let limit = ctx.limits.max_storage_buffer_binding_size;
        let cfg = res.cfg;
        let slots = (cfg.pool_slots as u64 * 2)
            .min(cfg.max_pool_slots as u64)
            .min(limit / 64) as u32;
        let arena = (cfg.arena_bytes as u64 * 2).min(limit) as u32 / 16 * 16;
        // Slots and arena grow together, within the slot cap.
        if slots <= cfg.pool_slots {
            return false;
        }
        let (slots, arena) = (slots.max(cfg.pool_slots), arena.max(cfg.arena_bytes));
        let dev = &ctx.device;
        let mut enc = dev.create_command_encoder(&wgpu::CommandEncoderDescriptor {
            label: Some("grow pool"),
        });
        let mut bigger = |old: &wgpu::Buffer, what: &'static str, size: u64| {
            let b = dev.create_buffer(&wgpu::BufferDescriptor {
                label: Some(what),
                size,
                usage: old.usage(),
                mapped_at_creation: false,
            });
            enc.copy_buffer_to_buffer(old, 0, &b, 0, old.size());
            b
        };
        let masks = bigger(&self.masks, "brick masks", slots as u64 * 64);
        let meta = bigger(&self.meta, "brick metadata", slots as u64 * META_BYTES);
        let arena_buf = bigger(&self.arena, "material arena", arena as u64);
        let last_seen = bigger(&self.last_seen, "last seen", slots as u64 * 4);
        ctx.queue.submit([enc.finish()]);
        self.masks = masks;
        self.meta = meta;
        self.arena = arena_buf;
        self.last_seen = last_seen;
        self.slots = slots;
        res.cfg.pool_slots = slots;
        res.cfg.arena_bytes = arena;
        res.last_seen.resize(slots as usize, 0);
        true
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
    /// coarse levels (16 and 32 voxels per cell) are refreshed. Only meaningful when streaming.
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
            .write_buffer(&self.coarse, 0, bytemuck::cast_slice(&coarse_words(grid)));
    }
}

#[cfg(test)]
mod tests;
