//! The sparse brick store: the world's voxels, keyed by unbounded signed brick
//! coordinates.
//!
//! Empty bricks cost nothing (no entry), uniform bricks cost one map entry and
//! no brick storage, and mixed bricks live in the [`BrickPool`]. Every edit
//! goes through [`BrickStore::edit_brick`] or [`BrickStore::set_brick`], which
//! stamp the brick's edit tick and append it to the modified list: there is no
//! way to change a voxel without the change being recorded.

use glam::{DVec3, IVec3};
use rustc_hash::{FxHashMap, FxHashSet};

use super::brick::{BRICK_EDGE, BRICK_VOXELS, BrickContent, voxel_index};
use super::palette::Palette;
use super::pool::{BrickId, BrickPool};

/// What the store holds at one brick coordinate.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Cell {
    /// No solid voxel.
    Empty,
    /// All voxels solid with one material.
    Uniform(u8),
    /// A mixed brick in the pool.
    Mixed(BrickId),
}

#[derive(Clone, Copy, Debug)]
struct Entry {
    cell: Cell,
    edit_tick: u64,
}

/// Brick coordinate containing voxel `p` (floor division, right for negatives).
#[inline]
pub fn brick_of(p: IVec3) -> IVec3 {
    IVec3::new(
        p.x.div_euclid(BRICK_EDGE),
        p.y.div_euclid(BRICK_EDGE),
        p.z.div_euclid(BRICK_EDGE),
    )
}

/// The sparse world.
///
/// ```
/// use brickworld::world::{BrickStore, Palette};
/// use glam::IVec3;
/// let mut store = BrickStore::new(Palette::grey_ramp());
/// store.set_voxel(IVec3::new(-1, 5, 9), 42);
/// assert_eq!(store.voxel(IVec3::new(-1, 5, 9)), 42);
/// // The edit was recorded: brick (-1, 0, 1) is in the modified list.
/// assert_eq!(store.take_modified(), vec![IVec3::new(-1, 0, 1)]);
/// ```
#[derive(Clone, Debug)]
pub struct BrickStore {
    entries: FxHashMap<IVec3, Entry>,
    pool: BrickPool,
    palette: Palette,
    tick: u64,
    modified: Vec<IVec3>,
    modified_set: FxHashSet<IVec3>,
}

impl BrickStore {
    /// An empty world coloured by `palette`.
    pub fn new(palette: Palette) -> Self {
        BrickStore {
            entries: FxHashMap::default(),
            pool: BrickPool::default(),
            palette,
            tick: 0,
            modified: Vec::new(),
            modified_set: FxHashSet::default(),
        }
    }

    /// The palette materials index into.
    pub fn palette(&self) -> &Palette {
        &self.palette
    }

    /// Give the store `palette` (colours only; bricks keep their material
    /// indices). The mixed bricks holding a material whose colour changed
    /// get new LOD colours and are recorded as modified
    /// ([`recolour`](Self::recolour)); returns how many. The only way to
    /// change colours, so that no LOD colour goes stale unrecorded (code-
    /// habits audit: a `&mut Palette` left that to each caller).
    pub fn set_palette(&mut self, palette: Palette) -> usize {
        let mut changed = [false; 256];
        for (id, c) in changed.iter_mut().enumerate().skip(1) {
            *c = self.palette.rgb(id as u8) != palette.rgb(id as u8);
        }
        self.palette = palette;
        self.recolour(&changed)
    }

    /// The pool holding mixed bricks.
    pub fn pool(&self) -> &BrickPool {
        &self.pool
    }

    /// What is stored at brick coordinate `b`.
    #[inline]
    pub fn cell(&self, b: IVec3) -> Cell {
        self.entries.get(&b).map_or(Cell::Empty, |e| e.cell)
    }

    /// Tick of the last edit that changed brick `b` (0 if never edited).
    pub fn edit_tick(&self, b: IVec3) -> u64 {
        self.entries.get(&b).map_or(0, |e| e.edit_tick)
    }

    /// The current edit tick; it advances once per edit operation.
    pub fn tick(&self) -> u64 {
        self.tick
    }

