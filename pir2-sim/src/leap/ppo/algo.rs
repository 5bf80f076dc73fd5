//! The PPO pieces that are pure arithmetic: the diagonal Gaussian policy's log-density,
//! generalised advantage estimation and the clipped surrogate's gradient.

/// `½·ln(2π)`.
const HALF_LN_2PI: f32 = 0.918_938_5;

/// Log-density of `a` under `N(mu, diag(exp(log_std))²)`.
pub fn log_prob(mu: &[f32], log_std: &[f32], a: &[f32]) -> f32 {
    let mut lp = 0.0f32;
    for j in 0..mu.len() {
        let z = (a[j] - mu[j]) * (-log_std[j]).exp();
        lp += -0.5 * z * z - log_std[j] - HALF_LN_2PI;
    }
    lp
}

/// Entropy of the diagonal Gaussian with `log_std`.
pub fn entropy(log_std: &[f32]) -> f32 {
    log_std.iter().map(|l| l + 0.5 + HALF_LN_2PI).sum()
}

/// How a transition ends (for [`gae`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Cut {
    /// The next row continues the same episode.
    No,
    /// The episode ended here; `next_value` is what follows (0 for a terminal state, the
    /// value of the final state for a time limit).
    Yes,
}

/// Generalised advantage estimation over one environment's rows in time order:
/// `δₜ = rₜ + γ·next_valueₜ − valueₜ`, `Aₜ = δₜ + γλ·[cutₜ = No]·Aₜ₊₁`. `next_value[t]` is the
/// value of the state after step `t` (the next row's value, the bootstrap at the end of the
/// rollout, the final state's value at a time limit, 0 after a terminal step). Writes the
/// advantages; returns are `advantage + value`.
pub fn gae(
    rewards: &[f32],
    values: &[f32],
    next_values: &[f32],
    cuts: &[Cut],
    gamma: f32,
    lambda: f32,
    adv: &mut [f32],
) {
    let n = rewards.len();
    assert!(values.len() == n && next_values.len() == n && cuts.len() == n && adv.len() == n);
    let mut next_adv = 0.0f32;
    for t in (0..n).rev() {
        let delta = rewards[t] + gamma * next_values[t] - values[t];
        let carry = if cuts[t] == Cut::No { next_adv } else { 0.0 };
        adv[t] = delta + gamma * lambda * carry;
        next_adv = adv[t];
    }
}

/// Statistics of one [`surrogate_grad`] call (sums over its rows).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct SurrogateStats {
    /// Σ of the clipped surrogate loss `−min(r·A, clip(r)·A)`.
    pub loss: f64,
    /// Rows whose ratio was clipped (no gradient).
    pub clipped: f64,
    /// Σ of `(r − 1) − ln r`, an estimate of KL(old ‖ new).
    pub approx_kl: f64,
}

