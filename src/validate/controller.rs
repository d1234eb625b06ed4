//! The experiment on the servo thread: the daemon's own [`Arbiter`] (compensation, Eq. 15, plus
//! the owner's force offset, with its staleness rules) fed by the [`Probe`] as its one owner, in
//! place of a client on the socket. The probe answers each state in `after_tick`, so its force is
//! applied at the next tick, as a client's is; the servo loop's safety layer limits the sum, as
//! in the daemon. Between runs the gravity model is swapped as the daemon hot-swaps a grid.
//!
//! Nothing here allocates, locks or blocks: the models wait in slots allocated before the run,
//! rests go into a vector with room for all of them, and progress leaves by `try_send`.

use crossbeam_channel::Sender;
use nalgebra::Vector3;

use super::probe::{Probe, Rest};
use crate::control::compensation::{Compensation, GravityModel};
use crate::control::{ControlOutput, Controller, DeviceState};
use crate::daemon::controller::Arbiter;
use crate::mailbox::{OffsetCommand, ServoCommand, ServoReturn};

/// The client id the probe owns the force under.
const PROBE_CLIENT: u64 = 1;

/// The experiment as the servo loop runs it.
pub struct ExperimentController {
    arbiter: Arbiter,
    /// The gravity model of each run (None: uncompensated); a run's slot is emptied when it
    /// starts and receives it back when the next one starts.
    models: Vec<Option<Box<GravityModel>>>,
    run: usize,
    probe: Probe,
    seq: u64,
    rests: Vec<Rest>,
    progress: Option<Sender<Rest>>,
}

impl ExperimentController {
    /// `models[r]` compensates run `r` of the probe's plan; `compensation` carries the offset
    /// settings (the daemon's `app.stale_*`). Rests are also sent to `progress`, if given.
    pub fn new(
        mut compensation: Compensation,
        mut models: Vec<Option<Box<GravityModel>>>,
        probe: Probe,
        progress: Option<Sender<Rest>>,
    ) -> Self {
        assert_eq!(models.len(), probe.plan().runs, "one model per run");
        compensation.model = models[0].take();
        let mut arbiter = Arbiter::new(compensation);
        arbiter.command(ServoCommand::SetOwner(Some(PROBE_CLIENT)));
        let rests = Vec::with_capacity(probe.plan().readings());
        Self {
            arbiter,
            models,
            run: 0,
            probe,
            seq: 0,
            rests,
            progress,
        }
    }

    /// What the experiment recorded, in order.
    pub fn into_rests(self) -> Vec<Rest> {
        self.rests
    }

    /// Start run `next`: its model in, the previous run's back to its slot.
    fn swap_model(&mut self, next: usize) {
        let model = self.models[next].take();
        if let Some(ServoReturn::OldModel(old)) =
            self.arbiter.command(ServoCommand::SwapModel(model))
        {
            self.models[self.run] = old;
        }
        self.run = next;
    }
}

impl Controller for ExperimentController {
    fn tick(&mut self, s: &DeviceState) -> ControlOutput {
        let (force, _) = self.arbiter.tick(s);
        if self.probe.finished() {
            ControlOutput::done(force)
        } else {
            ControlOutput::force(force)
        }
    }

    fn after_tick(&mut self, s: &DeviceState, _sent: &Vector3<f64>) {
        let step = self.probe.step(s);
        if self.probe.run() != self.run {
            self.swap_model(self.probe.run());
        }
        self.seq += 1;
        self.arbiter.offset(OffsetCommand {
            client: PROBE_CLIENT,
            seq: self.seq,
            force: step.force,
        });
        if let Some(rest) = step.rest {
            if self.rests.len() < self.rests.capacity() {
                self.rests.push(rest);
            }
            if let Some(tx) = &self.progress {
                let _ = tx.try_send(rest);
            }
        }
    }
}
