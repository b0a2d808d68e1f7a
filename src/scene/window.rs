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

use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use crossbeam_channel::{Receiver, Sender, unbounded};
use glam::{DVec3, IVec2, IVec3};
use rustc_hash::{FxHashMap, FxHashSet};

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

struct Cached {
    /// [`pack`]ed bricks, in one allocation of exactly their size.
    packed: Box<[u8]>,
    used: u64,
}

impl Cached {
    fn bytes(&self) -> u64 {
        // The allocation plus the map entry.
        self.packed.len() as u64 + 64
    }
}

/// Buffers [`pack`] reuses: packing allocates only its exact-size result
/// (no over-sized compression buffer shrunk in place, which would leave
/// the heap fragmented by every cached column).
#[derive(Default)]
struct PackScratch {
    raw: Vec<u8>,
    out: Vec<u8>,
}

/// A column's bricks as LZ4-compressed bytes: per brick its column-local
/// position (`u8` x, `u16` y, `u8` z) and `u8` tag, then the uniform
/// material or the 512 dense materials of a mixed brick.
fn pack(col: IVec2, bricks: &Bricks, scratch: &mut PackScratch) -> Box<[u8]> {
    let raw = &mut scratch.raw;
    raw.clear();
    let mut dense = [0u8; crate::world::BRICK_VOXELS];
    let base = col * CHUNK_BRICKS;
    for (b, c) in bricks {
        raw.push((b.x - base.x) as u8);
        raw.extend_from_slice(&(b.y as u16).to_le_bytes());
        raw.push((b.z - base.y) as u8);
        match c {
            BrickContent::Empty => raw.push(0),
            BrickContent::Uniform(m) => raw.extend_from_slice(&[1, *m]),
            BrickContent::Mixed(_) => {
                raw.push(2);
                c.to_dense(&mut dense);
                raw.extend_from_slice(&dense);
            }
        }
    }
    let out = &mut scratch.out;
    out.resize(4 + lz4_flex::block::get_maximum_output_size(raw.len()), 0);
    out[..4].copy_from_slice(&(raw.len() as u32).to_le_bytes());
    // The buffer holds the largest output, so this cannot fail; if it did,
    // the column would fail to unpack and be generated again.
    let n = lz4_flex::block::compress_into(raw, &mut out[4..]).unwrap_or(0);
    out[..4 + n].into()
}

