//! The kinematics of a WoodenHaptics / Polhem arm (`docs/devices.md` §2): a base that turns about
//! the vertical (joint a), an upper arm (body b) and a forearm (body c), each driven by a capstan
//! drum from a motor on the base, so the joint angles are each body's absolute angle. The host
//! turns encoder counts into joint angles and the handle's position, and a Cartesian force into
//! joint torques (Jᵀ F), motor torques and motor currents.
//!
//! Frame: z up; at zero angles body b points straight up from the top of the base and body c
//! straight down from the elbow. The handle in the arm's vertical plane lies `r` out and `h` up:
//!
//!   r = L_b sin θ_b + L_c sin θ_c,  h = L_a + L_b cos θ_b − L_c cos θ_c,
//!   x = (r cos θ_a, r sin θ_a, h) − workspace origin.

use nalgebra::{Matrix3, Vector3};

use crate::arm::{Arm, ArmFrame, ArmGeometry, SerialArm};

/// Kinematics of one point of a mechanism at (q, q̇): where it is, ∂x/∂q, and the part of its
/// acceleration that does not come from q̈ (ẍ = J q̈ + bias, bias = J̇ q̇). The simulated
/// linkages (`sim::linkage`) describe their points with it too.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Point {
    pub position: Vector3<f64>,
    pub jacobian: Matrix3<f64>,
    pub bias: Vector3<f64>,
}

/// Joint angles q (rad) and rates q̇ (rad/s) with the angles' sines and cosines, worked out once
/// and read by every point of an arm (a simulated linkage's step visits the handle and each of
/// its lumped masses at the same joints).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct JointState {
    pub q: Vector3<f64>,
    pub qd: Vector3<f64>,
    pub sin: Vector3<f64>,
    pub cos: Vector3<f64>,
}

impl JointState {
    /// The joints at `q` moving at `qd`.
    pub fn new(q: &Vector3<f64>, qd: &Vector3<f64>) -> Self {
        let mut sin = Vector3::zeros();
        let mut cos = Vector3::zeros();
        for j in 0..3 {
            (sin[j], cos[j]) = q[j].sin_cos();
        }
        Self {
            q: *q,
            qd: *qd,
            sin,
            cos,
        }
    }

    /// The joints at rest at `q`.
    pub fn at_rest(q: &Vector3<f64>) -> Self {
        Self::new(q, &Vector3::zeros())
    }
}

/// The parameters of one arm, SI units (a profile's `[kinematics]` table).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ArmModel {
    /// Height of the shoulder above the base's foot (L_a), upper arm (L_b), forearm (L_c), m.
    pub lengths: Vector3<f64>,
    /// Capstan (motor shaft) diameters of joints a, b, c, m.
    pub capstans: Vector3<f64>,
    /// Drum (body) diameters of joints a, b, c, m.
    pub drums: Vector3<f64>,
    /// Sign from motor angle to body angle: −1 where motor and body turn the same way
    /// (`motor_and_body_aligned` in the published configurations), else +1.
    pub directions: Vector3<f64>,
    /// Encoder counts per motor revolution, after quadrature decoding.
    pub counts_per_rev: Vector3<f64>,
    /// Motor torque constants, N m/A.
    pub torque_constants: Vector3<f64>,
    /// The amplifiers' full-scale current, A: the largest current commanded or rendered.
    pub max_current: f64,
    /// Where the handle is at the origin of the device frame, in the arm's own frame, m.
    pub origin: Vector3<f64>,
    /// Radius of the workspace about the origin, m.
    pub workspace_radius: f64,
    /// The encoder counts the arm reads at its calibration pose (a, b, c).
    pub home_counts: [i16; 3],
}

impl ArmModel {
    /// Joint angle per encoder count, rad: the motor's revolution over its counts, reduced by
    /// the capstan-to-drum ratio, with the motor's direction.
    pub fn radians_per_count(&self) -> Vector3<f64> {
        Vector3::repeat(std::f64::consts::TAU)
            .component_div(&self.counts_per_rev)
            .component_mul(&self.capstans)
            .component_div(&self.drums)
            .component_mul(&self.directions)
    }

    /// Joint torque per motor torque (the capstan drive's ratio, with the motor's direction).
    pub fn ratios(&self) -> Vector3<f64> {
        self.drums
            .component_div(&self.capstans)
            .component_mul(&self.directions)
    }

    /// Joint angles for encoder counts, rad.
    pub fn angles(&self, counts: &[i16; 3]) -> Vector3<f64> {
        Vector3::new(
            f64::from(counts[0]),
            f64::from(counts[1]),
            f64::from(counts[2]),
        )
        .component_mul(&self.radians_per_count())
    }

