//! The `hgcd` command line: parse, load config, call the library.

use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

use anyhow::{Context, Result};
use clap::{Parser, Subcommand};

use hgcd::calibrate::{calibrate, CalibrateError, CalibrateRequest};
use hgcd::config::{Config, DeviceSpec, DEFAULT_CONFIG_PATH};
use hgcd::daemon::{self, RunError, RunRequest, Signals};

mod ctl;
mod progress;
use hgcd::servo::ServoError;
use hgcd::transport::{hid, Pacing, TransportError};

#[derive(Parser, Debug)]
#[command(
    name = "hgcd",
    version,
    about = "Autocalibrated gravity compensation for 3-DoF haptic devices"
)]
struct Cli {
    /// Configuration file (default: /etc/hgcd/hgcd.toml if it exists, else built-in defaults).
    #[arg(long, global = true, value_name = "FILE")]
    config: Option<PathBuf>,
    /// Directory of calibration grids (default: config `paths.state_dir`, $STATE_DIRECTORY, /var/lib/hgcd).
    #[arg(long, global = true, value_name = "DIR")]
    state_dir: Option<PathBuf>,
    /// Application socket of the daemon (default: config `app.socket`, $RUNTIME_DIRECTORY/hgcd.sock, /run/hgcd/hgcd.sock).
    #[arg(long, global = true, value_name = "PATH")]
    socket: Option<PathBuf>,
    /// Log level: error, warn, info, debug or trace (RUST_LOG overrides).
    #[arg(long, global = true, default_value = "info", value_name = "LEVEL")]
    log_level: String,
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Run the servo loop on a device until Ctrl-C/SIGTERM or for --duration seconds.
    Run {
        /// Device: hid:VID:PID[:SERIAL], sim:MODEL or socket:PATH (default: config `device.spec`).
        #[arg(long, value_name = "SPEC")]
        device: Option<String>,
        /// Stop after this many seconds.
        #[arg(long, value_name = "S")]
        duration: Option<f64>,
        /// Run a simulated device in virtual time (as fast as possible) instead of real time.
        #[arg(long)]
        virtual_time: bool,
    },
    /// Run the off-line autocalibration (paper Algorithm 1) and save the mass grid.
    Calibrate {
        /// Device: hid:VID:PID[:SERIAL], sim:MODEL or socket:PATH (default: config `device.spec`).
        #[arg(long, value_name = "SPEC")]
        device: Option<String>,
        /// Write the grid to this file instead of <state-dir>/<device-id>.toml.
        #[arg(long, value_name = "FILE")]
        output: Option<PathBuf>,
        /// Run a simulated device in real time (default for simulated devices: virtual time).
        #[arg(long)]
        real_time: bool,
        /// Do not ask for confirmation before starting on a real device.
        #[arg(long)]
        yes: bool,
        /// Ask the running daemon to calibrate its device (it switches to the new grid after).
        #[arg(long)]
        via_daemon: bool,
    },
    /// Show the running daemon's state: device, grid, mode, clients, loop timing.
    Status,
    /// Serve the simulated device (config [sim]) on a Unix socket, for `--device socket:PATH`:
    /// the device side of the socket transport, as an external simulator or bridge would be.
    SimDevice {
        /// Socket to listen on.
        #[arg(long, value_name = "PATH")]
        listen: PathBuf,
        /// Wait for the host's output report after each input report (deterministic, as fast as
        /// both sides allow) instead of reporting in real time.
        #[arg(long)]
        lockstep: bool,
        /// The simulated model, as in `sim:MODEL` (docs/simulated-devices.md).
        #[arg(long, default_value = "point-mass")]
        model: String,
    },
    /// List the HID devices hgcd can see, with the spec that opens each.
    Devices,
}

fn load_config(path: Option<&Path>) -> Result<Config> {
    match path {
        Some(p) => Ok(Config::load(p)?),
        None if Path::new(DEFAULT_CONFIG_PATH).exists() => {
            Ok(Config::load(Path::new(DEFAULT_CONFIG_PATH))?)
        }
        None => Ok(Config::default()),
    }
}

