//! Coupling columns and voxels.
//!
//! At start, the `ground` channel is read from the bricks (the height of the
//! top solid voxel of each column). After each step, the columns of changed
//! tiles are written back: solid below `floor(ground)` (new ground becomes
//! sediment), snow above it for `floor(snow)` voxels, and water up to
//! `round(ground + snow + water)` where the water is at least half a voxel
//! deep (a dry column never shows water, whatever its ground's fraction).
//! Every surface is clamped into the world's height, so no channel value
//! can make the write-back allocate bricks outside the world. Only voxels
//! between a column's own old and new surfaces are touched, never below its
//! topmost solid voxel (a column cannot see a cave or an overhang's
//! underside, so it must not write there), and above its old ground only
//! air and the water and snow it wrote below its old top are changed: a
//! voxel another script placed in its way is kept. All of it goes through
//! [`BrickStore::edit_brick`], so every change is recorded as a dirty brick
//! for the renderer.

use glam::{IVec2, IVec3};
use rustc_hash::FxHashMap;

use crate::sim::channels::ChannelStore;
use crate::sim::tile::{TILE, TILE_CELLS, TileCoord, cell};
use crate::world::{BRICK_EDGE, BrickStore, voxel_index};

/// Material of water voxels written by the simulation.
pub const WATER: u8 = 252;
/// Material of snow voxels.
pub const SNOW: u8 = 253;
/// Material of ground deposited by erosion.
pub const SEDIMENT: u8 = 254;

/// Colours of the simulation materials (bricks already holding them get
/// new LOD colours, recorded as modified).
pub fn set_palette(store: &mut BrickStore) {
    let mut p = store.palette().clone();
    p.set(WATER, [64, 118, 196]);
    p.set(SNOW, [246, 248, 252]);
    p.set(SEDIMENT, [168, 140, 100]);
    store.set_palette(p);
}

/// Height of the top solid voxel + 1 of every column of tile `t`, scanning
/// down from `y_top` (0 where the column is empty).
pub fn ground_of_tile(store: &BrickStore, t: TileCoord, y_top: i32) -> [f64; TILE_CELLS] {
    let mut out = [0.0; TILE_CELLS];
    let mut found = [false; TILE_CELLS];
    let mut remaining = TILE_CELLS;
    let mut by = (y_top - 1).div_euclid(BRICK_EDGE);
    let mut dense = [0u8; 512];
    while remaining > 0 && by >= 0 {
        let b = IVec3::new(t.x, by, t.y);
        store.read_dense(b, &mut dense);
        for z in 0..TILE {
            for x in 0..TILE {
                let c = cell(x, z);
                if found[c] {
                    continue;
                }
                for ly in (0..BRICK_EDGE).rev() {
                    if dense[voxel_index(x, ly, z)] != 0 {
                        out[c] = (by * BRICK_EDGE + ly + 1) as f64;
                        found[c] = true;
                        remaining -= 1;
                        break;
                    }
                }
            }
        }
        by -= 1;
    }
    out
}

/// Surfaces last written per column: (ground top, snow top, water top), in voxels.
#[derive(Debug, Default)]
pub struct ColumnSync {
    last: FxHashMap<TileCoord, [[i32; 3]; TILE_CELLS]>,
    /// The world's top (voxels); surfaces are clamped into `[0, top]`.
    top: i32,
    /// Per tile, the cells outside the world (bit `cell(x, z)`): a world
    /// whose size is not a multiple of the tile has partial tiles, whose
    /// outer columns are simulated but never written into voxels.
    outside: FxHashMap<TileCoord, u64>,
    /// Per tile, for the next [`write`](Self::write) only: per cell, the
    /// height below which water and snow are another's, left as they are
    /// (set by [`follow_ground`](Self::follow_ground) where a voxel script
    /// holds the water or snow found where the ground was).
    theirs: FxHashMap<TileCoord, [i32; TILE_CELLS]>,
}

/// Whether voxel `m` at height `y`, at or above a column's old ground, is
/// the column's to change given its old surfaces `old`: air, or the water
/// and snow it wrote there, below its old top. The materials alone do not
/// say it: a voxel script's water (water3d's material is the column's
/// `water`) above the column's top is another's (review).
fn is_column_voxel(m: u8, y: i32, old: [i32; 3]) -> bool {
    m == 0 || ((m == WATER || m == SNOW) && y < old[2].max(old[0]))
}

