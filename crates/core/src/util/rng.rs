//! A small seeded random number generator (PCG32, O'Neill 2014) with uniform and normal
//! draws. Identical streams on every platform (native, wasm32), so seeds mean the same
//! weights, latents, synthetic scans and dataset cameras everywhere.

/// PCG32: 64-bit state, 32-bit output; `stream` selects one of 2⁶³ independent sequences.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Rng {
    state: u64,
    inc: u64,
}

impl Rng {
    pub fn new(seed: u64, stream: u64) -> Self {
        let mut r = Self { state: 0, inc: (stream << 1) | 1 };
        r.next_u32();
        r.state = r.state.wrapping_add(seed);
        r.next_u32();
        r
    }

    /// The raw generator state `(state, increment)`, e.g. for checkpoints.
    pub fn state(&self) -> (u64, u64) {
        (self.state, self.inc)
    }

    /// Restore a state returned by [`Rng::state`].
    pub fn from_state(state: u64, inc: u64) -> Self {
        Self { state, inc: inc | 1 }
    }

    pub fn next_u32(&mut self) -> u32 {
        let old = self.state;
        self.state = old.wrapping_mul(6364136223846793005).wrapping_add(self.inc);
        let xorshifted = (((old >> 18) ^ old) >> 27) as u32;
        let rot = (old >> 59) as u32;
        xorshifted.rotate_right(rot)
    }

    /// Uniform in (0, 1).
    pub fn uniform(&mut self) -> f32 {
        ((self.next_u32() >> 8) as f32 + 0.5) / (1u32 << 24) as f32
    }

    /// Uniform in (lo, hi).
    pub fn range(&mut self, lo: f32, hi: f32) -> f32 {
        lo + (hi - lo) * self.uniform()
    }

    /// Uniform integer in `0..n` (`n > 0`).
    pub fn below(&mut self, n: usize) -> usize {
        ((self.uniform() as f64 * n as f64) as usize).min(n.saturating_sub(1))
    }

    /// `true` with probability `p`.
    pub fn chance(&mut self, p: f32) -> bool {
        self.uniform() < p
    }

    /// Standard normal (Box–Muller).
    pub fn normal(&mut self) -> f32 {
        let (u1, u2) = (self.uniform(), self.uniform());
        (-2.0 * u1.ln()).sqrt() * (std::f32::consts::TAU * u2).cos()
    }

    pub fn normals(&mut self, n: usize) -> Vec<f32> {
        (0..n).map(|_| self.normal()).collect()
    }
}

/// A 64-bit FNV-1a hash of a string: stable seeds derived from names (e.g. subject ids).
pub fn hash_str(s: &str) -> u64 {
    s.bytes().fold(0xcbf29ce484222325u64, |h, b| (h ^ b as u64).wrapping_mul(0x100000001b3))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn uniform_and_normal_moments() {
        let mut r = Rng::new(7, 1);
        let n = 20_000;
        let u: Vec<f32> = (0..n).map(|_| r.uniform()).collect();
        let mean = u.iter().sum::<f32>() / n as f32;
        assert!((mean - 0.5).abs() < 0.01, "{mean}");
        let z = r.normals(n);
        let m = z.iter().sum::<f32>() / n as f32;
        let var = z.iter().map(|x| (x - m).powi(2)).sum::<f32>() / n as f32;
        assert!(m.abs() < 0.03 && (var - 1.0).abs() < 0.05, "{m} {var}");
        let (s, i) = r.state();
        let mut a = Rng::from_state(s, i);
        assert_eq!(a.next_u32(), r.next_u32());
        assert_ne!(hash_str("0001"), hash_str("0002"));
    }
}
