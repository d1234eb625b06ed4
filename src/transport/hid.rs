//! `hid:VID:PID[:SERIAL]`: real devices through hidapi (Linux hidraw backend, no system library).
//!
//! `hid_write` is synchronous and has been seen to stall for over 5 ms every few cycles
//! (libusb/hidapi#506), so output reports go to a writer thread ([`OutputWriter`]) through a
//! newest-wins slot: the servo thread never waits for the device to accept a write, and handing a
//! report over takes no lock (a triple-buffer swap and an unpark, which is an atomic swap and at
//! most a futex wake).

use std::ffi::CString;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::thread::{JoinHandle, Thread};
use std::time::{Duration, Instant};

use hidapi::{HidApi, HidDevice};

use super::{Burst, NoDeviceInfo, Speaks, Transport, TransportError};
use crate::config::DeviceSpec;
use crate::newest::{newest, NewestWriter};
use crate::profile::{Codec, Wire};
use crate::protocol::MAX_REPORT_LEN;
use crate::protocol::{DeviceInfo, DEVICE_INFO_LEN, DEVICE_INFO_REPORT_ID, OUTPUT_REPORT_LEN};

/// A HID device the system shows, as `hgcd devices` lists it.
#[derive(Clone, Debug)]
pub struct HidDeviceEntry {
    pub vid: u16,
    pub pid: u16,
    pub serial: Option<String>,
    pub manufacturer: Option<String>,
    pub product: Option<String>,
    pub path: String,
    pub interface: i32,
}

impl HidDeviceEntry {
    /// The device spec that opens this device.
    pub fn spec(&self) -> String {
        match &self.serial {
            Some(s) if !s.is_empty() => format!("hid:{:04x}:{:04x}:{s}", self.vid, self.pid),
            _ => format!("hid:{:04x}:{:04x}", self.vid, self.pid),
        }
    }
}

/// Every HID device visible to this process.
///
/// # Errors
/// [`TransportError::Hid`] when hidapi cannot start.
pub fn list_devices() -> Result<Vec<HidDeviceEntry>, TransportError> {
    let api = HidApi::new().map_err(|source| TransportError::Hid {
        spec: "hid".into(),
        doing: "starting hidapi".into(),
        source,
    })?;
    Ok(api
        .device_list()
        .map(|d| HidDeviceEntry {
            vid: d.vendor_id(),
            pid: d.product_id(),
            serial: d.serial_number().map(str::to_string),
            manufacturer: d.manufacturer_string().map(str::to_string),
            product: d.product_string().map(str::to_string),
            path: d.path().to_string_lossy().into_owned(),
            interface: d.interface_number(),
        })
        .collect())
}

/// Host side of a HID device: reads on the servo thread, writes on a writer thread.
pub struct HidTransport {
    /// Dropped first (fields drop in order): the final report is written while the lock is held.
    writer: OutputWriter,
    /// Exclusive advisory lock on the hidraw node: one hgcd process per device.
    _lock: std::fs::File,
    /// VID, PID and the serial number the device reports.
    resolved: DeviceSpec,
    /// Its device-info feature report, asked for when it was opened (or what its profile says).
    info: Result<DeviceInfo, NoDeviceInfo>,
    /// The device's protocol, and the host side of its profile.
    wire: Wire,
    codec: Codec,
    reader: HidDevice,
    spec: String,
    start: Instant,
    garbled_skipped: u64,
}

/// An output report as hidapi writes it (report ID first) and its length.
type Frame = ([u8; OUTPUT_REPORT_LEN + 1], usize);

/// A thread that writes output reports as they come, newest first: [`OutputWriter::send`] never
/// blocks, allocates or locks, so the servo thread can call it every tick; a report the thread
/// has not written yet is replaced by a newer one. Dropping it writes the last report sent (the
/// final zero force) and joins the thread.
pub struct OutputWriter {
    slot: NewestWriter<Frame>,
    thread: Thread,
    handle: Option<JoinHandle<()>>,
    failed: Arc<AtomicBool>,
    closing: Arc<AtomicBool>,
}

