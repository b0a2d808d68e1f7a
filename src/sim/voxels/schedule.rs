//! Which bricks a voxel step runs, and which sleep: the active set and
//! its quiet counters, waking on change and on parameter changes, the
//! per-brick material presence behind `only = {…}`, and the candidates of
//! each script (seeds dilated by what their passes can reach).
//!
//! A brick unchanged for [`SLEEP_AFTER`] steps sleeps; a change wakes its
//! 26 neighbours; bricks holding a `keep_awake` material never sleep. The
//! sleep state is part of a checkpoint, so a resumed run schedules what
//! the run that never stopped schedules.

use glam::IVec3;
use rustc_hash::FxHashSet;

use super::halo::{SELF, neighbour_offset};
use super::step::VoxelSim;
use crate::sim::script::VOXEL_CELLS;
use crate::world::{BRICK_EDGE, BrickStore};

/// Steps without change before a brick sleeps.
pub const SLEEP_AFTER: u8 = 2;

/// A 256-bit set of material ids.
pub(super) type MatSet = [u64; 4];

/// The set holding `ids`.
pub(super) fn set_of(ids: impl IntoIterator<Item = u8>) -> MatSet {
    let mut s = [0u64; 4];
    for i in ids {
        s[i as usize >> 6] |= 1 << (i & 63);
    }
    s
}

/// The materials present in a brick's dense cells.
pub(super) fn presence_of(d: &[u8; VOXEL_CELLS]) -> MatSet {
    set_of(d.iter().copied())
}

/// Whether two sets share a material.
fn meets(a: &MatSet, b: &MatSet) -> bool {
    a.iter().zip(b).any(|(x, y)| x & y != 0)
}

/// For each cell of a brick, the neighbours (bit n = neighbour n, the
/// brick itself included) that something in the cell can reach within
/// `passes` voxels: on each axis the brick itself, and the lower or upper
/// neighbour when the cell lies within `passes` of that face.
fn reach_masks(passes: usize) -> &'static [u32; VOXEL_CELLS] {
    static TABLES: std::sync::OnceLock<Vec<[u32; VOXEL_CELLS]>> = std::sync::OnceLock::new();
    let tables = TABLES.get_or_init(|| {
        (0..=BRICK_EDGE as usize)
            .map(|r| {
                let r = r as i32;
                std::array::from_fn(|i| {
                    let c = [i as i32 % 8, i as i32 / 8 % 8, i as i32 / 64];
                    let sides = |v: i32| -> Vec<i32> {
                        let mut s = vec![0];
                        if v < r {
                            s.push(-1);
                        }
                        if v >= BRICK_EDGE - r {
                            s.push(1);
                        }
                        s
                    };
                    let mut m = 0u32;
                    for dz in sides(c[2]) {
                        for dy in sides(c[1]) {
                            for dx in sides(c[0]) {
                                m |= 1 << ((dx + 1) + (dy + 1) * 3 + (dz + 1) * 9);
                            }
                        }
                    }
                    m
                })
            })
            .collect()
    });
    &tables[passes.clamp(1, BRICK_EDGE as usize)]
}

impl VoxelSim {
    /// Bricks awake.
    pub fn active_bricks(&self) -> usize {
        self.active.len()
    }

    pub(super) fn wake_all_known(&mut self) {
        self.wake_pending = true;
    }

    /// Wake every brick before the next step, as a reload or a parameter
    /// change does.
    pub fn wake_all(&mut self) {
        self.wake_all_known();
    }

    /// Wake every brick inside the bounds that is not empty or holds a
    /// channel array (see `wake_pending`).
    pub(super) fn wake_everything(&mut self, store: &BrickStore) {
        let mut all: Vec<IVec3> = store.iter().map(|(b, _)| b).collect();
        all.extend(self.channels.all_bricks());
        all.retain(|b| self.inside(*b));
        self.active.extend(all);
        self.quiet.clear();
    }

    /// Wake `bricks` and their neighbours, and forget their material
    /// presence (an edit from outside: the column write-back, a user).
    pub fn notify_edited(&mut self, bricks: &[IVec3]) {
        for &b in bricks {
            self.presence.remove(&b);
            self.wake(b);
        }
    }

    pub(super) fn wake(&mut self, b: IVec3) {
        for n in 0..27 {
            let nb = b + neighbour_offset(n);
            if self.inside(nb) {
                self.active.insert(nb);
                self.quiet.remove(&nb);
            }
        }
    }

    fn presence(&mut self, store: &BrickStore, b: IVec3) -> MatSet {
        if let Some(p) = self.presence.get(&b) {
            return *p;
        }
        let mut d = [0u8; VOXEL_CELLS];
        store.read_dense(b, &mut d);
        let p = presence_of(&d);
        self.presence.insert(b, p);
        p
    }

