//! The staircase family of per-position noise levels (docs/method.md §1).
//!
//! `τ = 0` is pure noise, `τ = 1` is clean. A staircase has a clean *front* of `d`
//! in-flight actions, a *ramp*, and a *tail* of fresh noise.

use serde::{Deserialize, Serialize};

use crate::error::{Error, Result};

/// Where the ramp sits relative to the emitted slots.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Alignment {
    /// Every emitted slot gets its last denoising step in the current call, on the
    /// current observation. Ramp of `L = n·d − 1` slots. The default.
    #[default]
    Fresh,
    /// The paper's literal formula: a full-chunk ramp `1 − (p−d)/(H−2d)`; slot `d` is
    /// already clean when the call starts (finalised on the previous observation).
    Paper,
}

impl Alignment {
    /// Lower-case name.
    pub fn name(self) -> &'static str {
        match self {
            Alignment::Fresh => "fresh",
            Alignment::Paper => "paper",
        }
    }
}

/// A validated staircase `τ*` for chunk length `h`, delay `d`, `n` NFEs per action.
///
/// ```
/// use pir2_schedule::{Staircase, Alignment};
/// // H = 8, d = 2, n = 2 (fresh alignment): front of 2, a ramp of n·d − 1 = 3, then noise.
/// let s = Staircase::fresh(8, 2, Some(2)).unwrap();
/// let tau: Vec<f32> = (0..8).map(|p| s.tau(p)).collect();
/// assert_eq!(tau, [1.0, 1.0, 0.75, 0.5, 0.25, 0.0, 0.0, 0.0]);
/// // The paper's literal full ramp for the same H and d:
/// let p = Staircase::new(8, 2, None, Alignment::Paper).unwrap();
/// assert_eq!(p.tau(2), 1.0); // slot d is already clean
/// assert_eq!(p.tau(6), 0.0); // d noise slots at the end
/// ```
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Staircase {
    h: usize,
    d: usize,
    n: usize,
    alignment: Alignment,
}

impl Staircase {
    /// Largest valid `n` (NFEs per action) for `(h, d)` with the fresh alignment:
    /// `⌊(H − d − e + 1)/e⌋` with `e = max(d, 1)`, i.e. `⌊(H−2d+1)/d⌋` for `d ≥ 1`
    /// and `H` for the streaming ramp `d = 0`. Returns 0 when no `n` is valid.
    pub fn n_max(h: usize, d: usize) -> usize {
        let e = d.max(1);
        (h + 1).saturating_sub(d + e) / e
    }

    /// Validate and build. `n = None` means the full-chunk ramp (`n_max` for the fresh
    /// alignment; the paper alignment is always the full ramp and accepts only `None`
    /// or its own implied value).
    pub fn new(h: usize, d: usize, n: Option<usize>, alignment: Alignment) -> Result<Self> {
        if h == 0 {
            return Err(Error::Invalid {
                field: "H",
                message: "chunk length must be at least 1".into(),
            });
        }
        match alignment {
            Alignment::Fresh => {
                let n_max = Self::n_max(h, d);
                if n_max == 0 {
                    let min_h = if d == 0 { 1 } else { 3 * d - 1 };
                    return Err(Error::HorizonTooShort {
                        h,
                        d,
                        alignment: "fresh",
                        min_h,
                    });
                }
                let n = n.unwrap_or(n_max);
                if n == 0 || n > n_max {
                    return Err(Error::NfeOutOfRange { n, h, d, n_max });
                }
                Ok(Self { h, d, n, alignment })
            }
            Alignment::Paper => {
                if d > 0 && h < 2 * d + 1 {
                    return Err(Error::HorizonTooShort {
                        h,
                        d,
                        alignment: "paper",
                        min_h: 2 * d + 1,
                    });
                }
                let implied = Self::paper_nfe(h, d);
                if let Some(n) = n {
                    if n != implied {
                        return Err(Error::Invalid {
                            field: "n",
                            message: format!(
                                "the paper alignment is the full-chunk ramp with n = {implied} for H = {h}, d = {d}; \
                                 use the fresh alignment to choose n (got {n})"
                            ),
                        });
                    }
                }
                Ok(Self {
                    h,
                    d,
                    n: implied,
                    alignment,
                })
            }
        }
    }

    /// Fresh-alignment staircase (the default).
    pub fn fresh(h: usize, d: usize, n: Option<usize>) -> Result<Self> {
        Self::new(h, d, n, Alignment::Fresh)
    }

    /// The paper's literal staircase.
    pub fn paper(h: usize, d: usize) -> Result<Self> {
        Self::new(h, d, None, Alignment::Paper)
    }

