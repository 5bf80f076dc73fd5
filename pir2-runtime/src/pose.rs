//! End-effector poses as action values, and poses relative to a reference pose (GR00T N1.7's
//! relative end-effector actions).
//!
//! A pose is a translation `t` and a rotation `R`, written in one of two layouts
//! ([`PoseFormat`]):
//! - `xyz_rot6d`, 9 values: `x, y, z`, then the first two **rows** of `R`, row-major
//!   (`R₀₀ R₀₁ R₀₂ R₁₀ R₁₁ R₁₂`). Reading one back orthonormalises it (Gram–Schmidt): the
//!   first row is normalised, the second made orthogonal to it and normalised, the third row
//!   is their cross product. So any 6 values with independent rows give a rotation;
//!   a zero first row or parallel rows give non-finite values (which a robot's safety layer
//!   refuses).
//! - `xyz_rotvec`, 6 values: `x, y, z`, then the rotation vector (unit axis × angle, angle in
//!   `[0, π]`).
//!
//! The pose `T = (R, t)` relative to the reference `T_ref = (R_ref, t_ref)` is
//! `T_rel = T_ref⁻¹·T`: `R_rel = R_refᵀ·R`, `t_rel = R_refᵀ·(t − t_ref)`, that is the target
//! expressed in the reference's own frame. Back: `T = T_ref·T_rel`, `R = R_ref·R_rel`,
//! `t = R_ref·t_rel + t_ref`. The reference is read in the same layout as the pose. The
//! arithmetic is in `f64`; nothing allocates.
//!
//! ```
//! use pir2_runtime::pose::{absolute, relative, PoseFormat};
//! // Reference: at (1, 0, 0), turned 90° about z. Target: at (1, 1, 0), the same orientation.
//! let reference = [1.0, 0.0, 0.0, 0.0, -1.0, 0.0, 1.0, 0.0, 0.0];
//! let target = [1.0, 1.0, 0.0, 0.0, -1.0, 0.0, 1.0, 0.0, 0.0];
//! let mut rel = [0.0; 9];
//! relative(PoseFormat::XyzRot6d, &reference, &target, &mut rel);
//! // One unit along the reference's own x axis, no rotation.
//! let want = [1.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0];
//! assert!(rel.iter().zip(want).all(|(a, b)| (a - b).abs() < 1e-6));
//! let mut back = [0.0; 9];
//! absolute(PoseFormat::XyzRot6d, &reference, &rel, &mut back);
//! assert!(back.iter().zip(target).all(|(a, b)| (a - b).abs() < 1e-6));
//! ```

use nalgebra::{Matrix3, Rotation3, Vector3};
use serde::{Deserialize, Serialize};

/// How a pose is written (GR00T's `ActionFormat` for end-effector actions).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum PoseFormat {
    /// Position and the first two rows of the rotation matrix (9 values).
    XyzRot6d,
    /// Position and the rotation vector (6 values).
    XyzRotvec,
}

impl PoseFormat {
    /// Values per pose.
    pub const fn width(self) -> usize {
        match self {
            PoseFormat::XyzRot6d => 9,
            PoseFormat::XyzRotvec => 6,
        }
    }
}

/// Read a pose: translation and rotation matrix (see the module docs).
fn read(format: PoseFormat, v: &[f32]) -> (Vector3<f64>, Matrix3<f64>) {
    let f = |i: usize| f64::from(v[i]);
    let t = Vector3::new(f(0), f(1), f(2));
    let r = match format {
        PoseFormat::XyzRot6d => {
            let a = Vector3::new(f(3), f(4), f(5));
            let b = Vector3::new(f(6), f(7), f(8));
            let r0 = a / a.norm();
            let b = b - r0 * r0.dot(&b);
            let r1 = b / b.norm();
            let r2 = r0.cross(&r1);
            Matrix3::from_rows(&[r0.transpose(), r1.transpose(), r2.transpose()])
        }
        PoseFormat::XyzRotvec => Rotation3::new(Vector3::new(f(3), f(4), f(5))).into_inner(),
    };
    (t, r)
}

/// Write a pose (see the module docs).
fn write(format: PoseFormat, t: &Vector3<f64>, r: &Matrix3<f64>, out: &mut [f32]) {
    for (o, v) in out[..3].iter_mut().zip(t.iter()) {
        *o = *v as f32;
    }
    match format {
        PoseFormat::XyzRot6d => {
            for i in 0..2 {
                for j in 0..3 {
                    out[3 + 3 * i + j] = r[(i, j)] as f32;
                }
            }
        }
        PoseFormat::XyzRotvec => {
            let v = Rotation3::from_matrix_unchecked(*r).scaled_axis();
            for (o, x) in out[3..6].iter_mut().zip(v.iter()) {
                *o = *x as f32;
            }
        }
    }
}

/// `out = T_ref⁻¹·T`: `pose` relative to `reference` (both and `out` of
/// [`PoseFormat::width`] values).
pub fn relative(format: PoseFormat, reference: &[f32], pose: &[f32], out: &mut [f32]) {
    let (t0, r0) = read(format, reference);
    let (t, r) = read(format, pose);
    let rt = r0.transpose();
    write(format, &(rt * (t - t0)), &(rt * r), out);
}

