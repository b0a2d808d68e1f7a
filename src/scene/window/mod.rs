//! The render window of a streamed world: the square of chunk columns around
//! the camera that the tracers see, kept in one [`SceneWorld`] whose brick
//! grid slides toroidally, with a byte-budgeted LRU cache of the columns that
//! left it and fetcher threads that generate the ones that enter.
//!
//! A column enters in one of three ways, cheapest first:
//! - **live**: it belongs to the simulated region, whose bricks the engine
//!   sends (the caller passes that world in); it is copied from there;
//! - **cached**: it was generated before and is still in the cache;
//! - **coarse**: otherwise a stand-in (each brick column a stack of uniform
//!   bricks at the sampled height, in the surface's colour) is installed at
//!   once, and the exact column is requested from the fetchers. The frame is
//!   never held up by generation: it shows the stand-in until the exact
//!   column arrives, nearest columns first.
//!
//! Memory is bounded by the view, not the world: the window holds
//! (2r + 1)² columns, and the cache holds what the budget leaves, least
//! recently used first out. Cached columns are LZ4-compressed (van
//! Wingerden §3.2.3 keeps its chunk cache the same way): a terrain column
//! shrinks several times, and one exact-size allocation per column makes
//! the cache's byte count the memory it really holds.

mod cache;
mod memory;
mod pack;
#[cfg(test)]
mod tests;

use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use crossbeam_channel::{Receiver, Sender, unbounded};
use glam::{DVec3, IVec2, IVec3};
use rustc_hash::{FxHashMap, FxHashSet};

use self::cache::ColumnCache;
use super::{CHUNK_BRICKS, CHUNK_VOXELS, ChunkGen, SceneError, SceneWorld, chunk_column_of};
use crate::world::{BRICK_EDGE, BrickContent, BrickStore, OCC_EDGE};

/// How large a window is and what it may cost.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct WindowSettings {
    /// Chunk columns from the centre column to the window's edge: the
    /// window is `2 radius + 1` columns square.
    pub radius: i32,
    /// The process's resident memory target: the cache gets what the
    /// window and everything else in the process (measured once, by
    /// [`RenderWindow::measure_overhead`]) leave.
    pub budget_bytes: u64,
    /// Fetcher threads generating exact columns.
    pub fetchers: usize,
}

impl WindowSettings {
    /// The window's radius for a view distance in voxels (at least one
    /// column beyond the camera's own).
    pub fn radius_for(view_distance: f64) -> i32 {
        ((view_distance / CHUNK_VOXELS as f64).ceil() as i32).max(1)
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Column {
    /// The stand-in, exact bricks requested.
    Coarse,
    /// The exact bricks (or a live copy, or nothing: outside the world).
    Exact,
}

type Bricks = Vec<(IVec3, BrickContent)>;

/// What the fetchers lay over a generated column before it enters: the
/// edits a world store holds for it (chunks stored since they were edited,
/// by a simulated region that has moved on). It replaces the bricks of
/// every chunk it has stored and leaves the rest as generated. An error
/// (the store could not be read) leaves the column's stand-in up, and the
/// column is asked for again.
pub type ColumnOverlay =
    Arc<dyn Fn(IVec2, &mut Vec<(IVec3, BrickContent)>) -> Result<(), String> + Send + Sync>;

/// A fetch request: the column and the request's number, so that an answer
/// to a cancelled request is recognised when it arrives.
type Request = (IVec2, u64);
/// A fetcher's answer: the column's bricks, or None if its stored edits
/// could not be read.
type Answer = (IVec2, u64, Option<Bricks>);

/// How often a window measures the rest of the process again.
pub const REMEASURE: Duration = Duration::from_secs(5);

/// What a window holds and has done, for `/status` and the benchmarks.
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize)]
pub struct WindowStats {
    /// Columns in the window.
    pub columns: usize,
    /// Columns still showing their stand-in.
    pub coarse: usize,
    /// Exact columns requested and not yet back.
    pub in_flight: usize,
    /// Bytes of the window's bricks and grid.
    pub window_bytes: u64,
    /// Bytes of cached columns.
    pub cache_bytes: u64,
    /// Cached columns.
    pub cache_columns: usize,
    /// Columns the fetchers generated.
    pub generated: u64,
    /// Columns that re-entered from the cache.
    pub cache_hits: u64,
    /// Columns dropped from the cache to stay in budget.
    pub evicted: u64,
    /// The rest of the process's resident memory, as measured once the
    /// first window was exact and every few seconds after, when it grew
    /// (0 until measured).
    pub overhead_bytes: u64,
    /// Times the window moved.
    pub slides: u64,
    /// Milliseconds the last move took.
    pub slide_ms: f64,
}

