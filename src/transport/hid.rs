//! `hid:VID:PID[:SERIAL]`: real devices through hidapi (Linux hidraw backend, no system library).
//!
//! `hid_write` is synchronous and has been seen to stall for over 5 ms every few cycles
//! (libusb/hidapi#506), so output reports go to a writer thread through a one-slot channel that
//! always holds the newest report: the servo thread never waits for the device to accept a write.

use std::ffi::CString;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use hidapi::{HidApi, HidDevice};

use super::{Transport, TransportError, MAX_REPORT_LEN};
use crate::config::DeviceSpec;
use crate::newest::{newest_wins, NewestSender};
use crate::protocol::OUTPUT_REPORT_LEN;

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
pub fn list_devices() -> Result<Vec<HidDeviceEntry>, TransportError> {
    let api = HidApi::new().map_err(|e| TransportError::Io(format!("hidapi: {e}")))?;
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
    /// Exclusive advisory lock on the hidraw node: one hgcd process per device.
    _lock: std::fs::File,
    /// VID, PID and the serial number the device reports.
    resolved: DeviceSpec,
    reader: HidDevice,
    spec: String,
    start: Instant,
    /// One-slot outbox to the writer thread; the newest report replaces one not yet taken.
    outbox: Option<NewestSender<[u8; OUTPUT_REPORT_LEN]>>,
    writer_failed: Arc<AtomicBool>,
    writer: Option<JoinHandle<()>>,
}

impl HidTransport {
    /// Open the first device matching VID, PID and (if given) serial number.
    pub fn open(vid: u16, pid: u16, serial: Option<&str>) -> Result<Self, TransportError> {
        let spec = match serial {
            Some(s) => format!("hid:{vid:04x}:{pid:04x}:{s}"),
            None => format!("hid:{vid:04x}:{pid:04x}"),
        };
        let open_err = |reason: String| TransportError::Open {
            spec: spec.clone(),
            reason,
        };
        let api = HidApi::new().map_err(|e| open_err(format!("hidapi: {e}")))?;
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
            .ok_or_else(|| {
                open_err(
                    "no such device is plugged in (run `hgcd devices` to list what hgcd can see)"
                        .into(),
                )
            })?;
        let open = |what: &str| {
            api.open_path(&path).map_err(|e| {
                let text = e.to_string();
                let hint = if text.contains("ermission") || text.contains("EACCES") {
                    " — permission denied: install udev/70-hgcd.rules and add yourself to group \
                     `hgcd` (see docs/install.md)"
                } else {
                    ""
                };
                open_err(format!("{what} {}: {text}{hint}", path.to_string_lossy()))
            })
        };
        let lock = lock_device(&path).map_err(open_err)?;
        let reader = open("opening")?;
        let writer_dev = open("opening a second handle on")?;
        let (outbox, inbox) = newest_wins::<[u8; OUTPUT_REPORT_LEN]>(1);
        let writer_failed = Arc::new(AtomicBool::new(false));
        let failed = writer_failed.clone();
        let writer = std::thread::Builder::new()
            .name("hgcd-hid-writer".into())
            .spawn(move || {
                for report in inbox.iter() {
                    if writer_dev.write(&report).is_err() {
                        failed.store(true, Ordering::Release);
                        break;
                    }
                }
            })
            .map_err(|e| open_err(format!("cannot start writer thread: {e}")))?;
        Ok(Self {
            _lock: lock,
            resolved: DeviceSpec::Hid {
                vid,
                pid,
                serial: found_serial,
            },
            reader,
            spec,
            start: Instant::now(),
            outbox: Some(outbox),
            writer_failed,
            writer: Some(writer),
        })
    }
}

/// Take an exclusive advisory lock (flock) on the device node, so that a second hgcd process (a
/// direct `hgcd calibrate` while the daemon runs) cannot drive the same device.
fn lock_device(path: &CString) -> Result<std::fs::File, String> {
    use std::os::unix::io::AsRawFd;
    let node = std::path::PathBuf::from(path.to_string_lossy().into_owned());
    let file = std::fs::File::open(&node).map_err(|e| {
        let hint = if e.kind() == std::io::ErrorKind::PermissionDenied {
            " — install udev/70-hgcd.rules and add yourself to group `hgcd` (see docs/install.md)"
        } else {
            ""
        };
        format!("opening {}: {e}{hint}", node.display())
    })?;
    // SAFETY: flock on a descriptor we own.
    if unsafe { libc::flock(file.as_raw_fd(), libc::LOCK_EX | libc::LOCK_NB) } != 0 {
        return Err(format!(
            "{} is in use by another hgcd process (the daemon? use `hgcd calibrate --via-daemon`)",
            node.display()
        ));
    }
    Ok(file)
}

impl Transport for HidTransport {
    fn read_input(
        &mut self,
        buf: &mut [u8; MAX_REPORT_LEN],
        timeout: Duration,
    ) -> Result<Option<usize>, TransportError> {
        if self.writer_failed.load(Ordering::Acquire) {
            return Err(TransportError::Disconnected(format!(
                "{}: write failed",
                self.spec
            )));
        }
        let ms = timeout.as_millis().clamp(1, i32::MAX as u128) as i32;
        let map = |e: hidapi::HidError| TransportError::Disconnected(format!("{}: {e}", self.spec));
        let mut n = self.reader.read_timeout(buf, ms).map_err(map)?;
        if n == 0 {
            return Ok(None);
        }
        // Skip ahead to the newest queued report rather than work through a backlog.
        let mut newer = [0u8; MAX_REPORT_LEN];
        loop {
            let m = self.reader.read_timeout(&mut newer, 0).map_err(map)?;
            if m == 0 {
                break;
            }
            buf[..m].copy_from_slice(&newer[..m]);
            n = m;
        }
        Ok(Some(n))
    }

    fn write_output(&mut self, report: &[u8; OUTPUT_REPORT_LEN]) -> Result<(), TransportError> {
        // A writer still busy with an older report finds this one in its place.
        if let Some(outbox) = &self.outbox {
            let _ = outbox.send(*report);
        }
        Ok(())
    }

    fn now(&self) -> f64 {
        self.start.elapsed().as_secs_f64()
    }

    fn describe(&self) -> String {
        format!("HID device {}", self.spec)
    }

    fn resolved_spec(&self) -> Option<DeviceSpec> {
        Some(self.resolved.clone())
    }
}

impl Drop for HidTransport {
    fn drop(&mut self) {
        // Closing the channel ends the writer after it has sent what it holds (the final zero).
        self.outbox = None;
        if let Some(w) = self.writer.take() {
            let _ = w.join();
        }
    }
}
