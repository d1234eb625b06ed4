//! The `hgcd` command line: parse, load config, call the library.

use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, LazyLock};
use std::time::Duration;

use anyhow::{Context, Result};
use clap::{CommandFactory, FromArgMatches, Parser, Subcommand};

use hgcd::app::endpoint::{self, FindError};
use hgcd::calibrate::check::{self, CheckRequest};
use hgcd::calibrate::{calibrate, CalibrateError, CalibrateRequest};
use hgcd::config::{Config, DeviceSpec, WorkspaceMode, DEFAULT_CONFIG_PATH, SIM_MODELS};
use hgcd::daemon::{self, RunError, RunRequest, Signals};
use hgcd::discrepancy::{self, AnalyzeRequest, RecordError, RecordRequest};

mod ctl;
mod progress;
use hgcd::profile::Profile;
use hgcd::servo::{ExitReason, ServoError};
use hgcd::transport::{hid, Pacing, TransportError};
use hgcd::validate::{self, Mode, ValidateError, ValidateRequest};

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
    /// Directory of calibration grids (default: config `paths.state_dir`, $STATE_DIRECTORY,
    /// /var/lib/hgcd if this user may write there, else ~/.local/state/hgcd).
    #[arg(long, global = true, value_name = "DIR")]
    state_dir: Option<PathBuf>,
    /// Application socket of the daemon (default: config `app.socket`, else the device's own,
    /// <device-id>.sock in $RUNTIME_DIRECTORY or /run/hgcd, which `status` and `calibrate
    /// --via-daemon` find by --device).
    #[arg(long, global = true, value_name = "PATH")]
    socket: Option<PathBuf>,
    /// Device profile: a built-in name (cartesian-v1, woodenhaptics_v2015, polhem_v1), a user
    /// profile's name or a profile file (default: config `device.profile`, else chosen by the
    /// device; docs/devices.md).
    #[arg(long, global = true, value_name = "NAME|FILE")]
    profile: Option<String>,
    /// Log level: error, warn, info, debug or trace (RUST_LOG overrides).
    #[arg(long, global = true, default_value = "info", value_name = "LEVEL")]
    log_level: String,
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Run the servo loop on a device until Ctrl-C/SIGTERM or for --duration seconds.
    Run(RunArgs),
    /// Run the off-line autocalibration (paper Algorithm 1) and save the mass grid.
    Calibrate(CalibrateArgs),
    /// The paper's validation experiment (Section 5, Fig. 2): a probe mass on a virtual surface
    /// at 27 points, without and with compensation; writes a table, CSV, summary.json and figure.
    Validate(ValidateArgs),
    /// Log an identification run: compensation on, a PD law tracking slow and fast multisines
    /// and holds inside the calibrated grid (docs/discrepancy.md). Ctrl-C ends it early with a
    /// valid, shorter log.
    Record(RecordArgs),
    /// Compare a measured log with a calibrated grid: where they disagree, which physical effect
    /// the model misses (or none), and how much adding it shrinks the gap on held-out data.
    Analyze(AnalyzeArgs),
    /// Is the saved gravity model still right? Two short friction-robust holds compared with it:
    /// unchanged (exit 0), a payload and/or a base tilt it can take in (exit 4), or something
    /// else: recalibrate (exit 5) (docs/calibration.md §2).
    Check(CheckArgs),
    /// Show the running daemons' state: device, grid, mode, clients, loop timing.
    Status(StatusArgs),
    /// Serve the simulated device (config [sim]) on a Unix socket, for `--device socket:PATH`:
    /// the device side of the socket transport, as an external simulator or bridge would be.
    /// Serves one host after another until Ctrl-C/SIGTERM; each connection is a power-on.
    SimDevice(SimDeviceArgs),
    /// List the HID devices hgcd can see, with the spec that opens each.
    Devices,
    /// Write the man pages, hgcd.1 and hgcd-SUBCOMMAND.1, into DIR (for packagers).
    #[command(hide = true)]
    Man(ManArgs),
    /// Print the completion script for SHELL on standard output (for packagers).
    #[command(hide = true)]
    Completions(CompletionsArgs),
}

#[derive(clap::Args, Debug)]
struct ManArgs {
    /// Directory for the pages (created if needed).
    #[arg(long, value_name = "DIR")]
    out: PathBuf,
}

#[derive(clap::Args, Debug)]
struct CompletionsArgs {
    /// The shell the script is for.
    #[arg(value_enum)]
    shell: clap_complete::Shell,
}