/// The window; see the module docs.
pub struct RenderWindow {
    world: SceneWorld,
    gen_: Arc<ChunkGen>,
    live: Option<(IVec2, IVec2)>,
    center: IVec2,
    settings: WindowSettings,
    columns: FxHashMap<IVec2, Column>,
    /// Columns requested and not answered, with their request's number.
    in_flight: FxHashMap<IVec2, u64>,
    next_request: u64,
    cache: ColumnCache,
    requests: Option<Sender<Request>>,
    results: Receiver<Answer>,
    workers: Vec<JoinHandle<()>>,
    stats: WindowStats,
    /// Bricks whose grid cells changed since [`take_changed`](Self::take_changed)
    /// (RenderWindow::take_changed), kept only when tracked (for a GPU
    /// copy of the grid).
    changed: Option<Vec<IVec3>>,
    /// The cache's share of the budget when the rest was first measured,
    /// and when it was last measured.
    measured: Option<(u64, Instant)>,
}

impl RenderWindow {
    /// A window around `eye` over `gen`'s world. Chunk columns `live`
    /// `[min, max)` are the simulated region, copied from the world passed to
    /// [`update`](Self::update) instead of generated. The fetchers lay
    /// `overlay` (the stored edits) over every column they generate.
    pub fn new(
        gen_: Arc<ChunkGen>,
        live: Option<(IVec2, IVec2)>,
        settings: WindowSettings,
        eye: DVec3,
        live_world: Option<&SceneWorld>,
        overlay: Option<ColumnOverlay>,
    ) -> Result<Self, SceneError> {
        let r = settings.radius.max(1);
        let center = Self::column_of(eye);
        let (lo, hi) = Self::bounds(center, r, gen_.height());
        let settings = WindowSettings {
            radius: r,
            fetchers: settings.fetchers.max(1),
            budget_bytes: Self::affordable(settings.budget_bytes, hi - lo)?,
        };
        let world = SceneWorld::new(BrickStore::new(gen_.palette().clone()), lo, hi)?;
        let (req_tx, req_rx) = unbounded::<Request>();
        let (res_tx, res_rx) = unbounded::<Answer>();
        let workers = (0..settings.fetchers)
            .map(|i| {
                let rx = req_rx.clone();
                let tx = res_tx.clone();
                let g = gen_.clone();
                let overlay = overlay.clone();
                std::thread::Builder::new()
                    .name(format!("fetch-{i}"))
                    .spawn(move || {
                        for (c, n) in rx.iter() {
                            let mut out = Vec::new();
                            g.generate(c, &mut out);
                            let ok = overlay.as_ref().is_none_or(|o| o(c, &mut out).is_ok());
                            if tx.send((c, n, ok.then_some(out))).is_err() {
                                break;
                            }
                        }
                    })
            })
            .collect::<Result<Vec<_>, _>>()
            .map_err(|e| SceneError::Threads(e.to_string()))?;
        let mut w = RenderWindow {
            world,
            gen_,
            live,
            center,
            settings,
            columns: FxHashMap::default(),
            in_flight: FxHashMap::default(),
            next_request: 0,
            cache: ColumnCache::default(),
            requests: Some(req_tx),
            results: res_rx,
            workers,
            stats: WindowStats::default(),
            changed: None,
            measured: None,
        };
        for c in w.window_columns() {
            w.enter(c, live_world);
        }
        w.world.grid = crate::world::BrickGrid::build(
            &w.world.store,
            w.world.grid.origin(),
            w.world.grid.dims(),
        )?;
        w.world.store.take_modified();
        w.request();
        Ok(w)
    }

