//! Little-endian byte writing and bounds-checked reading, shared by the
//! chunk blobs, the simulation-state blob and the legacy checkpoint files.
//! The reader never panics: every read is checked against what is left.
//! Also the one stable hash of bytes that stored and pinned values use.

/// FNV-1a of `bytes`: stable across runs, builds and platforms, so it may
/// be stored (a config's hash in the manifest, a script source's in the
/// state blob) or feed pinned results (a script's random stream).
///
/// ```
/// use brickworld::persist::bytes::fnv1a;
/// assert_eq!(fnv1a(b""), 0xcbf2_9ce4_8422_2325);
/// assert_eq!(fnv1a(b"a"), 0xaf63_dc4c_8601_ec8c);
/// ```
pub fn fnv1a(bytes: &[u8]) -> u64 {
    bytes.iter().fold(0xcbf2_9ce4_8422_2325u64, |h, &b| {
        (h ^ b as u64).wrapping_mul(0x0100_0000_01b3)
    })
}

/// How a [`StateHasher`] mixes what it is given.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Mixing {
    /// XXH3-64 of the words' little-endian bytes: every input bit reaches
    /// every output bit. The world hash of checkpoint format 6 on.
    Xxh3,
    /// FNV-1a over whole 64-bit words, as checkpoint formats 1 to 5
    /// recorded it. Kept only to check those files: a multiply carries a
    /// bit only upwards, so a change in a word's top byte reached only the
    /// hash's top byte (regression, modder probe: two worlds whose voxels
    /// differed at x ≡ 7 (mod 8) collided one time in 256, and two sign
    /// flips of channel values cancelled).
    Words,
}

/// A stable 64-bit hash of a world's state, fed word by word: the same on
/// every run, build and platform, so it may be pinned and stored.
///
/// ```
/// use brickworld::persist::bytes::{Mixing, StateHasher};
/// let hash = |top: u64, words: u64| {
///     let mut h = StateHasher::new(Mixing::Xxh3);
///     h.word(top << 56);
///     h.word(words);
///     h.finish()
/// };
/// // A change in a word's top byte changes the low bits too.
/// assert_ne!(hash(3, 10) & 0xff, hash(9, 10) & 0xff);
/// ```
pub struct StateHasher {
    fnv: u64,
    xxh3: Option<Box<twox_hash::XxHash3_64>>,
}

impl StateHasher {
    /// An empty hash.
    pub fn new(mixing: Mixing) -> Self {
        StateHasher {
            fnv: 0xcbf2_9ce4_8422_2325,
            xxh3: (mixing == Mixing::Xxh3).then(|| Box::new(twox_hash::XxHash3_64::with_seed(0))),
        }
    }

    /// Mix in one word.
    #[inline]
    pub fn word(&mut self, v: u64) {
        match &mut self.xxh3 {
            Some(x) => std::hash::Hasher::write(&mut **x, &v.to_le_bytes()),
            None => self.fnv = (self.fnv ^ v).wrapping_mul(0x0100_0000_01b3),
        }
    }

    /// Mix in `bytes` as little-endian words (a multiple of 8 bytes):
    /// the same as [`word`](Self::word) for each, in one call.
    pub fn words(&mut self, bytes: &[u8]) {
        debug_assert_eq!(bytes.len() % 8, 0);
        match &mut self.xxh3 {
            Some(x) => std::hash::Hasher::write(&mut **x, bytes),
            None => bytes
                .chunks_exact(8)
                .for_each(|c| self.word(u64::from_le_bytes(c.try_into().expect("8 bytes")))),
        }
    }

    /// The hash.
    pub fn finish(&self) -> u64 {
        match &self.xxh3 {
            Some(x) => std::hash::Hasher::finish(&**x),
            None => self.fnv,
        }
    }
}

/// An append-only little-endian writer.
#[derive(Debug, Default)]
pub struct Writer(pub Vec<u8>);