#[derive(clap::Args, Debug)]
struct RunArgs {
    /// Device: hid:VID:PID[:SERIAL], sim:MODEL or socket:PATH (default: config `device.spec`).
    #[arg(long, value_name = "SPEC")]
    device: Option<String>,
    /// Stop after this many seconds: of device time where the device sets the pace
    /// (--virtual-time, or a socket device in lock-step), of wall-clock time otherwise.
    #[arg(long, value_name = "S")]
    duration: Option<f64>,
    /// Run a simulated device in virtual time (as fast as possible) instead of real time.
    #[arg(long)]
    virtual_time: bool,
}

#[derive(clap::Args, Debug)]
struct CalibrateArgs {
    /// Device: hid:VID:PID[:SERIAL], sim:MODEL or socket:PATH (default: config `device.spec`);
    /// with --via-daemon, which daemon (a device id or spec; default: the only one running).
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
    /// `cube`: the paper's grid; `explore`: find the reachable workspace first and calibrate
    /// the lattice inside it (default: config `calibration.workspace`; docs/calibration.md §12).
    #[arg(long, value_name = "cube|explore")]
    workspace: Option<WorkspaceMode>,
}

#[derive(clap::Args, Debug)]
struct CheckArgs {
    /// Device: hid:VID:PID[:SERIAL], sim:MODEL or socket:PATH (default: config `device.spec`);
    /// with --via-daemon, which daemon (a device id or spec; default: the only one running).
    #[arg(long, value_name = "SPEC")]
    device: Option<String>,
    /// Check this grid (default: the device's stored grid).
    #[arg(long, value_name = "FILE")]
    grid: Option<PathBuf>,
    /// Run a simulated device in real time (default for simulated devices: virtual time).
    #[arg(long)]
    real_time: bool,
    /// Do not ask for confirmation before starting on a real device.
    #[arg(long)]
    yes: bool,
    /// Print one JSON object (verdict, payload_g, tilt_deg, tilt_axis, device_time_s, holds).
    #[arg(long)]
    json: bool,
    /// Take a payload and tilt found into the grid, keeping the model before as GRID.bak.
    #[arg(long, conflicts_with = "revert")]
    apply: bool,
    /// Put back the model kept as GRID.bak (before the last --apply or calibration); nothing is
    /// measured.
    #[arg(long)]
    revert: bool,
    /// Ask the running daemon to check its device against its grid (with --apply it takes the
    /// change in and compensates it at once; with --revert it puts the kept model back and
    /// compensates with it); --device then names the daemon.
    #[arg(long, conflicts_with_all = ["grid", "real_time"])]
    via_daemon: bool,
}

#[derive(clap::Args, Debug)]
struct ValidateArgs {
    /// Device: hid:VID:PID[:SERIAL], sim:MODEL or socket:PATH (default: config `device.spec`).
    #[arg(long, value_name = "SPEC")]
    device: Option<String>,
    /// Compensate with this grid (default: the device's stored grid; on a simulated device a
    /// fresh calibration, written to DIR/grid.toml).
    #[arg(long, value_name = "FILE")]
    grid: Option<PathBuf>,
    /// Directory for the results (created if needed).
    #[arg(long, value_name = "DIR")]
    out: PathBuf,
    /// Probe mass m_p, g (on a simulated device it is added to the plant; on hardware attach it).
    #[arg(long, value_name = "G", default_value_t = 30.0)]
    probe_mass_g: f64,
    /// Stiffness k of the virtual surface, N/mm.
    #[arg(long, value_name = "K", default_value_t = 1.0)]
    stiffness_n_per_mm: f64,
    /// Repetitions per contact point and mode.
    #[arg(long, value_name = "N", default_value_t = 10)]
    repetitions: usize,
    /// Compensation modes to run, in order (comma-separated: none, scalar, vector, arm);
    /// default: none, scalar, vector, and arm for a device whose profile has an arm.
    #[arg(long, value_name = "MODES", value_delimiter = ',')]
    modes: Vec<String>,
    /// Also compare the grid's force with the plant's own at N random points of a simulated
    /// device's reachable workspace; writes DIR/sweep.json (docs/calibration.md §11).
    #[arg(long, value_name = "N")]
    sweep: Option<usize>,
    /// Run a simulated device in real time (default for simulated devices: virtual time).
    #[arg(long)]
    real_time: bool,
    /// Do not ask for confirmation before starting on a real device.
    #[arg(long)]
    yes: bool,
}