    /// The (unrounded) encoder counts of joint angles `q`.
    pub fn counts(&self, q: &Vector3<f64>) -> Vector3<f64> {
        q.component_div(&self.radians_per_count())
    }

    /// The point `upper` along body b from the shoulder and then `fore` along body c's direction
    /// (from elbow to handle), at `joints`, in the device frame.
    pub fn point(&self, joints: &JointState, upper: f64, fore: f64) -> Point {
        let qd = &joints.qd;
        let (sa, ca) = (joints.sin[0], joints.cos[0]);
        let (sb, cb) = (joints.sin[1], joints.cos[1]);
        let (sc, cc) = (joints.sin[2], joints.cos[2]);
        let r = upper * sb + fore * sc;
        let h = self.lengths[0] + upper * cb - fore * cc;
        let (rb, rc) = (upper * cb, fore * cc);
        let (hb, hc) = (-upper * sb, fore * sc);
        let rd = rb * qd[1] + rc * qd[2];
        let r_bias = -upper * sb * qd[1] * qd[1] - fore * sc * qd[2] * qd[2];
        let h_bias = -upper * cb * qd[1] * qd[1] + fore * cc * qd[2] * qd[2];
        let wa = qd[0];
        Point {
            position: Vector3::new(ca * r, sa * r, h) - self.origin,
            jacobian: Matrix3::new(
                -sa * r,
                ca * rb,
                ca * rc, //
                ca * r,
                sa * rb,
                sa * rc, //
                0.0,
                hb,
                hc,
            ),
            bias: Vector3::new(
                -ca * wa * wa * r - 2.0 * sa * wa * rd + ca * r_bias,
                -sa * wa * wa * r + 2.0 * ca * wa * rd + sa * r_bias,
                h_bias,
            ),
        }
    }

    /// The handle at joint angles `q` (at rest: no bias).
    pub fn handle(&self, q: &Vector3<f64>) -> Point {
        self.point(&JointState::at_rest(q), self.lengths[1], self.lengths[2])
    }

    /// Joint angles that put the handle at `x` (device frame, m), elbow up and the handle in
    /// front of the base; `None` out of reach.
    pub fn joints_at(&self, x: &Vector3<f64>) -> Option<Vector3<f64>> {
        let p = x + self.origin;
        let r = p.xy().norm();
        if r < 1e-9 {
            return None;
        }
        let qa = p.y.atan2(p.x);
        let h = p.z - self.lengths[0];
        let (lb, lc) = (self.lengths[1], self.lengths[2]);
        let d = r.hypot(h);
        let cos_beta = (lb * lb + d * d - lc * lc) / (2.0 * lb * d);
        if !(-1.0..=1.0).contains(&cos_beta) {
            return None;
        }
        // The direction to the handle, from vertical toward r; the upper arm leans back of it.
        let qb = r.atan2(h) - cos_beta.acos();
        let (er, eh) = (lb * qb.sin(), lb * qb.cos());
        let qc = (r - er).atan2(eh - h);
        Some(Vector3::new(qa, qb, qc))
    }

    /// The arm as the gravity model knows it: a yaw–pitch–pitch arm with its shoulder L_a up
    /// the yaw axis, in a frame whose origin is the workspace origin.
    pub fn gravity_arm(&self) -> Arm {
        Arm {
            geometry: ArmGeometry::Serial(SerialArm {
                shoulder: Vector3::new(0.0, 0.0, self.lengths[0]),
                upper: self.lengths[1],
                fore: self.lengths[2],
            }),
            frame: ArmFrame::offset(self.origin),
        }
    }

    /// Motor currents, A (unclamped), that render the force `force` (N, device frame) at the
    /// handle with the arm at joint angles `q`: τ = Jᵀ F at the joints, over the drive ratio at
    /// the motors, over the torque constants.
    pub fn currents(&self, q: &Vector3<f64>, force: &Vector3<f64>) -> Vector3<f64> {
        let joint = self.handle(q).jacobian.transpose() * force;
        joint
            .component_div(&self.ratios())
            .component_div(&self.torque_constants)
    }

    /// The joint torques motor currents `amps` (A) exert, N m.
    pub fn joint_torques(&self, amps: &Vector3<f64>) -> Vector3<f64> {
        amps.component_mul(&self.torque_constants)
            .component_mul(&self.ratios())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::profile::Profile;

    fn arms() -> Vec<(String, ArmModel)> {
        ["woodenhaptics_v2015", "polhem_v1"]
            .into_iter()
            .map(|name| {
                let p = Profile::built_in(name).unwrap();
                (name.to_string(), p.arm().copied().unwrap())
            })
            .collect()
    }

    /// Points across each arm's workspace: a 5×5×5 lattice over the cube inscribed in its sphere.
    fn workspace(arm: &ArmModel) -> impl Iterator<Item = Vector3<f64>> + '_ {
        let half = arm.workspace_radius / 3f64.sqrt();
        (0..125).map(move |n| {
            let s = Vector3::new((n % 5) as f64, ((n / 5) % 5) as f64, (n / 25) as f64);
            (s / 2.0).add_scalar(-1.0) * half
        })
    }

