//! What a calibration ends with: a [`CalibrationResult`] or a [`CalibrationFailure`].

use nalgebra::Vector3;

use super::plan::Vertex;

/// What was measured at one vertex.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct VertexResult {
    pub vertex: Vertex,
    /// Apparent mass M̂(X_i), kg.
    pub mass: f64,
    /// Whole holding force at the last steady state, N (vector form of Eq. 11).
    pub force: Vector3<f64>,
    /// Mass updates made.
    pub iterations: u32,
    /// Distance from the vertex at the last steady state, m.
    pub final_error: f64,
    /// Device time spent on this vertex, move included, s.
    pub duration: f64,
}

/// A finished calibration.
#[derive(Clone, Debug, PartialEq)]
pub struct CalibrationResult {
    /// Unit v_G (Eq. 7).
    pub gravity_direction: Vector3<f64>,
    /// M̂_0 (Eq. 8), kg.
    pub initial_mass: f64,
    /// Rest point X_C and steady state X(∞) of the initialisation, m.
    pub rest_point: Vector3<f64>,
    pub initial_steady_state: Vector3<f64>,
    /// Results in grid order (x fastest).
    pub vertices: Vec<VertexResult>,
    pub origin: Vector3<f64>,
    pub dims: [usize; 3],
    pub left_out: Vec<Vertex>,
    /// Device time of the whole run, s.
    pub duration: f64,
}

/// Why a calibration failed.
#[derive(Clone, Copy, Debug, PartialEq, thiserror::Error)]
pub enum CalibrationFailure {
    #[error(
        "initialisation found no steady state within {timeout:.0} s (is the handle free to move \
         and held by nothing but the field?)"
    )]
    InitTimeout { timeout: f64 },
    #[error(
        "initialisation: the handle came to rest but sagged only {sag_mm:.3} mm under the field; \
         either something holds it, or it weighs less than {min_mass_g:.0} g (then lower \
         calibration.k_init_n_per_mm)"
    )]
    NoSag { sag_mm: f64, min_mass_g: f64 },
    #[error(
        "{vertex} did not converge within {timeout:.0} s ({iterations} mass updates); the handle \
         may be blocked by a stop, the vertex may lie outside the reachable workspace, or \
         calibration.eps_m_mm may be below the position noise"
    )]
    VertexTimeout {
        vertex: Vertex,
        timeout: f64,
        iterations: u32,
    },
    #[error(
        "{vertex} could not be reached: the handle settled {distance_mm:.1} mm away from it (a \
         mechanical stop or an obstacle? check device.workspace_*_mm)"
    )]
    Unreachable { vertex: Vertex, distance_mm: f64 },
    #[error("{vertex} did not converge after {iterations} mass updates")]
    TooManyIterations { vertex: Vertex, iterations: u32 },
    #[error(
        "{vertex}: the apparent mass came out as {mass:.4} kg; hgcd-grid/1 needs positive masses \
         (is the device over-balanced here?)"
    )]
    NonPositiveMass { vertex: Vertex, mass: f64 },
}