#[derive(clap::Args, Debug)]
struct RecordArgs {
    /// Device: hid:VID:PID[:SERIAL], sim:MODEL or socket:PATH (default: config `device.spec`).
    #[arg(long, value_name = "SPEC")]
    device: Option<String>,
    /// Compensate with this grid (default: the device's stored grid).
    #[arg(long, value_name = "FILE")]
    grid: Option<PathBuf>,
    /// The log to write (CSV, docs/log-format.md).
    #[arg(long, value_name = "FILE")]
    out: PathBuf,
    /// Seconds of device time to record.
    #[arg(long, value_name = "S", default_value_t = 40.0)]
    duration: f64,
    /// Run a simulated device in real time (default for simulated devices: virtual time).
    #[arg(long)]
    real_time: bool,
    /// Do not ask for confirmation before starting on a real device.
    #[arg(long)]
    yes: bool,
}

#[derive(clap::Args, Debug)]
struct AnalyzeArgs {
    /// The calibrated model (hgcd-grid/1).
    #[arg(long, value_name = "FILE")]
    grid: PathBuf,
    /// The measured log (CSV, docs/log-format.md).
    #[arg(long, value_name = "FILE")]
    log: PathBuf,
    /// Directory for the report (created if needed).
    #[arg(long, value_name = "DIR")]
    out: PathBuf,
}

#[derive(clap::Args, Debug)]
struct StatusArgs {
    /// Only the daemon of this device (a device id or spec; default: every daemon running).
    #[arg(long, value_name = "SPEC")]
    device: Option<String>,
}

#[derive(clap::Args, Debug)]
struct SimDeviceArgs {
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
}

/// Global options a subcommand ignores, by subcommand: left out of its help. (They are still
/// accepted there, as global options are everywhere.)
const IGNORED_OPTIONS: &[(&str, &[&str])] = &[
    ("status", &["state_dir", "profile"]),
    ("sim-device", &["state_dir", "socket"]),
    ("devices", &["state_dir", "socket"]),
    ("man", &["config", "state_dir", "socket", "profile"]),
    ("completions", &["config", "state_dir", "socket", "profile"]),
];

/// `hgcd --version`: the release, the git commit it was built from ("unknown" outside a git
/// checkout) and the HID report protocol it speaks.
static VERSION: LazyLock<String> = LazyLock::new(|| {
    format!(
        "{} (git {}, HID protocol v{})",
        env!("CARGO_PKG_VERSION"),
        env!("HGCD_GIT_COMMIT"),
        hgcd::protocol::PROTOCOL_VERSION
    )
});

/// The version the man pages give: the release and the HID report protocol, without the git
/// commit, so that the pages committed in packaging/generated/ (built into the package without
/// running hgcd) are the same whichever commit generated them.
static RELEASE: LazyLock<String> = LazyLock::new(|| {
    format!(
        "{} (HID protocol v{})",
        env!("CARGO_PKG_VERSION"),
        hgcd::protocol::PROTOCOL_VERSION
    )
});

/// The command line, each subcommand's help listing only the global options it uses.
fn command() -> clap::Command {
    let mut cmd = Cli::command().version(VERSION.as_str());
    for (sub, ignored) in IGNORED_OPTIONS {
        for id in *ignored {
            let hidden = cmd
                .get_arguments()
                .find(|a| a.get_id() == id)
                .unwrap_or_else(|| panic!("no global option {id}"))
                .clone()
                .hide(true);
            // A subcommand that has an option of that id does not get the global one's copy.
            cmd = cmd.mut_subcommand(sub, |s| s.arg(hidden));
        }
    }
    cmd
}

/// Print `text` on standard output. A reader that went away (`hgcd calibrate | head -3`) is not
/// an error: the command still does its work, what it would have printed is dropped, and it
/// exits as it would have.
fn out(text: &str) -> Result<()> {
    use std::io::Write;
    match std::io::stdout().lock().write_all(text.as_bytes()) {
        Err(e) if e.kind() == std::io::ErrorKind::BrokenPipe => Ok(()),
        written => written.context("writing to standard output"),
    }
}

/// Print `text` on standard error; when that fails there is nowhere left to say so.
fn err(text: &str) {
    use std::io::Write;
    let _ = std::io::stderr().lock().write_all(text.as_bytes());
}

/// The config file hgcd reads: `--config`, else the default path where it exists.
fn config_file(path: Option<&Path>) -> Option<PathBuf> {
    match path {
        Some(p) => Some(p.to_path_buf()),
        None => Some(PathBuf::from(DEFAULT_CONFIG_PATH)).filter(|p| p.exists()),
    }
}