/// `out = T_ref·T_rel`: the absolute pose of `rel`, a pose relative to `reference`.
pub fn absolute(format: PoseFormat, reference: &[f32], rel: &[f32], out: &mut [f32]) {
    let (t0, r0) = read(format, reference);
    let (t, r) = read(format, rel);
    write(format, &(r0 * t + t0), &(r0 * r), out);
}

#[cfg(test)]
mod tests {
    use super::*;

    fn close(a: &[f32], b: &[f32], tol: f32) -> bool {
        a.len() == b.len() && a.iter().zip(b).all(|(x, y)| (x - y).abs() < tol)
    }

    /// Worked by hand: reference at (1, 2, 0) turned 90° about z (`R_ref` rows
    /// `(0 −1 0) (1 0 0) (0 0 1)`); target at (0, 2, 1) turned 180° about z. In the reference's
    /// frame the target is `R_refᵀ·(−1, 0, 1) = (0, 1, 1)`, turned a further 90° about z:
    /// rot6d rows `(0 −1 0) (1 0 0)`, rotation vector `(0, 0, π/2)`.
    #[test]
    fn a_hand_worked_relative_pose_in_both_formats() {
        let half_pi = std::f32::consts::FRAC_PI_2;
        let pi = std::f32::consts::PI;
        let reference = [1.0, 2.0, 0.0, 0.0, -1.0, 0.0, 1.0, 0.0, 0.0];
        let target = [0.0, 2.0, 1.0, -1.0, 0.0, 0.0, 0.0, -1.0, 0.0];
        let mut rel = [0.0; 9];
        relative(PoseFormat::XyzRot6d, &reference, &target, &mut rel);
        let want = [0.0, 1.0, 1.0, 0.0, -1.0, 0.0, 1.0, 0.0, 0.0];
        assert!(close(&rel, &want, 1e-6), "{rel:?}");

        let reference = [1.0, 2.0, 0.0, 0.0, 0.0, half_pi];
        let target = [0.0, 2.0, 1.0, 0.0, 0.0, pi];
        let mut rel = [0.0; 6];
        relative(PoseFormat::XyzRotvec, &reference, &target, &mut rel);
        assert!(
            close(&rel, &[0.0, 1.0, 1.0, 0.0, 0.0, half_pi], 1e-6),
            "{rel:?}"
        );
        let mut back = [0.0; 6];
        absolute(PoseFormat::XyzRotvec, &reference, &rel, &mut back);
        // π about z and −π about z are the same rotation; scaled_axis picks one of them.
        assert!(close(&back[..3], &target[..3], 1e-6), "{back:?}");
        assert!(
            (back[5].abs() - pi).abs() < 1e-5 && back[3].abs() < 1e-6,
            "{back:?}"
        );
    }

    /// Random poses: relative then absolute gives the pose back, in both formats; the
    /// relative pose of the reference itself is the identity; a 6-d rotation that is not
    /// orthonormal is read as its Gram–Schmidt rotation (the first row's direction kept).
    #[test]
    fn relative_and_absolute_are_inverse() {
        let mut seed = 0x2545_f491_4f6c_dd1du64;
        let mut rnd = move || {
            seed ^= seed << 13;
            seed ^= seed >> 7;
            seed ^= seed << 17;
            (seed >> 11) as f64 / (1u64 << 53) as f64 * 2.0 - 1.0
        };
        for _ in 0..50 {
            let rot = Rotation3::new(Vector3::new(rnd(), rnd(), rnd()) * 1.5);
            let rot0 = Rotation3::new(Vector3::new(rnd(), rnd(), rnd()) * 1.5);
            let t = [rnd() as f32, rnd() as f32, rnd() as f32];
            let t0 = [rnd() as f32, rnd() as f32, rnd() as f32];
            for format in [PoseFormat::XyzRot6d, PoseFormat::XyzRotvec] {
                let (mut p, mut p0) = ([0f32; 9], [0f32; 9]);
                let w = format.width();
                write(
                    format,
                    &Vector3::from(t.map(f64::from)),
                    rot.matrix(),
                    &mut p,
                );
                write(
                    format,
                    &Vector3::from(t0.map(f64::from)),
                    rot0.matrix(),
                    &mut p0,
                );
                let (mut rel, mut back, mut id) = ([0f32; 9], [0f32; 9], [0f32; 9]);
                relative(format, &p0[..w], &p[..w], &mut rel[..w]);
                absolute(format, &p0[..w], &rel[..w], &mut back[..w]);
                assert!(close(&back[..w], &p[..w], 1e-5), "{format:?}");
                relative(format, &p0[..w], &p0[..w], &mut id[..w]);
                let identity: &[f32] = match format {
                    PoseFormat::XyzRot6d => &[0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0],
                    PoseFormat::XyzRotvec => &[0.0; 6],
                };
                assert!(close(&id[..w], identity, 1e-5), "{format:?}: {id:?}");
            }
        }
        // Gram–Schmidt: rows (2, 0, 0) and (1, 3, 0) are read as the identity.
        let skew = [0.0, 0.0, 0.0, 2.0, 0.0, 0.0, 1.0, 3.0, 0.0];
        let zero = [0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0];
        let mut out = [0.0; 9];
        absolute(PoseFormat::XyzRot6d, &zero, &skew, &mut out);
        assert!(close(&out, &zero, 1e-6), "{out:?}");
    }
}
