//! Off-line autocalibration (paper §3, Algorithm 1) as a tick-driven state machine, made to need
//! no tuning: it measures the handle instead of assuming it sags visibly under its own weight.
//!
//! 1. **Initialisation** (§3.1): an elastic field k_init (X_C − X) with some damping catches the
//!    handle where it rests. Then, instead of waiting for a sag, it *pushes*: along each axis a
//!    growing force finds the two edges of the stick band (the forces at which the handle slips
//!    one way and the other): their middle is the load there, their half-width the friction.
//!    A short pulse a known amount beyond the band along each axis times the handle's moving
//!    mass. The hold's gains follow from these: feedback-linearised (k_P = β m, k_D = α m,
//!    Eqs. 4–5) on the measured moving mass, stiffer where the friction band would otherwise
//!    span more than 0.2 mm of offset.
//! 2. **Vertices** (§3.2): the PD moves to each grid vertex along a minimum-jerk path and holds
//!    it with the force estimate F̂ as its gravity term (Eq. 10 with a vector). At rest off the
//!    vertex, F̂ becomes the force the hold applies there (the vector form of the signed Eq. 11);
//!    an update that does not bring the handle closer is followed by a growing push toward the
//!    vertex, and a handle that does not yield to it is blocked: the vertex is marked unreachable
//!    and the run goes on. At rest near the vertex (within the reach tolerance that follows the
//!    friction band), the stick band is measured along x, y and z from both sides and F̂ becomes
//!    its middle, until a round changes it by less than a quarter of the band. The next vertex
//!    starts from this one's force (Eqs. 12, 14).
//! 3. **Result**: the holds, each where it was measured. [`crate::fit::lattice`] completes the
//!    grid from them (v_G, each vertex's mass along it, unreachable vertices filled from their
//!    neighbours) and `calibrate::persist` builds the grid file with the model chosen.
//!
//! The parts: `plan.rs` (which vertices, in which order), `probe.rs` (the stick band, the moving mass and the strokes), `machine/` (the controller, one
//! method per phase: its state and dispatch in `mod.rs`, the phases in `initialise.rs`,
//! `visit.rs` and `hold.rs`) and `outcome.rs` (result or failure). The PD law is
//! [`AxisGains::pd_force`](crate::control::pd::AxisGains::pd_force); when the handle is at
//! rest, `estimate::steady`.
//! docs/calibration.md describes the method for users, beside the paper's.

pub mod explore;
mod machine;
mod outcome;
mod plan;
mod probe;

use machine::STROKES_AGAIN_SHARE;
pub use machine::{Calibration, CalibrationEvent};
pub use outcome::{
    unreachable_note, CalibrationFailure, CalibrationResult, InitialMeasurement, TimeSpent,
    VertexResult,
};
pub use plan::{GridPlan, PlanError, Vertex};

use nalgebra::Vector3;

use super::compensation::GravityModel;
use super::pd::LinearisedGains;
use crate::arm::Arm;
use crate::config::{Config, DeviceSpec, HoldPlan, WorkspaceMode};
use crate::estimate::FoawVariant;
use crate::profile::Profile;

/// Which of the cube's vertices a run holds the handle at (in cube mode; exploration holds
/// every vertex it reaches). The others are filled from the held ones.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Holds {
    /// Every vertex (the paper).
    Every,
    /// The eight corners, farthest apart in joint angles (`calibration.holds = "sparse"`).
    Corners,
    /// The two corners at the ends of the cube's main diagonal: the holds `hgcd check`
    /// compares with the saved model.
    Diagonal,
}

