//! The brick pool: dense storage for mixed bricks, addressed by small `Copy`
//! ids with generation counters so that a stale id can never read a reused
//! slot.

use super::brick::Brick;

/// Handle to a brick in a [`BrickPool`]. Stale handles are detected.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct BrickId {
    index: u32,
    generation: u32,
}

impl BrickId {
    /// Slot index (what the brick grid stores).
    pub fn index(self) -> u32 {
        self.index
    }
}

/// Slots of bricks with a free list; freed slots are reused.
#[derive(Debug, Default)]
pub struct BrickPool {
    bricks: Vec<Option<Brick>>,
    generations: Vec<u32>,
    free: Vec<u32>,
    live: usize,
    live_bytes: usize,
}

impl BrickPool {
    /// Store a brick, returning its id.
    pub fn insert(&mut self, brick: Brick) -> BrickId {
        self.live += 1;
        self.live_bytes += brick.bytes();
        if let Some(index) = self.free.pop() {
            let i = index as usize;
            self.generations[i] = self.generations[i].wrapping_add(1);
            self.bricks[i] = Some(brick);
            BrickId {
                index,
                generation: self.generations[i],
            }
        } else {
            let index = u32::try_from(self.bricks.len()).expect("brick pool exceeds 2^32 slots");
            assert!(index < (1 << 31), "brick pool exceeds 2^31 slots");
            self.bricks.push(Some(brick));
            self.generations.push(0);
            BrickId {
                index,
                generation: 0,
            }
        }
    }

    /// The brick behind `id`, or `None` if the id is stale.
    pub fn get(&self, id: BrickId) -> Option<&Brick> {
        if self.generations.get(id.index as usize) != Some(&id.generation) {
            return None;
        }
        self.bricks[id.index as usize].as_ref()
    }

    /// Replace the brick behind `id` in place. Returns false for a stale id.
    pub fn replace(&mut self, id: BrickId, brick: Brick) -> bool {
        if self.generations.get(id.index as usize) != Some(&id.generation) {
            return false;
        }
        let slot = &mut self.bricks[id.index as usize];
        if let Some(old) = slot.as_ref() {
            self.live_bytes -= old.bytes();
        }
        self.live_bytes += brick.bytes();
        *slot = Some(brick);
        true
    }

    /// Free the slot behind `id`. Returns the brick, or `None` if stale.
    pub fn remove(&mut self, id: BrickId) -> Option<Brick> {
        if self.generations.get(id.index as usize) != Some(&id.generation) {
            return None;
        }
        let brick = self.bricks[id.index as usize].take()?;
        self.live -= 1;
        self.live_bytes -= brick.bytes();
        self.generations[id.index as usize] = self.generations[id.index as usize].wrapping_add(1);
        self.free.push(id.index);
        Some(brick)
    }

    /// Brick in slot `index` without a generation check: for tracers that
    /// hold slot indices in a grid kept in sync with the store.
    #[inline(always)]
    pub fn slot(&self, index: u32) -> Option<&Brick> {
        self.bricks.get(index as usize).and_then(|b| b.as_ref())
    }

    /// Number of live bricks.
    pub fn len(&self) -> usize {
        self.live
    }

    /// Whether no brick is live.
    pub fn is_empty(&self) -> bool {
        self.live == 0
    }

    /// Bytes of the live bricks, heap included, plus the slot tables.
    pub fn bytes(&self) -> usize {
        self.live_bytes
            + (self.bricks.len() - self.live) * std::mem::size_of::<Option<Brick>>()
            + self.generations.len() * 4
            + self.free.len() * 4
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::world::{BrickContent, Palette};

    fn some_brick(m: u8) -> Brick {
        let mut d = [0u8; 512];
        d[3] = m;
        match BrickContent::from_dense(&d, &Palette::grey_ramp()) {
            BrickContent::Mixed(b) => b,
            _ => unreachable!(),
        }
    }

    #[test]
    fn stale_ids_are_rejected_after_slot_reuse() {
        let mut pool = BrickPool::default();
        let a = pool.insert(some_brick(1));
        assert!(pool.remove(a).is_some());
        let b = pool.insert(some_brick(2));
        assert_eq!(a.index(), b.index(), "slot is reused");
        assert!(
            pool.get(a).is_none(),
            "stale id must not read the new brick"
        );
        assert_eq!(pool.get(b).unwrap().material_index(3), 2);
        assert!(pool.remove(a).is_none());
        assert_eq!(pool.len(), 1);
    }
}