impl OutputWriter {
    /// Start the thread; `write` hands one report to the device (on the writer thread).
    ///
    /// # Errors
    /// The [`std::io::Error`] of a thread that cannot be spawned.
    pub fn spawn<W>(mut write: W) -> std::io::Result<Self>
    where
        W: FnMut(&[u8]) -> std::io::Result<()> + Send + 'static,
    {
        let (slot, mut reports) = newest::<Frame>();
        let failed = Arc::new(AtomicBool::new(false));
        let closing = Arc::new(AtomicBool::new(false));
        let (failed_w, closing_w) = (failed.clone(), closing.clone());
        let handle = std::thread::Builder::new()
            .name("hgcd-hid-writer".into())
            .spawn(move || loop {
                // Read the flag before the slot: a report sent before closing is still written.
                let last_round = closing_w.load(Ordering::Acquire);
                match reports.take() {
                    Some((bytes, len)) => {
                        if write(&bytes[..len]).is_err() {
                            failed_w.store(true, Ordering::Release);
                            return;
                        }
                    }
                    None if last_round => return,
                    // Woken by `send` (or `drop`); the timeout only bounds a lost wake-up.
                    None => std::thread::park_timeout(Duration::from_millis(100)),
                }
            })?;
        Ok(Self {
            slot,
            thread: handle.thread().clone(),
            handle: Some(handle),
            failed,
            closing,
        })
    }

    /// Hand `report` (at most [`OUTPUT_REPORT_LEN`] + 1 bytes: longer ones are cut) to the
    /// writer thread.
    pub fn send(&mut self, report: &[u8]) {
        let mut frame = [0u8; OUTPUT_REPORT_LEN + 1];
        let len = report.len().min(frame.len());
        frame[..len].copy_from_slice(&report[..len]);
        self.slot.publish((frame, len));
        self.thread.unpark();
    }

    /// Whether a write has failed (the thread has then stopped).
    pub fn failed(&self) -> bool {
        self.failed.load(Ordering::Acquire)
    }
}

impl Drop for OutputWriter {
    fn drop(&mut self) {
        self.closing.store(true, Ordering::Release);
        self.thread.unpark();
        if let Some(handle) = self.handle.take() {
            let _ = handle.join();
        }
    }
}

impl HidTransport {
    /// Open the first device matching VID, PID and (if given) serial number.
    ///
    /// # Errors
    /// [`TransportError::NotFound`] when none is plugged in, [`TransportError::Busy`] when another
    /// hgcd holds it, [`TransportError::Hid`] or [`TransportError::Open`] when it or its writer
    /// thread cannot be opened.
    pub fn open(
        vid: u16,
        pid: u16,
        serial: Option<&str>,
        speaks: Speaks,
    ) -> Result<Self, TransportError> {
        let spec = match serial {
            Some(s) => format!("hid:{vid:04x}:{pid:04x}:{s}"),
            None => format!("hid:{vid:04x}:{pid:04x}"),
        };
        let api = HidApi::new().map_err(|source| TransportError::Hid {
            spec: spec.clone(),
            doing: "starting hidapi".into(),
            source,
        })?;
        let (path, found_serial): (CString, Option<String>) = api
            .device_list()
            .find(|d| {
                d.vendor_id() == vid
                    && d.product_id() == pid
                    && serial.is_none_or(|s| d.serial_number() == Some(s))
            })
            .map(|d| {
                let serial = d
                    .serial_number()
                    .filter(|s| !s.is_empty())
                    .map(str::to_string);
                (d.path().to_owned(), serial)
            })
            .ok_or_else(|| TransportError::NotFound { spec: spec.clone() })?;
        let open = |what: &str| {
            api.open_path(&path).map_err(|source| TransportError::Hid {
                spec: spec.clone(),
                doing: format!("{what} {}", path.to_string_lossy()),
                source,
            })
        };
        let lock = lock_device(&spec, &path)?;
        let reader = open("opening")?;
        let info = match speaks.info {
            // A protocol without the report: its profile speaks for the device.
            Some(info) => Ok(info),
            None => device_info(&reader),
        };
        let writer_dev = open("opening a second handle on")?;
        let writer = OutputWriter::spawn(move |report| {
            writer_dev
                .write(report)
                .map(|_| ())
                .map_err(std::io::Error::other)
        })
        .map_err(|source| TransportError::Open {
            spec: spec.clone(),
            doing: "starting its writer thread".into(),
            source,
        })?;
        Ok(Self {
            _lock: lock,
            resolved: DeviceSpec::Hid {
                vid,
                pid,
                serial: found_serial,
            },
            info,
            wire: speaks.wire,
            codec: speaks.codec,
            reader,
            spec,
            start: Instant::now(),
            garbled_skipped: 0,
            writer,
        })
    }
}

/// Ask `device` for its device-info feature report (a GET_REPORT control transfer, which the
/// kernel bounds at 5 s; a device without the report stalls it at once).
fn device_info(device: &HidDevice) -> Result<DeviceInfo, NoDeviceInfo> {
    let mut report = [0u8; DEVICE_INFO_LEN];
    report[0] = DEVICE_INFO_REPORT_ID;
    let n = device
        .get_feature_report(&mut report)
        .map_err(|e| NoDeviceInfo::Refused(e.to_string()))?;
    DeviceInfo::decode(&report[..n.min(DEVICE_INFO_LEN)]).map_err(NoDeviceInfo::Malformed)
}

