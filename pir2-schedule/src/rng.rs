//! A small, portable, seeded random generator (xoshiro256++ seeded by SplitMix64).
//!
//! The schedule crate must stay dependency-light and its draws must be bit-reproducible
//! across platforms and dependency upgrades, so it carries its own generator instead of
//! relying on `rand`'s unspecified `StdRng`. Same seed → same bits, everywhere.

/// Seeded xoshiro256++ generator with a Box–Muller normal sampler.
#[derive(Debug, Clone)]
pub struct Rng {
    s: [u64; 4],
}

/// Ziggurat tables (Marsaglia & Tsang 2000), computed once.
struct Tables {
    k: [u32; 128],
    w: [f32; 128],
    f: [f32; 128],
}

fn tables() -> &'static Tables {
    static T: std::sync::OnceLock<Tables> = std::sync::OnceLock::new();
    T.get_or_init(|| {
        let m1 = 2147483648.0f64;
        let vn = 9.91256303526217e-3f64;
        let mut dn = 3.442619855899f64;
        let mut tn = dn;
        let q = vn / (-0.5 * dn * dn).exp();
        let mut t = Tables {
            k: [0; 128],
            w: [0.0; 128],
            f: [0.0; 128],
        };
        t.k[0] = ((dn / q) * m1) as u32;
        t.k[1] = 0;
        t.w[0] = (q / m1) as f32;
        t.w[127] = (dn / m1) as f32;
        t.f[0] = 1.0;
        t.f[127] = (-0.5 * dn * dn).exp() as f32;
        for i in (1..=126).rev() {
            dn = (-2.0 * (vn / dn + (-0.5 * dn * dn).exp()).ln()).sqrt();
            t.k[i + 1] = ((dn / tn) * m1) as u32;
            tn = dn;
            t.f[i] = (-0.5 * dn * dn).exp() as f32;
            t.w[i] = (dn / m1) as f32;
        }
        t
    })
}