    /// Material of voxel `p` (0 = empty).
    pub fn voxel(&self, p: IVec3) -> u8 {
        let b = brick_of(p);
        let l = p - b * BRICK_EDGE;
        match self.cell(b) {
            Cell::Empty => 0,
            Cell::Uniform(m) => m,
            Cell::Mixed(id) => self.pool.get(id).map_or(0, |br| br.material(l.x, l.y, l.z)),
        }
    }

    /// Dense materials of brick `b`.
    pub fn read_dense(&self, b: IVec3, out: &mut [u8; BRICK_VOXELS]) {
        match self.cell(b) {
            Cell::Empty => out.fill(0),
            Cell::Uniform(m) => out.fill(m),
            Cell::Mixed(id) => match self.pool.get(id) {
                Some(br) => br.to_dense(out),
                None => out.fill(0),
            },
        }
    }

    /// Brick `b`'s content, as [`set_brick`](Self::set_brick) takes it.
    pub fn content(&self, b: IVec3) -> BrickContent {
        match self.cell(b) {
            Cell::Empty => BrickContent::Empty,
            Cell::Uniform(m) => BrickContent::Uniform(m),
            Cell::Mixed(_) => {
                let mut dense = [0u8; BRICK_VOXELS];
                self.read_dense(b, &mut dense);
                BrickContent::from_dense(&dense, &self.palette)
            }
        }
    }

    /// Replace brick `b` wholesale and record the edit.
    pub fn set_brick(&mut self, b: IVec3, content: BrickContent) {
        self.tick += 1;
        self.put(b, content);
    }

    /// Edit brick `b` through a dense view. The brick is re-encoded and the
    /// edit recorded only if some voxel actually changed. Returns whether it did.
    pub fn edit_brick(&mut self, b: IVec3, f: impl FnOnce(&mut [u8; BRICK_VOXELS])) -> bool {
        self.tick += 1;
        self.edit_in_tick(b, f)
    }

    fn edit_in_tick(&mut self, b: IVec3, f: impl FnOnce(&mut [u8; BRICK_VOXELS])) -> bool {
        let mut before = [0u8; BRICK_VOXELS];
        self.read_dense(b, &mut before);
        let mut after = before;
        f(&mut after);
        if after == before {
            return false;
        }
        let content = BrickContent::from_dense(&after, &self.palette);
        self.put(b, content);
        true
    }

    /// Store `content` at `b` in the current tick, recording the edit.
    fn put(&mut self, b: IVec3, content: BrickContent) {
        let old = self.entries.get(&b).map(|e| e.cell);
        let new_cell = match (old, content) {
            (Some(Cell::Mixed(id)), BrickContent::Mixed(brick)) => {
                self.pool.replace(id, brick);
                Cell::Mixed(id)
            }
            (old, content) => {
                if let Some(Cell::Mixed(id)) = old {
                    self.pool.remove(id);
                }
                match content {
                    BrickContent::Empty => Cell::Empty,
                    BrickContent::Uniform(m) => Cell::Uniform(m),
                    BrickContent::Mixed(brick) => Cell::Mixed(self.pool.insert(brick)),
                }
            }
        };
        if self.pool.arena_fragmented() {
            // Amortised O(1) a freed byte; slots and ids stay.
            self.pool.compact_arena();
        }
        if new_cell == Cell::Empty {
            self.entries.remove(&b);
        } else {
            self.entries.insert(
                b,
                Entry {
                    cell: new_cell,
                    edit_tick: self.tick,
                },
            );
        }
        if self.modified_set.insert(b) {
            self.modified.push(b);
        }
    }

    /// Set one voxel.
    pub fn set_voxel(&mut self, p: IVec3, material: u8) {
        let b = brick_of(p);
        let l = p - b * BRICK_EDGE;
        self.edit_brick(b, |d| d[voxel_index(l.x, l.y, l.z)] = material);
    }

