//! The adaptive compliance controller (docs/method.md eqs. 18–20).

use super::config::Controller;

/// The pose change of one control step, [dx, dy, dz] in mm and
/// [dalpha, dbeta, dgamma] in degrees, in the hole frame:
///
/// - p_p = [0, 0, −L/steps, 0, 0, 0], the planned advance (eq. 18; z points
///   out of the hole, so advancing is −z);
/// - K = diag(a ⊙ k̂) + diag(k̂) (eq. 20);
/// - p_c = K (F − F_ref) with F_ref = 0 for a clearance fit (eq. 19).
///
/// F is the force the hole exerts on the peg (N) and the moment about the
/// flange (N·mm), so +K·F moves the peg the way the contact pushes it: the
/// correction yields to contact. `action` must already be clipped to
/// [lb, ub]; a = 0 is the constant compliance controller, a = −1 switches a
/// component's compliance off.
///
/// `planned_left_mm` is how far the plan still has to go (the commanded
/// depth short of L): the plan stops at the target depth instead of pushing
/// the peg past it into the hole floor.
pub fn pose_change(cfg: &Controller, target_depth_mm: f64, planned_left_mm: f64, action: &[f64; 6], wrench: &[f64; 6]) -> [f64; 6] {
    let mut change = [0.0; 6];
    for i in 0..6 {
        let stiffness_inverse = (1.0 + action[i]) * cfg.compliance[i];
        change[i] = stiffness_inverse * wrench[i];
    }
    change[2] -= (target_depth_mm / cfg.target_steps as f64).min(planned_left_mm.max(0.0));
    change
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::peg::config::PegConfig;

    #[test]
    fn follows_eqs_18_to_20() {
        let cfg = PegConfig::group1().controller;
        let wrench = [10.0, -4.0, 20.0, 100.0, 0.0, -50.0];
        // a = 0: nominal compliance; only the planned advance without force.
        let none = pose_change(&cfg, 30.0, 30.0, &[0.0; 6], &[0.0; 6]);
        assert_eq!(none, [0.0, 0.0, -0.6, 0.0, 0.0, 0.0]);
        let nominal = pose_change(&cfg, 30.0, 30.0, &[0.0; 6], &wrench);
        assert!((nominal[0] - 0.05).abs() < 1e-15 && (nominal[1] + 0.02).abs() < 1e-15);
        assert!((nominal[2] - (-0.6 + 20.0 * 5e-5)).abs() < 1e-15);
        assert!((nominal[3] - 0.1).abs() < 1e-15 && (nominal[5] + 0.05).abs() < 1e-15);
        // a = 1 doubles the compliance, a = −1 switches it off.
        let revised = pose_change(&cfg, 30.0, 30.0, &[1.0, -1.0, 0.0, 0.0, 0.0, 0.0], &wrench);
        assert!((revised[0] - 0.1).abs() < 1e-15);
        assert_eq!(revised[1], 0.0);
        // The plan stops at the target depth.
        assert_eq!(pose_change(&cfg, 30.0, 0.25, &[0.0; 6], &[0.0; 6])[2], -0.25);
    }
}
