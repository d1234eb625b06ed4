//! One transport wrapper for the tests: [`Tap`] carries reports between the servo loop and a
//! device and can record every output report with the time it was written, corrupt or drop input
//! reports by a rule ([`Fault`]), run a hook on every read, and hold each input report until the
//! test lets it through ([`Gate`]: a device that waits for the test, for lock-step runs).

use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use hgcd::profile::Codec;
use hgcd::protocol::MAX_REPORT_LEN;
use hgcd::protocol::{DeviceInfo, OutputReport};
use hgcd::transport::{NoDeviceInfo, Transport, TransportError};

/// How long a gated device waits for the test to let a report through, and the test for the
/// servo loop to take the reports it let through, before the run fails.
pub const GATE_WAIT: Duration = Duration::from_secs(60);

/// What a [`Tap`] does to one input report.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Fault {
    /// An unknown protocol version: the report no longer decodes.
    BadVersion,
    /// Five bytes short.
    Short,
    /// The report is lost: the read returns nothing (the device was silent for that period).
    Silence,
}

type FaultRule = Box<dyn FnMut(u64, f64) -> Option<Fault> + Send>;

/// Output reports a [`Tap`] saw written, each with the transport's time at the write (device time
/// in virtual time). Cloning shares the record.
#[derive(Clone, Default)]
pub struct Writes(Arc<Mutex<Vec<(f64, OutputReport)>>>);

impl Writes {
    fn lock(&self) -> MutexGuard<'_, Vec<(f64, OutputReport)>> {
        self.0.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Everything written so far, oldest first.
    pub fn all(&self) -> Vec<(f64, OutputReport)> {
        self.lock().clone()
    }

    /// The reports alone, oldest first.
    pub fn reports(&self) -> Vec<OutputReport> {
        self.lock().iter().map(|(_, r)| *r).collect()
    }
}

/// Passes reports between the servo loop and `inner`, doing what it was built to do on the way.
/// Nothing is recorded, faulted or held unless asked for, so a bare tap does not allocate.
pub struct Tap<T> {
    inner: T,
    reads: u64,
    faults: Option<FaultRule>,
    writes: Option<Writes>,
    gate: Option<Arc<Gate>>,
    on_read: Option<Box<dyn FnMut() + Send>>,
}

impl<T: Transport> Tap<T> {
    pub fn new(inner: T) -> Self {
        Self {
            inner,
            reads: 0,
            faults: None,
            writes: None,
            gate: None,
            on_read: None,
        }
    }

    /// Record every output report (see [`Tap::writes`]).
    pub fn recording(mut self) -> Self {
        self.writes = Some(Writes::default());
        self
    }

    /// Apply `rule(n, t)` to the n-th input report (from 1), read at transport time `t`.
    pub fn faults(mut self, rule: impl FnMut(u64, f64) -> Option<Fault> + Send + 'static) -> Self {
        self.faults = Some(Box::new(rule));
        self
    }

    /// Hold every read until `gate` lets it through.
    pub fn gated(mut self, gate: Arc<Gate>) -> Self {
        self.gate = Some(gate);
        self
    }

    /// Call `hook` at the start of every read, on the thread that reads (the servo thread).
    pub fn on_read(mut self, hook: impl FnMut() + Send + 'static) -> Self {
        self.on_read = Some(Box::new(hook));
        self
    }

    /// The record of output reports; panics if the tap was not built [`Tap::recording`].
    pub fn writes(&self) -> Writes {
        self.writes.clone().expect("a recording tap")
    }
}

impl<T: Transport> Transport for Tap<T> {
    fn read_input(
        &mut self,
        buf: &mut [u8; MAX_REPORT_LEN],
        timeout: Duration,
    ) -> Result<Option<usize>, TransportError> {
        if let Some(hook) = &mut self.on_read {
            hook();
        }
        if let Some(gate) = &self.gate {
            gate.pass()?;
        }
        let read = self.inner.read_input(buf, timeout)?;
        self.reads += 1;
        let fault = match &mut self.faults {
            Some(rule) => rule(self.reads, self.inner.now()),
            None => None,
        };
        Ok(read.and_then(|n| match fault {
            None => Some(n),
            Some(Fault::BadVersion) => {
                buf[1] = 0xee;
                Some(n)
            }
            Some(Fault::Short) => Some(n - 5),
            Some(Fault::Silence) => None,
        }))
    }

