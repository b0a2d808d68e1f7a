//! Scene sources and the traced world built from them.
//!
//! Every source is deterministic from its seed. `--size XxYxZ` sizes the
//! procedural ones (Y is up); heightmaps and `.vox` files size themselves.
//! A [`SceneWorld`] holds the store, the brick grid over the scene's bounds
//! and builds the three tracers over the same local frame.

pub mod budget;
mod chunkgen;
mod heightfield;
mod heightmap;
mod noise;
mod shapes;
mod terrain;
mod vox;
mod window;
mod world;

use std::path::{Path, PathBuf};
use std::str::FromStr;

use glam::IVec3;
use indicatif::ProgressBar;
use thiserror::Error;

pub use chunkgen::{CHUNK_BRICKS, CHUNK_VOXELS, ChunkGen, chunk_column_of, store_bytes};
pub use heightfield::{Heightfield, voxelize};
pub use heightmap::Heightmap;
pub use noise::Noise;
pub use shapes::{Prim, Rng, rasterize};
pub use terrain::Terrain;
pub use vox::{parse as parse_vox, store_from_voxels, voxels as vox_voxels};
pub use window::{ColumnOverlay, RenderWindow, WindowSettings, WindowStats};
pub use world::{DeltaBrick, SceneWorld, WorldDelta};

use crate::world::WorldError;
use crate::world::{MaterialDef, MaterialKind};

/// Errors loading or building a scene.
#[derive(Debug, Error)]
pub enum SceneError {
    /// A file could not be read.
    #[error("cannot read {}: {error}", path.display())]
    Io {
        /// The file.
        path: PathBuf,
        /// Why (part of the message, deliberately not a `source`, so that
        /// error chains do not print it twice).
        error: std::io::Error,
    },
    /// A file is not valid in its format.
    #[error("{} is not a valid {kind}: {msg}", path.display())]
    Format {
        /// The file.
        path: PathBuf,
        /// Expected format.
        kind: &'static str,
        /// What is wrong.
        msg: String,
    },
    /// A file is too large.
    #[error("{} is too large: {msg}", path.display())]
    TooLarge {
        /// The file.
        path: PathBuf,
        /// Details.
        msg: String,
    },
    /// A world source that is a device, pipe or directory.
    #[error("{} is not a regular file (a device, pipe or directory cannot be a world source)", path.display())]
    NotAFile {
        /// The path.
        path: PathBuf,
    },
    /// The world would not fit in memory.
    #[error("{what}: not enough memory: {msg}")]
    OutOfMemory {
        /// The source.
        what: String,
        /// Need and availability.
        msg: String,
    },
    /// The scene name is not known.
    #[error(
        "unknown scene '{0}' (expected terrain, terrain:caves, balls, hairball, heightmap:FILE.png or vox:FILE.vox)"
    )]
    UnknownScene(String),
    /// The world structures could not be built.
    #[error(transparent)]
    World(#[from] WorldError),
    /// Only procedural terrain generates chunk by chunk.
    #[error(
        "only terrain and terrain:caves worlds can stream (generate chunks on first touch); other sources are built whole"
    )]
    NotStreamable,
    /// Fetcher threads could not be started.
    #[error("cannot start the chunk fetcher threads: {0}")]
    Threads(String),
    /// A region with no chunk column inside the world.
    #[error("the region holds no part of the world")]
    EmptyRegion,
    /// A region that passed its memory limit while it was built.
    #[error(
        "the region's bricks passed {} after {built} of its {columns} chunk columns, over the {} it may take (the whole region would take about {})",
        budget::human(*bytes),
        budget::human(*limit),
        budget::human((*bytes as f64 * *columns as f64 / (*built).max(1) as f64) as u64)
    )]
    RegionOverLimit {
        /// Columns built when it was refused.
        built: u64,
        /// Columns in the region.
        columns: u64,
        /// Bytes its bricks took then.
        bytes: u64,
        /// The limit.
        limit: u64,
    },
}

impl SceneError {
    fn io(path: &Path, source: std::io::Error) -> Self {
        SceneError::Io {
            path: path.to_path_buf(),
            error: source,
        }
    }
    fn too_large(path: &Path, msg: String) -> Self {
        SceneError::TooLarge {
            path: path.to_path_buf(),
            msg,
        }
    }
}

/// Which scene to build.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum SceneSpec {
    /// fBm terrain, optionally with caves and overhangs.
    Terrain {
        /// Carve caves and overhangs.
        caves: bool,
    },
    /// Random spheres.
    Balls,
    /// Random thick tubes.
    Hairball,
    /// A grayscale PNG heightmap.
    Heightmap(PathBuf),
    /// A MagicaVoxel file.
    Vox(PathBuf),
}

