//! Hash maps keyed by mesh ids (vertex indices, edges as index pairs) with a multiplicative
//! hasher. std's default SipHash guards against keys chosen by an attacker, which ids
//! computed here are not, and costs several times more per lookup; in wasm (one thread) that
//! shows in marching tetrahedra's edge table and the rigging's caches.

use std::collections::HashMap;
use std::hash::{BuildHasherDefault, Hasher};

/// FxHash's step (rustc's hasher): rotate, xor the word in, multiply by an odd constant.
#[derive(Clone, Copy, Default)]
pub struct IdHasher(u64);

const K: u64 = 0x51_7c_c1_b7_27_22_0a_95;

impl IdHasher {
    #[inline]
    fn add(&mut self, word: u64) {
        self.0 = (self.0.rotate_left(5) ^ word).wrapping_mul(K);
    }
}

impl Hasher for IdHasher {
    #[inline]
    fn write(&mut self, bytes: &[u8]) {
        let mut chunks = bytes.chunks_exact(8);
        for c in &mut chunks {
            self.add(u64::from_le_bytes([c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7]]));
        }
        for &b in chunks.remainder() {
            self.add(u64::from(b));
        }
    }
    #[inline]
    fn write_u8(&mut self, n: u8) {
        self.add(u64::from(n));
    }
    #[inline]
    fn write_u32(&mut self, n: u32) {
        self.add(u64::from(n));
    }
    #[inline]
    fn write_u64(&mut self, n: u64) {
        self.add(n);
    }
    #[inline]
    fn write_usize(&mut self, n: usize) {
        self.add(n as u64);
    }
    #[inline]
    fn finish(&self) -> u64 {
        self.0
    }
}

/// A `HashMap` for id keys ([`IdHasher`]).
pub type IdMap<K, V> = HashMap<K, V, BuildHasherDefault<IdHasher>>;

/// An empty [`IdMap`] with room for `n` entries.
pub fn id_map_with_capacity<K, V>(n: usize) -> IdMap<K, V> {
    IdMap::with_capacity_and_hasher(n, Default::default())
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::hash::BuildHasher;

    /// Edge keys of a 64³ grid's neighbours spread over the table: no bucket of 4096 holds
    /// more than a few times its share (the top bits pick the group, the low ones the slot).
    #[test]
    fn grid_edge_keys_spread_over_the_buckets() {
        let build = BuildHasherDefault::<IdHasher>::default();
        let mut low = vec![0u32; 4096];
        let mut high = vec![0u32; 4096];
        let mut n = 0u32;
        for a in (0..64u32 * 64 * 64).step_by(7) {
            for d in [1, 64, 64 * 64] {
                let h = build.hash_one((a, a + d));
                low[(h & 4095) as usize] += 1;
                high[(h >> 52) as usize] += 1;
                n += 1;
            }
        }
        let share = n / 4096;
        let worst = |b: &[u32]| *b.iter().max().unwrap();
        assert!(worst(&low) <= 3 * share && worst(&high) <= 3 * share, "{share}: {} / {}", worst(&low), worst(&high));
    }

    #[test]
    fn the_map_keeps_what_is_put_in() {
        let mut m: IdMap<(u32, u32), u32> = id_map_with_capacity(4);
        for i in 0..1000u32 {
            m.insert((i, i + 1), i);
        }
        assert_eq!(m.len(), 1000);
        assert!((0..1000u32).all(|i| m[&(i, i + 1)] == i));
        assert_eq!(m.get(&(1, 0)), None);
    }
}