/// The bricks [`pack`] packed (None if the bytes are not a packed column).
fn unpack(col: IVec2, packed: &[u8], palette: &crate::world::Palette) -> Option<Bricks> {
    let raw = lz4_flex::decompress_size_prepended(packed).ok()?;
    let base = col * CHUNK_BRICKS;
    let mut out = Vec::new();
    let mut i = 0;
    let mut dense = [0u8; crate::world::BRICK_VOXELS];
    while i < raw.len() {
        let h = raw.get(i..i + 5)?;
        let b = IVec3::new(
            base.x + h[0] as i32,
            u16::from_le_bytes([h[1], h[2]]) as i32,
            base.y + h[3] as i32,
        );
        i += 5;
        let content = match h[4] {
            0 => BrickContent::Empty,
            1 => {
                i += 1;
                BrickContent::Uniform(*raw.get(i - 1)?)
            }
            2 => {
                let n = crate::world::BRICK_VOXELS;
                dense.copy_from_slice(raw.get(i..i + n)?);
                i += n;
                BrickContent::from_dense(&dense, palette)
            }
            _ => return None,
        };
        out.push((b, content));
    }
    Some(out)
}

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
    /// first window was exact (0 until measured).
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
    cache: FxHashMap<IVec2, Cached>,
    cache_bytes: u64,
    clock: u64,
    requests: Option<Sender<Request>>,
    results: Receiver<Answer>,
    workers: Vec<JoinHandle<()>>,
    stats: WindowStats,
    scratch: PackScratch,
    /// Bricks whose grid cells changed since [`take_changed`]
    /// (RenderWindow::take_changed), kept only when tracked (for a GPU
    /// copy of the grid).
    changed: Option<Vec<IVec3>>,
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
        let settings = WindowSettings {
            radius: r,
            fetchers: settings.fetchers.max(1),
            ..settings
        };
        let center = Self::column_of(eye);
        let (lo, hi) = Self::bounds(center, r, gen_.height());
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
            cache: FxHashMap::default(),
            cache_bytes: 0,
            clock: 0,
            requests: Some(req_tx),
            results: res_rx,
            workers,
            stats: WindowStats::default(),
            scratch: PackScratch::default(),
            changed: None,
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
        self.live
            .is_some_and(|(lo, hi)| c.cmpge(lo).all() && c.cmplt(hi).all())
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
        s.cache_bytes = self.cache_bytes;
        s.cache_columns = self.cache.len();
        s
    }

    fn window_bytes(&self) -> u64 {
        let store = &self.world.store;
        (store.pool().bytes()
            + store.pool().index_bytes()
            + self.world.grid.bytes()
            + store.non_empty_bricks() * 24) as u64
    }

    /// Keep a list of the bricks whose grid cells change (slides included),
    /// for whoever mirrors the grid (the GPU tracer) to
    /// [`take_changed`](Self::take_changed).
    pub fn track_changes(&mut self) {
        self.changed.get_or_insert_with(Vec::new);
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

    /// Measure what the process holds besides the window and its cache
    /// (code, threads, the simulation, its own world copy…) from its
    /// resident memory now; the cache's allowance is the budget less this
    /// and the window. Call it once the first window is exact.
    pub fn measure_overhead(&mut self) {
        let rss = crate::scene::budget::rss_kb() * 1024;
        self.stats.overhead_bytes = rss.saturating_sub(self.window_bytes() + self.cache_bytes);
        self.evict();
    }

    /// Follow the camera to `eye`, copy the live region's changed bricks
    /// (`changed`, read from `live_world`), install the exact columns the
    /// fetchers finished, request more and keep the cache in budget. Never
    /// waits for generation.
    pub fn update(&mut self, eye: DVec3, live_world: Option<&SceneWorld>, changed: &[IVec3]) {
        self.clock += 1;
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
        let was_live =
            |c: IVec2| old.is_some_and(|(lo, hi)| c.cmpge(lo).all() && c.cmplt(hi).all());
        let stale: FxHashSet<IVec2> = left
            .iter()
            .copied()
            .chain(self.window_columns().into_iter().filter(|c| was_live(*c)))
            .filter(|c| !self.is_live(*c))
            .collect();
        let gone: Vec<IVec2> = self
            .cache
            .keys()
            .copied()
            .filter(|c| self.is_live(*c) || stale.contains(c))
            .collect();
        for c in gone {
            if let Some(e) = self.cache.remove(&c) {
                self.cache_bytes -= e.bytes();
            }
        }
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
            self.install(&bricks);
            // When it leaves, its bricks move into the cache.
            self.columns.insert(col, Column::Exact);
        } else if !self.columns.contains_key(&col) {
            self.cache_put(col, bricks);
        }
    }

    fn install(&mut self, bricks: &Bricks) {
        for (b, content) in bricks {
            self.world.store.set_brick(*b, content.clone());
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

    fn cache_put(&mut self, col: IVec2, bricks: Bricks) {
        let entry = Cached {
            packed: pack(col, &bricks, &mut self.scratch),
            used: self.clock,
        };
        self.cache_bytes += entry.bytes();
        if let Some(old) = self.cache.insert(col, entry) {
            self.cache_bytes -= old.bytes();
        }
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
        if let Some(c) = self.cache.remove(&col) {
            self.cache_bytes -= c.bytes();
            if let Some(bricks) = unpack(col, &c.packed, self.gen_.palette()) {
                self.stats.cache_hits += 1;
                self.install(&bricks);
                self.columns.insert(col, Column::Exact);
                return;
            }
        }
        let mut coarse = Vec::new();
        self.gen_.generate_coarse(col, &mut coarse);
        self.install(&coarse);
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
                self.cache_put(col, bricks);
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

    fn evict(&mut self) {
        let allowance = self
            .settings
            .budget_bytes
            .saturating_sub(self.window_bytes() + self.stats.overhead_bytes);
        if self.cache_bytes <= allowance {
            return;
        }
        let mut by_age: Vec<(u64, IVec2)> = self.cache.iter().map(|(c, e)| (e.used, *c)).collect();
        by_age.sort_by_key(|(used, c)| (*used, c.x, c.y));
        for (_, c) in by_age {
            if self.cache_bytes <= allowance {
                break;
            }
            if let Some(e) = self.cache.remove(&c) {
                self.cache_bytes -= e.bytes();
                self.stats.evicted += 1;
            }
        }
    }
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::SceneSpec;

    fn gen_(size: Option<IVec3>) -> Arc<ChunkGen> {
        Arc::new(ChunkGen::new(&SceneSpec::Terrain { caves: false }, size, 64, 4).unwrap())
    }

    /// Every cell of `world`'s (toroidal) grid is occupied exactly where a
    /// grid built afresh from `bricks` is.
    fn assert_grid_follows(world: &SceneWorld, bricks: &BrickStore) {
        let fresh =
            crate::world::BrickGrid::build(bricks, world.grid.origin(), world.grid.dims()).unwrap();
        let d = world.grid.dims();
        for z in 0..d.z {
            for y in 0..d.y {
                for x in 0..d.x {
                    let l = IVec3::new(x, y, z);
                    assert_eq!(
                        world.grid.pointer(l) != 0,
                        fresh.pointer(l) != 0,
                        "cell {l}: the grid follows the bricks"
                    );
                }
            }
        }
    }

    /// The window after a flight, settled, holds exactly the bricks a
    /// direct generation of its columns gives, and its grid agrees.
    #[test]
    fn a_settled_window_equals_its_columns_generated_directly() {
        let g = gen_(None);
        let settings = WindowSettings {
            radius: 2,
            budget_bytes: 64 << 20,
            fetchers: 2,
        };
        let mut w = RenderWindow::new(
            g.clone(),
            None,
            settings,
            DVec3::new(10.0, 50.0, 10.0),
            None,
            None,
        )
        .unwrap();
        assert!(
            w.stats().coarse > 0,
            "nothing is exact before the fetchers answer"
        );
        assert!(w.settle(Duration::from_secs(30)));
        for step in 0..12 {
            let eye = DVec3::new(10.0 + 45.0 * step as f64, 50.0, 10.0 - 20.0 * step as f64);
            w.update(eye, None, &[]);
        }
        // And back over the start, so cached columns re-enter.
        w.update(DVec3::new(10.0, 50.0, 10.0), None, &[]);
        assert!(w.settle(Duration::from_secs(30)));
        let s = w.stats();
        assert!(s.slides >= 6 && s.cache_hits > 0, "{s:?}");
        let world = w.world();
        let mut expect = BrickStore::new(g.palette().clone());
        for col in w.window_columns() {
            let mut v = Vec::new();
            g.generate(col, &mut v);
            for (b, c) in v {
                expect.set_brick(b, c);
            }
        }
        assert_eq!(world.store.non_empty_bricks(), expect.non_empty_bricks());
        for (b, _) in expect.iter() {
            assert_eq!(world.store.content(b), expect.content(b), "brick {b}");
        }
        assert_grid_follows(world, &expect);
    }

    #[test]
    fn packed_columns_unpack_to_the_same_bricks() {
        let g = gen_(None);
        let col = IVec2::new(-7, 12);
        let mut bricks = Vec::new();
        g.generate(col, &mut bricks);
        let packed = pack(col, &bricks, &mut PackScratch::default());
        let raw_bytes = bricks.len() * 520;
        assert!(
            packed.len() * 3 < raw_bytes,
            "{} of {raw_bytes}",
            packed.len()
        );
        assert_eq!(unpack(col, &packed, g.palette()), Some(bricks));
        assert_eq!(unpack(col, &packed[..packed.len() / 2], g.palette()), None);
    }

    /// A small budget keeps the cache small; the window itself stays whole.
    #[test]
    fn the_cache_stays_within_the_budget() {
        let g = gen_(None);
        let settings = WindowSettings {
            radius: 1,
            budget_bytes: 1 << 30,
            fetchers: 1,
        };
        let mut w =
            RenderWindow::new(g, None, settings, DVec3::new(0.0, 40.0, 0.0), None, None).unwrap();
        let fly = |w: &mut RenderWindow, step: i32| {
            w.settle(Duration::from_secs(10));
            w.update(DVec3::new(64.0 * step as f64, 40.0, 0.0), None, &[]);
            w.stats()
        };
        for step in 0..10 {
            fly(&mut w, step);
        }
        // Half of what the cache holds now, beyond the window.
        let s = w.stats();
        assert_eq!(s.evicted, 0);
        w.settings.budget_bytes = s.window_bytes + s.cache_bytes / 2;
        let budget = w.settings.budget_bytes;
        for step in 10..40 {
            let s = fly(&mut w, step);
            // The window is never cut; the cache only uses what is left.
            assert!(
                s.cache_bytes + s.window_bytes <= budget.max(s.window_bytes),
                "step {step}: {s:?}"
            );
        }
        let s = w.stats();
        assert!(s.evicted > 0 && s.cache_columns > 0, "{s:?}");
    }

    /// Live columns come from the simulated world, with its edits.
    #[test]
    fn live_columns_copy_the_simulated_world() {
        let g = gen_(Some(IVec3::new(256, 64, 256)));
        let live = (IVec2::new(1, 1), IVec2::new(3, 3));
        let mut region = g.build_region(live.0, live.1).unwrap();
        region.store.set_voxel(IVec3::new(100, 62, 100), 9);
        region.apply_edits();
        let settings = WindowSettings {
            radius: 1,
            budget_bytes: 64 << 20,
            fetchers: 1,
        };
        let eye = DVec3::new(130.0, 60.0, 130.0);
        let mut w = RenderWindow::new(g, Some(live), settings, eye, Some(&region), None).unwrap();
        assert_eq!(w.world().store.voxel(IVec3::new(100, 62, 100)), 9);
        region.store.set_voxel(IVec3::new(101, 62, 100), 9);
        let changed = region.apply_edits();
        w.update(eye, Some(&region), &changed);
        assert_eq!(w.world().store.voxel(IVec3::new(101, 62, 100)), 9);
        // Columns outside a bounded world are empty and exact.
        assert!(w.settle(Duration::from_secs(10)));
    }

    /// When the simulated region moves, its new columns are copied from the
    /// new region, and the columns it left are fetched again, with the
    /// overlay (the store's chunks) laid over the generated bricks.
    #[test]
    fn a_moved_region_is_copied_and_the_columns_it_left_are_fetched_with_the_overlay() {
        let g = gen_(Some(IVec3::new(512, 64, 512)));
        let settings = WindowSettings {
            radius: 2,
            budget_bytes: 64 << 20,
            fetchers: 1,
        };
        let mark = IVec3::new(100, 62, 100); // chunk column (1, 1)
        let (a, b) = (
            (IVec2::new(1, 1), IVec2::new(2, 2)),
            (IVec2::new(2, 1), IVec2::new(3, 2)),
        );
        let mut region_a = g.build_region(a.0, a.1).unwrap();
        region_a.store.set_voxel(mark, 9);
        region_a.apply_edits();
        // What the store holds once region A moved on: its last edit,
        // which the window's copy of the region had not seen yet.
        let left: Bricks = vec![(mark >> 3, region_a.store.content(mark >> 3))];
        region_a.store.set_voxel(mark, 8);
        region_a.apply_edits();
        let overlay: ColumnOverlay = Arc::new(move |c: IVec2, bricks: &mut Bricks| {
            if c == IVec2::new(1, 1) {
                bricks.retain(|(b, _)| *b != left[0].0);
                bricks.extend(left.iter().cloned());
            }
            Ok(())
        });
        let eye = DVec3::new(130.0, 60.0, 100.0);
        let mut w = RenderWindow::new(
            g.clone(),
            Some(a),
            settings,
            eye,
            Some(&region_a),
            Some(overlay),
        )
        .unwrap();
        assert!(w.settle(Duration::from_secs(10)));
        assert_eq!(w.world().store.voxel(mark), 8, "the live copy");
        let mut region_b = g.build_region(b.0, b.1).unwrap();
        let mark_b = IVec3::new(150, 62, 100); // chunk column (2, 1)
        region_b.store.set_voxel(mark_b, 7);
        region_b.apply_edits();
        w.set_live(b, &region_b, &[a.0]);
        w.update(eye, Some(&region_b), &[]);
        assert_eq!(w.world().store.voxel(mark_b), 7, "the new region is copied");
        assert!(w.settle(Duration::from_secs(10)));
        // The column left behind: generated, with the stored edit over it.
        assert_eq!(w.world().store.voxel(mark), 9, "the overlay is shown");
        let mut direct = Vec::new();
        g.generate(IVec2::new(1, 1), &mut direct);
        for (bk, c) in direct.iter().filter(|(bk, _)| *bk != mark >> 3) {
            assert_eq!(&w.world().store.content(*bk), c, "brick {bk}");
        }
        assert_grid_follows(w.world(), &w.world().store);
    }
}
