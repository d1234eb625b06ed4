//! hgcd: autocalibrated gravity compensation for 3-DoF impedance haptic devices
//! (Formaglio et al.). The servo loop lives in [`servo`], controllers in [`control`], device
//! transports in [`transport`], simulated devices in [`sim`].

pub mod app; //        application socket: wire protocol, server, client library
pub mod arm; //        arms the host knows: kinematics and the gravity of their links
pub mod calibrate; //  `hgcd calibrate`: run Algorithm 1 on a device and persist the grid
pub mod config; //     typed configuration, defaults, validation
pub mod control; //    controllers: PD hold, calibration, compensation
pub mod daemon; //     `hgcd run`: compensation, application server, calibration on request
pub mod discrepancy; // `hgcd record` and `hgcd analyze`: where model and measurement disagree
pub mod estimate; //   FOAW velocity estimation
pub mod figure; //     SVG and PNG figures without system libraries
pub mod fit; //        gravity models fitted from holds, chosen by held-out score
pub mod grid; //       apparent-mass grid, trilinear interpolation, hgcd-grid/1 files
pub mod mailbox; //    what the daemon hands the servo thread and gets back, lock-free
pub mod newest; //     a slot where the newest value wins, wait-free on both sides
pub mod profile; //    device profiles: wire protocol and host-side kinematics per device
pub mod protocol; //   HID report layout v1: encode/decode
pub mod servo; //      the 1 kHz tick loop, safety layer, timing statistics
pub mod sim; //        simulated devices: plants, encoders, firmware, socket server
pub mod sys; //        ppoll, recv without waiting, absolute sleeps
pub mod transport; //  hid, in-process sim and socket transports
pub mod validate; //   `hgcd validate`: the paper's validation experiment (Section 5, Fig. 2)

pub use app::client;