    #[test]
    fn inverse_then_forward_kinematics_returns_every_point_of_the_workspace() {
        for (name, arm) in arms() {
            for x in workspace(&arm) {
                let q = arm.joints_at(&x).unwrap_or_else(|| panic!("{name}: {x:?}"));
                let back = arm.handle(&q).position;
                assert!((back - x).norm() < 1e-12, "{name}: {x:?} -> {back:?}");
            }
        }
    }

    #[test]
    fn forward_then_inverse_kinematics_returns_the_joint_angles_over_the_workspace() {
        // Joint angles on a lattice; those that put the handle inside the workspace sphere.
        for (name, arm) in arms() {
            let mut inside = 0;
            for n in 0..9261 {
                let s = Vector3::new((n % 21) as f64, ((n / 21) % 21) as f64, (n / 441) as f64);
                let q =
                    Vector3::new(-1.0, -0.6, -0.4) + s.component_mul(&Vector3::new(0.1, 0.1, 0.1));
                let x = arm.handle(&q).position;
                if x.norm() > arm.workspace_radius {
                    continue;
                }
                inside += 1;
                let back = arm.joints_at(&x).unwrap_or_else(|| panic!("{name}: {q:?}"));
                assert!(
                    (back - q).norm() < 1e-9,
                    "{name}: {q:?} -> {x:?} -> {back:?}"
                );
            }
            assert!(
                inside > 100,
                "{name}: {inside} lattice points in the workspace"
            );
        }
    }

    #[test]
    fn counts_round_trip_through_angles_to_the_resolution() {
        for (name, arm) in arms() {
            for x in workspace(&arm) {
                let q = arm.joints_at(&x).unwrap();
                let counts = arm.counts(&q).map(f64::round);
                let raw = [counts[0] as i16, counts[1] as i16, counts[2] as i16];
                let read = arm.angles(&raw);
                let step = arm.radians_per_count().abs();
                assert!(
                    ((read - q).abs() - step / 2.0).max() <= 1e-12,
                    "{name}: {q:?} read as {read:?}"
                );
            }
        }
    }

    #[test]
    fn jacobian_and_bias_match_finite_differences_across_the_workspace() {
        let h = 1e-6;
        for (name, arm) in arms() {
            for x in workspace(&arm) {
                let q = arm.joints_at(&x).unwrap();
                let qd = Vector3::new(0.7, -1.1, 1.3);
                let (upper, fore) = (arm.lengths[1], arm.lengths[2]);
                let j = arm.point(&JointState::new(&q, &qd), upper, fore);
                for c in 0..3 {
                    let mut e = Vector3::zeros();
                    e[c] = h;
                    let fd =
                        (arm.handle(&(q + e)).position - arm.handle(&(q - e)).position) / (2.0 * h);
                    assert!((fd - j.jacobian.column(c)).amax() < 1e-8, "{name} {x:?}");
                }
                let jdot = (arm.handle(&(q + qd * h)).jacobian
                    - arm.handle(&(q - qd * h)).jacobian)
                    / (2.0 * h);
                assert!((jdot * qd - j.bias).amax() < 1e-6, "{name} {x:?}");
            }
        }
    }

    #[test]
    fn currents_render_the_force_by_virtual_work() {
        // The motors' power at the joints equals the force's at the handle: F·(J q̇) = τ·q̇.
        for (name, arm) in arms() {
            for x in workspace(&arm) {
                let q = arm.joints_at(&x).unwrap();
                let force = Vector3::new(0.3, -1.2, 2.0);
                let tau = arm.joint_torques(&arm.currents(&q, &force));
                let qd = Vector3::new(0.2, 0.5, -0.4);
                let power = force.dot(&(arm.handle(&q).jacobian * qd));
                assert!((power - tau.dot(&qd)).abs() < 1e-12, "{name} {x:?}");
            }
        }
    }

    #[test]
    fn the_published_calibration_pose_puts_the_forearm_horizontal() {
        // woodenhaptics_v2015: encoder c reads 6000 at the pose the user homes the arm in.
        let (_, arm) = &arms()[0];
        let q = arm.angles(&arm.home_counts);
        assert!((q - Vector3::new(0.0, 0.0, std::f64::consts::FRAC_PI_2)).norm() < 1e-12);
    }
}