/// Whether a voxel of material `m` is ground to a column: anything but
/// air and the water and snow the columns draw (a voxel script's water is
/// the columns' material too, and is not ground either).
pub fn is_ground(m: u8) -> bool {
    m != 0 && m != WATER && m != SNOW
}

/// Water shallower than this many voxels is not drawn.
pub const MIN_WATER_DRAWN: f64 = 0.5;

/// The surfaces (ground top, snow top, water top) of a column with ground
/// `g`, snow `s` and water `w`, each clamped into `[0, top]`.
pub fn levels(g: f64, s: f64, w: f64, top: i32) -> [i32; 3] {
    // A world whose voxels all lie below 0 has a negative top (a .vox
    // model can): its surfaces stay at 0 (regression: `clamp` panicked).
    let clamp = |v: f64| v.clamp(0.0, top.max(0) as f64) as i32;
    let gt = clamp(g.floor());
    let st = clamp((g + s).floor()).max(gt);
    let wt = if w >= MIN_WATER_DRAWN {
        clamp((g + s + w + 0.5).floor()).max(st)
    } else {
        st
    };
    [gt, st, wt]
}

impl ColumnSync {
    /// A record for a world whose voxels end below `top`.
    pub fn new(top: i32) -> Self {
        ColumnSync {
            last: FxHashMap::default(),
            top,
            outside: FxHashMap::default(),
            theirs: FxHashMap::default(),
        }
    }

    /// Mark the cells of tile `t` that lie outside the world (bit
    /// `cell(x, z)` of `mask`): they are never written.
    pub fn set_outside(&mut self, t: TileCoord, mask: u64) {
        self.outside.insert(t, mask);
    }

    /// Remember the initial surfaces (the world as built) of tile `t`.
    pub fn record(&mut self, t: TileCoord, ground: &[f64; TILE_CELLS]) {
        let mut l = [[0; 3]; TILE_CELLS];
        for (c, g) in ground.iter().enumerate() {
            l[c] = levels(*g, 0.0, 0.0, self.top);
        }
        self.last.insert(t, l);
    }

    /// Set tile `t`'s record from the channels, as a step's write-back
    /// leaves it (used after a resume replaced the channels).
    pub fn resync(&mut self, channels: &ChannelStore, t: TileCoord) {
        let get = |n: &str| channels.find(n).and_then(|id| channels.get(t, id)).copied();
        // A tile whose ground is all zero holds no ground array: its ground
        // is zeros, not unknown (regression: the resync skipped it, and a
        // resumed run left water voxels a run that never stopped cleared).
        let g = get("ground").unwrap_or([0.0; TILE_CELLS]);
        let s = get("snow").unwrap_or([0.0; TILE_CELLS]);
        let w = get("water").unwrap_or([0.0; TILE_CELLS]);
        let mut l = [[0; 3]; TILE_CELLS];
        for c in 0..TILE_CELLS {
            l[c] = levels(g[c], s[c], w[c], self.top);
        }
        self.last.insert(t, l);
    }

