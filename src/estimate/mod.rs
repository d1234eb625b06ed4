//! State estimation: velocity from sampled positions.

pub mod foaw;

pub use foaw::{Foaw, FoawAxis, FoawError, FoawVariant};
