//! What one timeline row holds: the fixed [`COLUMNS`] and [`Row`], the
//! values the engine measures each frame interval (the file that keeps
//! them is the parent module's).

/// Column names, in order.
pub const COLUMNS: [&str; 12] = [
    "tick",
    "steps_per_s",
    "active_bricks",
    "dirty_bricks",
    "frame_ms",
    "bricks_streamed",
    "rss_kb",
    "water",
    "ground_plus_sediment",
    "snow",
    "drained",
    "unix_s",
];

/// One row.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Row {
    /// Simulation tick.
    pub tick: u64,
    /// Steps per second.
    pub steps_per_s: f64,
    /// Active tiles.
    pub active_bricks: usize,
    /// Dirty bricks this tick.
    pub dirty_bricks: usize,
    /// Last frame's time.
    pub frame_ms: f64,
    /// Bricks streamed so far.
    pub bricks_streamed: u64,
    /// Resident memory, KiB.
    pub rss_kb: u64,
    /// Total water.
    pub water: f64,
    /// Total ground plus sediment.
    pub ground_plus_sediment: f64,
    /// Total snow.
    pub snow: f64,
    /// Water drained over the edges so far.
    pub drained: f64,
    /// When the row was written: seconds since the Unix epoch, to the
    /// millisecond (a world left running for days is read against the
    /// wall clock; ticks alone do not say when).
    pub unix_s: f64,
    /// Each script's time in the step, ms (the `ms:` columns, in order).
    pub script_ms: Vec<f64>,
    /// Each declared conserved total (the `total:` columns, in order).
    pub conserved: Vec<f64>,
}

impl Row {
    /// The row's values in column order ([`COLUMNS`], then the per-script
    /// ones), as the viewer's charts take them.
    pub fn values(&self) -> Vec<f64> {
        let mut v = vec![
            self.tick as f64,
            self.steps_per_s,
            self.active_bricks as f64,
            self.dirty_bricks as f64,
            self.frame_ms,
            self.bricks_streamed as f64,
            self.rss_kb as f64,
            self.water,
            self.ground_plus_sediment,
            self.snow,
            self.drained,
            self.unix_s,
        ];
        v.extend(&self.script_ms);
        v.extend(&self.conserved);
        v
    }
}