    /// After something other than the columns changed the voxels of
    /// `tiles` (a voxel script's step, a box placed at the first start),
    /// give every column whose ground moved its new height in the `ground`
    /// channel, and record its surfaces as the voxels now hold them, so
    /// that the next [`write`](Self::write) redraws its snow and water on
    /// the new ground. Returns the tiles whose ground moved.
    ///
    /// A column's ground is the run of ground voxels ([`is_ground`]) that
    /// holds its old top: voxels piled on it raise it (sand sinking into a
    /// lake displaces the lake's water), voxels dug from it lower it, and
    /// what floats above it behind air or water (a bridge, a drop of lava
    /// on a lake) is not ground to it, as an overhang is not. The
    /// fractional part erosion gave the ground is dropped where it moves.
    /// The columns used to read the ground once, at the start, so their
    /// water flowed through sand a voxel script had piled as if it were
    /// not there (a known gap since the modder probe).
    ///
    /// Water and snow voxels found where the ground was (ground that
    /// melted, or a pit a script dug and filled in one step) join the
    /// column's `water` and `snow`, so the redraw puts them back on the new
    /// ground: a column owns the water and snow under its old top, and its
    /// write-back erased them (review). Those a voxel script holds in its
    /// own channel (`held`: water3d's fill) stay that script's, untouched
    /// by the next write, and are not counted twice (second review).
    pub fn follow_ground(
        &mut self,
        store: &BrickStore,
        channels: &mut ChannelStore,
        tiles: &[TileCoord],
        held: impl Fn(IVec3, u8) -> bool,
    ) -> Vec<TileCoord> {
        let Some(g_id) = channels.find("ground") else {
            return Vec::new();
        };
        let top = self.top.max(0);
        let ground_at = |x: i32, y: i32, z: i32| {
            (0..top).contains(&y) && is_ground(store.voxel(IVec3::new(x, y, z)))
        };
        let mut moved = Vec::new();
        for &t in tiles {
            let Some(rec) = self.last.get_mut(&t) else {
                continue;
            };
            let outside = self.outside.get(&t).copied().unwrap_or(0);
            let mut ground = None;
            // Water and snow voxels found where the ground was, per cell,
            // and the height below which a voxel script holds some.
            let (mut water, mut snow) = ([0.0; TILE_CELLS], [0.0; TILE_CELLS]);
            let mut theirs: Option<[i32; TILE_CELLS]> = None;
            for z in 0..TILE {
                for x in 0..TILE {
                    let c = cell(x, z);
                    if outside >> c & 1 != 0 {
                        continue;
                    }
                    let (wx, wz) = (t.x * TILE + x, t.y * TILE + z);
                    let was = rec[c][0];
                    let mut now = was;
                    if now > 0 && !ground_at(wx, now - 1, wz) {
                        while now > 0 && !ground_at(wx, now - 1, wz) {
                            now -= 1;
                            let p = IVec3::new(wx, now, wz);
                            let m = store.voxel(p);
                            if (m == WATER || m == SNOW) && held(p, m) {
                                theirs.get_or_insert([i32::MIN; TILE_CELLS])[c] = was;
                            } else if m == WATER {
                                water[c] += 1.0;
                            } else if m == SNOW {
                                snow[c] += 1.0;
                            }
                        }
                    } else {
                        while ground_at(wx, now, wz) {
                            now += 1;
                        }
                    }
                    if now == was {
                        continue;
                    }
                    let g = ground.get_or_insert_with(|| {
                        channels.get(t, g_id).copied().unwrap_or([0.0; TILE_CELLS])
                    });
                    g[c] = now as f64;
                    rec[c] = [now, rec[c][1].max(now), rec[c][2].max(now)];
                }
            }
            for (name, found) in [("water", &water), ("snow", &snow)] {
                if found.iter().any(|&v| v > 0.0) {
                    let id = channels.channel(name);
                    let mut have = channels.get(t, id).copied().unwrap_or([0.0; TILE_CELLS]);
                    for (h, f) in have.iter_mut().zip(found) {
                        *h += f;
                    }
                    channels.set(t, id, &have);
                }
            }
            if let Some(f) = theirs {
                self.theirs.insert(t, f);
            }
            if let Some(g) = ground {
                channels.set(t, g_id, &g);
                moved.push(t);
            }
        }
        moved
    }

