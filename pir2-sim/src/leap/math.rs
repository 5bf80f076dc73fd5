//! Quaternion helpers in MuJoCo's `(w, x, y, z)` convention, on top of `nalgebra`.

use nalgebra::{Quaternion, UnitQuaternion, Vector3};
use pir2_schedule::Rng;

/// A quaternion as MuJoCo stores it: `[w, x, y, z]`.
pub type Quat = [f64; 4];

/// `nalgebra` quaternion from `[w, x, y, z]` (not normalised).
#[inline]
pub fn to_na(q: &Quat) -> Quaternion<f64> {
    Quaternion::new(q[0], q[1], q[2], q[3])
}

/// `[w, x, y, z]` from an `nalgebra` quaternion.
#[inline]
pub fn from_na(q: &Quaternion<f64>) -> Quat {
    [q.w, q.i, q.j, q.k]
}

/// `a ⊗ b⁻¹` for unit quaternions, normalised.
#[inline]
pub fn mul_inv(a: &Quat, b: &Quat) -> Quat {
    let d = to_na(a) * to_na(b).conjugate();
    from_na(&d.normalize())
}

/// Angle of the rotation between `q` and `goal`: `2·asin(min(‖vec(q ⊗ goal⁻¹)‖, 1))`
/// (the playground's `_cube_orientation_error`), in `[0, π]`.
#[inline]
pub fn orientation_error(q: &Quat, goal: &Quat) -> f64 {
    let d = mul_inv(q, goal);
    let v = (d[1] * d[1] + d[2] * d[2] + d[3] * d[3]).sqrt();
    2.0 * v.min(1.0).asin()
}

/// The smallest [`orientation_error`] over `goals`.
#[inline]
pub fn nearest_goal_error(q: &Quat, goals: &[Quat]) -> f64 {
    goals
        .iter()
        .map(|g| orientation_error(q, g))
        .fold(f64::INFINITY, f64::min)
}

/// Rows 2 and 3 of the rotation matrix of `q` (`quat_to_mat(q).ravel()[3:]`), the 6-d
/// orientation feature of the playground observation.
#[inline]
pub fn rot_rows_23(q: &Quat) -> [f64; 6] {
    let r = UnitQuaternion::from_quaternion(to_na(q)).to_rotation_matrix();
    let m = r.matrix();
    [
        m[(1, 0)],
        m[(1, 1)],
        m[(1, 2)],
        m[(2, 0)],
        m[(2, 1)],
        m[(2, 2)],
    ]
}

/// The paper's four goals: the cube's blue face (body `−z`) up, yaw `ψ ∈ {0, π/2, π, 3π/2}`:
/// `q(ψ) = (0, cos ψ/2, sin ψ/2, 0)`, a half turn about the horizontal axis at `ψ/2`.
pub fn blue_side_up_goals() -> [Quat; 4] {
    let mut out = [[0.0; 4]; 4];
    for (k, g) in out.iter_mut().enumerate() {
        let psi = k as f64 * std::f64::consts::FRAC_PI_2;
        *g = [0.0, (psi / 2.0).cos(), (psi / 2.0).sin(), 0.0];
    }
    out
}

/// A uniformly distributed unit quaternion (normalised 4-d Gaussian), from `rng`.
pub fn uniform_quat(rng: &mut Rng) -> Quat {
    loop {
        let q = [
            rng.normal() as f64,
            rng.normal() as f64,
            rng.normal() as f64,
            rng.normal() as f64,
        ];
        let n = (q.iter().map(|v| v * v).sum::<f64>()).sqrt();
        if n > 1e-6 {
            return [q[0] / n, q[1] / n, q[2] / n, q[3] / n];
        }
    }
}

/// `q ⊗ exp(ω·dt/2)` normalised: MJX's `quat_integrate(q, ω, dt)`.
pub fn quat_integrate(q: &Quat, omega: &[f64; 3], dt: f64) -> Quat {
    let w = Vector3::new(omega[0], omega[1], omega[2]);
    let n = w.norm();
    if n < 1e-12 {
        return *q;
    }
    let dq = UnitQuaternion::from_axis_angle(&nalgebra::Unit::new_unchecked(w / n), n * dt);
    from_na(&(to_na(q) * dq.into_inner()).normalize())
}