    /// The bricks script `si` runs on this step, sorted. Its seeds are the
    /// active bricks that hold one of its `only` materials or any value of
    /// its channels (water too shallow to be drawn still flows); without
    /// `only`, every active brick. Each seed runs, and so does each
    /// neighbour that something in the seed can reach this step: a script
    /// of P passes moves things at most P voxels, so a neighbour is added
    /// only when a seed's material or value lies within P voxels of it. A
    /// falling drop in the middle of a brick runs that one brick, not 27.
    /// `sky` scripts run on the world's top layer of bricks only.
    pub(super) fn candidates(&mut self, store: &BrickStore, si: usize) -> Vec<IVec3> {
        if self.scripts[si].spec.sky {
            let mut out = Vec::new();
            for z in self.lo.z..self.hi.z {
                for x in self.lo.x..self.hi.x {
                    out.push(IVec3::new(x, self.hi.y - 1, z));
                }
            }
            return out;
        }
        let only = self.scripts[si].only;
        let chans = self.scripts[si].channel_ids.clone();
        let reach = reach_masks(self.scripts[si].spec.passes.len());
        let mut active: Vec<IVec3> = self.active.iter().copied().collect();
        active.sort_by_key(|b| (b.z, b.y, b.x));
        let mut out = FxHashSet::default();
        let mut dense = [0u8; VOXEL_CELLS];
        for b in active {
            let mut mask = 0u32;
            for &c in &chans {
                if let Some(v) = self.channels.get(c, b) {
                    for (i, x) in v.iter().enumerate() {
                        if x.to_bits() != 0 {
                            mask |= reach[i];
                        }
                    }
                }
            }
            match only {
                Some(o) => {
                    if meets(&self.presence(store, b), &o) {
                        store.read_dense(b, &mut dense);
                        for (i, &m) in dense.iter().enumerate() {
                            if o[m as usize >> 6] & (1 << (m & 63)) != 0 {
                                mask |= reach[i];
                            }
                        }
                    }
                }
                None => {
                    mask |= 1 << SELF;
                    if store.cell(b) != crate::world::Cell::Empty {
                        store.read_dense(b, &mut dense);
                        for (i, &m) in dense.iter().enumerate() {
                            if m != 0 {
                                mask |= reach[i];
                            }
                        }
                    }
                }
            }
            for n in 0..27 {
                if mask & (1 << n) != 0 {
                    let nb = b + neighbour_offset(n);
                    if self.inside(nb) {
                        out.insert(nb);
                    }
                }
            }
        }
        let mut out: Vec<IVec3> = out.into_iter().collect();
        out.sort_by_key(|b| (b.z, b.y, b.x));
        out
    }

    /// The active set and quiet counters, sorted (for checkpoints).
    #[allow(clippy::type_complexity)]
    ///
    /// A wake still pending (a parameter changed since the last step) is
    /// saved as done, from `store`: the next step of a run that never
    /// stopped wakes exactly those bricks, from the same world (nothing
    /// edits it between a commit and the next step), so the resumed run
    /// continues the same (regression: a pending wake was lost on stop).
    pub fn sleep_state(&self, store: &BrickStore) -> (Vec<IVec3>, Vec<(IVec3, u8)>) {
        let mut active = self.active.clone();
        let mut quiet = self.quiet.clone();
        if self.wake_pending {
            active.extend(
                store
                    .iter()
                    .map(|(b, _)| b)
                    .chain(self.channels.all_bricks())
                    .filter(|b| self.inside(*b)),
            );
            quiet.clear();
        }
        let mut a: Vec<IVec3> = active.into_iter().collect();
        a.sort_by_key(|b| (b.z, b.y, b.x));
        let mut q: Vec<(IVec3, u8)> = quiet.iter().map(|(b, n)| (*b, *n)).collect();
        q.sort_by_key(|(b, _)| (b.z, b.y, b.x));
        (a, q)
    }

    /// Restore what [`sleep_state`](Self::sleep_state) saved. A wake
    /// pending from parameters set before (a resume sets the stored ones)
    /// is dropped: the saved state already holds the wake that was pending
    /// when it was saved, and nothing else (regression: every resume woke
    /// every brick at its first step, which the run that never stopped did
    /// not).
    pub fn restore_sleep_state(&mut self, active: &[IVec3], quiet: &[(IVec3, u8)]) {
        self.wake_pending = false;
        self.active = active.iter().copied().filter(|b| self.inside(*b)).collect();
        self.quiet = quiet
            .iter()
            .copied()
            .filter(|(b, _)| self.inside(*b))
            .collect();
    }