impl Writer {
    /// Append a byte.
    pub fn u8(&mut self, v: u8) {
        self.0.push(v);
    }
    /// Append a `u16`.
    pub fn u16(&mut self, v: u16) {
        self.0.extend_from_slice(&v.to_le_bytes());
    }
    /// Append a `u32`.
    pub fn u32(&mut self, v: u32) {
        self.0.extend_from_slice(&v.to_le_bytes());
    }
    /// Append a `u64`.
    pub fn u64(&mut self, v: u64) {
        self.0.extend_from_slice(&v.to_le_bytes());
    }
    /// Append an `i32`.
    pub fn i32(&mut self, v: i32) {
        self.0.extend_from_slice(&v.to_le_bytes());
    }
    /// Append an `f64`.
    pub fn f64(&mut self, v: f64) {
        self.0.extend_from_slice(&v.to_le_bytes());
    }
    /// Append a length-prefixed UTF-8 string.
    pub fn str(&mut self, s: &str) {
        self.u32(s.len() as u32);
        self.0.extend_from_slice(s.as_bytes());
    }
}

/// A bounds-checked reader over a byte slice.
#[derive(Debug)]
pub struct Reader<'a> {
    /// The bytes.
    pub data: &'a [u8],
    /// The read position.
    pub at: usize,
}

impl<'a> Reader<'a> {
    /// A reader at the start of `data`.
    pub fn new(data: &'a [u8]) -> Self {
        Reader { data, at: 0 }
    }
    /// Bytes not read yet.
    pub fn left(&self) -> usize {
        self.data.len() - self.at
    }
    /// The next `n` bytes.
    pub fn take(&mut self, n: usize) -> Result<&'a [u8], String> {
        if n > self.left() {
            return Err(format!("payload ends early at byte {}", self.at));
        }
        let s = &self.data[self.at..self.at + n];
        self.at += n;
        Ok(s)
    }
    /// A byte.
    pub fn u8(&mut self) -> Result<u8, String> {
        Ok(self.take(1)?[0])
    }
    /// A `u16`.
    pub fn u16(&mut self) -> Result<u16, String> {
        Ok(u16::from_le_bytes(self.take(2)?.try_into().expect("2")))
    }
    /// A `u32`.
    pub fn u32(&mut self) -> Result<u32, String> {
        Ok(u32::from_le_bytes(self.take(4)?.try_into().expect("4")))
    }
    /// A `u64`.
    pub fn u64(&mut self) -> Result<u64, String> {
        Ok(u64::from_le_bytes(self.take(8)?.try_into().expect("8")))
    }
    /// An `i32`.
    pub fn i32(&mut self) -> Result<i32, String> {
        Ok(i32::from_le_bytes(self.take(4)?.try_into().expect("4")))
    }
    /// An `f64`.
    pub fn f64(&mut self) -> Result<f64, String> {
        Ok(f64::from_le_bytes(self.take(8)?.try_into().expect("8")))
    }
    /// A length-prefixed UTF-8 string.
    pub fn str(&mut self) -> Result<String, String> {
        let n = self.u32()? as usize;
        String::from_utf8(self.take(n)?.to_vec()).map_err(|_| "a name is not UTF-8".to_string())
    }
    /// A count, refused above `max`.
    pub fn count(&mut self, max: usize, what: &str) -> Result<usize, String> {
        let n = self.u32()? as usize;
        if n > max {
            return Err(format!("{what} count {n} exceeds {max}"));
        }
        Ok(n)
    }
    /// Fail unless every byte was read.
    pub fn finish(&self) -> Result<(), String> {
        if self.left() != 0 {
            return Err(format!("{} trailing bytes", self.left()));
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn words_in_one_call_are_the_words_one_by_one() {
        let bytes: Vec<u8> = (0..200u32).map(|i| (i * 37 % 251) as u8).collect();
        for mixing in [Mixing::Xxh3, Mixing::Words] {
            let mut one = StateHasher::new(mixing);
            one.word(5);
            one.words(&bytes);
            let mut each = StateHasher::new(mixing);
            each.word(5);
            for c in bytes.chunks_exact(8) {
                each.word(u64::from_le_bytes(c.try_into().unwrap()));
            }
            assert_eq!(one.finish(), each.finish(), "{mixing:?}");
        }
        // Words is FNV-1a over whole words, as formats 1 to 5 recorded it.
        let mut w = StateHasher::new(Mixing::Words);
        w.word(7);
        assert_eq!(
            w.finish(),
            (0xcbf2_9ce4_8422_2325u64 ^ 7).wrapping_mul(0x0100_0000_01b3)
        );
    }
}