    /// Write the columns of `tiles` into `store`. Returns how many bricks changed.
    pub fn write(
        &mut self,
        channels: &ChannelStore,
        tiles: &[TileCoord],
        store: &mut BrickStore,
    ) -> usize {
        let (g_id, s_id, w_id) = (
            channels.find("ground"),
            channels.find("snow"),
            channels.find("water"),
        );
        let get = |id: Option<crate::sim::ChannelId>, t: TileCoord| {
            id.and_then(|id| channels.get(t, id)).copied()
        };
        let mut edited = 0;
        for &t in tiles {
            let g = get(g_id, t);
            let s = get(s_id, t).unwrap_or([0.0; TILE_CELLS]);
            let w = get(w_id, t).unwrap_or([0.0; TILE_CELLS]);
            let old = self.last.get(&t).copied().unwrap_or([[0; 3]; TILE_CELLS]);
            let theirs = self.theirs.remove(&t).unwrap_or([i32::MIN; TILE_CELLS]);
            let mut new = old;
            let (mut lo, mut hi) = (i32::MAX, i32::MIN);
            let outside = self.outside.get(&t).copied().unwrap_or(0);
            for c in 0..TILE_CELLS {
                if outside >> c & 1 != 0 {
                    continue;
                }
                let gv = g.map_or(old[c][0] as f64, |g| g[c]);
                new[c] = levels(gv, s[c], w[c], self.top);
                if new[c] != old[c] {
                    lo = lo.min(old[c][0].min(new[c][0]));
                    hi = hi.max(old[c][2].max(new[c][2]));
                }
            }
            if lo > hi {
                continue;
            }
            for by in lo.div_euclid(BRICK_EDGE)..=(hi - 1).max(lo).div_euclid(BRICK_EDGE) {
                let b = IVec3::new(t.x, by, t.y);
                let y0 = by * BRICK_EDGE;
                let changed = store.edit_brick(b, |d| {
                    for z in 0..TILE {
                        for x in 0..TILE {
                            let c = cell(x, z);
                            if new[c] == old[c] {
                                continue;
                            }
                            let [gt, st, wt] = new[c];
                            // Only this column's own span between its old and
                            // new surfaces: the tile's span reaches lower where
                            // another column's ground is lower, and filling
                            // there would fill caves and overhangs' undersides.
                            let span = old[c][0].min(gt)..old[c][2].max(old[c][0]).max(wt);
                            for ly in 0..BRICK_EDGE {
                                let y = y0 + ly;
                                if !span.contains(&y) {
                                    continue;
                                }
                                let i = voxel_index(x, ly, z);
                                let cur = d[i];
                                // Above its old ground, a column owns only
                                // air and what it writes: a voxel another
                                // script placed there is kept (regression,
                                // modder probe: water rising over sand a
                                // voxel script had piled turned it to water,
                                // and falling again cleared it).
                                // And water or snow a voxel script holds
                                // where the ground was (second review).
                                let held = y < theirs[c] && (cur == WATER || cur == SNOW);
                                if y >= old[c][0] && (held || !is_column_voxel(cur, y, old[c])) {
                                    continue;
                                }
                                d[i] = if y < gt {
                                    if cur == 0 || cur == WATER || cur == SNOW {
                                        SEDIMENT
                                    } else {
                                        cur
                                    }
                                } else if y < st {
                                    SNOW
                                } else if y < wt {
                                    WATER
                                } else if y < old[c][2].max(old[c][0])
                                    || cur == WATER
                                    || cur == SNOW
                                    || cur == SEDIMENT
                                {
                                    0
                                } else {
                                    cur
                                };
                            }
                        }
                    }
                });
                edited += changed as usize;
            }
            self.last.insert(t, new);
        }
        edited
    }
}

/// The cells of tile `t` whose columns lie outside the voxel box `[lo, hi)`
/// (bit `cell(x, z)`; 0 for a tile wholly inside).
pub fn outside_mask(t: TileCoord, lo: IVec3, hi: IVec3) -> u64 {
    let mut m = 0u64;
    for z in 0..TILE {
        for x in 0..TILE {
            let (wx, wz) = (t.x * TILE + x, t.y * TILE + z);
            if wx < lo.x || wx >= hi.x || wz < lo.z || wz >= hi.z {
                m |= 1 << cell(x, z);
            }
        }
    }
    m
}