/// Calibration parameters in SI units.
#[derive(Clone, Debug, PartialEq)]
pub struct CalibrationParams {
    /// Cube side L, m.
    pub spacing: f64,
    /// N: vertex indices run over [−N, N] on each axis.
    pub half_size: u32,
    /// Grid centre, m.
    pub centre: Vector3<f64>,
    /// Initial field stiffness, N/m.
    pub k_init: f64,
    /// Initial field damping, N·s/m.
    pub init_damping: f64,
    pub n_init: usize,
    /// m.
    pub eps_init: f64,
    pub n_m: usize,
    /// m.
    pub eps_m: f64,
    /// m/s².
    pub g: f64,
    pub gains: LinearisedGains,
    /// Duration of a one-cell move, s; longer moves take proportionally longer.
    pub move_time: f64,
    /// Limit per vertex (and for the initialisation), s.
    pub vertex_timeout: f64,
    pub max_iterations: u32,
    /// Box the handle may be driven in, m.
    pub workspace: (Vector3<f64>, Vector3<f64>),
    /// The largest force the safety layer lets through, N (calibration pushes with at most a
    /// quarter of it beyond the forces it holds).
    pub max_force: f64,
    /// Report period of the device, s (bounds the hold's bandwidth).
    pub period: f64,
    /// The velocity filter the servo loop uses (`[estimate]`): calibration runs its own copy,
    /// whose noise bound it raises to the encoder step it measures.
    pub foaw_variant: FoawVariant,
    /// m.
    pub noise_bound: f64,
    pub max_window: usize,
    /// The paper's cube, or the workspace explored first.
    pub workspace_mode: WorkspaceMode,
    /// Which of the cube's vertices are held (`calibration.holds`, or `hgcd check`'s one).
    pub holds: Holds,
    /// The arm the device's profile gives, if any: one stroke through each vertex then turns
    /// each of its joints at the same rate ([`crate::arm::Arm::jacobian`]), and its gravity,
    /// fitted to the vertices measured so far, predicts the next.
    pub arm: Option<Arm>,
    /// Strokes that moved F̂ by more than 30 mN and this share of the force they found are
    /// measured once more (not a config key: 0.1, see `machine/mod.rs`).
    pub strokes_again_share: f64,
    /// Whether a vertex's force is predicted from the vertices measured before it, and then
    /// measured by strokes alone, where friction dominates (not a config key: true, see
    /// `machine/`; false runs the paper's Eq. 12 and the bands at every vertex).
    pub predict_vertices: bool,
    /// What an earlier calibration of this device measured at X_C (`hgcd check`): with it, the
    /// initialisation ends once the handle is caught.
    pub prior: Option<Prior>,
}

/// What an earlier calibration's initialisation measured at X_C (its grid file's
/// `[calibration]` record). A run given it skips the stick bands, the moving-mass pulses and the
/// survey strokes: the handle is caught, and the holds begin with the gains built from the
/// prior friction and moving mass. The load is the prior's where the catch agrees with it
/// within the friction, else the nearest value the catch allows (a payload, a tilt: what a
/// check is for), per axis.
#[derive(Clone, Debug, PartialEq)]
pub struct Prior {
    /// Holding force at X_C, N.
    pub load: Vector3<f64>,
    /// Friction along x, y, z, N.
    pub friction: Vector3<f64>,
    /// Moving mass along x, y, z, kg.
    pub inertia: Vector3<f64>,
    /// The encoder's step, m.
    pub step: f64,
    /// The saved model: each hold starts from the force last measured plus the model's change
    /// from there to the vertex, where the paper's calibration starts from the force last
    /// measured (its Eq. 12).
    pub model: Option<GravityModel>,
}

impl Prior {
    /// A prior from a grid file's record, if it holds every value and each is one a device can
    /// have (finite; friction and step not negative; moving mass positive; none beyond
    /// `max_force` N, a tonne or a millimetre): else why not.
    pub fn from_record(
        record: &crate::grid::CalibrationRecord,
        max_force: f64,
    ) -> Result<Self, &'static str> {
        let (Some(load), Some(friction), Some(inertia), Some(step)) = (
            record.load_n,
            record.friction_n,
            record.inertia_kg,
            record.step_mm,
        ) else {
            return Err("its [calibration] record lacks load_n, friction_n, inertia_kg or step_mm");
        };
        let prior = Self {
            load: Vector3::from(load),
            friction: Vector3::from(friction),
            inertia: Vector3::from(inertia),
            step: step * 1e-3,
            model: None,
        };
        let within = |v: &Vector3<f64>, lo: f64, hi: f64| v.iter().all(|x| (lo..=hi).contains(x));
        let plausible = within(&prior.load, -max_force, max_force)
            && within(&prior.friction, 0.0, max_force)
            && within(&prior.inertia, f64::MIN_POSITIVE, 1000.0)
            && (0.0..=1e-3).contains(&prior.step);
        if plausible {
            Ok(prior)
        } else {
            Err("its [calibration] record's load_n, friction_n, inertia_kg or step_mm is out of range")
        }
    }

    /// The holding force the saved model expects at `x` (allocation-free).
    pub fn expected_at(&self, x: &Vector3<f64>) -> Option<Vector3<f64>> {
        self.model.as_ref().map(|model| model.force(x))
    }
}

