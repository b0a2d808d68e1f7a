//! [`SceneWorld`]: a world ready to trace (its store, bounds, brick grid
//! and named materials), edited only through [`SceneWorld::edit`], which
//! patches the grid; and [`WorldDelta`], the changes that keep a copy of it
//! (the render thread's) current.

use glam::{DVec3, IVec3};
use indicatif::ProgressBar;
use rayon::prelude::*;

use super::View;
use crate::trace::{BrickmapTracer, DenseGrid, Frame, Svo, TraceError};
use crate::world::{BRICK_SHIFT, BrickGrid, BrickStore, WorldError, brick_of};
use crate::world::{MaterialDef, MaterialKind, MaterialRegistry};

/// The changes between two moments of a [`SceneWorld`], to keep a copy of
/// it current (the render thread's) without copying the world.
#[derive(Clone, Debug)]
pub struct WorldDelta {
    /// Changed bricks and their contents now.
    pub bricks: Vec<(IVec3, DeltaBrick)>,
    /// The palette now.
    pub palette: crate::world::Palette,
    /// The materials now.
    pub materials: MaterialRegistry,
}

/// One brick of a [`WorldDelta`]. A mixed brick travels as its 512 dense
/// materials: reading them out of the pool is cheap, and the expensive
/// half of a copy (re-encoding: palette, packed indices, LOD colour) then
/// happens on the receiving thread, not on the engine loop's snapshot.
#[derive(Clone, Debug)]
pub enum DeltaBrick {
    /// No solid voxel.
    Empty,
    /// One material throughout.
    Uniform(u8),
    /// Dense materials.
    Dense(Box<[u8; crate::world::BRICK_VOXELS]>),
}

/// A scene ready to trace: its store, bounds and brick grid.
///
/// The store is reached for writing only through [`edit`](Self::edit),
/// which patches the grid with whatever the edit changed before it returns:
/// the grid cannot be forgotten.
///
/// ```
/// use brickworld::scene::SceneWorld;
/// use brickworld::world::{BrickStore, Palette};
/// use glam::IVec3;
/// let mut w = SceneWorld::new(BrickStore::new(Palette::grey_ramp()), IVec3::ZERO, IVec3::splat(32)).unwrap();
/// let ((), changed) = w.edit(|store, _| store.set_voxel(IVec3::new(9, 1, 2), 5));
/// assert_eq!(changed, vec![IVec3::new(1, 0, 0)]);
/// assert_ne!(w.grid().pointer(IVec3::new(1, 0, 0)), 0); // the grid saw it
/// ```
#[derive(Clone, Debug)]
pub struct SceneWorld {
    // `pub(super)`: the render window (`scene::window`) rebuilds them in
    // place when it slides.
    pub(super) store: BrickStore,
    pub(super) grid: BrickGrid,
    pub(super) bounds: (IVec3, IVec3),
    /// The world's named materials (scene materials, the simulation's,
    /// then `materials.lua`'s); their colours are the store's palette.
    pub materials: MaterialRegistry,
}

impl SceneWorld {
    /// Wrap a store whose voxels lie in `[lo, hi)`.
    pub fn new(mut store: BrickStore, lo: IVec3, hi: IVec3) -> Result<Self, WorldError> {
        let b0 = brick_of(lo);
        let b1 = brick_of(hi - IVec3::ONE);
        let grid = BrickGrid::build(&store, b0, b1 - b0 + IVec3::ONE)?;
        // The grid was built from everything the store holds.
        store.take_modified();
        let materials = materials_present(&store);
        Ok(SceneWorld {
            store,
            grid,
            bounds: (lo, hi),
            materials,
        })
    }

    /// The voxels (read-only; write through [`edit`](Self::edit)).
    pub fn store(&self) -> &BrickStore {
        &self.store
    }

    /// The brick grid over the bounds.
    pub fn grid(&self) -> &BrickGrid {
        &self.grid
    }

    /// Voxel bounds `[min, max)`.
    pub fn bounds(&self) -> (IVec3, IVec3) {
        self.bounds
    }

    /// Give the world `palette`. A mixed brick's LOD colour is the mean of
    /// its voxels' colours, so the mixed bricks holding a material whose
    /// colour changes get new ones ([`BrickStore::recolour`]); they are
    /// returned (their voxels are the same: for the renderer, not for a
    /// commit).
    pub fn set_palette(&mut self, palette: crate::world::Palette) -> Vec<IVec3> {
        let (_, recoloured) = self.edit(|s, _| s.set_palette(palette));
        recoloured
    }

    /// Change the world: `f` gets the store and the materials; afterwards
    /// the grid is patched with the bricks `f` changed, which are returned
    /// with `f`'s result.
    #[must_use = "the bricks changed must reach the renderer and the next commit"]
    pub fn edit<R>(
        &mut self,
        f: impl FnOnce(&mut BrickStore, &mut MaterialRegistry) -> R,
    ) -> (R, Vec<IVec3>) {
        let r = f(&mut self.store, &mut self.materials);
        (r, self.apply_edits())
    }

    /// The local frame every tracer of this world uses.
    pub fn frame(&self) -> Frame {
        Frame {
            anchor: self.grid.origin() << BRICK_SHIFT,
        }
    }