/// Rotate vector `v` by `q`.
pub fn rotate(q: &Quat, v: [f64; 3]) -> [f64; 3] {
    let r = UnitQuaternion::from_quaternion(to_na(q)) * Vector3::new(v[0], v[1], v[2]);
    [r.x, r.y, r.z]
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f64::consts::PI;

    fn axis_angle(axis: [f64; 3], angle: f64) -> Quat {
        from_na(
            &UnitQuaternion::from_axis_angle(
                &nalgebra::Unit::new_normalize(Vector3::new(axis[0], axis[1], axis[2])),
                angle,
            )
            .into_inner(),
        )
    }

    #[test]
    fn blue_side_up_goals_put_body_minus_z_up_at_quarter_turn_yaws() {
        let goals = blue_side_up_goals();
        for (k, g) in goals.iter().enumerate() {
            let n = (g.iter().map(|v| v * v).sum::<f64>()).sqrt();
            assert!((n - 1.0).abs() < 1e-12);
            let up = rotate(g, [0.0, 0.0, -1.0]);
            assert!(
                (up[2] - 1.0).abs() < 1e-12,
                "goal {k}: body -z maps to {up:?}"
            );
            // Body +x ends up at yaw -ψ... any fixed convention: consecutive goals differ by
            // a quarter turn about world z.
            let next = goals[(k + 1) % 4];
            assert!((orientation_error(&next, g) - PI / 2.0).abs() < 1e-9);
            let rel = mul_inv(&next, g);
            let axis = [rel[1], rel[2], rel[3]];
            assert!(
                axis[0].abs() < 1e-9 && axis[1].abs() < 1e-9,
                "not a yaw: {rel:?}"
            );
        }
        assert_eq!(goals[0], [0.0, 1.0, 0.0, 0.0]);
    }

    #[test]
    fn orientation_error_is_the_rotation_angle() {
        let g = blue_side_up_goals()[1];
        for angle in [0.0, 0.1, 0.19, 0.21, 1.0, 3.0] {
            let q = from_na(&(to_na(&axis_angle([0.3, -1.0, 0.5], angle)) * to_na(&g)));
            assert!((orientation_error(&q, &g) - angle).abs() < 1e-9, "{angle}");
            // q and -q are the same rotation.
            let neg = [-q[0], -q[1], -q[2], -q[3]];
            assert!((orientation_error(&neg, &g) - angle).abs() < 1e-9);
        }
    }

    #[test]
    fn success_threshold_separates_0_19_from_0_21_rad_of_a_goal() {
        let goals = blue_side_up_goals();
        for g in goals {
            let near = from_na(&(to_na(&axis_angle([1.0, 2.0, 0.0], 0.19)) * to_na(&g)));
            let far = from_na(&(to_na(&axis_angle([1.0, 2.0, 0.0], 0.21)) * to_na(&g)));
            assert!(nearest_goal_error(&near, &goals) < 0.2);
            assert!(nearest_goal_error(&far, &goals) > 0.2);
        }
        // Blue side down (identity) is far from every goal.
        assert!(nearest_goal_error(&[1.0, 0.0, 0.0, 0.0], &goals) > 3.0);
        // Any yaw of a blue-up cube is within π/4 of a goal.
        for k in 0..32 {
            let yaw = axis_angle([0.0, 0.0, 1.0], k as f64 * 0.2);
            let q = from_na(&(to_na(&yaw) * to_na(&goals[0])));
            assert!(nearest_goal_error(&q, &goals) <= PI / 4.0 + 1e-9);
        }
    }

    #[test]
    fn rot_rows_match_rotation_matrix() {
        let q = axis_angle([0.0, 0.0, 1.0], PI / 2.0);
        let r = rot_rows_23(&q);
        // Rz(90°) = [[0,-1,0],[1,0,0],[0,0,1]].
        let want = [1.0, 0.0, 0.0, 0.0, 0.0, 1.0];
        for (a, b) in r.iter().zip(want) {
            assert!((a - b).abs() < 1e-12, "{r:?}");
        }
    }

    #[test]
    fn uniform_quat_has_isotropic_second_moment() {
        let mut rng = Rng::new(3);
        let n = 20_000;
        let mut m = [[0.0f64; 4]; 4];
        for _ in 0..n {
            let q = uniform_quat(&mut rng);
            for i in 0..4 {
                for j in 0..4 {
                    m[i][j] += q[i] * q[j] / n as f64;
                }
            }
        }
        for (i, row) in m.iter().enumerate() {
            for (j, v) in row.iter().enumerate() {
                let want = if i == j { 0.25 } else { 0.0 };
                assert!((v - want).abs() < 0.01, "E[q q^T][{i}][{j}] = {v}");
            }
        }
    }

    #[test]
    fn quat_integrate_rotates_by_norm_times_dt() {
        let q = blue_side_up_goals()[0];
        let out = quat_integrate(&q, &[0.0, 3.0, 4.0], 0.1);
        assert!((orientation_error(&out, &q) - 0.5).abs() < 1e-9);
    }
}