    /// Fill the voxel box `[min, max)` with `material` (0 clears it).
    pub fn fill_box(&mut self, min: IVec3, max: IVec3, material: u8) {
        if min.cmpge(max).any() {
            return;
        }
        self.tick += 1;
        let bmin = brick_of(min);
        let bmax = brick_of(max - IVec3::ONE);
        for bz in bmin.z..=bmax.z {
            for by in bmin.y..=bmax.y {
                for bx in bmin.x..=bmax.x {
                    let b = IVec3::new(bx, by, bz);
                    let lo = b * BRICK_EDGE;
                    let hi = lo + IVec3::splat(BRICK_EDGE);
                    if min.cmple(lo).all() && max.cmpge(hi).all() {
                        let content = if material == 0 {
                            BrickContent::Empty
                        } else {
                            BrickContent::Uniform(material)
                        };
                        if self.cell_matches(b, &content) {
                            continue;
                        }
                        self.put(b, content);
                        continue;
                    }
                    let a = (min - lo).max(IVec3::ZERO);
                    let c = (max - lo).min(IVec3::splat(BRICK_EDGE));
                    self.edit_in_tick(b, |d| {
                        for z in a.z..c.z {
                            for y in a.y..c.y {
                                for x in a.x..c.x {
                                    d[voxel_index(x, y, z)] = material;
                                }
                            }
                        }
                    });
                }
            }
        }
    }

    fn cell_matches(&self, b: IVec3, content: &BrickContent) -> bool {
        matches!((self.cell(b), content), (Cell::Empty, BrickContent::Empty))
            || matches!((self.cell(b), content), (Cell::Uniform(a), BrickContent::Uniform(c)) if a == *c)
    }

    /// Fill every voxel whose centre lies within `radius` of `center`.
    pub fn fill_sphere(&mut self, center: DVec3, radius: f64, material: u8) {
        if radius.is_nan() || radius <= 0.0 || !center.is_finite() {
            return;
        }
        self.tick += 1;
        let lo = (center - DVec3::splat(radius)).floor().as_ivec3();
        let hi = (center + DVec3::splat(radius)).ceil().as_ivec3();
        let bmin = brick_of(lo);
        let bmax = brick_of(hi);
        let r2 = radius * radius;
        for bz in bmin.z..=bmax.z {
            for by in bmin.y..=bmax.y {
                for bx in bmin.x..=bmax.x {
                    let b = IVec3::new(bx, by, bz);
                    let base = b * BRICK_EDGE;
                    self.edit_in_tick(b, |d| {
                        for z in 0..BRICK_EDGE {
                            for y in 0..BRICK_EDGE {
                                for x in 0..BRICK_EDGE {
                                    let p = (base + IVec3::new(x, y, z)).as_dvec3() + 0.5;
                                    if p.distance_squared(center) <= r2 {
                                        d[voxel_index(x, y, z)] = material;
                                    }
                                }
                            }
                        }
                    });
                }
            }
        }
    }

    /// New LOD colours for the mixed bricks that hold a material `changed`
    /// names, after the palette gave it a new colour: a mixed brick's LOD
    /// colour is its voxels' mean colour in the palette (the grid's
    /// pointers and the GPU's stand-ins carry it). Each is recorded as
    /// modified (for the grid and the renderer) but takes no edit tick:
    /// its voxels are the same. Uniform bricks are left alone: their colour
    /// is their one material's, read from the palette. The bricks are found
    /// from their local palettes and their colours computed in parallel
    /// (a hostile probe's 593 000 bricks held the engine 1.7 s when each
    /// was re-encoded). Returns how many.
    fn recolour(&mut self, changed: &[bool; 256]) -> usize {
        use rayon::prelude::*;
        if !changed.iter().any(|&c| c) {
            return 0;
        }
        let cells: Vec<(IVec3, BrickId)> = self
            .entries
            .iter()
            .filter_map(|(b, e)| match e.cell {
                Cell::Mixed(id) => Some((*b, id)),
                _ => None,
            })
            .collect();
        let (pool, palette) = (&self.pool, &self.palette);
        let mut mixed: Vec<(IVec3, BrickId, u16)> = cells
            .into_par_iter()
            .filter_map(|(b, id)| {
                let br = pool.get(id)?;
                br.holds_any(changed)
                    .then(|| (b, id, br.lod565_with(palette)))
            })
            .collect();
        mixed.sort_by_key(|(b, _, _)| (b.z, b.y, b.x));
        for &(b, id, lod565) in &mixed {
            self.pool.set_lod565(id, lod565);
            if self.modified_set.insert(b) {
                self.modified.push(b);
            }
        }
        mixed.len()
    }

    /// Drain the list of bricks changed since the last call, each once, in
    /// the order they were first changed.
    pub fn take_modified(&mut self) -> Vec<IVec3> {
        self.modified_set.clear();
        std::mem::take(&mut self.modified)
    }