    fn column_of(eye: DVec3) -> IVec2 {
        // Clamped as the engine clamps it: far enough for any flight, and
        // the window's voxel bounds cannot overflow.
        let v = |x: f64| x.floor().clamp(-1e9, 1e9) as i32;
        chunk_column_of(v(eye.x), v(eye.z))
    }

    fn bounds(center: IVec2, r: i32, height: i32) -> (IVec3, IVec3) {
        let lo = (center - IVec2::splat(r)) * CHUNK_VOXELS;
        let hi = (center + IVec2::splat(r + 1)) * CHUNK_VOXELS;
        // Whole occupancy cells in y, so the grid's dims equal the bounds'.
        let cell = BRICK_EDGE * OCC_EDGE;
        let top = (height.max(1) + cell - 1) / cell * cell;
        (IVec3::new(lo.x, 0, lo.y), IVec3::new(hi.x, top, hi.y))
    }

    fn window_columns(&self) -> Vec<IVec2> {
        let r = self.settings.radius;
        let c = self.center;
        (c.y - r..=c.y + r)
            .flat_map(|z| (c.x - r..=c.x + r).map(move |x| IVec2::new(x, z)))
            .collect()
    }

    fn in_window(&self, c: IVec2) -> bool {
        (c - self.center).abs().max_element() <= self.settings.radius
    }

    fn is_live(&self, c: IVec2) -> bool {
        in_region(self.live, c)
    }

    /// Brick coordinates of column `c` (every height).
    fn column_bricks(&self, c: IVec2) -> impl Iterator<Item = IVec3> + use<> {
        let ny = self.world.grid.dims().y;
        let b0 = c * CHUNK_BRICKS;
        (0..CHUNK_BRICKS).flat_map(move |z| {
            (0..CHUNK_BRICKS)
                .flat_map(move |x| (0..ny).map(move |y| IVec3::new(b0.x + x, y, b0.y + z)))
        })
    }

    /// The world the tracers see: the window's bricks, grid and bounds.
    pub fn world(&self) -> &SceneWorld {
        &self.world
    }

    /// What the window holds now.
    pub fn stats(&self) -> WindowStats {
        let mut s = self.stats;
        s.columns = self.columns.len();
        s.coarse = self
            .columns
            .values()
            .filter(|c| **c == Column::Coarse)
            .count();
        s.in_flight = self.in_flight.len();
        s.window_bytes = self.window_bytes();
        s.cache_bytes = self.cache.bytes();
        s.cache_columns = self.cache.len();
        s
    }

    /// Keep a list of the bricks whose grid cells change (slides included),
    /// for whoever mirrors the grid (the GPU tracer) to
    /// [`take_changed`](Self::take_changed).
    pub fn track_changes(&mut self) {
        self.changed.get_or_insert_with(Vec::new);
    }

    /// Colour the window's world with the engine's palette (the
    /// simulation's and `materials.lua`'s colours; a hot reload recolours).
    /// Bricks whose LOD colours change count as changed; columns that enter
    /// later take their LOD colours from it too.
    pub fn set_palette(&mut self, palette: crate::world::Palette) {
        let recoloured = self.world.set_palette(palette);
        if let Some(c) = self.changed.as_mut() {
            c.extend(recoloured);
        }
    }

    /// The bricks whose grid cells changed since the last call (empty
    /// unless [`track_changes`](Self::track_changes) was called).
    pub fn take_changed(&mut self) -> Vec<IVec3> {
        self.changed
            .as_mut()
            .map(std::mem::take)
            .unwrap_or_default()
    }

    fn patch(&mut self) {
        let c = self.world.apply_edits();
        if let Some(v) = self.changed.as_mut() {
            v.extend(c);
        }
    }

