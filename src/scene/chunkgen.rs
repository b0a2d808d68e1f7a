//! Generation on first touch: a procedural terrain, bounded or not, produced
//! one chunk column (64 × 64 voxels, the whole height) at a time.
//!
//! Columns are independent and deterministic from the seed, so any set of
//! them, generated in any order on any thread, gives exactly the bricks a
//! whole-world build gives (tested). That is what lets a streamed world keep
//! only what is near the camera and regenerate the rest when it is needed:
//! a generated chunk is never stored until something edits it.

use glam::{IVec2, IVec3};
use indicatif::ProgressBar;
use rayon::prelude::*;

use super::heightfield::{Heightfield, column};
use super::terrain::{self, Terrain};
use super::{SceneError, SceneSpec, SceneWorld};
use crate::world::{BRICK_EDGE, BrickContent, BrickStore, Palette};

/// Bricks per chunk edge (the world store's chunk: 8³ bricks, 64³ voxels).
pub const CHUNK_BRICKS: i32 = 8;
/// Voxels per chunk edge.
pub const CHUNK_VOXELS: i32 = CHUNK_BRICKS * BRICK_EDGE;

/// The chunk column holding voxel column (`x`, `z`).
pub fn chunk_column_of(x: i32, z: i32) -> IVec2 {
    IVec2::new(x.div_euclid(CHUNK_VOXELS), z.div_euclid(CHUNK_VOXELS))
}

/// The bytes a store's bricks take: the pool's slots and index, and each
/// non-empty brick's entry. A region's [`SceneWorld`] adds its grid.
pub fn store_bytes(store: &BrickStore) -> u64 {
    (store.pool().bytes() + store.pool().index_bytes() + store.non_empty_bricks() * 24) as u64
}

/// A procedural terrain that generates chunk columns on demand.
///
/// ```
/// use brickworld::scene::{ChunkGen, SceneSpec};
/// use glam::{IVec2, IVec3};
/// let g = ChunkGen::new(&SceneSpec::Terrain { caves: false }, None, 128, 7).unwrap();
/// let mut bricks = Vec::new();
/// g.generate(IVec2::new(-40, 1_000), &mut bricks); // unbounded: any column exists
/// assert!(!bricks.is_empty());
/// ```
#[derive(Clone, Debug)]
pub struct ChunkGen {
    terrain: Terrain,
    palette: Palette,
    /// Chunk columns `[min, max)` of a bounded world; None when unbounded.
    columns: Option<(IVec2, IVec2)>,
    height: i32,
}

impl ChunkGen {
    /// A generator for `spec` (only `terrain` and `terrain:caves` generate
    /// by columns). `size` bounds the world; None makes it unbounded in x and
    /// z with `height` voxels of height.
    pub fn new(
        spec: &SceneSpec,
        size: Option<IVec3>,
        height: i32,
        seed: u64,
    ) -> Result<Self, SceneError> {
        let SceneSpec::Terrain { caves } = spec else {
            return Err(SceneError::NotStreamable);
        };
        let (terrain, columns, height) = match size {
            Some(s) => (
                Terrain::new(s, seed, *caves),
                Some((
                    IVec2::ZERO,
                    IVec2::new(s.x, s.z).map(|v| (v + CHUNK_VOXELS - 1).div_euclid(CHUNK_VOXELS)),
                )),
                s.y,
            ),
            None => (Terrain::unbounded(height, seed, *caves), None, height),
        };
        Ok(ChunkGen {
            terrain,
            palette: terrain::palette(),
            columns,
            height,
        })
    }

    /// The world's height in voxels.
    pub fn height(&self) -> i32 {
        self.height
    }

    /// The chunk columns `[min, max)` of a bounded world; None if unbounded.
    pub fn columns(&self) -> Option<(IVec2, IVec2)> {
        self.columns
    }

    /// Whether chunk column `c` is part of the world.
    pub fn contains(&self, c: IVec2) -> bool {
        self.columns
            .is_none_or(|(lo, hi)| c.cmpge(lo).all() && c.cmplt(hi).all())
    }

    /// The terrain palette.
    pub fn palette(&self) -> &Palette {
        &self.palette
    }

    /// Append the non-empty bricks of chunk column `c` to `out` (nothing if
    /// `c` is outside a bounded world).
    pub fn generate(&self, c: IVec2, out: &mut Vec<(IVec3, BrickContent)>) {
        if !self.contains(c) {
            return;
        }
        let ext = self.terrain.extent();
        let bmax = IVec2::new(ext.x, ext.z).map(|v| {
            if v == i32::MAX {
                i32::MAX
            } else {
                (v + BRICK_EDGE - 1) / BRICK_EDGE
            }
        });
        for bz in c.y * CHUNK_BRICKS..(c.y + 1) * CHUNK_BRICKS {
            for bx in c.x * CHUNK_BRICKS..(c.x + 1) * CHUNK_BRICKS {
                if bx < bmax.x && bz < bmax.y {
                    column(&self.terrain, bx, bz, out, &self.palette);
                }
            }
        }
    }

