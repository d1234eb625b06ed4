//! `sim:phantom`: a PHANToM 1.5 / Premium 1.5 style serial arm with the mechanics published by
//! Çavuşoğlu, Feygin and Tendick (Presence 11(6), 2002) and an identified model of the Premium 1.5
//! (drives and friction). Every number and approximation is listed in docs/simulated-devices.md.
//!
//! Joints: θ1 base yaw, θ2 upper arm pitch, θ3 forearm pitch (driven through the rear link of the
//! parallelogram, so it is the forearm's absolute angle from vertical). At q = 0 the upper arm is
//! horizontal and the forearm hangs vertically: that is the home pose, the origin of the device
//! frame. Device axes are the paper's renamed, (x, y, z) = (z, x, y) of the paper: x toward the
//! user, y to the user's right, z up (along the default `sim.gravity_direction`).

use nalgebra::{Matrix3, Vector3};

use super::linkage::{Drives, JointState, Linkage, Mechanism, Point, UnitVariation, Unreachable};
use crate::config::SimConfig;

/// Geometry and masses of the arm (SI units).
#[derive(Clone, Debug, PartialEq)]
pub struct Phantom {
    /// Upper arm length l1 and forearm length l2, m.
    pub l1: f64,
    pub l2: f64,
    /// Lumped masses, kg: forearm (a), parallelogram link parallel to the upper arm (c), upper
    /// arm with its motor-side parts (be), rear link with the counterweight (df).
    pub m_a: f64,
    pub m_c: f64,
    pub m_be: f64,
    pub m_df: f64,
    /// Centre-of-mass distances, m: forearm a along the forearm from the elbow, link c along the
    /// upper arm from the shoulder, l3 (c's offset along the forearm direction), l5 (be along the
    /// upper arm; negative: behind the shoulder), l6 (df against the forearm direction).
    pub a_along_forearm: f64,
    pub c_along_upper_arm: f64,
    pub l3: f64,
    pub l5: f64,
    pub l6: f64,
    /// Principal inertias about each centre of mass, kg m², in the paper's body axes (x, y, z)
    /// at the home pose.
    pub i_a: Vector3<f64>,
    pub i_c: Vector3<f64>,
    pub i_be: Vector3<f64>,
    pub i_df: Vector3<f64>,
    /// The base's inertia about the vertical (θ1) axis, kg m².
    pub i_base_yy: f64,
    /// Mechanical stops (lower, upper), rad.
    pub limits: (Vector3<f64>, Vector3<f64>),
    /// Where the home pose (q = 0) puts the handle in the device frame, m: zero on the
    /// published arm, up to a millimetre off on a unit.
    pub home_offset: Vector3<f64>,
}

impl Phantom {
    /// The published arm (Çavuşoğlu et al. 2002, Tables 1 and 2).
    pub fn published() -> Self {
        let l1 = 0.215;
        let l2 = 0.170;
        Self {
            l1,
            l2,
            m_a: 0.0202,
            m_c: 0.0249,
            m_be: 0.2359,
            m_df: 0.1906,
            a_along_forearm: l2 / 2.0,
            c_along_upper_arm: l1 / 2.0,
            l3: 0.0325,
            l5: -0.0368,
            l6: 0.0527,
            i_a: Vector3::new(0.4864, 0.001843, 0.4864) * 1e-4,
            i_c: Vector3::new(0.959, 0.959, 0.0051) * 1e-4,
            i_be: Vector3::new(11.09, 10.06, 0.591) * 1e-4,
            i_df: Vector3::new(7.11, 0.629, 6.246) * 1e-4,
            i_base_yy: 11.87e-4,
            // Estimates: the forearm stays at least 10° from straight (θ3 − θ2 = 90°) and from
            // folded (θ2 − θ3 = 90°), where the Jacobian is singular.
            limits: (
                Vector3::new(-60f64, -35.0, -40.0).map(f64::to_radians),
                Vector3::new(60f64, 40.0, 45.0).map(f64::to_radians),
            ),
            home_offset: Vector3::zeros(),
        }
    }