    /// Follow the camera to `eye`, copy the live region's changed bricks
    /// (`changed`, read from `live_world`), install the exact columns the
    /// fetchers finished, request more and keep the cache in budget. Never
    /// waits for generation.
    pub fn update(&mut self, eye: DVec3, live_world: Option<&SceneWorld>, changed: &[IVec3]) {
        self.cache.tick();
        let c = Self::column_of(eye);
        if c != self.center {
            self.slide(c, live_world);
        }
        if let Some(lw) = live_world {
            for &b in changed {
                let col = chunk_column_of(b.x * BRICK_EDGE, b.z * BRICK_EDGE);
                if self.is_live(col) && self.in_window(col) {
                    self.world.store.set_brick(b, lw.store.content(b));
                }
            }
        }
        while let Ok((col, n, bricks)) = self.results.try_recv() {
            self.arrived(col, n, bricks);
        }
        self.patch();
        self.request();
        self.remeasure();
        self.evict();
    }

    /// The simulated region moved to chunk columns `live` `[min, max)`;
    /// `left` are the columns it covered since the last call and no longer
    /// does (all of them, when it moved more than once in between). The
    /// window's live columns are copied whole from `live_world` (the
    /// engine's new region: edits the window missed included); the columns
    /// it left are fetched again, with the stored edits laid over them, and
    /// show their last bricks until then. Cached copies of either are
    /// dropped, and requests in flight for them cancelled: they are stale.
    pub fn set_live(&mut self, live: (IVec2, IVec2), live_world: &SceneWorld, left: &[IVec2]) {
        let old = self.live.replace(live);
        let was_live = |c: IVec2| in_region(old, c);
        let stale: FxHashSet<IVec2> = left
            .iter()
            .copied()
            .chain(self.window_columns().into_iter().filter(|c| was_live(*c)))
            .filter(|c| !self.is_live(*c))
            .collect();
        let live = self.live;
        self.cache
            .drop_where(|c| in_region(live, c) || stale.contains(&c));
        for col in self.window_columns() {
            if !self.gen_.contains(col) {
                continue;
            }
            if self.is_live(col) {
                self.in_flight.remove(&col);
                self.clear(col);
                self.enter(col, Some(live_world));
            } else if stale.contains(&col) {
                // Its bricks stay until the fetched ones replace them.
                self.in_flight.remove(&col);
                self.columns.insert(col, Column::Coarse);
            }
        }
        self.patch();
        self.request();
    }

    /// Wait up to `limit` for every column in the window to be exact (for
    /// the first frame of a benchmark or a test); returns whether they are.
    pub fn settle(&mut self, limit: Duration) -> bool {
        let end = Instant::now() + limit;
        while self.columns.values().any(|c| *c == Column::Coarse) {
            let left = end.saturating_duration_since(Instant::now());
            match self.results.recv_timeout(left) {
                Ok((col, n, bricks)) => self.arrived(col, n, bricks),
                Err(_) => break,
            }
            self.request();
        }
        self.patch();
        self.evict();
        !self.columns.values().any(|c| *c == Column::Coarse)
    }

    fn arrived(&mut self, col: IVec2, n: u64, bricks: Option<Bricks>) {
        // An answer to a cancelled request (its column became live, or its
        // stored edits changed since): stale.
        if self.in_flight.get(&col) != Some(&n) {
            return;
        }
        self.in_flight.remove(&col);
        // The stored edits could not be read: asked for again.
        let Some(bricks) = bricks else { return };
        self.stats.generated += 1;
        if self.is_live(col) {
            return;
        }
        if self.columns.get(&col) == Some(&Column::Coarse) {
            self.clear(col);
            self.install_generated(bricks);
            // When it leaves, its bricks move into the cache.
            self.columns.insert(col, Column::Exact);
        } else if !self.columns.contains_key(&col) {
            self.cache.put(col, &bricks);
        }
    }

    /// Put generated bricks (with any stored edits over them) into the
    /// window. They were encoded with the generator's palette: once the
    /// engine's palette differs (a simulation's colours, `materials.lua`),
    /// the LOD colours of mixed bricks are computed again from the
    /// window's.
    fn install_generated(&mut self, bricks: Bricks) {
        let palette = (self.world.store.palette() != self.gen_.palette())
            .then(|| self.world.store.palette().clone());
        for (b, content) in bricks {
            let content = match (content, &palette) {
                (BrickContent::Mixed(brick), Some(p)) => BrickContent::Mixed(brick.with_palette(p)),
                (content, _) => content,
            };
            self.world.store.set_brick(b, content);
        }
    }