impl CalibrationParams {
    pub fn from_config(config: &Config) -> Self {
        let c = &config.calibration;
        let rise_time = c.rise_time();
        Self {
            spacing: c.spacing(),
            half_size: c.half_size,
            centre: c.centre(),
            k_init: c.k_init(),
            init_damping: c.init_damping_n_s_per_m,
            n_init: c.n_init,
            eps_init: c.eps_init(),
            n_m: c.n_m,
            eps_m: c.eps_m(),
            g: c.g,
            gains: LinearisedGains::from_rise_time(rise_time, c.damping_ratio),
            move_time: c.move_time(),
            vertex_timeout: c.vertex_timeout_s,
            max_iterations: c.max_iterations,
            workspace: config.device.workspace(),
            max_force: config.safety.max_force_n,
            period: config.servo_period(),
            foaw_variant: config.estimate.foaw_variant,
            noise_bound: config.estimate.noise_bound(),
            max_window: config.estimate.max_window,
            workspace_mode: c.workspace,
            holds: if c.holds == HoldPlan::Sparse {
                Holds::Corners
            } else {
                Holds::Every
            },
            arm: None,
            strokes_again_share: STROKES_AGAIN_SHARE,
            predict_vertices: true,
            prior: None,
        }
    }

    /// [`from_config`](Self::from_config) for the device `device`: `calibration.holds = "auto"`
    /// holds sparsely on a device whose profile has an arm (the arm model needs few holds, far
    /// apart in joint angles; docs/calibration.md §13).
    pub fn for_device(config: &Config, device: &DeviceSpec) -> Self {
        let mut params = Self::from_config(config);
        params.arm = Profile::for_device(device, config)
            .ok()
            .and_then(|p| p.gravity_arm());
        if config.calibration.holds == HoldPlan::Auto && params.arm.is_some() {
            params.holds = Holds::Corners;
        }
        params
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::grid::CalibrationRecord;

    fn record() -> CalibrationRecord {
        CalibrationRecord {
            load_n: Some([0.01, -0.02, 1.2]),
            friction_n: Some([0.1, 0.1, 0.12]),
            inertia_kg: Some([0.05, 0.07, 0.06]),
            step_mm: Some(0.01),
            ..CalibrationRecord::default()
        }
    }

    #[test]
    fn a_prior_is_taken_from_a_whole_record_in_si_units() {
        let prior = Prior::from_record(&record(), 8.0).unwrap();
        assert_eq!(prior.load, Vector3::new(0.01, -0.02, 1.2));
        assert_eq!(prior.inertia, Vector3::new(0.05, 0.07, 0.06));
        assert!((prior.step - 1e-5).abs() < 1e-18);
        assert_eq!(prior.expected_at(&Vector3::zeros()), None);
    }

    /// A record from before `step_mm`, or one a hand or a fault spoiled, gives no prior: the
    /// check measures the initialisation again rather than build its gains on it.
    #[test]
    fn a_partial_or_implausible_record_gives_no_prior() {
        let spoiled: [fn(&mut CalibrationRecord); 7] = [
            |r| r.step_mm = None,
            |r| r.inertia_kg = None,
            |r| r.friction_n = Some([0.1, f64::NAN, 0.1]),
            |r| r.friction_n = Some([0.1, -0.1, 0.1]),
            |r| r.inertia_kg = Some([0.05, 0.0, 0.06]),
            |r| r.load_n = Some([0.0, 0.0, 1e300]),
            |r| r.step_mm = Some(5.0),
        ];
        for (n, spoil) in spoiled.iter().enumerate() {
            let mut r = record();
            spoil(&mut r);
            assert!(Prior::from_record(&r, 8.0).is_err(), "case {n}: {r:?}");
        }
    }
}