    /// The published arm with its masses and centres of mass varied as one unit (`variation`),
    /// its link lengths and home pose a little off the published ones.
    pub fn unit(variation: &mut UnitVariation) -> Self {
        let p = Self::published();
        let (l1, l2) = (variation.vary_length(p.l1), variation.vary_length(p.l2));
        let home_offset = variation.home_offset();
        Self {
            l1,
            l2,
            home_offset,
            m_a: variation.vary(p.m_a),
            m_c: variation.vary(p.m_c),
            m_be: variation.vary(p.m_be),
            m_df: variation.vary(p.m_df),
            a_along_forearm: variation.vary(p.a_along_forearm),
            c_along_upper_arm: variation.vary(p.c_along_upper_arm),
            l3: variation.vary(p.l3),
            l5: variation.vary(p.l5),
            l6: variation.vary(p.l6),
            ..p
        }
    }

    /// Kinematics of the point `along_upper` along the upper arm from the shoulder and then
    /// `along_fore` along the forearm direction (the direction from elbow to handle).
    fn arm_point(&self, joints: &JointState, along_upper: f64, along_fore: f64) -> Point {
        let (a, b) = (along_upper, along_fore);
        let qd = &joints.qd;
        let (s1, c1) = (joints.sin[0], joints.cos[0]);
        let (s2, c2) = (joints.sin[1], joints.cos[1]);
        let (s3, c3) = (joints.sin[2], joints.cos[2]);
        // In the arm's vertical plane, from the shoulder: r outward, h up.
        let r = a * c2 + b * s3;
        let h = a * s2 - b * c3;
        let (r2, r3) = (-a * s2, b * c3);
        let (h2, h3) = (a * c2, b * s3);
        let rd = r2 * qd[1] + r3 * qd[2];
        let r_bias = -a * c2 * qd[1] * qd[1] - b * s3 * qd[2] * qd[2];
        let h_bias = -a * s2 * qd[1] * qd[1] + b * c3 * qd[2] * qd[2];
        let w1 = qd[0];
        Point {
            // The shoulder is l1 behind and l2 above the home handle position.
            position: Vector3::new(c1 * r - self.l1, s1 * r, self.l2 + h) + self.home_offset,
            jacobian: Matrix3::new(
                -s1 * r,
                c1 * r2,
                c1 * r3, //
                c1 * r,
                s1 * r2,
                s1 * r3, //
                0.0,
                h2,
                h3,
            ),
            bias: Vector3::new(
                -c1 * w1 * w1 * r - 2.0 * s1 * w1 * rd + c1 * r_bias,
                -s1 * w1 * w1 * r + 2.0 * c1 * w1 * rd + s1 * r_bias,
                h_bias,
            ),
        }
    }

    /// What a link's rotation adds to the joint-space dynamics, accumulated into `m` and `h`.
    /// The link turns with the base (θ1) and pitches with joint `pitch` (1: with the upper arm,
    /// 2: with the forearm); `principal` are its principal inertias in the paper's axes at home.
    ///
    /// Its orientation is R_z(θ1) R_y(−φ), φ its pitch angle, so in its own axes ω = (θ̇1 sin φ,
    /// −φ̇, θ̇1 cos φ) and T = ½ (I_yy φ̇² + m11(φ) θ̇1²) with m11 = I_xx sin²φ + I_zz cos²φ (device
    /// axes x, y, z are the paper's z, x, y).
    fn add_link_rotation(
        joints: &JointState,
        pitch: usize,
        principal: &Vector3<f64>,
        m: &mut Matrix3<f64>,
        h: &mut Vector3<f64>,
    ) {
        let (i_x, i_y, i_z) = (principal[2], principal[0], principal[1]);
        let (s, c, qd) = (joints.sin[pitch], joints.cos[pitch], &joints.qd);
        let m11 = i_x * s * s + i_z * c * c;
        let dm11 = 2.0 * (i_x - i_z) * s * c;
        m[(0, 0)] += m11;
        m[(pitch, pitch)] += i_y;
        // Lagrange: d/dt ∂T/∂q̇ − ∂T/∂q beyond the M q̈ terms.
        h[0] += dm11 * qd[pitch] * qd[0];
        h[pitch] -= 0.5 * dm11 * qd[0] * qd[0];
    }
}