    fn write_output(&mut self, report: &[u8]) -> Result<(), TransportError> {
        if let Some(writes) = &self.writes {
            let decoded =
                OutputReport::decode(report).expect("the servo loop writes valid reports");
            writes.lock().push((self.inner.now(), decoded));
        }
        self.inner.write_output(report)
    }

    fn now(&self) -> f64 {
        self.inner.now()
    }

    fn clock_drift(&self) -> f64 {
        self.inner.clock_drift()
    }
    fn take_garbled_skipped(&mut self) -> u64 {
        self.inner.take_garbled_skipped()
    }

    fn describe(&self) -> String {
        format!("tap on {}", self.inner.describe())
    }

    fn device_info(&self) -> Result<&DeviceInfo, &NoDeviceInfo> {
        self.inner.device_info()
    }

    fn codec(&self) -> Codec {
        self.inner.codec()
    }

    fn sim_world(&self) -> Option<std::sync::Arc<hgcd::sim::LiveWorld>> {
        self.inner.sim_world()
    }
}

#[derive(Debug, Default)]
struct GateState {
    /// Reads the test has let through so far.
    allowed: u64,
    /// Reads that went through.
    passed: u64,
    /// The reader is blocked waiting for the next permission.
    waiting: bool,
    /// Every read goes through (shutdown, or a phase that needs no lock-step).
    open: bool,
}

/// Lock-step between a test and the servo loop: the device's next input report goes out only
/// when the test lets it, as a device would that waits for the host's answer. On a virtual-time
/// device one read is one tick, so the test counts ticks exactly, whatever the load on the machine.
#[derive(Debug, Default)]
pub struct Gate {
    state: Mutex<GateState>,
    changed: Condvar,
}

impl Gate {
    pub fn new() -> Arc<Self> {
        Arc::default()
    }

    fn lock(&self) -> MutexGuard<'_, GateState> {
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Reads let through so far.
    pub fn passed(&self) -> u64 {
        self.lock().passed
    }

    /// Let `reads` more reads through, and wait until the servo loop has taken them all and is
    /// waiting for the next one: the ticks they drove are over, their states published.
    pub fn advance(&self, reads: u64) {
        let mut s = self.lock();
        assert!(!s.open, "advance on an open gate");
        s.allowed += reads;
        let target = s.allowed;
        self.changed.notify_all();
        let deadline = Instant::now() + GATE_WAIT;
        while !(s.passed == target && s.waiting) {
            let left = deadline.saturating_duration_since(Instant::now());
            assert!(
                !left.is_zero(),
                "the servo loop took {} of the {reads} reports let through within {GATE_WAIT:?} \
                 (did the run end?)",
                reads - (target - s.passed)
            );
            s = self
                .changed
                .wait_timeout(s, left)
                .unwrap_or_else(|e| e.into_inner())
                .0;
        }
    }

    /// Let every read through from now on (before stopping a run, or to let it run flat out).
    pub fn open(&self) {
        self.lock().open = true;
        self.changed.notify_all();
    }

    /// The reader's side: wait until the test lets one read through.
    fn pass(&self) -> Result<(), TransportError> {
        let mut s = self.lock();
        let deadline = Instant::now() + GATE_WAIT;
        while !(s.open || s.passed < s.allowed) {
            s.waiting = true;
            self.changed.notify_all();
            let left = deadline.saturating_duration_since(Instant::now());
            if left.is_zero() {
                return Err(TransportError::Disconnected {
                    spec: "test gate".into(),
                    source: std::io::Error::new(
                        std::io::ErrorKind::TimedOut,
                        format!(
                            "no report let through for {GATE_WAIT:?} (the test stopped driving \
                             the device)"
                        ),
                    ),
                });
            }
            s = self
                .changed
                .wait_timeout(s, left)
                .unwrap_or_else(|e| e.into_inner())
                .0;
        }
        s.waiting = false;
        s.passed += 1;
        Ok(())
    }
}
