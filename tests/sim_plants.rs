//! The linkage plants behind the emulated firmware: the whole byte path (firmware, protocol,
//! servo loop, safety layer) in virtual time, checked against each plant's own physics.

use std::sync::atomic::AtomicBool;

use nalgebra::Vector3;

use hgcd::config::Config;
use hgcd::control::{ControlOutput, Controller, DeviceState};
use hgcd::servo::{self, ServoOptions};
use hgcd::sim::SimDevice;
use hgcd::transport::sim::SimTransport;
use hgcd::transport::Pacing;

/// A PD hold with a constant gravity feed-forward: F = k_P (X_D − X) − k_D V̂ + F_G.
struct Hold {
    set_point: Vector3<f64>,
    k_p: f64,
    k_d: f64,
    feed_forward: Vector3<f64>,
}

impl Controller for Hold {
    fn tick(&mut self, s: &DeviceState) -> ControlOutput {
        ControlOutput::force(
            (self.set_point - s.position) * self.k_p - s.velocity * self.k_d + self.feed_forward,
        )
    }
}

/// `sim:MODEL` on `config`, held at `set_point` with the gains [`K_P`], [`K_D`] and
/// `feed_forward` for 3 s of device time; the transport after.
fn hold(
    model: &str,
    config: &Config,
    set_point: Vector3<f64>,
    feed_forward: Vector3<f64>,
) -> SimTransport {
    let device = SimDevice::from_config(model, config).unwrap();
    let mut transport = SimTransport::new(device, Pacing::Virtual);
    let mut options = ServoOptions::from_config(config);
    options.duration = Some(3.0);
    let mut hold = Hold {
        set_point,
        k_p: K_P,
        k_d: K_D,
        feed_forward,
    };
    let stop = AtomicBool::new(false);
    servo::run(&mut transport, &mut hold, &options, &stop, None).unwrap();
    transport
}

/// The plant's holding force with the handle at `x`, from a twin device started there.
fn holding_force_at(model: &str, config: &Config, x: &Vector3<f64>) -> Vector3<f64> {
    let mut twin = config.clone();
    twin.sim.start_position_mm = (x * 1e3).into();
    SimDevice::from_config(model, &twin)
        .unwrap()
        .plant()
        .holding_force()
}

fn quiet(friction_scale: f64) -> Config {
    let mut config = Config::default();
    config.sim.noise_mm = 0.0;
    config.sim.friction_scale = friction_scale;
    config
}

const K_P: f64 = 300.0;
const K_D: f64 = 5.0;

/// A PD hold without feed-forward on `sim:MODEL` (frictionless) comes to rest where the spring
/// carries the plant's own gravity force: k_P (X_D − X) = J⁻ᵀ τ_g(X).
fn a_pd_hold_settles_where_the_gravity_force_puts_it(model: &str) -> Vector3<f64> {
    let config = quiet(0.0);
    let set_point = Vector3::new(0.010, -0.010, 0.010);
    let transport = hold(model, &config, set_point, Vector3::zeros());
    let plant = transport.device().plant();
    let x = plant.position();
    // Without friction the handle keeps a limit cycle of about one encoder count there.
    let residual = (set_point - x) * K_P - plant.holding_force();
    // Within what the encoder steps (0.03 mm) let the spring see.
    assert!(residual.amax() < K_P * 0.04e-3, "{residual:?} at {x:?}");
    x - set_point
}

/// With the plant's holding force at the set point fed forward, `sim:MODEL` holds it, whatever
/// the direction of gravity.
fn the_holding_force_fed_forward_holds_the_set_point(model: &str, config: &Config) {
    let set_point = Vector3::new(-0.030, 0.020, 0.035);
    let feed_forward = holding_force_at(model, config, &set_point);
    let transport = hold(model, config, set_point, feed_forward);
    let x = transport.device().plant().position();
    assert!((x - set_point).amax() < 0.04e-3, "{x:?}");
}