impl Mechanism for Phantom {
    fn handle(&self, joints: &JointState) -> Point {
        self.arm_point(joints, self.l1, self.l2)
    }

    fn joints_at(&self, x: &Vector3<f64>) -> Option<Vector3<f64>> {
        // Relative to the shoulder: r outward in the arm's plane, h up.
        let x = x - self.home_offset;
        let (fx, fy) = (x[0] + self.l1, x[1]);
        let theta1 = fy.atan2(fx);
        let r = fx.hypot(fy);
        let h = x[2] - self.l2;
        let d = r.hypot(h);
        let cos_shoulder = (self.l1 * self.l1 + d * d - self.l2 * self.l2) / (2.0 * self.l1 * d);
        if !(-1.0..=1.0).contains(&cos_shoulder) {
            return None;
        }
        // Elbow up: the elbow lies above the line from shoulder to handle.
        let theta2 = h.atan2(r) + cos_shoulder.acos();
        let theta3 = (r - self.l1 * theta2.cos()).atan2(self.l1 * theta2.sin() - h);
        Some(Vector3::new(theta1, theta2, theta3))
    }

    fn masses(&self, joints: &JointState, visit: &mut dyn FnMut(f64, &Point)) {
        visit(
            self.m_a,
            &self.arm_point(joints, self.l1, self.a_along_forearm),
        );
        visit(
            self.m_c,
            &self.arm_point(joints, self.c_along_upper_arm, self.l3),
        );
        visit(self.m_be, &self.arm_point(joints, self.l5, 0.0));
        visit(self.m_df, &self.arm_point(joints, 0.0, -self.l6));
    }

    fn rotations(&self, joints: &JointState) -> (Matrix3<f64>, Vector3<f64>) {
        let mut m = Matrix3::zeros();
        let mut h = Vector3::zeros();
        // The base turns about the vertical θ1 axis only.
        m[(0, 0)] = self.i_base_yy;
        Self::add_link_rotation(joints, 2, &self.i_a, &mut m, &mut h);
        Self::add_link_rotation(joints, 1, &self.i_c, &mut m, &mut h);
        Self::add_link_rotation(joints, 1, &self.i_be, &mut m, &mut h);
        Self::add_link_rotation(joints, 2, &self.i_df, &mut m, &mut h);
        (m, h)
    }

    fn joint_limits(&self) -> (Vector3<f64>, Vector3<f64>) {
        self.limits
    }
}

/// The Premium 1.5's drives: capstan ratios 13.3, 11.2, 11.2; Maxon-class motors with 1.08e-6 kg m²
/// rotors and 0.129 N m peak torque; 1024-line quadrature encoders (4096 counts per motor turn);
/// joint Coulomb friction 0.01 N m and viscous friction 0.0005 N m s/rad.
pub fn published_drives() -> Drives {
    Drives {
        ratio: Vector3::new(13.3, 11.2, 11.2),
        rotor_inertia: Vector3::repeat(1.08e-6),
        peak_torque: Vector3::repeat(0.129),
        counts_per_rev: Vector3::repeat(4096.0),
        coulomb: Vector3::repeat(0.01),
        viscous: Vector3::repeat(0.0005),
    }
}