impl SceneSpec {
    /// The file a heightmap or .vox scene is read from.
    pub fn file(&self) -> Option<&Path> {
        match self {
            SceneSpec::Heightmap(p) | SceneSpec::Vox(p) => Some(p),
            _ => None,
        }
    }

    /// Whether `--size` applies.
    pub fn is_procedural(&self) -> bool {
        !matches!(self, SceneSpec::Heightmap(_) | SceneSpec::Vox(_))
    }
}

impl FromStr for SceneSpec {
    type Err = SceneError;
    fn from_str(s: &str) -> Result<Self, SceneError> {
        Ok(match s {
            "terrain" => SceneSpec::Terrain { caves: false },
            "terrain:caves" => SceneSpec::Terrain { caves: true },
            "balls" => SceneSpec::Balls,
            "hairball" => SceneSpec::Hairball,
            _ => {
                if let Some(f) = s.strip_prefix("heightmap:").filter(|f| !f.is_empty()) {
                    SceneSpec::Heightmap(PathBuf::from(f))
                } else if let Some(f) = s.strip_prefix("vox:").filter(|f| !f.is_empty()) {
                    SceneSpec::Vox(PathBuf::from(f))
                } else {
                    return Err(SceneError::UnknownScene(s.to_string()));
                }
            }
        })
    }
}

/// A viewpoint.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct View {
    /// Eye position.
    pub eye: [f64; 3],
    /// Look-at point.
    pub target: [f64; 3],
    /// Vertical field of view, degrees.
    pub fov: f64,
}

/// Parse `.vox` bytes and place their voxels, as `vox:FILE` does (the
/// fuzz target for the .vox loader): an error, never a panic. Returns the
/// number of voxels placed.
pub fn vox_voxels_from_bytes(bytes: &[u8]) -> Result<usize, String> {
    let data = vox::parse(bytes)?;
    vox::voxels(&data).map(|(v, _)| v.len())
}

/// Decode heightmap PNG bytes, as `heightmap:FILE` does (the fuzz target
/// for the PNG loader): an error, never a panic. Returns the world's extent.
pub fn heightmap_from_bytes(bytes: &[u8]) -> Result<IVec3, String> {
    use heightfield::Heightfield;
    heightmap::Heightmap::decode(bytes).map(|h| h.extent())
}

/// Build `spec` at `size` voxels (procedural scenes only) from `seed`.
pub fn build_scene(
    spec: &SceneSpec,
    size: IVec3,
    seed: u64,
    progress: &ProgressBar,
) -> Result<SceneWorld, SceneError> {
    if spec.is_procedural() {
        budget::check_world("world.size", size)?;
    }
    let (store, lo, hi) = match spec {
        SceneSpec::Terrain { caves } => {
            let t = Terrain::new(size, seed, *caves);
            (
                voxelize(&t, terrain::palette(), progress),
                IVec3::ZERO,
                size,
            )
        }
        SceneSpec::Balls => {
            let prims = shapes::balls(size, seed);
            (
                rasterize(&prims, size, shapes::palette(), progress),
                IVec3::ZERO,
                size,
            )
        }
        SceneSpec::Hairball => {
            let prims = shapes::hairball(size, seed);
            (
                rasterize(&prims, size, shapes::palette(), progress),
                IVec3::ZERO,
                size,
            )
        }
        SceneSpec::Heightmap(path) => {
            let hm = Heightmap::load(path)?;
            let ext = hm.extent();
            let what = path.display().to_string();
            budget::check_world(&what, ext)?;
            // A rough or tall map stores far more bricks a column than
            // the estimate above allows for: count them from the heights.
            budget::check_stored_bricks(
                &what,
                heightfield::stored_bricks(&hm),
                budget::grid_bytes(ext),
            )?;
            (
                voxelize(&hm, Heightmap::palette(), progress),
                IVec3::ZERO,
                ext,
            )
        }
        SceneSpec::Vox(path) => vox::load(path)?,
    };
    let mut world = SceneWorld::new(store, lo, hi)?;
    if let SceneSpec::Terrain { .. } = spec {
        name_terrain_materials(&mut world);
    }
    Ok(world)
}

/// Give a terrain world's materials their names.
fn name_terrain_materials(world: &mut SceneWorld) {
    for (id, name) in terrain::NAMES {
        let def = MaterialDef {
            color: world.store().palette().rgb(*id),
            kind: MaterialKind::Solid,
            density: 2.5,
        };
        let _ = world.materials.register_at(*id, name, def);
    }
}