/// Gradient of the clipped PPO surrogate `L = scale·Σᵢ −min(rᵢAᵢ, clip(rᵢ, 1±ε)Aᵢ)` with
/// `rᵢ = exp(log π(aᵢ) − old_logpᵢ)` with respect to the means (written to `d_mu`, rows ×
/// action dim) and **added** to `d_log_std`. The entropy bonus is not included.
pub fn surrogate_grad(
    mu: &[f32],
    log_std: &[f32],
    actions: &[f32],
    old_logp: &[f32],
    adv: &[f32],
    clip_eps: f32,
    scale: f32,
    d_mu: &mut [f32],
    d_log_std: &mut [f32],
) -> SurrogateStats {
    let ad = log_std.len();
    let inv_std: Vec<f32> = log_std.iter().map(|l| (-l).exp()).collect();
    let mut st = SurrogateStats::default();
    for i in 0..adv.len() {
        let (m, a) = (&mu[i * ad..(i + 1) * ad], &actions[i * ad..(i + 1) * ad]);
        let lp = log_prob(m, log_std, a);
        let log_ratio = lp - old_logp[i];
        let r = log_ratio.exp();
        let (u, c) = (r * adv[i], r.clamp(1.0 - clip_eps, 1.0 + clip_eps) * adv[i]);
        st.loss += -f64::from(u.min(c));
        st.approx_kl += f64::from((r - 1.0) - log_ratio);
        let dm = &mut d_mu[i * ad..(i + 1) * ad];
        // The gradient flows through r·A when it is the smaller term (or they tie).
        if u <= c {
            // ∂L/∂log π = −scale·r·A; ∂log π/∂μⱼ = zⱼ/σⱼ; ∂log π/∂log σⱼ = zⱼ² − 1.
            let g = -scale * r * adv[i];
            for j in 0..ad {
                let z = (a[j] - m[j]) * inv_std[j];
                dm[j] = g * z * inv_std[j];
                d_log_std[j] += g * (z * z - 1.0);
            }
        } else {
            st.clipped += 1.0;
            dm.fill(0.0);
        }
    }
    st
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn gae_matches_a_hand_computed_case() {
        // Three steps: episode A ends by time limit after t = 1 (bootstrap 2.0), episode B
        // starts at t = 2 and the rollout ends (bootstrap 0.5).
        let r = [1.0, 0.0, 2.0];
        let v = [0.5, 1.0, 1.5];
        let next = [1.0, 2.0, 0.5];
        let cuts = [Cut::No, Cut::Yes, Cut::No];
        let (g, l) = (0.9f32, 0.8f32);
        let mut adv = [0.0; 3];
        gae(&r, &v, &next, &cuts, g, l, &mut adv);
        // δ₂ = 2 + 0.9·0.5 − 1.5 = 0.95; A₂ = 0.95.
        // δ₁ = 0 + 0.9·2 − 1 = 0.8; cut → A₁ = 0.8.
        // δ₀ = 1 + 0.9·1 − 0.5 = 1.4; A₀ = 1.4 + 0.72·0.8 = 1.976.
        let want = [1.976f32, 0.8, 0.95];
        for (a, w) in adv.iter().zip(want) {
            assert!((a - w).abs() < 1e-6, "{adv:?}");
        }
        // λ = 1, no cuts, zero values: discounted returns.
        let mut adv = [0.0; 3];
        gae(
            &[1.0, 1.0, 1.0],
            &[0.0; 3],
            &[0.0; 3],
            &[Cut::No; 3],
            0.5,
            1.0,
            &mut adv,
        );
        assert_eq!(adv, [1.75, 1.5, 1.0]);
    }

    #[test]
    fn log_prob_is_the_gaussian_density() {
        let lp = log_prob(&[0.0, 1.0], &[0.0, 2f32.ln()], &[1.0, 1.0]);
        let want = -0.5 - HALF_LN_2PI + (-(2f32.ln()) - HALF_LN_2PI);
        assert!((lp - want).abs() < 1e-6);
        assert!((entropy(&[0.0]) - (0.5 + HALF_LN_2PI)).abs() < 1e-6);
    }

    #[test]
    fn surrogate_gradient_moves_the_mean_toward_good_actions() {
        // One row, action above the mean. A > 0: a descent step on L must raise μ (−∂L/∂μ > 0)
        // and, since |z| > 1, raise σ toward the sample; A < 0: the opposite.
        let (mu, ls, a) = ([0.0f32], [0.0f32], [1.5f32]);
        let old = [log_prob(&mu, &ls, &a)];
        for (adv, sign) in [(1.0f32, 1.0f32), (-1.0, -1.0)] {
            let (mut dmu, mut dls) = ([0.0f32], [0.0f32]);
            let st = surrogate_grad(&mu, &ls, &a, &old, &[adv], 0.2, 1.0, &mut dmu, &mut dls);
            assert!(sign * -dmu[0] > 0.0, "adv {adv}: dmu {dmu:?}");
            assert!(sign * -dls[0] > 0.0, "adv {adv}: dlog_std {dls:?}");
            assert_eq!(st.clipped, 0.0);
            assert!((st.loss + f64::from(adv)).abs() < 1e-6);
        }
        // Ratio beyond 1 + ε with A > 0: clipped, no gradient.
        let old = [log_prob(&mu, &ls, &a) - 1.0];
        let (mut dmu, mut dls) = ([0.0f32], [0.0f32]);
        let st = surrogate_grad(&mu, &ls, &a, &old, &[1.0], 0.2, 1.0, &mut dmu, &mut dls);
        assert_eq!((dmu[0], dls[0], st.clipped), (0.0, 0.0, 1.0));
    }

    #[test]
    fn surrogate_gradient_matches_finite_differences() {
        let mu = [0.3f32, -0.2, 0.1, 0.4];
        let ls = [-0.5f32, -0.3];
        let a = [0.5f32, -0.6, 0.0, 0.9];
        // Old log-probs near the current ones so the ratios stay inside the clip range.
        let old: Vec<f32> = (0..2)
            .map(|i| log_prob(&mu[2 * i..2 * i + 2], &ls, &a[2 * i..2 * i + 2]) + 0.05)
            .collect();
        let adv = [0.7f32, -1.2];
        let loss = |mu: &[f32], ls: &[f32]| {
            let (mut d, mut l) = (vec![0.0; 4], vec![0.0; 2]);
            surrogate_grad(mu, ls, &a, &old, &adv, 0.2, 0.5, &mut d, &mut l).loss * 0.5
        };
        let (mut dmu, mut dls) = (vec![0.0; 4], vec![0.0; 2]);
        surrogate_grad(&mu, &ls, &a, &old, &adv, 0.2, 0.5, &mut dmu, &mut dls);
        let h = 1e-3f32;
        for j in 0..4 {
            let (mut p, mut m) = (mu, mu);
            p[j] += h;
            m[j] -= h;
            let fd = (loss(&p, &ls) - loss(&m, &ls)) / (2.0 * f64::from(h));
            assert!(
                (fd - f64::from(dmu[j])).abs() < 2e-3,
                "mu {j}: {fd} vs {}",
                dmu[j]
            );
        }
        for j in 0..2 {
            let (mut p, mut m) = (ls, ls);
            p[j] += h;
            m[j] -= h;
            let fd = (loss(&mu, &p) - loss(&mu, &m)) / (2.0 * f64::from(h));
            assert!(
                (fd - f64::from(dls[j])).abs() < 2e-3,
                "ls {j}: {fd} vs {}",
                dls[j]
            );
        }
    }
}