/// The `sim:phantom` plant a `[sim]` section describes.
///
/// # Errors
/// [`Unreachable`] when the handle cannot start at `sim.start_position_mm`.
pub fn from_config(sim: &SimConfig) -> Result<Linkage<Phantom>, Unreachable> {
    Linkage::unit_from_config(sim, Phantom::unit, published_drives())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sim::linkage::checks::{self, env, G};
    use crate::sim::linkage::Environment;
    use crate::sim::Plant;

    fn arm_at(x_mm: [f64; 3], env: Environment) -> Linkage<Phantom> {
        checks::at(Phantom::published(), published_drives(), x_mm, env)
    }

    /// Joint configurations spread over the working range.
    fn poses() -> impl Iterator<Item = Vector3<f64>> {
        (0..27).map(|n| {
            let t = Vector3::new((n % 3) as f64, ((n / 3) % 3) as f64, (n / 9) as f64);
            Vector3::new(-0.5, -0.4, -0.5) + t.component_mul(&Vector3::new(0.45, 0.35, 0.4))
        })
    }

    /// The published gravity torques (τ1, τ2, τ3) of `arm` for gravity `g` along −y of the
    /// paper's frame (Çavuşoğlu et al. 2002).
    fn published_gravity_torque(arm: &Phantom, q: &Vector3<f64>, g: f64) -> Vector3<f64> {
        Vector3::new(
            0.0,
            0.5 * g
                * (2.0 * arm.l1 * arm.m_a + 2.0 * arm.l5 * arm.m_be + arm.l1 * arm.m_c)
                * q[1].cos(),
            0.5 * g
                * (arm.l2 * arm.m_a + 2.0 * arm.l3 * arm.m_c - 2.0 * arm.l6 * arm.m_df)
                * q[2].sin(),
        )
    }

    #[test]
    fn lumped_masses_reproduce_the_published_gravity_torques() {
        let arm = Phantom::published();
        let (lo, hi) = arm.limits;
        let mut plant = arm_at([0.0; 3], env(1.0, 0.0));
        for q in poses().chain([lo, hi]) {
            plant.set_state(q, Vector3::zeros());
            let published = published_gravity_torque(&arm, &q, G);
            assert!(
                (plant.gravity_torque() - published).amax() < 1e-12,
                "at {q:?}: {:?} vs published {published:?}",
                plant.gravity_torque()
            );
        }
        // The published coefficients in numbers: τ2 ≈ −0.016 cos θ2, τ3 ≈ −0.074 sin θ3.
        let unit = published_gravity_torque(
            &arm,
            &Vector3::new(0.0, 0.0, std::f64::consts::FRAC_PI_2),
            G,
        );
        assert!((unit[1] + 0.0163).abs() < 5e-4 && (unit[2] + 0.0737).abs() < 5e-4);
    }

    #[test]
    fn gravity_torque_is_the_gradient_of_the_potential_energy_for_any_gravity() {
        let mut plant = arm_at([0.0; 3], checks::tilted());
        for q in poses() {
            checks::assert_gravity_torque_is_the_gradient(&mut plant, &q);
        }
    }

    #[test]
    fn inverse_kinematics_inverts_forward_kinematics_and_home_is_the_origin() {
        let arm = Phantom::published();
        let zero = Vector3::zeros();
        assert!(arm.handle(&JointState::at_rest(&zero)).position.norm() < 1e-15);
        for q in poses() {
            let x = arm.handle(&JointState::at_rest(&q)).position;
            let back = arm.joints_at(&x).unwrap();
            assert!((back - q).amax() < 1e-9, "{q:?} -> {x:?} -> {back:?}");
        }
        assert!(arm.joints_at(&Vector3::new(0.5, 0.0, 0.0)).is_none());
    }

    #[test]
    fn jacobians_and_velocity_products_match_finite_differences() {
        let arm = Phantom::published();
        let qd = Vector3::new(0.7, -1.1, 0.9);
        for q in poses() {
            checks::assert_points_match_finite_differences(&arm, &q, &qd, 1e-7);
        }
    }

    #[test]
    fn at_home_gravity_pushes_the_handle_up_by_about_0_076_n() {
        let plant = arm_at([0.0; 3], env(1.0, 0.0));
        let gravity_force = -plant.holding_force();
        assert!(gravity_force.xy().norm() < 1e-12);
        assert!((gravity_force.z - 0.0758).abs() < 5e-4, "{gravity_force:?}");
        // With the paper's 30 g probe the handle weighs down instead.
        let probed = arm_at([0.0; 3], env(1.0, 0.03));
        assert!((probed.holding_force().z - (0.03 * G - 0.0758)).abs() < 5e-4);
    }

    #[test]
    fn over_the_calibration_cube_the_gravity_force_varies_and_turns_far_from_vertical() {
        let (least, most, steepest, sideways) =
            checks::gravity_force_spread(|x| arm_at(x, env(1.0, 0.0)), &Vector3::z());
        // design.md: 0.075–0.13 N, up to about 66° from vertical, horizontal parts up to 0.11 N.
        assert!((0.072..0.078).contains(&least), "{least}");
        assert!((0.128..0.136).contains(&most), "{most}");
        assert!((64.0..68.0).contains(&steepest), "{steepest}");
        assert!((0.105..0.12).contains(&sideways), "{sideways}");
    }

    #[test]
    fn frictionless_motion_conserves_energy() {
        // Largest energy error over 0.3 s of free motion, relative to the starting kinetic energy.
        checks::assert_energy_is_conserved(|dt| {
            let mut plant = arm_at([0.0; 3], env(0.0, 0.0));
            plant.set_state(Vector3::new(0.1, 0.05, -0.05), Vector3::new(0.8, 0.3, 0.4));
            let start = plant.kinetic_energy();
            let (worst, _) = checks::free_motion_energy(&mut plant, 0.3, dt);
            worst / start
        });
    }

    #[test]
    fn the_holding_force_holds_a_frictionless_arm_still_for_seconds() {
        for x in [[0.0, 0.0, 0.0], [30.0, -25.0, 35.0], [-40.0, 40.0, -40.0]] {
            checks::assert_holding_force_holds_still(arm_at(x, env(0.0, 0.03)));
        }
    }

    #[test]
    fn static_friction_holds_below_its_band_and_slips_above_it() {
        let x = [20.0, 10.0, -15.0];
        let drives = published_drives();
        for (fraction, slips) in [(0.8, false), (1.2, true)] {
            let mut plant = arm_at(x, env(1.0, 0.0));
            let start = plant.position();
            let jt = plant
                .mechanism()
                .handle(&JointState::at_rest(&plant.joints()))
                .jacobian
                .transpose();
            // A load whose net joint torques are `fraction` of the static band, on every joint.
            let load = jt.lu().solve(&(drives.coulomb * fraction)).unwrap();
            let force = plant.holding_force() + load;
            for _ in 0..20_000 {
                plant.step(&force, 1e-4);
            }
            let moved = (plant.position() - start).norm();
            if slips {
                assert!(
                    moved > 1e-3,
                    "a load above the band moved it only {moved} m"
                );
            } else {
                assert_eq!(moved, 0.0, "a load inside the band moved it");
            }
        }
    }

    #[test]
    fn a_sliding_joint_comes_to_rest_against_coulomb_friction() {
        let mut plant = arm_at([0.0; 3], env(1.0, 0.0));
        let hold = plant.holding_force();
        plant.set_state(plant.joints(), Vector3::new(0.5, 0.0, 0.0));
        for _ in 0..20_000 {
            plant.step(&hold, 1e-4);
        }
        assert_eq!(plant.joint_velocities(), Vector3::zeros());
        // θ1 carries no gravity: the base decelerates at about τ_c / inertia and stops.
        assert!(plant.joints()[0] > 0.01);
    }

    #[test]
    fn the_motors_saturate_at_their_peak_torque() {
        let zero_g = Environment {
            gravity: Vector3::zeros(),
            payload: 0.0,
            friction_scale: 0.0,
            handle_friction: 0.0,
            spring: (0.0, Vector3::zeros()),
            handle_damping: 0.0,
        };
        let pushed = |fx: f64| {
            let mut plant = arm_at([0.0; 3], zero_g);
            plant.step(&Vector3::new(fx, 0.0, 0.0), 1e-4);
            plant.joint_velocities()[2]
        };
        // At home a force along x turns only θ3, through the forearm: 0.129 N m × 11.2 / l2.
        let peak: f64 = 0.129 * 11.2 / 0.170;
        assert!((peak - 8.5).abs() < 0.01);
        assert_eq!(pushed(20.0), pushed(peak + 0.01));
        assert!(pushed(peak - 0.5) < pushed(peak));
    }

    #[test]
    fn the_stops_end_the_motion_at_the_joint_limits() {
        let mut plant = arm_at([0.0; 3], env(1.0, 0.0));
        // Without a force the over-counterbalanced arm rises: θ2 slides to its upper stop.
        for _ in 0..50_000 {
            plant.step(&Vector3::zeros(), 1e-4);
        }
        let (_, hi) = plant.mechanism().limits;
        assert_eq!(plant.joints()[1], hi[1]);
        assert_eq!(plant.joint_velocities()[1], 0.0);
    }

    #[test]
    fn the_coarsest_substep_the_config_allows_stays_bounded() {
        // sim.substep_hz may be as low as 100 Hz: stops and friction are constraints, not stiff
        // springs, so even 10 ms steps neither blow up nor leave the workspace.
        for friction in [0.0, 1.0] {
            let mut plant = arm_at([30.0, -30.0, 30.0], env(friction, 0.03));
            let (lo, hi) = plant.workspace();
            for n in 0..1_000 {
                let push = if n % 200 < 100 { 3.0 } else { -3.0 };
                plant.step(&Vector3::new(push, -push, push), 0.01);
                let x = plant.position();
                assert!(x.iter().all(|c| c.is_finite()));
                assert!((0..3).all(|a| x[a] >= lo[a] && x[a] <= hi[a]), "{x:?}");
            }
        }
    }

    #[test]
    fn the_encoders_resolve_about_0_03_mm_at_the_handle() {
        let drives = published_drives();
        let arm = Phantom::published();
        let step = drives.joint_resolution();
        let at_handle = Vector3::new(step[0] * arm.l1, step[1] * arm.l1, step[2] * arm.l2);
        assert!(
            at_handle.iter().all(|s| (0.020e-3..0.031e-3).contains(s)),
            "{at_handle:?}"
        );
        for x in [[0.0, 0.0, 0.0], [13.7, -21.1, 33.3], [-38.0, 5.5, -12.0]] {
            let plant = arm_at(x, env(1.0, 0.0));
            let sensed = plant.sensed_position(&Vector3::zeros());
            assert!((sensed - plant.position()).amax() < 0.025e-3, "{x:?}");
            // Noise moves the reading by about as much as it moves the handle.
            let noise = Vector3::new(0.3e-3, -0.2e-3, 0.25e-3);
            assert!((plant.sensed_position(&noise) - plant.position() - noise).amax() < 0.03e-3);
        }
    }

    #[test]
    fn the_joint_limits_keep_the_mechanism_away_from_singular_poses() {
        let m = Phantom::published();
        let (lo, hi) = m.joint_limits();
        let zero = Vector3::zeros();
        let home = m
            .handle(&JointState::at_rest(&zero))
            .jacobian
            .determinant()
            .abs();
        let mut least = f64::INFINITY;
        for n in 0..729 {
            let s = Vector3::new((n % 9) as f64, ((n / 9) % 9) as f64, (n / 81) as f64) / 8.0;
            let q = lo + (hi - lo).component_mul(&s);
            least = least.min(
                m.handle(&JointState::at_rest(&q))
                    .jacobian
                    .determinant()
                    .abs(),
            );
        }
        // The least is 4.5 % of home, at θ2 = 40°, θ3 = −40° (forearm 10° from folded, handle
        // near the base axis).
        assert!(least > 0.03 * home, "{}", least / home);
    }

    #[test]
    fn units_differ_by_a_few_percent_and_seed_zero_is_the_published_arm() {
        assert_eq!(
            Phantom::unit(&mut UnitVariation::new(0)),
            Phantom::published()
        );
        let units: Vec<Phantom> = (1..=2)
            .map(|s| Phantom::unit(&mut UnitVariation::new(s)))
            .collect();
        assert_eq!(
            units[0],
            Phantom::unit(&mut UnitVariation::new(1)),
            "deterministic"
        );
        let p = Phantom::published();
        for u in &units {
            for (a, b) in [
                (u.m_a, p.m_a),
                (u.m_be, p.m_be),
                (u.m_df, p.m_df),
                (u.l6, p.l6),
            ] {
                assert!((a / b - 1.0).abs() <= UnitVariation::SPREAD + 1e-12);
            }
        }
        let nominal = arm_at([0.0; 3], env(1.0, 0.0)).holding_force();
        checks::assert_units_differ(from_config, nominal, 0.005..0.5);
    }

    #[test]
    fn an_obstacle_stops_the_arm_at_its_face_and_the_contact_is_logged_once() {
        // A wall at x = +20 mm across the whole workspace; the handle starts at home, 20 mm
        // from it, and is pushed toward it with 0.3 N beyond its holding force for 2 s.
        let mut sim = crate::config::SimConfig {
            obstacle_min_mm: Some([20.0, -500.0, -500.0]),
            obstacle_max_mm: Some([500.0, 500.0, 500.0]),
            ..Default::default()
        };
        let mut arm = from_config(&sim).unwrap();
        assert_eq!(arm.contacts().count(), 0);
        let dt = 1e-4;
        let mut fastest = 0.0f64;
        for _ in 0..20_000 {
            fastest = fastest.max(arm.velocity().norm());
            let push = arm.holding_force() + Vector3::new(0.3, 0.0, 0.0);
            arm.step(&push, dt);
            assert!(arm.position().x <= 0.020 + 1e-9, "{:?}", arm.position());
        }
        // Held at the face: still, within a step's travel of it.
        assert!(arm.position().x > 0.019, "{:?}", arm.position());
        assert!(arm.velocity().norm() < 1e-9);
        let log = arm.contacts();
        assert_eq!(log.count(), 1, "{:?}", log.contacts());
        let contact = log.contacts()[0];
        // The wall stops the arm where its last step began: within a step's travel of the face.
        let travel = contact.speed * dt;
        assert!(contact.position.x <= 0.020 && contact.position.x >= 0.020 - 1.01 * travel);
        // The speed it met the wall at: the handle's, one step's acceleration after the fastest
        // seen before the step.
        assert!(
            contact.speed >= fastest && contact.speed < 1.01 * fastest,
            "{contact:?}, {fastest}"
        );
        assert!(contact.time > 0.0 && contact.time < 2.0);
        // A handle cannot start inside the obstacle.
        sim.start_position_mm = [30.0, 0.0, 0.0];
        assert!(from_config(&sim).is_err());
    }

    #[test]
    fn handle_friction_holds_below_its_level_and_takes_the_energy_of_a_slide() {
        checks::assert_handle_friction_sticks_and_slides(arm_at, [20.0, -15.0, 10.0]);
    }

    /// A spring at the handle adds k (X − X_0) to the holding force, and the handle held by
    /// that force stays put; damping at the handle takes energy from a moving handle.
    #[test]
    fn a_spring_at_the_handle_is_held_and_damping_slows_it() {
        let x = [20.0, -15.0, 10.0];
        let anchor = Vector3::new(0.05, 0.02, -0.03);
        let mut sprung = env(0.0, 0.0);
        sprung.spring = (40.0, anchor);
        let plain = arm_at(x, env(0.0, 0.0)).holding_force();
        let mut plant = arm_at(x, sprung);
        let held = plant.holding_force();
        let expected = plain + (plant.position() - anchor) * 40.0;
        assert!((held - expected).norm() < 1e-9, "{held} vs {expected}");
        let start = plant.position();
        for _ in 0..10_000 {
            plant.step(&held, 1e-4);
        }
        assert!((plant.position() - start).norm() < 1e-4);
        // Damping: the same push, the damped handle moves less far.
        let mut damped_env = env(0.0, 0.0);
        damped_env.handle_damping = 5.0;
        let push = plain + Vector3::new(0.3, 0.0, 0.0);
        let (mut free, mut damped) = (arm_at(x, env(0.0, 0.0)), arm_at(x, damped_env));
        for _ in 0..2_000 {
            free.step(&push, 1e-4);
            damped.step(&push, 1e-4);
        }
        let travel = |p: &Linkage<Phantom>| (p.position() - start).norm();
        assert!(travel(&damped) < 0.8 * travel(&free));
    }
}
