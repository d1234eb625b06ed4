//! The daemon's controller on the servo thread, in two layers:
//! - [`Arbiter`], pure: state in, force out. It decides between compensation (Eq. 15) with the
//!   owner's force offset, a calibration in progress, and the hold that bridges a finished
//!   calibration to its grid. Commands and offsets are method calls; it is tested tick by tick
//!   without threads.
//! - [`DaemonController`]: the arbiter plus its mailbox. Before each tick it takes what arrived
//!   (a bounded number of commands, the newest offset); after it, it publishes the state with the
//!   force the output report carried.
//!
//! Nothing here allocates, locks or blocks; boxes arrive built and leave to be dropped elsewhere.

use nalgebra::Vector3;

use crate::control::calibration::Calibration;
use crate::control::compensation::Compensation;
use crate::control::pd::PointHold;
use crate::control::{ControlOutput, Controller, DeviceState};
use crate::mailbox::{
    OffsetCommand, PublishedState, ServoCommand, ServoMailbox, ServoReturn, COMMAND_CAPACITY,
};

/// Who drives the handle, and with what: compensation plus the owner's offset, a calibration, or
/// the hold after a calibration until its grid arrives.
pub struct Arbiter {
    compensation: Compensation,
    calibration: Option<Box<Calibration>>,
    /// After a successful calibration, until its grid arrives: hold at the last vertex.
    hold: Option<PointHold>,
    owner: Option<u64>,
    /// The newest offset from the owner, applied at the next tick.
    pending: Option<OffsetCommand>,
    offset_seq: u64,
    /// The last tick's force was the gravity model's alone.
    gravity_only: bool,
}

impl Arbiter {
    pub fn new(compensation: Compensation) -> Self {
        Self {
            compensation,
            calibration: None,
            hold: None,
            owner: None,
            pending: None,
            offset_seq: 0,
            gravity_only: false,
        }
    }

    /// `seq` of the last force offset applied (0: none).
    pub fn offset_seq(&self) -> u64 {
        self.offset_seq
    }

    /// Whether the last tick's force was the gravity model's alone (a model, no offset, no
    /// calibration, no hold).
    pub fn gravity_only(&self) -> bool {
        self.gravity_only
    }

    fn drop_offset(&mut self) {
        self.compensation.offset.clear();
        self.pending = None;
        self.offset_seq = 0;
    }

    /// Act on a command; returns what must go back to the hub.
    pub fn command(&mut self, command: ServoCommand) -> Option<ServoReturn> {
        match command {
            ServoCommand::SetOwner(owner) => {
                if owner != self.owner {
                    self.drop_offset();
                }
                self.owner = owner;
                None
            }
            ServoCommand::ClientGone(client) => {
                if self.owner == Some(client) {
                    self.owner = None;
                    self.drop_offset();
                }
                None
            }
            ServoCommand::StartCalibration(calibration) => {
                if self.calibration.is_some() {
                    return Some(ServoReturn::CalibrationRefused(calibration));
                }
                self.drop_offset();
                self.calibration = Some(calibration);
                None
            }
            ServoCommand::AbortCalibration => {
                self.calibration.take().map(ServoReturn::CalibrationDone)
            }
            ServoCommand::ReleaseHold => {
                self.hold = None;
                None
            }
            ServoCommand::SwapModel(model) => {
                self.hold = None;
                let old = std::mem::replace(&mut self.compensation.model, model);
                Some(ServoReturn::OldModel(old))
            }
        }
    }

    /// A force offset; only the owner's count, and none while calibrating or holding the handle
    /// for the new grid. It takes effect at the next tick.
    pub fn offset(&mut self, offset: OffsetCommand) {
        if Some(offset.client) == self.owner && self.calibration.is_none() && self.hold.is_none() {
            self.pending = Some(offset);
        }
    }

    /// The force for this tick, and what must go back to the hub (a finished calibration).
    pub fn tick(&mut self, s: &DeviceState) -> (Vector3<f64>, Option<ServoReturn>) {
        if let Some(offset) = self.pending.take() {
            self.compensation.offset.set(offset.force, s);
            self.offset_seq = offset.seq;
        }
        self.gravity_only = false;
        let Some(calibration) = self.calibration.as_mut() else {
            let force = match &self.hold {
                Some(hold) => hold.force(s),
                None => {
                    self.gravity_only = self.compensation.model.is_some()
                        && self.compensation.offset.at(s) == Vector3::zeros();
                    self.compensation.tick(s).force
                }
            };
            return (force, None);
        };
        let out = calibration.tick(s);
        if !out.done {
            return (out.force, None);
        }
        let finished = self.calibration.take().expect("calibration present");
        // Keep the handle up at the last vertex until the new grid is swapped in (saving it
        // takes a disk write); after a failure, compensation resumes.
        self.hold = finished.final_hold();
        let force = match &self.hold {
            Some(hold) => hold.force(s),
            None => self.compensation.gravity_force(&s.position),
        };
        (force, Some(ServoReturn::CalibrationDone(finished)))
    }
}