    /// A cheap stand-in for chunk column `c` while its exact bricks are
    /// being generated: each brick column becomes a stack of uniform bricks
    /// up to the height sampled at its centre, coloured by the surface
    /// material there. It costs 64 height samples instead of 4 096 plus the
    /// voxels, and shows the land's shape and colour (its LOD colours)
    /// rather than a hole.
    pub fn generate_coarse(&self, c: IVec2, out: &mut Vec<(IVec3, BrickContent)>) {
        if !self.contains(c) {
            return;
        }
        let ext = self.terrain.extent();
        for bz in c.y * CHUNK_BRICKS..(c.y + 1) * CHUNK_BRICKS {
            for bx in c.x * CHUNK_BRICKS..(c.x + 1) * CHUNK_BRICKS {
                let (x, z) = (bx * BRICK_EDGE + 4, bz * BRICK_EDGE + 4);
                if x >= ext.x || z >= ext.z {
                    continue;
                }
                let h = self.terrain.height(x, z).clamp(0, ext.y);
                let top = h.div_euclid(BRICK_EDGE).max(1);
                let surface = self.terrain.material(x, h - 1, z, h, 0.0);
                let deep = self.terrain.deep().map_or(surface, |(_, m)| m);
                for by in 0..top {
                    let m = if by == top - 1 { surface } else { deep };
                    out.push((IVec3::new(bx, by, bz), BrickContent::Uniform(m)));
                }
            }
        }
    }

    /// The world restricted to chunk columns `[lo, hi)` (clipped to a bounded
    /// world), generated in parallel: the part of a streamed world the
    /// simulation keeps resident. Its bounds are the columns' voxels, the
    /// whole height.
    pub fn build_region(&self, lo: IVec2, hi: IVec2) -> Result<SceneWorld, SceneError> {
        self.build_region_within(lo, hi, u64::MAX, &ProgressBar::hidden())
    }

