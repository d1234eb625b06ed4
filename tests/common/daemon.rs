//! One way to start a daemon in a test: a simulated device (the point mass unless told), in a
//! temporary directory of its own (state dir, socket, truth field), behind whatever transport
//! wrapper the test needs.

use std::path::PathBuf;
use std::sync::atomic::Ordering;
use std::thread::JoinHandle;

use hgcd::config::Config;
use hgcd::daemon::{Daemon, RunError, RunRequest, Signals};
use hgcd::grid::{grid_path, GridFile, MassGrid};
use hgcd::servo::ServoReport;
use hgcd::sim::SimDevice;
use hgcd::transport::sim::SimTransport;
use hgcd::transport::{identify, Pacing, Transport};

use super::{truth_field_27, WAIT};

/// What to start: a config, the device's stored grid, the plant's truth field, the pacing.
pub struct TestDaemon {
    config: Config,
    /// `sim:MODEL`.
    model: &'static str,
    grid: Option<GridFile>,
    /// The plant's mass field; None: the config's own plant, as it is.
    truth: Option<MassGrid>,
    pacing: Pacing,
    duration: Option<f64>,
    /// The config file SIGHUP reads a simulated device's world from.
    config_file: Option<PathBuf>,
}

impl TestDaemon {
    /// A daemon on `sim:point-mass` in virtual time, no stored grid, truth field
    /// [`truth_field_27`]. A frictionless point mass is a double integrator: any bias force,
    /// however small, makes it drift quadratically, so unless the config says otherwise that
    /// plant gets 1 N·s/m of viscous friction, typical of desktop haptic devices.
    pub fn new(mut config: Config) -> Self {
        config.servo.lock_memory = false;
        Self {
            config,
            model: "point-mass",
            grid: None,
            truth: Some(truth_field_27()),
            pacing: Pacing::Virtual,
            duration: None,
            config_file: None,
        }
    }

    /// The config file the daemon was started with (`hgcd run --config`).
    pub fn config_file(mut self, path: &std::path::Path) -> Self {
        self.config_file = Some(path.to_path_buf());
        self
    }

    /// Store `grid` as the device's calibration before the daemon starts.
    pub fn grid(mut self, grid: Option<&GridFile>) -> Self {
        self.grid = grid.cloned();
        self
    }

    /// The plant's apparent-mass field.
    pub fn truth(mut self, truth: &MassGrid) -> Self {
        self.truth = Some(truth.clone());
        self
    }

    /// The plant the config's `[sim]` section describes, untouched.
    pub fn plant_from_config(mut self) -> Self {
        self.truth = None;
        self
    }

    /// `sim:MODEL` instead of the point mass, its plant the config's `[sim]` section.
    pub fn model(mut self, model: &'static str) -> Self {
        self.model = model;
        self.plant_from_config()
    }

    /// Run the simulated device in real time for `seconds`.
    pub fn real_time_for(mut self, seconds: f64) -> Self {
        self.pacing = Pacing::RealTime;
        self.duration = Some(seconds);
        self
    }

    /// Start it on the bare simulated device.
    pub fn start(self) -> Running {
        self.start_with(|sim| sim)
    }

    /// Start it on the transport `wrap` makes of the simulated device (a tap, a counter), and
    /// return once it serves its socket (or has failed before: then `join` says why).
    pub fn start_with<T: Transport + 'static>(
        mut self,
        wrap: impl FnOnce(SimTransport) -> T,
    ) -> Running {
        let dir = tempfile::tempdir().unwrap();
        let state = dir.path().join("state");
        std::fs::create_dir_all(&state).unwrap();
        if let Some(field) = self.truth {
            let truth = dir.path().join("truth.toml");
            GridFile::from(field).save_atomic(&truth).unwrap();
            self.config.sim.mass_grid = Some(truth);
            if self.config.sim.damping_n_s_per_m == 0.0 {
                self.config.sim.damping_n_s_per_m = 1.0;
            }
        }
        let sim = SimTransport::new(
            SimDevice::from_config(self.model, &self.config).unwrap(),
            self.pacing,
        );
        let request = RunRequest {
            device: format!("sim:{}", self.model).parse().unwrap(),
            duration: self.duration,
            pacing: self.pacing,
            config_file: self.config_file.clone(),
        };
        if let Some(grid) = &self.grid {
            // Where the daemon looks for it: named after the device (`sim.serial` included).
            let device = identify(&sim, &request.device, &self.config).unwrap();
            grid.save_atomic(&grid_path(&state, &device.grid_id()))
                .unwrap();
        }
        self.config.paths.state_dir = Some(state);
        let socket = dir.path().join("hgcd.sock");
        self.config.app.socket = Some(socket.clone());
        let transport = Box::new(wrap(sim));
        let signals = Signals::default();
        let daemon_signals = signals.clone();
        let config = self.config;
        let (ready_tx, ready_rx) = crossbeam_channel::bounded(1);
        let handle = std::thread::spawn(move || {
            Daemon::new(config, &request).run(transport, daemon_signals, &mut |_| {
                let _ = ready_tx.send(());
            })
        });
        // Ready, or ended before it (then `join` says why). A loaded machine may take a while
        // to start it: wait as long as that, not a fixed [`WAIT`].
        let deadline = std::time::Instant::now() + 4 * WAIT;
        while ready_rx.recv_timeout(WAIT / 100).is_err() && !handle.is_finished() {
            assert!(
                std::time::Instant::now() < deadline,
                "the daemon neither served its socket nor ended within {:?}",
                4 * WAIT
            );
        }
        Running {
            dir,
            socket,
            signals,
            handle: Some(handle),
        }
    }
}

/// A daemon running on its own thread; stopped when dropped.
pub struct Running {
    pub dir: tempfile::TempDir,
    pub socket: PathBuf,
    pub signals: Signals,
    handle: Option<JoinHandle<Result<ServoReport, RunError>>>,
}

impl Running {
    /// Ask the daemon to stop (as SIGTERM does) and wait for it; its servo report.
    pub fn stop(mut self) -> Result<ServoReport, RunError> {
        self.signals.stop.store(true, Ordering::SeqCst);
        self.join()
    }

    /// Wait for the daemon to end by itself (or after `stop`).
    pub fn join(&mut self) -> Result<ServoReport, RunError> {
        let handle = self.handle.take().expect("the daemon runs");
        handle.join().expect("the daemon thread does not panic")
    }
}

impl Drop for Running {
    fn drop(&mut self) {
        self.signals.stop.store(true, Ordering::SeqCst);
    }
}