fn splitmix64(state: &mut u64) -> u64 {
    *state = state.wrapping_add(0x9E37_79B9_7F4A_7C15);
    let mut z = *state;
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

impl Rng {
    /// A generator seeded from `seed`.
    pub fn new(seed: u64) -> Self {
        let mut st = seed;
        let s = [
            splitmix64(&mut st),
            splitmix64(&mut st),
            splitmix64(&mut st),
            splitmix64(&mut st),
        ];
        Self { s }
    }

    /// An independent stream derived from this seed and a stream id (for workers, episodes).
    pub fn derive(seed: u64, stream: u64) -> Self {
        let mut st = seed ^ stream.wrapping_mul(0xD1B5_4A32_D192_ED03);
        let _ = splitmix64(&mut st);
        Self::new(splitmix64(&mut st))
    }

    /// The generator's full state (save it to continue the same stream later, e.g. when a
    /// training run resumes from a checkpoint).
    pub fn state(&self) -> [u64; 4] {
        self.s
    }

    /// A generator continuing from a [`Rng::state`]. The all-zero state (a fixed point of
    /// xoshiro) is rejected.
    pub fn from_state(s: [u64; 4]) -> Option<Self> {
        (s != [0; 4]).then_some(Self { s })
    }

    /// Next 64 random bits.
    #[inline]
    pub fn next_u64(&mut self) -> u64 {
        let s = &mut self.s;
        let result = s[0].wrapping_add(s[3]).rotate_left(23).wrapping_add(s[0]);
        let t = s[1] << 17;
        s[2] ^= s[0];
        s[3] ^= s[1];
        s[1] ^= s[2];
        s[0] ^= s[3];
        s[2] ^= t;
        s[3] = s[3].rotate_left(45);
        result
    }

    /// Uniform in `[0, 1)` with 24 bits of resolution.
    #[inline]
    pub fn uniform(&mut self) -> f32 {
        (self.next_u64() >> 40) as f32 * (1.0 / (1u64 << 24) as f32)
    }

    /// Uniform in `[0, 1)` as `f64` with 53 bits.
    #[inline]
    pub fn uniform_f64(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
    }

    /// Uniform in `[lo, hi)`.
    #[inline]
    pub fn uniform_range(&mut self, lo: f32, hi: f32) -> f32 {
        lo + (hi - lo) * self.uniform()
    }

    /// Uniform integer in `[0, n)` (`n > 0`), unbiased (Lemire's method).
    #[inline]
    pub fn below(&mut self, n: u64) -> u64 {
        assert!(n > 0, "Rng::below(0)");
        loop {
            let m = (self.next_u64() as u128) * (n as u128);
            let lo = m as u64;
            if lo >= n.wrapping_neg() % n {
                return (m >> 64) as u64;
            }
        }
    }

    /// Standard normal sample (Marsaglia–Tsang ziggurat, 128 layers; ~99% of draws cost
    /// one table lookup and one multiply).
    #[inline]
    pub fn normal(&mut self) -> f32 {
        let t = tables();
        let bits = self.next_u64();
        let hz = (bits >> 32) as u32 as i32;
        let iz = (bits & 127) as usize;
        if hz.unsigned_abs() < t.k[iz] {
            return hz as f32 * t.w[iz];
        }
        self.normal_tail(hz, iz)
    }

    #[cold]
    fn normal_tail(&mut self, mut hz: i32, mut iz: usize) -> f32 {
        let t = tables();
        const R: f32 = 3.442_62;
        loop {
            let x = hz as f32 * t.w[iz];
            if iz == 0 {
                loop {
                    let x = -(1.0 - self.uniform()).ln() * (1.0 / R);
                    let y = -(1.0 - self.uniform()).ln();
                    if y + y >= x * x {
                        return if hz > 0 { R + x } else { -R - x };
                    }
                }
            }
            if t.f[iz] + self.uniform() * (t.f[iz - 1] - t.f[iz]) < (-0.5 * x * x).exp() {
                return x;
            }
            let bits = self.next_u64();
            hz = (bits >> 32) as u32 as i32;
            iz = (bits & 127) as usize;
            if hz.unsigned_abs() < t.k[iz] {
                return hz as f32 * t.w[iz];
            }
        }
    }

    /// Fill `out` with standard normal samples.
    pub fn fill_normal(&mut self, out: &mut [f32]) {
        for v in out {
            *v = self.normal();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn state_round_trip_continues_the_stream() {
        let mut a = Rng::new(9);
        for _ in 0..5 {
            a.next_u64();
        }
        let mut b = Rng::from_state(a.state()).unwrap();
        for _ in 0..100 {
            assert_eq!(a.next_u64(), b.next_u64());
        }
        assert!(Rng::from_state([0; 4]).is_none());
    }

    #[test]
    fn same_seed_same_bits() {
        let mut a = Rng::new(7);
        let mut b = Rng::new(7);
        for _ in 0..1000 {
            assert_eq!(a.normal().to_bits(), b.normal().to_bits());
        }
        assert_ne!(Rng::new(7).next_u64(), Rng::new(8).next_u64());
    }

    #[test]
    fn moments_are_plausible() {
        let mut r = Rng::new(1);
        let n = 200_000;
        let (mut m, mut v, mut u) = (0.0f64, 0.0f64, 0.0f64);
        for _ in 0..n {
            let z = r.normal() as f64;
            m += z;
            v += z * z;
            u += r.uniform() as f64;
        }
        m /= n as f64;
        v /= n as f64;
        u /= n as f64;
        assert!(m.abs() < 0.01, "mean {m}");
        // Shape: mass within 1σ and 2σ, and the tail beyond the ziggurat's base strip.
        let mut r = Rng::new(2);
        let (mut in1, mut in2, mut tail) = (0, 0, 0);
        for _ in 0..n {
            let z = r.normal().abs();
            in1 += (z < 1.0) as usize;
            in2 += (z < 2.0) as usize;
            tail += (z > 3.442_62) as usize;
        }
        let f = |c: usize| c as f64 / n as f64;
        assert!((f(in1) - 0.682_69).abs() < 0.004, "P(|z|<1) = {}", f(in1));
        assert!((f(in2) - 0.954_50).abs() < 0.002, "P(|z|<2) = {}", f(in2));
        assert!(
            (f(tail) - 0.000_576).abs() < 0.000_2,
            "P(|z|>3.44) = {}",
            f(tail)
        );
        assert!((v - 1.0).abs() < 0.02, "var {v}");
        assert!((u - 0.5).abs() < 0.005, "uniform mean {u}");
    }
}
