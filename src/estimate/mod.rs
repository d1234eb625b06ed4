//! State estimation: velocity from sampled positions (`foaw`), and whether the handle is at
//! rest and how noisy its position is (`steady`: the calibration's and the validation's).

pub mod foaw;
pub(crate) mod steady;

pub use foaw::{Foaw, FoawAxis, FoawError, FoawVariant};
