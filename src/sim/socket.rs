//! The device side of the socket transport (`docs/hid-protocol.md`, "Socket framing"): serves a
//! [`SimDevice`] to a host that connects with `--device socket:PATH`, as `hgcd sim-device` does and
//! as an external simulator or hardware bridge would.

use std::io::{ErrorKind, Write};
use std::os::unix::net::{UnixListener, UnixStream};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use super::SimDevice;
use crate::protocol::{INPUT_REPORT_LEN, MAX_REPORT_LEN};
use crate::sys::{read_available, wait_readable};

/// Device side: serve `device` to one host connected to `listener`. In lock-step mode each input
/// report waits for the host's output report (deterministic, as fast as both sides allow); otherwise
/// reports go out in real time, one per period. Returns when the host disconnects or `stop` is set.
pub fn serve(
    listener: &UnixListener,
    device: &mut SimDevice,
    lockstep: bool,
    stop: &AtomicBool,
) -> std::io::Result<()> {
    listener.set_nonblocking(true)?;
    let mut stream = loop {
        match listener.accept() {
            Ok((stream, _)) => break stream,
            Err(e) if e.kind() == ErrorKind::WouldBlock => {
                if stop.load(Ordering::Relaxed) {
                    return Ok(());
                }
                // Wake at once when the host connects (its watchdog starts with its loop).
                wait_readable(listener, Duration::from_millis(50))?;
            }
            Err(e) => return Err(e),
        }
    };
    // Blocking writes; reads only what has arrived (recv with MSG_DONTWAIT after ppoll).
    stream.set_nonblocking(false)?;
    let period = Duration::from_secs_f64(device.period());
    let mut next = Instant::now();
    let mut inbuf = Vec::with_capacity(256);
    let mut first = true;
    let result = loop {
        if stop.load(Ordering::Relaxed) {
            break Ok(());
        }
        // The first report shows the power-on state, as over HID.
        if !first {
            device.advance();
        }
        first = false;
        if !device.is_silent() {
            let mut report = [0u8; INPUT_REPORT_LEN];
            device.input_report(&mut report);
            let mut frame = vec![INPUT_REPORT_LEN as u8];
            frame.extend_from_slice(&report);
            if stream.write_all(&frame).is_err() {
                break Ok(()); // the host went away
            }
        }
        next += period;
        // Lock-step: until the host's output report (at most 100 ms). Real time: until the next
        // period starts.
        let until = if lockstep {
            Instant::now() + Duration::from_millis(100)
        } else {
            next
        };
        let mut got_output = false;
        let mut host_gone = false;
        while !(stop.load(Ordering::Relaxed) || lockstep && got_output || host_gone) {
            let now = Instant::now();
            if now >= until {
                break;
            }
            wait_readable(&stream, until - now)?;
            host_gone = receive(&stream, &mut inbuf)?;
            got_output |= apply_frames(&mut inbuf, device)?;
        }
        if host_gone {
            break Ok(());
        }
        if !lockstep && Instant::now() > next + period {
            // Fell behind (a stall): drop the missed periods rather than burst.
            next = Instant::now();
        }
    };
    // Whatever the host sent last (its final zero-force report) still reaches the firmware.
    let _ = receive(&stream, &mut inbuf);
    let _ = apply_frames(&mut inbuf, device);
    result
}

/// Move whatever the host has sent into `inbuf`; true when the host has closed its side.
fn receive(stream: &UnixStream, inbuf: &mut Vec<u8>) -> std::io::Result<bool> {
    let mut chunk = [0u8; 256];
    loop {
        match read_available(stream, &mut chunk) {
            Ok(0) => return Ok(true),
            Ok(n) => inbuf.extend_from_slice(&chunk[..n]),
            Err(e) if e.kind() == ErrorKind::WouldBlock => return Ok(false),
            Err(e) if e.kind() == ErrorKind::Interrupted => {}
            Err(_) => return Ok(true),
        }
    }
}

/// Hand every complete output frame in `inbuf` to the firmware; true if there was one.
fn apply_frames(inbuf: &mut Vec<u8>, device: &mut SimDevice) -> std::io::Result<bool> {
    let mut any = false;
    while let Some(&n) = inbuf.first() {
        let n = n as usize;
        if n == 0 || n > MAX_REPORT_LEN {
            return Err(std::io::Error::new(
                ErrorKind::InvalidData,
                format!("bad frame length {n} from host"),
            ));
        }
        if inbuf.len() < n + 1 {
            break;
        }
        let _ = device.receive_output(&inbuf[1..=n]);
        inbuf.drain(..=n);
        any = true;
    }
    Ok(any)
}