fn init_logging(level: &str) -> Result<()> {
    let filter = match std::env::var("RUST_LOG") {
        Ok(env) => tracing_subscriber::EnvFilter::new(env),
        Err(_) => tracing_subscriber::EnvFilter::try_new(level).map_err(|_| {
            anyhow::anyhow!("--log-level `{level}` is not one of error, warn, info, debug, trace")
        })?,
    };
    // Under systemd stderr is the journal, which stamps time itself and shows no colours.
    if std::env::var_os("JOURNAL_STREAM").is_some() {
        tracing_subscriber::fmt()
            .with_env_filter(filter)
            .with_writer(std::io::stderr)
            .with_ansi(false)
            .without_time()
            .init();
    } else {
        use std::io::IsTerminal;
        tracing_subscriber::fmt()
            .with_env_filter(filter)
            .with_writer(std::io::stderr)
            .with_ansi(std::io::stderr().is_terminal())
            .init();
    }
    Ok(())
}

/// SIGINT/SIGTERM stop the daemon (zero force, exit 0); SIGHUP reloads the grid.
fn install_signal_handlers() -> Result<Signals> {
    let signals = Signals {
        stop: install_stop_handler()?,
        reload: Arc::new(AtomicBool::new(false)),
    };
    signal_hook::flag::register(signal_hook::consts::SIGHUP, signals.reload.clone())
        .context("installing the SIGHUP handler")?;
    Ok(signals)
}

fn install_stop_handler() -> Result<Arc<AtomicBool>> {
    let stop = Arc::new(AtomicBool::new(false));
    let flag = stop.clone();
    ctrlc::set_handler(move || flag.store(true, Ordering::SeqCst))
        .context("installing the SIGINT/SIGTERM handler")?;
    Ok(stop)
}

fn device_spec(arg: Option<&str>, config: &Config) -> Result<DeviceSpec> {
    Ok(match arg {
        Some(s) => s.parse()?,
        None => config.device_spec()?,
    })
}

fn real_main(cli: Cli) -> Result<()> {
    init_logging(&cli.log_level)?;
    let mut config = load_config(cli.config.as_deref())?;
    if let Some(dir) = cli.state_dir {
        config.paths.state_dir = Some(dir);
    }
    if let Some(socket) = cli.socket {
        config.app.socket = Some(socket);
    }
    match cli.command {
        Command::Run {
            device,
            duration,
            virtual_time,
        } => run(&config, device.as_deref(), duration, virtual_time),
        Command::Calibrate {
            via_daemon: true,
            yes,
            ..
        } => {
            if !yes {
                confirm_start()?;
            }
            ctl::calibrate_via_daemon(&config.socket_path())
        }
        Command::Calibrate {
            device,
            output,
            real_time,
            yes,
            ..
        } => calibrate_here(&config, device.as_deref(), output, real_time, yes),
        Command::Status => ctl::status(&config.socket_path()),
        Command::SimDevice {
            listen,
            lockstep,
            model,
        } => sim_device(&config, &listen, lockstep, &model),
        Command::Devices => devices(),
    }
}

/// `hgcd run`: the daemon, until a signal or `--duration`; prints the loop's statistics.
fn run(
    config: &Config,
    device: Option<&str>,
    duration: Option<f64>,
    virtual_time: bool,
) -> Result<()> {
    if let Some(d) = duration {
        anyhow::ensure!(
            d.is_finite() && d > 0.0,
            "--duration must be a positive number of seconds"
        );
    }
    let request = RunRequest {
        device: device_spec(device, config)?,
        duration,
        pacing: if virtual_time {
            Pacing::Virtual
        } else {
            Pacing::RealTime
        },
    };
    let signals = install_signal_handlers()?;
    let report = daemon::run(config, &request, signals)?;
    println!("{}", report.stats);
    Ok(())
}