/// With published friction the handle sticks anywhere the spring and gravity leave less than the
/// static band: the residual force is at most the joints' friction seen at the handle.
fn friction_leaves_the_handle_within_its_band(model: &str, band_n: f64) {
    let config = quiet(1.0);
    let set_point = Vector3::new(0.020, 0.030, -0.020);
    let transport = hold(model, &config, set_point, Vector3::zeros());
    let plant = transport.device().plant();
    assert_eq!(plant.velocity(), Vector3::zeros(), "stuck, not creeping");
    let residual = (set_point - plant.position()) * K_P - plant.holding_force();
    assert!(residual.amax() < band_n, "{residual:?}");
}

#[test]
fn a_pd_hold_on_the_phantom_settles_above_its_set_point() {
    // The arm is over-counterbalanced: gravity pushes its handle up.
    assert!(a_pd_hold_settles_where_the_gravity_force_puts_it("phantom").z > 0.0);
}

#[test]
fn a_pd_hold_on_the_delta_settles_below_its_set_point() {
    assert!(a_pd_hold_settles_where_the_gravity_force_puts_it("delta").z < -0.002);
}

/// The device stands tilted by 10° about y.
fn tilted() -> Config {
    let mut config = quiet(0.0);
    let tilt = 10f64.to_radians();
    config.sim.gravity_direction = [tilt.sin(), 0.0, tilt.cos()];
    config
}

#[test]
fn with_its_holding_force_fed_forward_the_phantom_holds_the_set_point() {
    the_holding_force_fed_forward_holds_the_set_point("phantom", &quiet(0.0));
    the_holding_force_fed_forward_holds_the_set_point("phantom", &tilted());
}

#[test]
fn with_its_holding_force_fed_forward_the_delta_holds_the_set_point() {
    the_holding_force_fed_forward_holds_the_set_point("delta", &quiet(0.0));
    the_holding_force_fed_forward_holds_the_set_point("delta", &tilted());
}

#[test]
fn a_tilted_device_feels_gravity_turned_with_it() {
    // At home the delta's holding force lies along the gravity direction, symmetric as it is
    // only about its axis: tilted, it turns by about the tilt, and stays as strong to a few %.
    let upright = holding_force_at("delta", &quiet(0.0), &Vector3::zeros());
    let leaning = holding_force_at("delta", &tilted(), &Vector3::zeros());
    let angle = upright.angle(&leaning).to_degrees();
    assert!((5.0..15.0).contains(&angle), "{angle}");
    assert!((leaning.norm() / upright.norm() - 1.0).abs() < 0.1);
    assert!(leaning.x > 0.0);
}

#[test]
fn joint_friction_leaves_the_phantom_anywhere_within_its_band() {
    // 0.01 N m of static friction per joint is about 0.05 N at the handle per axis.
    friction_leaves_the_handle_within_its_band("phantom", 0.1);
}

#[test]
fn joint_friction_leaves_the_delta_anywhere_within_its_band() {
    // 0.004 N m per joint: about 0.14 N along the axis at home, through all three arms.
    friction_leaves_the_handle_within_its_band("delta", 0.2);
}

#[test]
fn a_start_position_out_of_reach_is_refused_with_the_key_to_change() {
    let mut config = Config::default();
    config.sim.start_position_mm = [400.0, 0.0, 0.0];
    let Err(err) = SimDevice::from_config("phantom", &config) else {
        panic!("started out of reach");
    };
    assert_eq!(
        err.to_string(),
        "sim.start_position_mm [400.0, 0.0, 0.0] is out of reach of sim:phantom: give a point \
         inside its joint limits (the origin is its home pose)"
    );
    let Err(err) = SimDevice::from_config("nope", &Config::default()) else {
        panic!("built an unknown model");
    };
    assert!(err
        .to_string()
        .starts_with("unknown simulated model `nope`; known: point-mass, phantom, delta"));
}
