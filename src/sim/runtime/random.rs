//! Deterministic randomness for kernels: `c.random(x, y, z, k)` is a pure
//! function of the world seed, tick, script and position.

/// What keys a step's random numbers: `c.random(x, y, z, k)` is a pure
/// function of (world seed, tick, script, x, y, z, k), so a world is
/// reproducible whatever the thread count, and across a stop and resume.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct StepKey {
    /// The world's seed.
    pub seed: u64,
    /// The tick being computed.
    pub tick: u64,
    /// A hash of the script's name.
    pub script: u64,
}

fn mix64(mut z: u64) -> u64 {
    // SplitMix64's finaliser: a bijection with full avalanche.
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

impl StepKey {
    /// The key of `script` at `tick` in a world of `seed`.
    pub fn new(seed: u64, tick: u64, script: &str) -> Self {
        let script = crate::persist::bytes::fnv1a(script.as_bytes());
        StepKey { seed, tick, script }
    }

    /// A uniform number in [0, 1) for the position (x, y, z) and counter k
    /// (each truncated to a whole number).
    pub fn random(&self, x: f64, y: f64, z: f64, k: f64) -> f64 {
        let mut h = mix64(self.seed ^ 0x9e37_79b9_7f4a_7c15);
        for v in [
            self.tick,
            self.script,
            x as i64 as u64,
            y as i64 as u64,
            z as i64 as u64,
            k as i64 as u64,
        ] {
            h = mix64(h ^ v);
        }
        (h >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
    }
}