    /// [`build_region`](Self::build_region), refusing as soon as the
    /// region's bricks pass `limit` bytes (as [`store_bytes`] counts them)
    /// with columns still to build, so that a region too large for a
    /// memory budget is refused after building no more than the budget,
    /// not the whole region (a region whose last batch passes the limit is
    /// returned: the caller's own check then names its exact need). Columns are
    /// generated in batches, each inserted before the next is made, so the
    /// build never holds the region twice; `pb` counts columns.
    pub fn build_region_within(
        &self,
        lo: IVec2,
        hi: IVec2,
        limit: u64,
        pb: &ProgressBar,
    ) -> Result<SceneWorld, SceneError> {
        let (lo, hi) = match self.columns {
            Some((a, b)) => (lo.max(a), hi.min(b)),
            None => (lo, hi),
        };
        if hi.cmple(lo).any() {
            return Err(SceneError::EmptyRegion);
        }
        let cols: Vec<IVec2> = (lo.y..hi.y)
            .flat_map(|z| (lo.x..hi.x).map(move |x| IVec2::new(x, z)))
            .collect();
        pb.set_length(cols.len() as u64);
        let mut store = BrickStore::new(self.palette.clone());
        let batch = (rayon::current_num_threads() * 16).max(64);
        for (i, part) in cols.chunks(batch).enumerate() {
            let made: Vec<Vec<(IVec3, BrickContent)>> = part
                .par_iter()
                .map(|c| {
                    let mut v = Vec::new();
                    self.generate(*c, &mut v);
                    v
                })
                .collect();
            for (b, content) in made.into_iter().flatten() {
                store.set_brick(b, content);
            }
            pb.inc(part.len() as u64);
            let bytes = store_bytes(&store);
            let built = i * batch + part.len();
            // Once it is whole, the caller's check names the exact need.
            if bytes > limit && built < cols.len() {
                return Err(SceneError::RegionOverLimit {
                    built: built as u64,
                    columns: cols.len() as u64,
                    bytes,
                    limit,
                });
            }
        }
        let ext = self.terrain.extent();
        let v0 = lo * CHUNK_VOXELS;
        let v1 = (hi * CHUNK_VOXELS).min(IVec2::new(ext.x, ext.z));
        let mut world = SceneWorld::new(
            store,
            IVec3::new(v0.x, 0, v0.y),
            IVec3::new(v1.x, self.height, v1.y),
        )?;
        super::name_terrain_materials(&mut world);
        Ok(world)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use indicatif::ProgressBar;

    /// Any set of generated columns equals the same part of a whole build.
    #[test]
    fn columns_match_a_whole_world_build() {
        let size = IVec3::new(150, 64, 131);
        let spec = SceneSpec::Terrain { caves: true };
        let whole = super::super::build_scene(&spec, size, 9, &ProgressBar::hidden()).unwrap();
        let g = ChunkGen::new(&spec, Some(size), 0, 9).unwrap();
        assert_eq!(g.columns(), Some((IVec2::ZERO, IVec2::new(3, 3))));
        let region = g.build_region(IVec2::new(1, 0), IVec2::new(9, 9)).unwrap();
        assert_eq!(
            region.bounds,
            (IVec3::new(64, 0, 0), IVec3::new(150, 64, 131))
        );
        let mut n = 0;
        for (b, _) in whole.store.iter() {
            if b.x >= 8 {
                assert_eq!(region.store.content(b), whole.store.content(b), "brick {b}");
                n += 1;
            }
        }
        assert_eq!(n, region.store.non_empty_bricks());
        assert!(n > 100);
        assert_eq!(region.materials.id("grass"), Some(1));
    }

    /// A region built in batches under a limit is the whole build when it
    /// fits, and is refused part-way, not after the last column, when it
    /// does not (regression, scale probe: a region too large for its
    /// budget was built in full before its refusal).
    #[test]
    fn a_region_over_its_limit_is_refused_part_way() {
        let g = ChunkGen::new(&SceneSpec::Terrain { caves: false }, None, 128, 4).unwrap();
        let (lo, hi) = (IVec2::new(-6, -5), IVec2::new(9, 11));
        let whole = g.build_region(lo, hi).unwrap();
        let bytes = store_bytes(&whole.store);
        let pb = ProgressBar::hidden();
        let fits = g.build_region_within(lo, hi, bytes, &pb).unwrap();
        assert_eq!(pb.position(), 15 * 16);
        assert_eq!(fits.bounds, whole.bounds);
        assert_eq!(
            fits.store.non_empty_bricks(),
            whole.store.non_empty_bricks()
        );
        for (b, _) in whole.store.iter() {
            assert_eq!(fits.store.content(b), whole.store.content(b), "brick {b}");
        }
        match g.build_region_within(lo, hi, bytes / 3, &ProgressBar::hidden()) {
            Err(SceneError::RegionOverLimit {
                built,
                columns,
                bytes: at,
                limit,
            }) => {
                assert_eq!(columns, 15 * 16);
                assert!(built < columns, "refused after {built} of {columns}");
                assert!(at > limit && at < bytes, "{at} against {limit} and {bytes}");
            }
            other => panic!("expected a refusal, got {:?}", other.map(|w| w.bounds)),
        }
    }

    #[test]
    fn unbounded_columns_exist_everywhere_and_repeat_exactly() {
        let g = ChunkGen::new(&SceneSpec::Terrain { caves: false }, None, 96, 3).unwrap();
        assert!(g.contains(IVec2::new(-1_000_000, 1_000_000)));
        let (mut a, mut b) = (Vec::new(), Vec::new());
        g.generate(IVec2::new(-3, 1_500), &mut a);
        g.generate(IVec2::new(-3, 1_500), &mut b);
        assert!(!a.is_empty());
        assert_eq!(a, b);
        assert!(a.iter().all(|(p, _)| p.y >= 0 && p.y * BRICK_EDGE < 96));
    }

    #[test]
    fn coarse_columns_follow_the_exact_ground() {
        let g = ChunkGen::new(&SceneSpec::Terrain { caves: false }, None, 128, 5).unwrap();
        let (mut exact, mut coarse) = (Vec::new(), Vec::new());
        g.generate(IVec2::new(4, -2), &mut exact);
        g.generate_coarse(IVec2::new(4, -2), &mut coarse);
        // Every brick column has a stand-in, no taller than the exact
        // column's highest brick.
        assert_eq!(
            coarse
                .iter()
                .map(|(b, _)| (b.x, b.z))
                .collect::<std::collections::BTreeSet<_>>()
                .len(),
            64
        );
        for (b, _) in &coarse {
            let top = exact
                .iter()
                .filter(|(e, _)| e.x == b.x && e.z == b.z)
                .map(|(e, _)| e.y)
                .max();
            assert!(
                top.is_some_and(|t| b.y <= t),
                "coarse brick {b} above the ground"
            );
        }
    }

    #[test]
    fn other_sources_do_not_stream() {
        assert!(matches!(
            ChunkGen::new(&SceneSpec::Balls, Some(IVec3::splat(64)), 0, 1),
            Err(SceneError::NotStreamable)
        ));
    }
}
