//! Off-line autocalibration (paper §3, Algorithm 1) as a tick-driven state machine.
//!
//! 1. **Initialisation** (§3.1): an elastic field k_init (X_C − X) (plus a little damping, beyond
//!    the paper, so a frictionless handle settles) holds the handle near where it rests. At steady
//!    state the sag gives the gravity direction v_G (Eq. 7) and a rough mass M̂_0 (Eq. 8).
//! 2. **Vertices** (§3.2): a feedback-linearised PD (k_D = αM, k_P = βM) moves to each grid
//!    vertex along a minimum-jerk path and holds it with the gravity term M_j g v_G (Eq. 10). At
//!    each steady state the mass is updated with the *signed* form of Eq. 11,
//!    M_{j+1} = M_j + k_P (X_i − X̄)·v_G / g (the paper's norm loses the sign; see docs), and the
//!    whole holding force k_P (X_i − X̄) + M_j g v_G is kept for the vector mode. The next vertex
//!    starts from this one's mass (Eqs. 12, 14). Unlike Eq. 13 (k_P(i,j) = β M_{j−1}), the gains
//!    follow the newest estimate: lagged gains leave the loop mis-linearised for a whole iteration
//!    after a large correction. If a hold finds no steady state for a second, its gains are
//!    halved (at most three times): gains built on a mass several times too large oscillate
//!    through the velocity filter's lag.
//!
//! The parts: `plan.rs` (which vertices, in which order), `steady.rs` (when the handle is at
//! rest), `machine.rs` (the controller, one method per phase: initialisation, move, hold) and
//! `outcome.rs` (result or failure). The PD law itself is
//! [`LinearisedGains::pd_force`](crate::control::pd::LinearisedGains::pd_force).
//! docs/calibration.md describes the method for users, with every deviation from the paper.

mod machine;
mod outcome;
pub mod persist;
mod plan;
mod steady;

pub use machine::{Calibration, CalibrationEvent};
pub use outcome::{CalibrationFailure, CalibrationResult, VertexResult};
pub use plan::{GridPlan, PlanError, Vertex};

use nalgebra::Vector3;

use super::pd::LinearisedGains;
use crate::config::Config;

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
    /// Time after a move or a mass update before steady-state samples count, s (2 × rise time).
    pub settle_time: f64,
    /// Duration of a one-cell move, s; longer moves take proportionally longer.
    pub move_time: f64,
    /// Limit per vertex (and for the initialisation), s.
    pub vertex_timeout: f64,
    pub max_iterations: u32,
    /// Box the handle may be driven in, m.
    pub workspace: (Vector3<f64>, Vector3<f64>),
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
            settle_time: 2.0 * rise_time,
            move_time: c.move_time(),
            vertex_timeout: c.vertex_timeout_s,
            max_iterations: c.max_iterations,
            workspace: config.device.workspace(),
        }
    }
}