    /// The brickmap tracer (borrows the grid and the store's pool).
    pub fn brickmap(&self) -> BrickmapTracer<'_> {
        BrickmapTracer::new(&self.grid, self.store.pool())
    }

    /// Build the sparse voxel octree.
    pub fn svo(&self, progress: &ProgressBar) -> Result<Svo, TraceError> {
        Svo::build(&self.grid, self.store.pool(), progress)
    }

    /// Build the dense grid, refusing above `limit` bytes.
    pub fn dense(&self, limit: u64) -> Result<DenseGrid, TraceError> {
        let frame = self.frame();
        DenseGrid::build(&self.store, frame, self.bounds.1 - frame.anchor, limit)
    }

    /// Patch the grid with the store's pending edits; returns the bricks changed.
    pub(super) fn apply_edits(&mut self) -> Vec<IVec3> {
        let changed = self.store.take_modified();
        self.grid.apply_edits(&self.store, &changed);
        changed
    }

    /// What changed at `bricks` since a copy of this world was taken, for
    /// that copy's owner to [`apply_delta`](Self::apply_delta): the bricks'
    /// current contents, the palette and the materials. Costs O(bricks),
    /// not O(world).
    pub fn delta(&self, bricks: &[IVec3]) -> WorldDelta {
        WorldDelta {
            bricks: bricks
                .par_iter()
                .map(|b| {
                    let d = match self.store.cell(*b) {
                        crate::world::Cell::Empty => DeltaBrick::Empty,
                        crate::world::Cell::Uniform(m) => DeltaBrick::Uniform(m),
                        crate::world::Cell::Mixed(_) => {
                            let mut dense = Box::new([0u8; crate::world::BRICK_VOXELS]);
                            self.store.read_dense(*b, &mut dense);
                            DeltaBrick::Dense(dense)
                        }
                    };
                    (*b, d)
                })
                .collect(),
            palette: self.store.palette().clone(),
            materials: self.materials.clone(),
        }
    }

    /// Bring a copy up to date with a [`delta`](Self::delta) of the world it
    /// was copied from (grid patched); returns the bricks changed.
    pub fn apply_delta(&mut self, delta: WorldDelta) -> Vec<IVec3> {
        // A new palette (a hot reload of `materials.lua`) recolours this
        // copy's own bricks: the engine does not send them.
        let mut changed = self.set_palette(delta.palette);
        let encoded: Vec<(IVec3, crate::world::BrickContent)> = delta
            .bricks
            .into_par_iter()
            .map(|(b, d)| {
                let c = match d {
                    DeltaBrick::Empty => crate::world::BrickContent::Empty,
                    DeltaBrick::Uniform(m) => crate::world::BrickContent::Uniform(m),
                    DeltaBrick::Dense(dense) => {
                        crate::world::BrickContent::from_dense(&dense, self.store.palette())
                    }
                };
                (b, c)
            })
            .collect();
        for (b, content) in encoded {
            self.store.set_brick(b, content);
        }
        self.materials = delta.materials;
        changed.extend(self.apply_edits());
        changed
    }

    /// Three documented viewpoints from the bounds: a distant overview, a
    /// medium view and a close-up, all looking at the centre from the
    /// (−x, +y, −z) side.
    pub fn default_views(&self) -> [View; 3] {
        let (lo, hi) = (self.bounds.0.as_dvec3(), self.bounds.1.as_dvec3());
        let c = (lo + hi) * 0.5;
        let e = hi - lo;
        let radius = e.length() * 0.5;
        let dir = DVec3::new(-0.62, 0.5, -0.6).normalize();
        let top = DVec3::new(c.x, hi.y, c.z);
        [
            View {
                eye: (c + dir * radius * 1.45).to_array(),
                target: c.to_array(),
                fov: 50.0,
            },
            View {
                eye: (c + dir * radius * 0.8).to_array(),
                target: (c * 0.7 + top * 0.3).to_array(),
                fov: 50.0,
            },
            View {
                eye: (top + DVec3::new(-0.18 * e.x, 0.05 * e.y + 4.0, -0.18 * e.z)).to_array(),
                target: (c + DVec3::new(0.08 * e.x, -0.2 * e.y, 0.1 * e.z)).to_array(),
                fov: 60.0,
            },
        ]
    }
}

/// A registry naming every material id present in `store` `mN` (solid, in
/// its palette colour); scene builders then give the ones they know their
/// names.
fn materials_present(store: &crate::world::BrickStore) -> MaterialRegistry {
    let mut seen = [false; 256];
    let mut d = [0u8; crate::world::BRICK_VOXELS];
    for (b, _) in store.iter() {
        store.read_dense(b, &mut d);
        for &m in d.iter() {
            seen[m as usize] = true;
        }
    }
    let mut r = MaterialRegistry::new();
    for m in 1..=255u8 {
        if seen[m as usize] {
            let def = MaterialDef {
                color: store.palette().rgb(m),
                kind: MaterialKind::Solid,
                density: 2.5,
            };
            let _ = r.register_at(m, &format!("m{m}"), def);
        }
    }
    r
}