    /// The same family (alignment, requested `n`) at another delay; `n` is capped at the
    /// new delay's `n_max` (docs/method.md §1, "changing d").
    pub fn at_delay(&self, d: usize, requested_n: Option<usize>) -> Result<Self> {
        match self.alignment {
            Alignment::Fresh => {
                let n_max = Self::n_max(self.h, d);
                let n = requested_n.map(|n| n.min(n_max));
                Self::new(self.h, d, n, Alignment::Fresh)
            }
            Alignment::Paper => Self::new(self.h, d, None, Alignment::Paper),
        }
    }

    /// Calls an action spends in the paper's ramp (`⌈(H−2d)/d⌉`, or `H` for `d = 0`).
    fn paper_nfe(h: usize, d: usize) -> usize {
        if d == 0 {
            h
        } else {
            (h - 2 * d).div_ceil(d)
        }
    }

    /// Chunk length `H`.
    pub fn horizon(&self) -> usize {
        self.h
    }
    /// Delay `d` (front length).
    pub fn delay(&self) -> usize {
        self.d
    }
    /// NFEs per action `n`.
    pub fn nfe(&self) -> usize {
        self.n
    }
    /// The alignment.
    pub fn alignment(&self) -> Alignment {
        self.alignment
    }
    /// Slots emitted per call at steady state: `e = max(d, 1)`.
    pub fn emitted(&self) -> usize {
        self.d.max(1)
    }

    /// `τ*_p`. Positions `p ≥ H` are 0; the shifted form uses `p < 0` → 1.
    #[inline]
    pub fn tau(&self, p: usize) -> f32 {
        let (h, d) = (self.h, self.d);
        if p < d {
            return 1.0;
        }
        if p >= h {
            return 0.0;
        }
        match self.alignment {
            Alignment::Fresh => {
                let l = self.n * self.emitted() - 1;
                if p < d + l {
                    (d + l - p) as f32 / (l + 1) as f32
                } else {
                    0.0
                }
            }
            Alignment::Paper => {
                if d == 0 {
                    1.0 - p as f32 / h as f32
                } else if p < h - d {
                    1.0 - (p - d) as f32 / (h - 2 * d) as f32
                } else {
                    0.0
                }
            }
        }
    }

    /// The target after one call: the staircase shifted right by `e = max(d,1)`:
    /// `1` for `p < e`, `τ*_{p−e}` otherwise.
    #[inline]
    pub fn tau_after(&self, p: usize) -> f32 {
        let e = self.emitted();
        if p < e {
            1.0
        } else {
            self.tau(p - e)
        }
    }

    /// Write `τ*` into `out` (`out.len() == H`).
    pub fn fill(&self, out: &mut [f32]) {
        for (p, t) in out.iter_mut().enumerate() {
            *t = self.tau(p);
        }
    }

    /// `τ*` as a vector.
    pub fn to_vec(&self) -> Vec<f32> {
        (0..self.h).map(|p| self.tau(p)).collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fresh_formula_matches_design() {
        // H = 16, d = 1, n = 2: L = 1 → τ = [1, 0.5, 0, ...]
        let s = Staircase::fresh(16, 1, Some(2)).unwrap();
        assert_eq!(&s.to_vec()[..3], &[1.0, 0.5, 0.0]);
        // n_max = ⌊(H−2d+1)/d⌋
        assert_eq!(Staircase::n_max(16, 1), 15);
        assert_eq!(Staircase::n_max(16, 3), 3);
        assert_eq!(Staircase::n_max(16, 0), 16);
        assert_eq!(Staircase::n_max(4, 2), 0);
        assert!(matches!(
            Staircase::fresh(16, 3, Some(4)),
            Err(Error::NfeOutOfRange { n_max: 3, .. })
        ));
        assert!(matches!(
            Staircase::fresh(7, 3, None),
            Err(Error::HorizonTooShort { min_h: 8, .. })
        ));
    }

    #[test]
    fn paper_formula_matches_design() {
        let s = Staircase::paper(10, 2).unwrap();
        let t = s.to_vec();
        assert_eq!(&t[..3], &[1.0, 1.0, 1.0]);
        assert_eq!(t[8], 0.0);
        assert!((t[4] - (1.0 - 2.0 / 6.0)).abs() < 1e-7);
        let z = Staircase::paper(8, 0).unwrap();
        assert_eq!(z.tau(0), 1.0);
        assert_eq!(z.tau(4), 0.5);
        assert!(Staircase::paper(4, 2).is_err());
        assert!(Staircase::new(10, 2, Some(4), Alignment::Paper).is_err());
    }
}