/// Take an exclusive advisory lock (flock) on the device node, so that a second hgcd process (a
/// direct `hgcd calibrate` while the daemon runs) cannot drive the same device.
fn lock_device(spec: &str, path: &CString) -> Result<std::fs::File, TransportError> {
    use std::os::unix::io::AsRawFd;
    let node = path.to_string_lossy().into_owned();
    let file = std::fs::File::open(&node).map_err(|source| TransportError::Open {
        spec: spec.into(),
        doing: format!("opening {node}"),
        source,
    })?;
    // SAFETY: flock on a descriptor we own.
    if unsafe { libc::flock(file.as_raw_fd(), libc::LOCK_EX | libc::LOCK_NB) } != 0 {
        return Err(TransportError::Busy {
            spec: spec.into(),
            node,
        });
    }
    Ok(file)
}

impl Transport for HidTransport {
    fn read_input(
        &mut self,
        buf: &mut [u8; MAX_REPORT_LEN],
        timeout: Duration,
    ) -> Result<Option<usize>, TransportError> {
        if self.writer.failed() {
            return Err(TransportError::Disconnected {
                spec: self.spec.clone(),
                source: std::io::Error::other("writing an output report failed"),
            });
        }
        let ms = timeout.as_millis().clamp(1, i32::MAX as u128) as i32;
        let map = |e: hidapi::HidError| TransportError::Disconnected {
            spec: self.spec.clone(),
            source: std::io::Error::other(e),
        };
        let mut report = [0u8; MAX_REPORT_LEN];
        let n = self.reader.read_timeout(&mut report, ms).map_err(map)?;
        if n == 0 {
            return Ok(None);
        }
        // Skip ahead to the newest valid queued report rather than work through a backlog.
        let mut burst = Burst::new(self.wire);
        burst.offer(&report[..n], buf);
        loop {
            let m = self.reader.read_timeout(&mut report, 0).map_err(map)?;
            if m == 0 {
                break;
            }
            burst.offer(&report[..m], buf);
        }
        let (chosen, garbled) = burst.finish();
        self.garbled_skipped += garbled;
        Ok(chosen)
    }

    fn write_output(&mut self, report: &[u8]) -> Result<(), TransportError> {
        // A writer still busy with an older report finds this one in its place.
        if self.wire.numbered_reports() {
            self.writer.send(report);
        } else {
            // hidapi takes the report ID first, 0 for a device without IDs.
            let mut numbered = [0u8; OUTPUT_REPORT_LEN + 1];
            let n = report.len().min(OUTPUT_REPORT_LEN);
            numbered[1..=n].copy_from_slice(&report[..n]);
            self.writer.send(&numbered[..=n]);
        }
        Ok(())
    }

    fn codec(&self) -> Codec {
        self.codec.clone()
    }

    fn now(&self) -> f64 {
        self.start.elapsed().as_secs_f64()
    }

    fn take_garbled_skipped(&mut self) -> u64 {
        std::mem::take(&mut self.garbled_skipped)
    }

    fn describe(&self) -> String {
        format!("HID device {}", self.spec)
    }

    fn resolved_spec(&self) -> Option<DeviceSpec> {
        Some(self.resolved.clone())
    }

    fn device_info(&self) -> Result<&DeviceInfo, &NoDeviceInfo> {
        self.info.as_ref()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::Mutex;

    fn report(n: u8) -> [u8; OUTPUT_REPORT_LEN] {
        let mut r = [0u8; OUTPUT_REPORT_LEN];
        r[1] = n;
        r
    }

    #[test]
    fn the_writer_writes_in_order_newest_wins_and_the_last_report_always_lands() {
        let written = Arc::new(Mutex::new(Vec::new()));
        let sink = written.clone();
        let mut writer = OutputWriter::spawn(move |r| {
            sink.lock().unwrap().push(r[1]);
            Ok(())
        })
        .unwrap();
        for n in 1..=200u8 {
            writer.send(&report(n));
        }
        drop(writer);
        let written = written.lock().unwrap();
        assert_eq!(written.last(), Some(&200), "the final report is written");
        assert!(
            written.windows(2).all(|w| w[0] < w[1]),
            "never an older one after a newer one"
        );
    }

    #[test]
    fn a_failed_write_is_reported() {
        let mut writer = OutputWriter::spawn(|_| Err(std::io::Error::other("unplugged"))).unwrap();
        writer.send(&report(1));
        let deadline = Instant::now() + Duration::from_secs(30);
        while !writer.failed() {
            assert!(Instant::now() < deadline, "the failure was never reported");
            std::thread::yield_now();
        }
    }
}