    /// Sleep and wake after a step's scripts ran: every awake brick that
    /// nothing `changed` (whether or not a script visited it) moves towards
    /// sleep, unless it holds a `keep_awake` material or the step `rejected`
    /// a script; then every changed brick wakes its neighbours. Returns the
    /// changed bricks, sorted.
    pub(super) fn settle(
        &mut self,
        store: &BrickStore,
        changed: FxHashSet<IVec3>,
        rejected: bool,
    ) -> Vec<IVec3> {
        let keep = self.scripts.iter().fold([0u64; 4], |a, s| {
            std::array::from_fn(|i| a[i] | s.keep_awake[i])
        });
        // Every awake brick that nothing changed this tick (whether or not a
        // script visited it) moves towards sleep.
        // A step that rejected a script moves nothing towards sleep.
        let mut awake: Vec<IVec3> = if !rejected {
            self.active.iter().copied().collect()
        } else {
            Vec::new()
        };
        awake.sort_by_key(|b| (b.z, b.y, b.x));
        for b in awake {
            if changed.contains(&b) {
                continue;
            }
            if keep != [0; 4] && meets(&self.presence(store, b), &keep) {
                continue;
            }
            let q = self.quiet.entry(b).or_insert(0);
            *q += 1;
            if *q >= SLEEP_AFTER {
                self.active.remove(&b);
                self.quiet.remove(&b);
            }
        }
        let mut changed: Vec<IVec3> = changed.into_iter().collect();
        changed.sort_by_key(|b| (b.z, b.y, b.x));
        for &b in &changed {
            self.wake(b);
        }
        changed
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::world::voxel_index;

    #[test]
    fn a_cell_reaches_only_the_neighbours_within_the_scripts_passes() {
        let count = |m: u32| m.count_ones();
        let two = reach_masks(2);
        // The middle of a brick: only the brick itself.
        assert_eq!(two[voxel_index(3, 3, 4)], 1 << SELF);
        // One voxel from the -x face: that neighbour too.
        let m = two[voxel_index(1, 4, 4)];
        assert_eq!(count(m), 2);
        assert_ne!(m & (1 << 12), 0, "-x is neighbour 12");
        // A corner reaches the seven bricks around it.
        assert_eq!(count(reach_masks(1)[voxel_index(7, 7, 7)]), 8);
        assert_eq!(count(reach_masks(1)[voxel_index(6, 7, 7)]), 4);
        // Eight passes reach every neighbour from anywhere.
        assert!(reach_masks(8).iter().all(|&m| count(m) == 27));
    }

    /// A wake pending at a commit (a parameter changed, no step since) is
    /// in the saved sleep state: a resumed run wakes what the run that
    /// never stopped wakes at its next step.
    #[test]
    fn a_pending_wake_is_saved_with_the_sleep_state() {
        let mut store = BrickStore::new(crate::world::Palette::grey_ramp());
        store.set_voxel(IVec3::new(3, 3, 3), 1);
        store.set_voxel(IVec3::new(20, 3, 3), 1);
        let mut sim = VoxelSim::new(&store, IVec3::ZERO, IVec3::splat(32), 1);
        // Everything fell asleep; one brick is quiet.
        sim.active.clear();
        sim.quiet.insert(IVec3::new(2, 0, 0), 3);
        assert_eq!(sim.sleep_state(&store).0, Vec::<IVec3>::new());
        sim.wake_all_known();
        let (active, quiet) = sim.sleep_state(&store);
        assert_eq!(active, vec![IVec3::ZERO, IVec3::new(2, 0, 0)]);
        assert!(quiet.is_empty());
        // The next step wakes the same bricks.
        sim.wake_everything(&store);
        assert_eq!(sim.sleep_state(&store).0, active);
    }

    /// A resume sets the stored parameters (each set wakes everything) and
    /// then restores the sleep state: only the saved bricks are awake after
    /// it (regression: every resume woke every brick at its first step).
    #[test]
    fn restoring_a_sleep_state_drops_the_wake_of_the_parameters_set_before() {
        let mut store = BrickStore::new(crate::world::Palette::grey_ramp());
        store.set_voxel(IVec3::new(3, 3, 3), 1);
        store.set_voxel(IVec3::new(20, 3, 3), 1);
        let mut sim = VoxelSim::new(&store, IVec3::ZERO, IVec3::splat(32), 1);
        sim.wake_all_known();
        sim.restore_sleep_state(&[IVec3::new(2, 0, 0)], &[]);
        assert_eq!(sim.sleep_state(&store).0, vec![IVec3::new(2, 0, 0)]);
    }
}