    /// Put bricks encoded with the window's palette into the window.
    fn install(&mut self, bricks: Bricks) {
        for (b, content) in bricks {
            self.world.store.set_brick(b, content);
        }
    }

    /// Remove column `col`'s bricks from the window; returns the exact ones.
    fn clear(&mut self, col: IVec2) -> Bricks {
        let mut out = Vec::new();
        for b in self.column_bricks(col) {
            if self.world.store.cell(b) != crate::world::Cell::Empty {
                out.push((b, self.world.store.content(b)));
                self.world.store.set_brick(b, BrickContent::Empty);
            }
        }
        out
    }

    fn enter(&mut self, col: IVec2, live_world: Option<&SceneWorld>) {
        if !self.gen_.contains(col) {
            self.columns.insert(col, Column::Exact);
            return;
        }
        if self.is_live(col)
            && let Some(lw) = live_world
        {
            for b in self.column_bricks(col) {
                let content = lw.store.content(b);
                if content != BrickContent::Empty {
                    self.world.store.set_brick(b, content);
                }
            }
            self.columns.insert(col, Column::Exact);
            return;
        }
        // Cached columns are kept as voxels and encoded afresh, with the
        // window's palette.
        if let Some(bricks) = self.cache.take(col, self.world.store.palette()) {
            self.stats.cache_hits += 1;
            self.install(bricks);
            self.columns.insert(col, Column::Exact);
            return;
        }
        let mut coarse = Vec::new();
        self.gen_.generate_coarse(col, &mut coarse);
        self.install(coarse);
        self.columns.insert(col, Column::Coarse);
    }

    fn slide(&mut self, to: IVec2, live_world: Option<&SceneWorld>) {
        let t = Instant::now();
        // Edits not yet in the grid go in first: the slide forgets the
        // store's record of them.
        self.patch();
        let old = self.window_columns();
        self.center = to;
        for col in old {
            if self.in_window(col) {
                continue;
            }
            let state = self.columns.remove(&col);
            let bricks = self.clear(col);
            if state == Some(Column::Exact) && !self.is_live(col) && self.gen_.contains(col) {
                self.cache.put(col, &bricks);
            }
        }
        for col in self.window_columns() {
            if !self.columns.contains_key(&col) {
                self.enter(col, live_world);
                if self.changed.is_some() {
                    let cells: Vec<IVec3> = self.column_bricks(col).collect();
                    if let Some(v) = self.changed.as_mut() {
                        v.extend(cells);
                    }
                }
            }
        }
        let (lo, hi) = Self::bounds(to, self.settings.radius, self.gen_.height());
        self.world.grid.slide(&self.world.store, lo >> 3);
        self.world.bounds = (lo, hi);
        // The slide re-read every entering cell; the cleared ones are
        // outside the window now.
        self.world.store.take_modified();
        self.stats.slides += 1;
        self.stats.slide_ms = t.elapsed().as_secs_f64() * 1e3;
    }

    fn request(&mut self) {
        let cap = self.settings.fetchers * 4;
        if self.in_flight.len() >= cap {
            return;
        }
        let mut want: Vec<IVec2> = self
            .columns
            .iter()
            .filter(|(c, s)| **s == Column::Coarse && !self.in_flight.contains_key(*c))
            .map(|(c, _)| *c)
            .collect();
        let center = self.center;
        want.sort_by_key(|c| ((*c - center).length_squared(), c.x, c.y));
        let Some(tx) = &self.requests else { return };
        for c in want.into_iter().take(cap - self.in_flight.len()) {
            self.next_request += 1;
            if tx.send((c, self.next_request)).is_ok() {
                self.in_flight.insert(c, self.next_request);
            }
        }
    }
}

/// Whether chunk column `c` lies in the region `[min, max)`, if any.
fn in_region(region: Option<(IVec2, IVec2)>, c: IVec2) -> bool {
    region.is_some_and(|(lo, hi)| c.cmpge(lo).all() && c.cmplt(hi).all())
}

impl Drop for RenderWindow {
    fn drop(&mut self) {
        // Closing the request channel ends the fetchers after their column.
        self.requests = None;
        for w in self.workers.drain(..) {
            let _ = w.join();
        }
    }
}
