//! The `hgcd` command line: parse, load config, call the library.

use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

use anyhow::{Context, Result};
use clap::{Parser, Subcommand};

use hgcd::config::{Config, DeviceSpec, DEFAULT_CONFIG_PATH};
use hgcd::daemon::{self, RunRequest};
use hgcd::transport::{hid, Pacing};

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
    tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .init();
    Ok(())
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
    let config = load_config(cli.config.as_deref())?;
    match cli.command {
        Command::Run {
            device,
            duration,
            virtual_time,
        } => {
            if let Some(d) = duration {
                anyhow::ensure!(
                    d.is_finite() && d > 0.0,
                    "--duration must be a positive number of seconds"
                );
            }
            let request = RunRequest {
                device: device_spec(device.as_deref(), &config)?,
                duration,
                pacing: if virtual_time {
                    Pacing::Virtual
                } else {
                    Pacing::RealTime
                },
            };
            let stop = install_stop_handler()?;
            let report = daemon::run(&config, &request, stop)?;
            println!("{}", report.stats);
            Ok(())
        }
        Command::Devices => {
            let devices = hid::list_devices()?;
            if devices.is_empty() {
                println!(
                    "no HID devices visible (unplugged, or no permission: see docs/install.md)"
                );
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
    }
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    match real_main(cli) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("hgcd: {e:#}");
            ExitCode::FAILURE
        }
    }
}
