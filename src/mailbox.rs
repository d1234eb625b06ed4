//! The daemon's mailbox to and from the servo thread: what the application server (`app`) and the
//! daemon's hub (`daemon`) hand to the controller on the servo thread, and what comes back. Both
//! sides import it from here, so neither imports the other.
//!
//! The servo thread never waits on any of it:
//! - commands travel on a wait-free single-producer ring (rtrb); the threads that send them take
//!   a mutex among themselves, the servo thread only pops;
//! - force offsets go through a newest-wins slot ([`crate::newest`]): a flood of offsets costs the
//!   servo thread one atomic swap per tick, whatever the rate;
//! - what the servo thread sends back (finished calibrations, replaced models, state samples)
//!   goes on rings it alone writes, read by the hub, which polls.

use std::sync::{Arc, Mutex, MutexGuard};

use nalgebra::Vector3;

use crate::control::calibration::Calibration;
use crate::control::compensation::GravityModel;
use crate::control::DeviceState;
use crate::newest::{newest, NewestReader, NewestWriter};

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

/// One tick as the servo thread publishes it: the state it acted on and the force the output
/// report carried (after the safety layer: what the device was actually told).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PublishedState {
    pub state: DeviceState,
    /// N.
    pub force: Vector3<f64>,
    /// `seq` of the last force offset applied (0: none).
    pub offset_seq: u64,
    /// The force was the gravity model's alone: no application offset (or one of zero), no
    /// calibration, no hold. The moments the model can be tested in use.
    pub gravity_only: bool,
}

/// Commands a ring holds; a full ring means the servo thread is not ticking (device silent).
pub const COMMAND_CAPACITY: usize = 64;
/// Returns a ring holds: at most a calibration and a model are in flight at once.
pub const RETURN_CAPACITY: usize = 16;
/// State samples a ring holds: about a second at 1 kHz between two hub polls.
pub const STATE_CAPACITY: usize = 1024;

/// Sends commands to the servo thread; cloneable, never blocks on the servo thread.
#[derive(Clone)]
pub struct CommandSender {
    ring: Arc<Mutex<rtrb::Producer<ServoCommand>>>,
}

/// Sends force offsets to the servo thread; the newest wins.
#[derive(Clone)]
pub struct OffsetSender {
    slot: Arc<Mutex<NewestWriter<OffsetCommand>>>,
}

/// The servo thread's end: what arrives and what goes back.
pub struct ServoMailbox {
    commands: rtrb::Consumer<ServoCommand>,
    offsets: NewestReader<OffsetCommand>,
    returns: rtrb::Producer<ServoReturn>,
    states: rtrb::Producer<PublishedState>,
}

/// The hub's end of what the servo thread sends back.
pub struct HubMailbox {
    pub returns: rtrb::Consumer<ServoReturn>,
    pub states: rtrb::Consumer<PublishedState>,
}

/// A new mailbox: senders for the server and hub, the servo end, and the hub's receiving end.
pub fn mailbox() -> (CommandSender, OffsetSender, ServoMailbox, HubMailbox) {
    let (command_tx, command_rx) = rtrb::RingBuffer::new(COMMAND_CAPACITY);
    let (offset_tx, offset_rx) = newest();
    let (return_tx, return_rx) = rtrb::RingBuffer::new(RETURN_CAPACITY);
    let (state_tx, state_rx) = rtrb::RingBuffer::new(STATE_CAPACITY);
    (
        CommandSender {
            ring: Arc::new(Mutex::new(command_tx)),
        },
        OffsetSender {
            slot: Arc::new(Mutex::new(offset_tx)),
        },
        ServoMailbox {
            commands: command_rx,
            offsets: offset_rx,
            returns: return_tx,
            states: state_tx,
        },
        HubMailbox {
            returns: return_rx,
            states: state_rx,
        },
    )
}

/// Lock a sender's mutex; a panic in another sender does not make the queue unusable.
fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

impl CommandSender {
    /// Queue `command`; gives it back when the ring is full (the servo thread is not ticking).
    pub fn send(&self, command: ServoCommand) -> Result<(), ServoCommand> {
        lock(&self.ring).push(command).map_err(|e| match e {
            rtrb::PushError::Full(c) => c,
        })
    }
}

impl OffsetSender {
    /// Make `offset` the newest; an older one the servo thread has not taken is replaced.
    pub fn send(&self, offset: OffsetCommand) {
        lock(&self.slot).publish(offset);
    }
}

impl ServoMailbox {
    /// The next command, if any. Call it at most [`COMMAND_CAPACITY`] times a tick: a sender that
    /// keeps refilling the ring must not hold the servo thread in the loop.
    pub fn command(&mut self) -> Option<ServoCommand> {
        self.commands.pop().ok()
    }

    /// Commands waiting now (an upper bound for one tick's draining).
    pub fn commands_waiting(&self) -> usize {
        self.commands.slots()
    }

    /// The newest offset sent since the last call, if any.
    pub fn offset(&mut self) -> Option<OffsetCommand> {
        self.offsets.take()
    }

    /// Hand `item` back to the hub. The ring is sized so this does not fail while the hub runs;
    /// if the hub is gone the item is dropped here.
    pub fn give_back(&mut self, item: ServoReturn) {
        let _ = self.returns.push(item);
    }

    /// Publish one tick's state; dropped when the hub has fallen a ring behind.
    pub fn publish(&mut self, state: PublishedState) {
        let _ = self.states.push(state);
    }
}