fn load_config(path: Option<&Path>) -> Result<Config> {
    match config_file(path) {
        Some(p) => Ok(Config::load(&p)?),
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
    // A log line that cannot be written (stderr's reader went away) is dropped without a word:
    // saying so on stderr would fail the same way.
    let builder = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .log_internal_errors(false);
    // Under systemd stderr is the journal, which stamps time itself and shows no colours.
    if std::env::var_os("JOURNAL_STREAM").is_some() {
        builder.with_ansi(false).without_time().init();
    } else {
        use std::io::IsTerminal;
        builder.with_ansi(std::io::stderr().is_terminal()).init();
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

/// How long, after SIGINT or SIGTERM, the work in hand has to stop cleanly (the servo loop sees
/// the stop flag within a tick and zeroes the force) before hgcd ends anyway, wherever it is
/// blocked. A second signal ends it at once.
const STOP_GRACE: Duration = Duration::from_secs(3);

/// Set the returned flag on SIGINT or SIGTERM, and end the process if it has not ended
/// [`STOP_GRACE`] later or at a second signal.
fn install_stop_handler() -> Result<Arc<AtomicBool>> {
    let stop = Arc::new(AtomicBool::new(false));
    let flag = stop.clone();
    ctrlc::set_handler(move || {
        if flag.swap(true, Ordering::SeqCst) {
            stopped_by_signal("a second signal came");
        }
        std::thread::spawn(|| {
            std::thread::sleep(STOP_GRACE);
            stopped_by_signal(&format!(
                "what it was doing did not stop within {} s",
                STOP_GRACE.as_secs()
            ));
        });
    })
    .context("installing the SIGINT/SIGTERM handler")?;
    Ok(stop)
}

/// End the process after a stop signal the work in hand did not answer.
fn stopped_by_signal(why: &str) -> ! {
    eprintln!("hgcd: stopped by a signal: {why}");
    std::process::exit(1)
}

fn device_spec(arg: Option<&str>, config: &Config) -> Result<DeviceSpec> {
    Ok(match arg {
        Some(s) => s.parse()?,
        None => config.device_spec()?,
    })
}

fn real_main(cli: Cli) -> Result<()> {
    init_logging(&cli.log_level)?;
    // Read by the commands that use it.
    let config = || -> Result<Config> {
        let mut config = load_config(cli.config.as_deref())?;
        if let Some(dir) = &cli.state_dir {
            config.paths.state_dir = Some(dir.clone());
        }
        if let Some(socket) = &cli.socket {
            config.app.socket = Some(socket.clone());
        }
        if let Some(profile) = &cli.profile {
            config.device.profile = profile.clone();
        }
        Ok(config)
    };
    match cli.command {
        Command::Run(args) => {
            // SIGHUP gives a simulated device the payload and gravity of this file again.
            run(&config()?, &args, config_file(cli.config.as_deref()))
        }
        Command::Calibrate(args) => calibrate_command(config()?, args),
        Command::Validate(args) => validate_command(&config()?, args),
        Command::Record(args) => record_command(&config()?, args),
        Command::Analyze(AnalyzeArgs { grid, log, out }) => {
            analyze_here(&AnalyzeRequest { grid, log, out })
        }
        Command::Status(args) => status(&config()?, args.device.as_deref()),
        Command::SimDevice(args) => sim_device(&config()?, &args),
        Command::Devices => devices(&config()?),
        Command::Check(args) => check_command(&config()?, &args),
        Command::Man(args) => man_pages(&args.out),
        Command::Completions(args) => {
            let mut script = Vec::new();
            clap_complete::generate(args.shell, &mut visible_command(), "hgcd", &mut script);
            out(&String::from_utf8_lossy(&script))
        }
    }
}

/// The command line without its hidden subcommands (clap has no way to leave them out of a
/// completion script), as completions offer it.
fn visible_command() -> clap::Command {
    let full = command();
    let mut visible = clap::Command::new("hgcd").version(VERSION.as_str());
    for arg in full.get_arguments() {
        visible = visible.arg(arg.clone());
    }
    for sub in full.get_subcommands().filter(|s| !s.is_hide_set()) {
        visible = visible.subcommand(sub.clone());
    }
    visible
}

/// `hgcd man`: a page for hgcd and one for each subcommand a user sees, from the command line's
/// own definition (the hidden ones, `man` and `completions`, are left out).
fn man_pages(dir: &Path) -> Result<()> {
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    // `hgcd help` has no page of its own: `--help` is on every page.
    let mut cmd = command()
        .version(RELEASE.as_str())
        .disable_help_subcommand(true);
    // Building gives each subcommand the global options it accepts.
    cmd.build();
    let source = format!("hgcd {}", *RELEASE);
    let write = |name: &str, page: clap::Command| -> Result<()> {
        let path = dir.join(format!("{name}.1"));
        let mut roff = Vec::new();
        let man = clap_mangen::Man::new(page).title(name).source(&source);
        man.render(&mut roff)?;
        std::fs::write(&path, roff).with_context(|| format!("writing {}", path.display()))
    };
    for sub in cmd.get_subcommands() {
        if sub.is_hide_set() {
            continue;
        }
        let name = format!("hgcd-{}", sub.get_name());
        write(&name, sub.clone())?;
    }
    write("hgcd", cmd)
}

/// `hgcd calibrate`: through the running daemon with `--via-daemon`, else in this process.
fn calibrate_command(mut config: Config, args: CalibrateArgs) -> Result<()> {
    if args.via_daemon {
        anyhow::ensure!(
            args.workspace.is_none(),
            "--workspace cannot be given with --via-daemon: the daemon calibrates with its own \
             config; set calibration.workspace there"
        );
        let socket = daemon_socket(&config, args.device.as_deref())?;
        if !args.yes {
            confirm_start()?;
        }
        return ctl::calibrate_via_daemon(&socket);
    }
    if let Some(workspace) = args.workspace {
        config.calibration.workspace = workspace;
    }
    calibrate_here(
        &config,
        args.device.as_deref(),
        args.output,
        args.real_time,
        args.yes,
    )
}

/// `hgcd validate`: the options as a request, run in this process.
fn validate_command(config: &Config, args: ValidateArgs) -> Result<()> {
    let modes = args
        .modes
        .iter()
        .map(|m| m.parse::<Mode>())
        .collect::<Result<Vec<_>, _>>()
        .map_err(|e| anyhow::anyhow!("--modes: {e}"))?;
    let device = device_spec(args.device.as_deref(), config)?;
    let request = ValidateRequest {
        pacing: pacing(&device, args.real_time),
        device,
        grid: args.grid,
        out: args.out,
        probe_mass: args.probe_mass_g * 1e-3,
        stiffness: args.stiffness_n_per_mm * 1e3,
        repetitions: args.repetitions,
        modes,
        sweep: args.sweep,
    };
    validate_here(config, &request, args.yes)
}

/// `hgcd record`: the options as a request, confirmed on hardware, run in this process.
fn record_command(config: &Config, args: RecordArgs) -> Result<()> {
    let device = device_spec(args.device.as_deref(), config)?;
    let pacing = confirmed_pacing(&device, args.real_time, args.yes)?;
    let request = RecordRequest {
        device,
        pacing,
        grid: args.grid,
        out: args.out,
        duration: args.duration,
    };
    record_here(config, &request)
}

/// The socket of the daemon a command talks to: `--socket` (or `app.socket`), else that of the
/// daemon of `device`, else that of the only daemon running.
fn daemon_socket(config: &Config, device: Option<&str>) -> Result<PathBuf> {
    match &config.app.socket {
        Some(socket) => Ok(socket.clone()),
        None => Ok(endpoint::find(&endpoint::runtime_dir(), device)?.socket),
    }
}

/// `hgcd status`: the daemon of `--socket` or `device`, else every daemon running.
fn status(config: &Config, device: Option<&str>) -> Result<()> {
    let sockets = match (&config.app.socket, device) {
        (None, None) => {
            let dir = endpoint::runtime_dir();
            let all = endpoint::running(&dir)?;
            anyhow::ensure!(!all.is_empty(), FindError::NoDaemon { dir });
            all.into_iter().map(|i| i.socket).collect()
        }
        _ => vec![daemon_socket(config, device)?],
    };
    ctl::status(&sockets)
}

/// `hgcd run`: the daemon, until a signal or `--duration`; prints the loop's statistics.
fn run(config: &Config, args: &RunArgs, config_file: Option<PathBuf>) -> Result<()> {
    if let Some(d) = args.duration {
        anyhow::ensure!(
            d.is_finite() && d > 0.0,
            "--duration must be a positive number of seconds"
        );
    }
    let request = RunRequest {
        device: device_spec(args.device.as_deref(), config)?,
        duration: args.duration,
        pacing: if args.virtual_time {
            Pacing::Virtual
        } else {
            Pacing::RealTime
        },
        config_file,
    };
    let signals = install_signal_handlers()?;
    let report = daemon::run(config, &request, signals)?;
    out(&format!("{}\n", report.stats))?;
    match report.exit {
        ExitReason::Fault(fault) => anyhow::bail!("the servo loop ended: {fault}"),
        _ => Ok(()),
    }
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
    let pacing = confirmed_pacing(&device, real_time, yes)?;
    let request = CalibrateRequest {
        device,
        pacing,
        output,
        state_dir: config.state_dir(),
    };
    let stop = install_stop_handler()?;
    let mut display = progress::Display::new(progress::vertex_count(config, &request.device));
    let run = calibrate(config, &request, stop, &mut |e| display.show(e));
    display.finish();
    let run = run?;
    out(&progress::summary(&run))
}

/// Virtual time for a simulated device unless `--real-time`; hardware always runs in real time.
fn pacing(device: &DeviceSpec, real_time: bool) -> Pacing {
    if matches!(device, DeviceSpec::Sim { .. }) && !real_time {
        Pacing::Virtual
    } else {
        Pacing::RealTime
    }
}

/// The pacing of a command that moves the handle on `device`, once it may start: a real device
/// waits for the user's confirmation unless `--yes` was given.
fn confirmed_pacing(device: &DeviceSpec, real_time: bool, yes: bool) -> Result<Pacing> {
    if !matches!(device, DeviceSpec::Sim { .. }) && !yes {
        confirm_start()?;
    }
    Ok(pacing(device, real_time))
}

/// The verdict of `hgcd check` as its exit status (printed already; nothing more to say).
#[derive(Debug, thiserror::Error)]
#[error("check verdict: exit status {0}")]
struct CheckVerdict(u8);

/// `hgcd check`: the two holds, the verdict, and the exit status that says it.
fn check_command(config: &Config, args: &CheckArgs) -> Result<()> {
    if args.revert {
        if args.via_daemon {
            let socket = daemon_socket(config, args.device.as_deref())?;
            let reverted = ctl::revert_via_daemon(&socket)?;
            return out(&format!(
                "{}the daemon compensates with it now\n",
                progress::revert_summary(&reverted)
            ));
        }
        let reverted = check::revert(config, &check_request(config, args)?)?;
        return out(&progress::revert_summary(&reverted));
    }
    let found = if args.via_daemon {
        let socket = daemon_socket(config, args.device.as_deref())?;
        if !args.yes {
            confirm_start()?;
        }
        ctl::check_via_daemon(&socket, args.apply)?
    } else {
        check_here(config, args)?
    };
    if args.json {
        out(&format!("{}\n", serde_json::to_string(&found)?))?;
    } else {
        out(&progress::check_summary(&found))?;
    }
    match found.verdict.exit_code() {
        0 => Ok(()),
        code => Err(CheckVerdict(code).into()),
    }
}

/// What `hgcd check` in this process (or `--revert`) works on.
fn check_request(config: &Config, args: &CheckArgs) -> Result<CheckRequest> {
    let device = device_spec(args.device.as_deref(), config)?;
    let pacing = confirmed_pacing(&device, args.real_time, args.yes)?;
    Ok(CheckRequest {
        device,
        pacing,
        grid: args.grid.clone(),
        state_dir: config.state_dir(),
    })
}

/// `hgcd check` in this process: the two holds, and `--apply`.
fn check_here(config: &Config, args: &CheckArgs) -> Result<check::Check> {
    let request = check_request(config, args)?;
    let stop = install_stop_handler()?;
    // The initialisation, then the two holds, shown as a calibration's are.
    let mut display = progress::Display::new(2);
    let found = check::check(config, &request, stop, &mut |e| display.show(e));
    display.finish();
    let mut found = found?;
    if args.apply && found.verdict == check::Verdict::Apply {
        check::apply(&mut found)?;
    }
    Ok(found)
}

/// `hgcd record`: the identification run; says where the log went.
fn record_here(config: &Config, request: &RecordRequest) -> Result<()> {
    let stop = install_stop_handler()?;
    let mut display = progress::RecordDisplay::new(request.duration);
    let recording = discrepancy::record(config, request, stop, &mut |share| display.show(share));
    display.finish();
    let recording = recording?;
    out(&format!(
        "{} rows, {:.1} s{} in {}\n",
        recording.log.len(),
        recording.log.duration(),
        if recording.interrupted {
            " (stopped early)"
        } else {
            ""
        },
        request.out.display()
    ))
}

/// `hgcd analyze`: a line per stage on stderr, the verdict on stdout.
fn analyze_here(request: &AnalyzeRequest) -> Result<()> {
    let analysis = discrepancy::analyze(request, &mut |stage| err(&format!("analyze: {stage}\n")))?;
    let (before, after) = analysis.errors();
    let mut text = format!(
        "effects: {}\nheld-out RMS force residual: {:.4} N nominal, {:.4} N augmented \
         ({:+.0} %), noise floor {:.4} N\n",
        discrepancy::names(&analysis.effects),
        before,
        after,
        (after / before - 1.0) * 1e2,
        analysis.noise_floor.force,
    );
    if analysis.unexplained {
        text.push_str(&format!(
            "unexplained: the residual stays {:.1} times the noise floor, ordered best by {}\n",
            after / analysis.noise_floor.force,
            analysis.ordering.by
        ));
    }
    for limit in &analysis.limits {
        text.push_str(&format!("cannot show: {}\n", limit.message));
    }
    text.push_str(&format!(
        "report in {} ({:.1} s wall time)\n",
        request.out.join("report.md").display(),
        analysis.wall_time
    ));
    out(&text)
}

/// `hgcd validate` in this process: prepare, confirm on hardware, run; prints the table.
fn validate_here(config: &Config, request: &ValidateRequest, yes: bool) -> Result<()> {
    let prepared = validate::prepare(config, request)?;
    let simulated = matches!(prepared.device(), DeviceSpec::Sim { .. });
    if !simulated && !yes {
        confirm_validation(request.probe_mass)?;
    }
    if prepared.calibrates_first() {
        out(&format!(
            "calibrating {} first (grid to {})\n",
            prepared.device(),
            request.out.join("grid.toml").display()
        ))?;
    }
    let stop = install_stop_handler()?;
    let mut display = progress::ValidationDisplay::new(config, prepared.device());
    let run = prepared.run(stop, &mut |e| display.show(e));
    display.finish();
    let run = run?;
    out(&run.report.table())?;
    out(&format!(
        "results in {}: {}, {}, {} and {} ({:.1} s wall time)\n",
        request.out.display(),
        file_name(&run.outputs.csv),
        file_name(&run.outputs.summary),
        file_name(&run.outputs.svg),
        file_name(&run.outputs.png),
        run.wall_time
    ))?;
    if let Some(sweep) = &run.sweep {
        let grids = [("cube", &sweep.cube), ("explored grid", &sweep.explored)];
        for (name, grid) in grids {
            let Some(g) = grid else { continue };
            let (r, a) = (&g.residual_pct, &g.residual_mn);
            out(&format!(
                "sweep over {} reachable points (sweep.json), {name} ({} model): its measured \
                 cells cover {:.1} % of them; residual p50 {:.1} %, p95 {:.1} %, max {:.1} % \
                 (p95 {:.1} mN)\n",
                sweep.points,
                g.model,
                100.0 * g.covered_fraction,
                r.p50,
                r.p95,
                r.max,
                a.p95
            ))?;
        }
        if let Some(lattice) = &sweep.exact_lattice {
            let (s, r) = (&lattice.sweep, &lattice.sweep.residual_pct);
            out(&format!(
                "the best any {} mm grid can do here (the plant's own force at its {} reachable \
                 vertices): residual p50 {:.1} %, p95 {:.1} %, max {:.1} %\n",
                lattice.spacing_mm, s.measured_vertices, r.p50, r.p95, r.max
            ))?;
        }
    }
    Ok(())
}

fn file_name(path: &Path) -> String {
    path.file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default()
}

/// On a real device the user attaches the probe mass before any force is applied (paper §5).
fn confirm_validation(probe_mass: f64) -> Result<()> {
    use std::io::{BufRead, IsTerminal, Write};
    let stdin = std::io::stdin();
    anyhow::ensure!(
        stdin.is_terminal(),
        "validating a real device needs confirmation: run it on a terminal or pass --yes once the \
         probe mass is attached and the handle rests near the centre of the workspace"
    );
    eprint!(
        "Attach the {:.0} g probe mass to the handle, bring the handle near the centre of the \
         workspace and let go of it; hgcd will carry it to 27 points and lower it onto a virtual \
         surface at each.\nKeep clear of the handle until the run ends; then it drops.\nPress \
         Enter to start (Ctrl-C aborts). ",
        probe_mass * 1e3
    );
    std::io::stderr().flush().ok();
    let mut line = String::new();
    stdin.lock().read_line(&mut line)?;
    Ok(())
}

/// `hgcd sim-device`: serve the simulated device on a Unix socket, host after host, until stopped.
fn sim_device(config: &Config, args: &SimDeviceArgs) -> Result<()> {
    let (listen, lockstep, model) = (&args.listen, args.lockstep, args.model.as_str());
    let stop = install_stop_handler()?;
    let power_on = || hgcd::sim::SimDevice::from_config(model, config);
    // A config whose device cannot be built fails now, not at the first host.
    power_on()?;
    // Replaces a stale socket, refuses a live one or anything that is not a socket.
    let listener = hgcd::app::server::bind(listen, 0o660)
        .with_context(|| format!("listening on {}", listen.display()))?;
    tracing::info!(
        "simulated device listening on {} ({})",
        listen.display(),
        if lockstep { "lock-step" } else { "real time" }
    );
    let served = hgcd::sim::socket::serve(&listener, power_on, lockstep, &stop);
    let _ = std::fs::remove_file(listen);
    let served = served.with_context(|| format!("serving {}", listen.display()))?;
    out(&format!(
        "simulated device served {} host(s), {:.3} s of device time; {} output reports rejected\n",
        served.hosts, served.device_time, served.rejected
    ))
}

/// The profile hgcd would use for `spec` (docs/devices.md), or why none loads.
fn profile_of(spec: &DeviceSpec, config: &Config) -> String {
    match Profile::for_device(spec, config) {
        Ok(p) => format!("profile {}", p.name),
        Err(e) => format!("no profile: {e}"),
    }
}

/// `hgcd devices`: the HID devices this process can see, then the simulated ones, each with the
/// profile it would be driven with.
fn devices(config: &Config) -> Result<()> {
    let listed = hid::list_devices();
    match &listed {
        Ok(devices) if devices.is_empty() => {
            out("no HID devices visible (unplugged, or no permission: see docs/install.md)\n")?
        }
        Ok(devices) => {
            for d in devices {
                let spec = DeviceSpec::Hid {
                    vid: d.vid,
                    pid: d.pid,
                    serial: d.serial.clone(),
                };
                out(&format!(
                    "{:<32} {}: {} {} (interface {}, {})\n",
                    d.spec(),
                    profile_of(&spec, config),
                    d.manufacturer.as_deref().unwrap_or("?"),
                    d.product.as_deref().unwrap_or("?"),
                    d.interface,
                    d.path
                ))?;
            }
        }
        Err(_) => {}
    }
    for model in SIM_MODELS {
        let spec = DeviceSpec::Sim {
            model: model.to_string(),
        };
        out(&format!(
            "{:<32} {}: simulated, firmware around a {model} plant (config [sim]); no hardware \
             needed\n",
            spec.to_string(),
            profile_of(&spec, config)
        ))?;
    }
    listed.map(|_| ()).context("listing HID devices")
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
    err(
        "Bring the handle near the centre of the workspace and let go of it; hgcd will hold it with \
         a soft spring.\nPress Enter to start (Ctrl-C aborts). ",
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
    let calibrate_gone = |c: &CalibrateError| match c {
        CalibrateError::Open(t) => gone(t),
        CalibrateError::Servo(s) => servo_gone(s),
        _ => false,
    };
    let device_gone = match (
        e.downcast_ref::<RunError>(),
        e.downcast_ref::<CalibrateError>(),
        e.downcast_ref::<ValidateError>(),
    ) {
        (Some(RunError::Open(t)), _, _) => gone(t),
        (Some(RunError::Servo(s)), _, _) => servo_gone(s),
        (_, Some(c), _) => calibrate_gone(c),
        (_, _, Some(ValidateError::Open(t))) => gone(t),
        (_, _, Some(ValidateError::Servo(s))) => servo_gone(s),
        (_, _, Some(ValidateError::Calibration(c))) => calibrate_gone(c),
        _ => false,
    };
    let recording_gone = match e.downcast_ref::<RecordError>() {
        Some(RecordError::Open(t)) => gone(t),
        Some(RecordError::Servo(s)) => servo_gone(s),
        _ => false,
    };
    let check_gone = matches!(
        e.downcast_ref::<check::CheckError>(),
        Some(check::CheckError::Measure(c)) if calibrate_gone(c)
    );
    if device_gone || recording_gone || check_gone {
        EXIT_DEVICE_GONE
    } else {
        1
    }
}

fn main() -> ExitCode {
    let cli = Cli::from_arg_matches(&command().get_matches()).unwrap_or_else(|e| e.exit());
    match real_main(cli) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            if let Some(CheckVerdict(code)) = e.downcast_ref() {
                return ExitCode::from(*code);
            }
            err(&format!("hgcd: {e:#}\n"));
            ExitCode::from(exit_status(&e))
        }
    }
}
