//! The daemon's controller on the servo thread: compensation (Eq. 15) with the application's
//! offset, or a calibration in progress; commands in and state out through bounded channels.
//! Nothing here allocates, locks or blocks; boxes arrive built and leave to be dropped elsewhere.

use crossbeam_channel::{Receiver, Sender};
use nalgebra::Vector3;

use crate::app::protocol::StateSample;
use crate::control::calibration::Calibration;
use crate::control::compensation::{Compensation, GravityModel};
use crate::control::pd::PointHold;
use crate::control::{ControlOutput, Controller, DeviceState};

/// A force offset from the client that owns the force.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct OffsetCommand {
    pub client: u64,
    pub seq: u64,
    /// N.
    pub force: Vector3<f64>,
}

/// Everything else the daemon tells the servo thread.
#[derive(Debug)]
pub enum ServoCommand {
    /// This client now owns the force (None: nobody); any offset from before is dropped.
    SetOwner(Option<u64>),
    /// This client disconnected: its force goes at once.
    ClientGone(u64),
    /// Run this calibration now (offsets are ignored until it ends).
    StartCalibration(Box<Calibration>),
    /// Abandon the calibration in progress (its requester went away); it comes back unfinished.
    AbortCalibration,
    /// Stop holding the handle where the last calibration left it (no new grid is coming).
    ReleaseHold,
    /// Use this gravity model from the next tick (None: no compensation).
    SwapModel(Option<Box<GravityModel>>),
}

/// What the servo thread hands back to be dealt with (and dropped) outside the loop.
#[derive(Debug)]
pub enum ServoReturn {
    CalibrationDone(Box<Calibration>),
    /// A calibration was requested while one was running.
    CalibrationRefused(Box<Calibration>),
    OldModel(Option<Box<GravityModel>>),
}

/// The channels the controller talks through.
pub struct ControllerLinks {
    pub commands: Receiver<ServoCommand>,
    pub offsets: Receiver<OffsetCommand>,
    pub returns: Sender<ServoReturn>,
    pub states: Sender<StateSample>,
}

pub struct DaemonController {
    compensation: Compensation,
    calibration: Option<Box<Calibration>>,
    /// After a successful calibration, until its grid arrives: hold at the last vertex.
    hold: Option<PointHold>,
    owner: Option<u64>,
    offset_seq: u64,
    links: ControllerLinks,
}

impl DaemonController {
    pub fn new(compensation: Compensation, links: ControllerLinks) -> Self {
        Self {
            compensation,
            calibration: None,
            hold: None,
            owner: None,
            offset_seq: 0,
            links,
        }
    }

    fn give_back(&self, item: ServoReturn) {
        // The return channel is sized so this does not fail; if it ever did, the item would be
        // dropped here, off the hot path only in the sense that it is rare.
        let _ = self.links.returns.try_send(item);
    }

    fn drain_commands(&mut self) {
        while let Ok(command) = self.links.commands.try_recv() {
            match command {
                ServoCommand::SetOwner(owner) => {
                    if owner != self.owner {
                        self.compensation.offset.clear();
                        self.offset_seq = 0;
                    }
                    self.owner = owner;
                }
                ServoCommand::ClientGone(client) => {
                    if self.owner == Some(client) {
                        self.owner = None;
                        self.compensation.offset.clear();
                        self.offset_seq = 0;
                    }
                }
                ServoCommand::StartCalibration(calibration) => {
                    if self.calibration.is_some() {
                        self.give_back(ServoReturn::CalibrationRefused(calibration));
                    } else {
                        self.compensation.offset.clear();
                        self.offset_seq = 0;
                        self.calibration = Some(calibration);
                    }
                }
                ServoCommand::AbortCalibration => {
                    if let Some(calibration) = self.calibration.take() {
                        self.give_back(ServoReturn::CalibrationDone(calibration));
                    }
                }
                ServoCommand::ReleaseHold => self.hold = None,
                ServoCommand::SwapModel(model) => {
                    self.hold = None;
                    let old = std::mem::replace(&mut self.compensation.model, model);
                    self.give_back(ServoReturn::OldModel(old));
                }
            }
        }
    }

    /// Apply the newest offset from the owner; offsets from anyone else (or stale ones from a
    /// client that just lost ownership) are ignored.
    fn drain_offsets(&mut self, now: f64) {
        let mut newest: Option<OffsetCommand> = None;
        while let Ok(offset) = self.links.offsets.try_recv() {
            // The channel is FIFO per client, so the last one from the owner is the newest.
            if Some(offset.client) == self.owner {
                newest = Some(offset);
            }
        }
        if let Some(offset) = newest {
            // No offsets while calibrating or holding the handle for the new grid.
            if self.calibration.is_none() && self.hold.is_none() {
                self.compensation.offset.set(offset.force, now);
                self.offset_seq = offset.seq;
            }
        }
    }
}

impl Controller for DaemonController {
    fn tick(&mut self, s: &DeviceState) -> ControlOutput {
        self.drain_commands();
        self.drain_offsets(s.time);
        let force = match self.calibration.as_mut() {
            Some(calibration) => {
                let out = calibration.tick(s);
                if out.done {
                    let finished = self.calibration.take().expect("calibration present");
                    // Keep the handle up at the last vertex until the new grid is swapped in
                    // (saving it takes a disk write); after a failure, compensation resumes.
                    self.hold = finished.final_hold();
                    self.give_back(ServoReturn::CalibrationDone(finished));
                    match &self.hold {
                        Some(hold) => hold.force(s),
                        None => self.compensation.gravity_force(&s.position),
                    }
                } else {
                    out.force
                }
            }
            None => match &self.hold {
                Some(hold) => hold.force(s),
                None => self.compensation.tick(s).force,
            },
        };
        let _ = self.links.states.try_send(StateSample {
            tick: s.tick,
            time: s.time,
            position: s.position.into(),
            velocity: s.velocity.into(),
            force: force.into(),
            flags: s.status.bits(),
            offset_seq: self.offset_seq,
        });
        ControlOutput::force(force)
    }
}