/// The arbiter with its mailbox: what the daemon's servo thread runs.
pub struct DaemonController {
    arbiter: Arbiter,
    mailbox: ServoMailbox,
}

impl DaemonController {
    pub fn new(compensation: Compensation, mailbox: ServoMailbox) -> Self {
        Self {
            arbiter: Arbiter::new(compensation),
            mailbox,
        }
    }
}

impl Controller for DaemonController {
    fn before_tick(&mut self, _: &DeviceState) {
        // Only what was waiting when the tick began, and at most a ring's worth.
        let waiting = self.mailbox.commands_waiting().min(COMMAND_CAPACITY);
        for _ in 0..waiting {
            let Some(command) = self.mailbox.command() else {
                break;
            };
            if let Some(item) = self.arbiter.command(command) {
                self.mailbox.give_back(item);
            }
        }
        if let Some(offset) = self.mailbox.offset() {
            self.arbiter.offset(offset);
        }
    }

    fn tick(&mut self, s: &DeviceState) -> ControlOutput {
        let (force, item) = self.arbiter.tick(s);
        if let Some(item) = item {
            self.mailbox.give_back(item);
        }
        ControlOutput::force(force)
    }

    fn after_tick(&mut self, s: &DeviceState, sent: &Vector3<f64>) {
        self.mailbox.publish(PublishedState {
            state: *s,
            force: *sent,
            offset_seq: self.arbiter.offset_seq(),
            gravity_only: self.arbiter.gravity_only(),
        });
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::control::compensation::{CompensationMode, ForceOffset, GravityModel, OutsideGrid};
    use crate::grid::MassGrid;
    use crate::protocol::Status;

    fn state(tick: u64) -> DeviceState {
        let t = tick as f64 * 1e-3;
        DeviceState {
            time: t,
            host_time: t,
            position: Vector3::new(0.0, 0.0, 0.01),
            velocity: Vector3::zeros(),
            status: Status::default(),
            tick,
        }
    }

    fn arbiter(mass: f64) -> Arbiter {
        let grid = MassGrid::uniform(
            mass,
            9.81,
            Vector3::z(),
            Vector3::new(-0.04, -0.04, -0.04),
            0.08,
            [2, 2, 2],
        );
        let model = GravityModel::new(
            grid.into(),
            CompensationMode::Scalar,
            OutsideGrid::HoldNearest,
        )
        .expect("scalar model");
        Arbiter::new(Compensation::new(
            Some(Box::new(model)),
            ForceOffset::new(0.05, 0.05),
        ))
    }

    fn offset(client: u64, seq: u64, x: f64) -> OffsetCommand {
        OffsetCommand {
            client,
            seq,
            force: Vector3::new(x, 0.0, 0.0),
        }
    }

    #[test]
    fn compensation_plus_only_the_owners_offset() {
        let mut a = arbiter(0.1);
        let weight = Vector3::new(0.0, 0.0, 0.1 * 9.81);
        assert_eq!(a.tick(&state(0)).0, weight);
        a.offset(offset(7, 1, 1.0));
        assert_eq!(a.tick(&state(1)).0, weight, "nobody owns the force yet");
        assert!(a.command(ServoCommand::SetOwner(Some(7))).is_none());
        a.offset(offset(8, 1, 2.0));
        a.offset(offset(7, 2, 1.0));
        let (f, _) = a.tick(&state(2));
        assert_eq!(f, weight + Vector3::new(1.0, 0.0, 0.0));
        assert_eq!(a.offset_seq(), 2);
        // The owner leaves: its force goes on the next tick.
        a.command(ServoCommand::ClientGone(7));
        assert_eq!(a.tick(&state(3)).0, weight);
        assert_eq!(a.offset_seq(), 0);
    }

    #[test]
    fn a_swapped_model_comes_back_to_be_dropped_elsewhere() {
        let mut a = arbiter(0.1);
        let old = a.command(ServoCommand::SwapModel(None));
        assert!(matches!(old, Some(ServoReturn::OldModel(Some(_)))));
        assert_eq!(a.tick(&state(0)).0, Vector3::zeros());
    }
}