/// Tiles covering the voxel box `[lo, hi)` (x and z).
pub fn tiles_of(lo: IVec3, hi: IVec3) -> (TileCoord, TileCoord) {
    (
        IVec2::new(lo.x.div_euclid(TILE), lo.z.div_euclid(TILE)),
        IVec2::new(
            (hi.x - 1).div_euclid(TILE) + 1,
            (hi.z - 1).div_euclid(TILE) + 1,
        ),
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::world::Palette;

    /// A resumed tile with zero ground (no ground array) gets the record a
    /// run that never stopped has.
    #[test]
    fn a_resume_resyncs_tiles_whose_ground_is_zero() {
        let t = TileCoord::new(0, 0);
        let mut ch = ChannelStore::default();
        ch.channel("ground");
        let w = ch.channel("water");
        ch.set(t, w, &[3.0; TILE_CELLS]);
        // Uninterrupted: built with zero ground, then stepped and written.
        let mut ran = ColumnSync::new(32);
        ran.record(t, &[0.0; TILE_CELLS]);
        ran.write(&ch, &[t], &mut BrickStore::new(Palette::grey_ramp()));
        // Resumed: built with zero ground, then the stored channels resynced.
        let mut resumed = ColumnSync::new(32);
        resumed.record(t, &[0.0; TILE_CELLS]);
        resumed.resync(&ch, t);
        assert_eq!(ran.last.get(&t), resumed.last.get(&t));
    }

    /// The ground follows the voxels others change: piled on, dug out, and
    /// sunk into the column's water it moves; floating above air or water,
    /// or made of water or snow, it does not. The water is then redrawn on
    /// the new ground (known gap: the ground was read once, at the start).
    #[test]
    fn the_ground_follows_voxels_piled_on_or_dug_from_it() {
        const SAND: u8 = 7;
        let t = TileCoord::new(0, 0);
        let mut ch = ChannelStore::default();
        let g = ch.channel("ground");
        let w = ch.channel("water");
        let mut ground = [4.0; TILE_CELLS];
        ground[cell(6, 6)] = 4.7; // erosion's fraction, kept where still
        ch.set(t, g, &ground);
        let mut water = [0.0; TILE_CELLS];
        water[cell(4, 4)] = 3.0;
        ch.set(t, w, &water);
        let mut store = BrickStore::new(Palette::grey_ramp());
        store.fill_box(IVec3::ZERO, IVec3::new(8, 4, 8), 1);
        let mut sync = ColumnSync::new(32);
        sync.record(t, &ground);
        sync.write(&ch, &[t], &mut store);
        assert_eq!(store.voxel(IVec3::new(4, 6, 4)), WATER);
        // Nothing moved: nothing changes.
        let none = |_: IVec3, _: u8| false;
        assert!(sync.follow_ground(&store, &mut ch, &[t], none).is_empty());
        store.set_voxel(IVec3::new(1, 4, 1), SAND); // piled, two high
        store.set_voxel(IVec3::new(1, 5, 1), SAND);
        store.set_voxel(IVec3::new(2, 3, 2), 0); // dug, two deep
        store.set_voxel(IVec3::new(2, 2, 2), 0);
        store.set_voxel(IVec3::new(3, 6, 3), SAND); // floating over air
        store.set_voxel(IVec3::new(4, 4, 4), SAND); // sunk into the water
        store.set_voxel(IVec3::new(4, 9, 4), SAND); // floating above it
        store.set_voxel(IVec3::new(5, 4, 5), SNOW); // not ground
        store.set_voxel(IVec3::new(0, 4, 7), WATER); // not ground either
        store.set_voxel(IVec3::new(7, 3, 7), WATER); // ground that melted
        // Water a voxel script holds in its own channel (water3d's).
        let held_at = IVec3::new(6, 3, 1);
        store.set_voxel(held_at, WATER);
        let held = |p: IVec3, m: u8| p == held_at && m == WATER;
        assert_eq!(sync.follow_ground(&store, &mut ch, &[t], held), vec![t]);
        let now = *ch.get(t, g).unwrap();
        assert_eq!(now[cell(1, 1)], 6.0);
        assert_eq!(now[cell(2, 2)], 2.0);
        assert_eq!(now[cell(4, 4)], 5.0);
        for (x, z) in [(3, 3), (5, 5), (0, 7), (0, 0)] {
            assert_eq!(now[cell(x, z)], 4.0, "column ({x}, {z})");
        }
        assert_eq!(now[cell(6, 6)], 4.7);
        assert_eq!(now[cell(7, 7)], 3.0);
        // The melt joined the column's water (review: the redraw erased it).
        assert_eq!(ch.get(t, w).unwrap()[cell(7, 7)], 1.0);
        // The held water is not the column's: not counted, and left.
        assert_eq!(now[cell(6, 1)], 3.0);
        assert_eq!(ch.get(t, w).unwrap()[cell(6, 1)], 0.0);
        // The water is redrawn on the sand it sank under: 3 deep from 5.
        sync.write(&ch, &[t], &mut store);
        for y in 5..8 {
            assert_eq!(store.voxel(IVec3::new(4, y, 4)), WATER, "y = {y}");
        }
        assert_eq!(store.voxel(IVec3::new(4, 8, 4)), 0);
        assert_eq!(store.voxel(IVec3::new(7, 3, 7)), WATER);
        assert_eq!(store.voxel(IVec3::new(7, 4, 7)), 0);
        assert_eq!(
            store.voxel(held_at),
            WATER,
            "the write-back erased held water"
        );
        // The record is what a resume would make of the channels.
        let mut resumed = ColumnSync::new(32);
        resumed.resync(&ch, t);
        assert_eq!(sync.last.get(&t), resumed.last.get(&t));
        assert!(sync.follow_ground(&store, &mut ch, &[t], none).is_empty());
    }

    /// Regression (modder probe): a voxel script's sand on a column's
    /// ground was turned to water when the column's water rose over it,
    /// and cleared when the water fell: the write-back changes only air
    /// and its own materials above the old ground.
    #[test]
    fn the_write_back_keeps_voxels_another_script_placed() {
        const SAND: u8 = 7;
        let t = TileCoord::new(0, 0);
        let mut ch = ChannelStore::default();
        let g = ch.channel("ground");
        let w = ch.channel("water");
        ch.set(t, g, &[4.0; TILE_CELLS]);
        let mut store = BrickStore::new(Palette::grey_ramp());
        store.edit_brick(IVec3::ZERO, |d| {
            for z in 0..TILE {
                for x in 0..TILE {
                    for y in 0..4 {
                        d[voxel_index(x, y, z)] = 1;
                    }
                }
            }
            // Sand on the ground of column (2, 3), two voxels high.
            d[voxel_index(2, 4, 3)] = SAND;
            d[voxel_index(2, 5, 3)] = SAND;
        });
        let mut sync = ColumnSync::new(32);
        sync.record(t, &[4.0; TILE_CELLS]);
        let at = |store: &BrickStore, x: i32, y: i32, z: i32| {
            let mut d = [0u8; 512];
            store.read_dense(IVec3::ZERO, &mut d);
            d[voxel_index(x, y, z)]
        };
        // Water 3 deep rises over the sand: the sand stays, the water fills
        // around it, and the column beside it fills.
        ch.set(t, w, &[3.0; TILE_CELLS]);
        sync.write(&ch, &[t], &mut store);
        assert_eq!(at(&store, 2, 4, 3), SAND);
        assert_eq!(at(&store, 2, 5, 3), SAND);
        assert_eq!(at(&store, 2, 6, 3), WATER);
        assert_eq!(at(&store, 1, 5, 3), WATER);
        // The water drains away: the sand is still there, the water gone.
        ch.set(t, w, &[0.0; TILE_CELLS]);
        sync.write(&ch, &[t], &mut store);
        assert_eq!(at(&store, 2, 4, 3), SAND);
        assert_eq!(at(&store, 2, 5, 3), SAND);
        assert_eq!(at(&store, 2, 6, 3), 0);
        assert_eq!(at(&store, 1, 5, 3), 0);
        // A voxel script's water above the column's top (water3d uses the
        // same material) is not the column's either: deposition under it
        // does not turn it to sediment (review).
        store.edit_brick(IVec3::ZERO, |d| d[voxel_index(5, 5, 5)] = WATER);
        let mut g6 = [4.0; TILE_CELLS];
        g6[cell(5, 5)] = 6.0;
        ch.set(t, g, &g6);
        sync.write(&ch, &[t], &mut store);
        assert_eq!(at(&store, 5, 4, 5), SEDIMENT, "the column's deposit");
        assert_eq!(at(&store, 5, 5, 5), WATER, "another's water is kept");
        ch.set(t, g, &[4.0; TILE_CELLS]);
        sync.write(&ch, &[t], &mut store);
        // Erosion takes a voxel of ground from under it: the column's own
        // ground changes as before, and the sand is left where it was.
        ch.set(t, g, &[3.0; TILE_CELLS]);
        sync.write(&ch, &[t], &mut store);
        assert_eq!(at(&store, 2, 3, 3), 0);
        assert_eq!(at(&store, 2, 4, 3), SAND);
    }
}