    /// Every non-empty brick coordinate and its cell, in no particular order.
    pub fn iter(&self) -> impl Iterator<Item = (IVec3, Cell)> + '_ {
        self.entries.iter().map(|(k, e)| (*k, e.cell))
    }

    /// Number of non-empty bricks (uniform plus mixed).
    pub fn non_empty_bricks(&self) -> usize {
        self.entries.len()
    }

    /// Total solid voxels.
    pub fn solid_voxels(&self) -> u64 {
        self.entries
            .values()
            .map(|e| match e.cell {
                Cell::Empty => 0,
                Cell::Uniform(_) => BRICK_VOXELS as u64,
                Cell::Mixed(id) => self.pool.get(id).map_or(0, |b| b.solid_voxels() as u64),
            })
            .sum()
    }

    /// Inclusive brick-coordinate bounds of the non-empty bricks.
    pub fn brick_bounds(&self) -> Option<(IVec3, IVec3)> {
        let mut it = self.entries.keys();
        let first = *it.next()?;
        Some(it.fold((first, first), |(lo, hi), &k| (lo.min(k), hi.max(k))))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn recolour_gives_new_lod_colours_to_the_mixed_bricks_holding_a_material_and_keeps_their_voxels()
     {
        let mut s = BrickStore::new(Palette::grey_ramp());
        s.set_brick(IVec3::ZERO, BrickContent::Uniform(5));
        s.set_voxel(IVec3::new(8, 0, 0), 5); // mixed, holds 5
        s.set_voxel(IVec3::new(9, 0, 0), 7); // two materials
        s.set_voxel(IVec3::new(16, 0, 0), 6); // mixed, does not
        s.set_voxel(IVec3::new(24, 0, 0), 6); // two materials, neither 5
        s.set_voxel(IVec3::new(25, 0, 0), 7);
        s.take_modified();
        let ticks: Vec<u64> = (0..3).map(|x| s.edit_tick(IVec3::new(x, 0, 0))).collect();
        let id = |s: &BrickStore, x| match s.cell(IVec3::new(x, 0, 0)) {
            Cell::Mixed(id) => id,
            c => panic!("{c:?}"),
        };
        let before = s.pool().get(id(&s, 1)).unwrap().lod_rgb();
        let mut dense = [0u8; BRICK_VOXELS];
        s.read_dense(IVec3::X, &mut dense);
        let mut p = s.palette().clone();
        p.set(5, [250, 10, 10]);
        assert_eq!(s.set_palette(p.clone()), 1, "the mixed brick that holds 5");
        assert_eq!(s.take_modified(), vec![IVec3::X]);
        assert_eq!(s.set_palette(p), 0, "no colour changed");
        let after = s.pool().get(id(&s, 1)).unwrap().lod_rgb();
        assert_ne!(after, before);
        // What a brick encoded afresh with the new palette holds.
        let mut fresh = BrickStore::new(s.palette().clone());
        fresh.set_brick(IVec3::X, s.content(IVec3::X));
        assert_eq!(after, fresh.pool().get(id(&fresh, 1)).unwrap().lod_rgb());
        // A mixed brick of one material, too.
        let mut p = s.palette().clone();
        p.set(6, [3, 200, 90]);
        assert_eq!(s.set_palette(p), 2);
        let mut fresh = BrickStore::new(s.palette().clone());
        fresh.set_brick(IVec3::new(2, 0, 0), s.content(IVec3::new(2, 0, 0)));
        assert_eq!(
            s.pool().get(id(&s, 2)).unwrap().lod_rgb(),
            fresh.pool().get(id(&fresh, 2)).unwrap().lod_rgb()
        );
        let mut again = [0u8; BRICK_VOXELS];
        s.read_dense(IVec3::X, &mut again);
        assert_eq!(again, dense, "the voxels are the same");
        let now: Vec<u64> = (0..3).map(|x| s.edit_tick(IVec3::new(x, 0, 0))).collect();
        assert_eq!(now, ticks, "not an edit");
    }

    #[test]
    fn negative_coordinates_use_floor_division() {
        assert_eq!(brick_of(IVec3::new(-1, -8, -9)), IVec3::new(-1, -1, -2));
        let mut s = BrickStore::new(Palette::grey_ramp());
        s.set_voxel(IVec3::new(-1, -1, -1), 3);
        assert_eq!(s.voxel(IVec3::new(-1, -1, -1)), 3);
        assert_eq!(s.voxel(IVec3::new(7, 7, 7)), 0);
        assert_eq!(s.take_modified(), vec![IVec3::splat(-1)]);
    }

    #[test]
    fn every_edit_is_recorded_once_and_only_real_changes_count() {
        let mut s = BrickStore::new(Palette::grey_ramp());
        s.fill_box(IVec3::ZERO, IVec3::new(16, 8, 8), 2);
        s.set_voxel(IVec3::new(1, 1, 1), 9);
        let m = s.take_modified();
        assert_eq!(m, vec![IVec3::ZERO, IVec3::new(1, 0, 0)]);
        // Writing the same value again changes nothing and records nothing.
        s.set_voxel(IVec3::new(1, 1, 1), 9);
        s.fill_box(IVec3::new(8, 0, 0), IVec3::new(16, 8, 8), 2);
        assert!(s.take_modified().is_empty());
        assert!(s.edit_tick(IVec3::ZERO) > s.edit_tick(IVec3::new(1, 0, 0)));
    }

    /// Bricks whose material count changes move between arena size
    /// classes, and a freed block is reused only by its own class. A
    /// simulation that keeps adding materials (here 2, 3, … 120 per brick,
    /// over 64 bricks) used to leave every old class's blocks behind as
    /// holes: the arena grew to the sum of every class's peak. It now
    /// stays within twice what is live, and the voxels are kept.
    #[test]
    fn a_brick_arena_churned_through_size_classes_stays_bounded() {
        let mut s = BrickStore::new(Palette::grey_ramp());
        let dense = |k: usize, b: i32| -> [u8; BRICK_VOXELS] {
            std::array::from_fn(|i| 1 + ((i + b as usize) % k) as u8)
        };
        let mut most = 0;
        for k in 2..=120 {
            for b in 0..64 {
                let content = BrickContent::from_dense(&dense(k, b), s.palette());
                s.set_brick(IVec3::new(b, 0, 0), content);
            }
            s.take_modified();
            let live: usize = (0..s.pool().slots() as u32)
                .filter_map(|i| s.pool().arena_block(i).map(|(_, l)| l))
                .sum();
            let (_, _, arena) = s.pool().raw();
            assert!(
                arena.len() <= (2 * live).max(live + (64 << 10)),
                "{k} materials: arena {} bytes for {live} live",
                arena.len()
            );
            most = most.max(arena.len());
        }
        for b in 0..64 {
            let mut out = [0u8; BRICK_VOXELS];
            s.read_dense(IVec3::new(b, 0, 0), &mut out);
            assert_eq!(out, dense(120, b), "brick {b}");
        }
        assert!(most > 0);
    }

    #[test]
    fn uniform_bricks_take_no_pool_slot_and_clearing_frees_slots() {
        let mut s = BrickStore::new(Palette::grey_ramp());
        s.fill_box(IVec3::ZERO, IVec3::splat(8), 4);
        assert_eq!(s.cell(IVec3::ZERO), Cell::Uniform(4));
        assert_eq!(s.pool().len(), 0);
        s.set_voxel(IVec3::ZERO, 0);
        assert!(matches!(s.cell(IVec3::ZERO), Cell::Mixed(_)));
        assert_eq!(s.pool().len(), 1);
        s.fill_box(IVec3::ZERO, IVec3::splat(8), 0);
        assert_eq!(s.cell(IVec3::ZERO), Cell::Empty);
        assert_eq!(s.pool().len(), 0);
        assert_eq!(s.non_empty_bricks(), 0);
    }

    #[test]
    fn sphere_fill_matches_the_centre_rule() {
        let mut s = BrickStore::new(Palette::grey_ramp());
        let c = DVec3::new(-3.2, 4.0, 10.5);
        s.fill_sphere(c, 5.5, 7);
        let mut count = 0u64;
        for z in -20..20 {
            for y in -20..20 {
                for x in -20..20 {
                    let p = IVec3::new(x, y, z);
                    let inside = (p.as_dvec3() + 0.5).distance_squared(c) <= 5.5 * 5.5;
                    assert_eq!(s.voxel(p) == 7, inside, "{p}");
                    count += inside as u64;
                }
            }
        }
        assert_eq!(s.solid_voxels(), count);
    }
}