/// `hgcd calibrate` on a device this process opens itself; prints the summary.
fn calibrate_here(
    config: &Config,
    device: Option<&str>,
    output: Option<PathBuf>,
    real_time: bool,
    yes: bool,
) -> Result<()> {
    let device = device_spec(device, config)?;
    let simulated = matches!(device, DeviceSpec::Sim { .. });
    if !simulated && !yes {
        confirm_start()?;
    }
    let request = CalibrateRequest {
        device,
        pacing: if simulated && !real_time {
            Pacing::Virtual
        } else {
            Pacing::RealTime
        },
        output,
        state_dir: config.state_dir(),
    };
    let stop = install_stop_handler()?;
    let mut display = progress::Display::new(
        hgcd::control::calibration::GridPlan::new(
            &hgcd::control::calibration::CalibrationParams::from_config(config),
        )
        .map(|p| p.path.len())
        .unwrap_or(0),
    );
    let run = calibrate(config, &request, stop, &mut |e| display.show(e));
    display.finish();
    let run = run?;
    print!("{}", progress::summary(&run));
    Ok(())
}

/// `hgcd sim-device`: serve the simulated device on a Unix socket until the host leaves.
fn sim_device(config: &Config, listen: &Path, lockstep: bool, model: &str) -> Result<()> {
    let stop = install_stop_handler()?;
    let mut device = hgcd::sim::SimDevice::from_config(model, config)?;
    // Replaces a stale socket, refuses a live one or anything that is not a socket.
    let listener = hgcd::app::server::bind(listen, 0o660)
        .with_context(|| format!("listening on {}", listen.display()))?;
    tracing::info!(
        "simulated device listening on {} ({})",
        listen.display(),
        if lockstep { "lock-step" } else { "real time" }
    );
    let served = hgcd::sim::socket::serve(&listener, &mut device, lockstep, &stop);
    let _ = std::fs::remove_file(listen);
    served.with_context(|| format!("serving {}", listen.display()))?;
    println!(
        "simulated device served {:.3} s of device time; {} output reports rejected",
        device.time(),
        device.rejected_outputs()
    );
    Ok(())
}

/// `hgcd devices`: the HID devices this process can see.
fn devices() -> Result<()> {
    let devices = hid::list_devices()?;
    if devices.is_empty() {
        println!("no HID devices visible (unplugged, or no permission: see docs/install.md)");
    }
    for d in devices {
        println!(
            "{:<32} {} {} (interface {}, {})",
            d.spec(),
            d.manufacturer.as_deref().unwrap_or("?"),
            d.product.as_deref().unwrap_or("?"),
            d.interface,
            d.path
        );
    }
    Ok(())
}

/// On a real device the user brings the handle near the workspace centre first (paper §3.1).
fn confirm_start() -> Result<()> {
    use std::io::{BufRead, IsTerminal, Write};
    let stdin = std::io::stdin();
    anyhow::ensure!(
        stdin.is_terminal(),
        "calibrating a real device needs confirmation: run it on a terminal or pass --yes once the \
         handle rests near the centre of the workspace"
    );
    eprint!(
        "Bring the handle near the centre of the workspace and let go of it; hgcd will hold it with \
         a soft spring.\nPress Enter to start (Ctrl-C aborts). "
    );
    std::io::stderr().flush().ok();
    let mut line = String::new();
    stdin.lock().read_line(&mut line)?;
    Ok(())
}

/// Exit status when the device cannot be opened or went away (the systemd unit does not restart
/// on it: udev starts the instance again when the device is plugged back in).
const EXIT_DEVICE_GONE: u8 = 3;

/// The exit status for an error: the device family gets its own, everything else 1.
fn exit_status(e: &anyhow::Error) -> u8 {
    let gone = TransportError::device_unavailable;
    let servo_gone = |s: &ServoError| matches!(s, ServoError::Transport(t) if gone(t));
    let device_gone = match (
        e.downcast_ref::<RunError>(),
        e.downcast_ref::<CalibrateError>(),
    ) {
        (Some(RunError::Open(t)), _) => gone(t),
        (Some(RunError::Servo(s)), _) => servo_gone(s),
        (_, Some(CalibrateError::Open(t))) => gone(t),
        (_, Some(CalibrateError::Servo(s))) => servo_gone(s),
        _ => false,
    };
    if device_gone {
        EXIT_DEVICE_GONE
    } else {
        1
    }
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    match real_main(cli) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("hgcd: {e:#}");
            ExitCode::from(exit_status(&e))
        }
    }
}
