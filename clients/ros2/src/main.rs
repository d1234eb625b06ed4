//! `hgcd-ros2`: a ROS 2 bridge for one hgcd daemon (docs/ros2.md). It connects to the daemon as
//! any application does (`hgcd::client`) and speaks ROS 2 over DDS with `ros2-client`, pure
//! Rust: the device state out as topics, `servo_cf` in as the force offset, `calibrate` and
//! `status` as services.
//!
//! Two connections to the daemon: one asks for `control` and carries the offsets, the service
//! requests and the status polls; the other observes and streams the state. The bridge dying
//! closes both, which removes its offset at once and leaves the daemon and its other clients as
//! they were.

mod logic;
mod msgs;

use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc;
use std::sync::{Arc, Mutex, MutexGuard};
use std::thread;
use std::time::{Duration, Instant};

use anyhow::{anyhow, bail, Context as _};
use clap::{Parser, ValueEnum};
use mio::{Events, Poll, PollOpt, Ready, Token};
use nalgebra::Vector3;
use ros2_client::ros2::{policy, QosPolicies, QosPolicyBuilder};
use ros2_client::{
    AService, Context, ContextOptions, MessageTypeName, Name, Node, NodeName, NodeOptions,
    Publisher, Server, ServiceMapping, ServiceTypeName, Subscription,
};
use serde::Serialize;
use tracing::{debug, error, info, warn};

use hgcd::client::{CalibrationStage, Client, ClientError, Reply, Role, StateSample, Status};

use logic::{Hold, Send, Throttle};
use msgs::{
    Header, Pose, PoseStamped, Quaternion, StringMsg, Time, TriggerRequest, TriggerResponse, Twist,
    TwistStamped, Vector3 as V3, Wrench, WrenchStamped,
};

/// Bridge one hgcd daemon to ROS 2: the handle's state as topics, `servo_cf` as its force
/// offset, calibrate and status as services (docs/ros2.md). The DDS domain is
/// `ROS_DOMAIN_ID` (default 0).
#[derive(Parser, Debug)]
#[command(name = "hgcd-ros2", version)]
struct Args {
    /// The daemon's socket.
    #[arg(long, value_name = "PATH", conflicts_with = "device")]
    socket: Option<PathBuf>,
    /// The daemon of this device (a device id or spec; default: the only daemon running).
    #[arg(long, value_name = "SPEC")]
    device: Option<String>,
    /// Namespace of the topics and services (default: /hgcd/ and the device id, its `-` made `_`).
    #[arg(long, value_name = "NS")]
    namespace: Option<String>,
    /// Rate of measured_cp, measured_cv, measured_cf and gravity_cf, Hz (at most the servo
    /// rate; the daemon delivers its rate divided by a whole number).
    #[arg(long, value_name = "HZ", default_value_t = 1000.0)]
    rate: f64,
    /// servo_cf silent this long (ms): the offset is released (set to zero).
    #[arg(long, value_name = "MS", default_value_t = 50)]
    servo_timeout_ms: u64,
    /// How often the daemon's status is read for operating_state, ms.
    #[arg(long, value_name = "MS", default_value_t = 100)]
    status_period_ms: u64,
    /// How the services map onto DDS: `enhanced` for ROS 2 on Fast DDS (the default RMW),
    /// `cyclone` for rmw_cyclonedds_cpp.
    #[arg(long, value_enum, default_value_t = Mapping::Enhanced)]
    service_mapping: Mapping,
    /// The frame of every message and the only one servo_cf is taken in (default: the device
    /// id, the device frame of docs/hid-protocol.md §2).
    #[arg(long, value_name = "FRAME")]
    frame_id: Option<String>,
    /// The ROS 2 node's name.
    #[arg(long, value_name = "NAME", default_value = "hgcd_ros2")]
    node_name: String,
}

#[derive(Clone, Copy, Debug, ValueEnum)]
enum Mapping {
    Enhanced,
    Cyclone,
    Basic,
}

impl From<Mapping> for ServiceMapping {
    fn from(m: Mapping) -> Self {
        match m {
            Mapping::Enhanced => ServiceMapping::Enhanced,
            Mapping::Cyclone => ServiceMapping::Cyclone,
            Mapping::Basic => ServiceMapping::Basic,
        }
    }
}

/// How often a held offset is sent again while servo_cf is alive: well within the daemon's
/// default `app.stale_offset_ms` (50 ms).
const REFRESH: Duration = Duration::from_millis(20);
/// The pause after creating each DDS writer (see `ros`).
const WRITER_SETTLE: Duration = Duration::from_millis(10);
/// At most one line a second for each kind of refusal.
const LOG_PERIOD: Duration = Duration::from_secs(1);
/// Name the bridge gives the daemon (shown as `owner` in its status).
const CLIENT_NAME: &str = "hgcd-ros2";

/// Set once the bridge stops: RustDDS's complaints while it is torn down are not shown.
static STOPPING: AtomicBool = AtomicBool::new(false);

fn main() -> ExitCode {
    use tracing_subscriber::prelude::*;
    let filter =
        tracing_subscriber::EnvFilter::try_from_env("HGCD_ROS2_LOG").unwrap_or_else(|_| {
            tracing_subscriber::EnvFilter::new("info,rustdds=warn,ros2_client=warn")
        });
    let quiet_teardown = tracing_subscriber::filter::filter_fn(|meta| {
        !(STOPPING.load(Ordering::Relaxed) && meta.target().starts_with("rustdds"))
    });
    tracing_subscriber::registry()
        .with(
            tracing_subscriber::fmt::layer()
                .with_writer(std::io::stderr)
                .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
                .with_filter(filter)
                .with_filter(quiet_teardown),
        )
        .init();
    let args = Args::parse();
    match run(args) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            error!("{e:#}");
            eprintln!("hgcd-ros2: {e:#}");
            ExitCode::FAILURE
        }
    }
}

/// `ROS_DOMAIN_ID`, 0 when unset.
fn domain_id() -> anyhow::Result<u16> {
    match std::env::var("ROS_DOMAIN_ID") {
        Err(std::env::VarError::NotPresent) => Ok(0),
        Ok(s) if s.trim().is_empty() => Ok(0),
        Ok(s) => match s.trim().parse::<u16>() {
            Ok(id) if id <= 232 => Ok(id),
            _ => bail!("ROS_DOMAIN_ID={s:?}: a DDS domain is a whole number from 0 to 232"),
        },
        Err(e) => bail!("ROS_DOMAIN_ID: {e}"),
    }
}

fn connect(args: &Args, role: Role) -> anyhow::Result<Client> {
    match &args.socket {
        Some(path) => Ok(Client::connect(path, role, CLIENT_NAME)?),
        None => Client::connect_to(args.device.as_deref(), role, CLIENT_NAME)
            .map_err(|e| anyhow!("{e}")),
    }
}

fn best_effort() -> QosPolicies {
    QosPolicyBuilder::new()
        .reliability(policy::Reliability::BestEffort)
        .durability(policy::Durability::Volatile)
        .history(policy::History::KeepLast { depth: 5 })
        .build()
}

fn latched() -> QosPolicies {
    QosPolicyBuilder::new()
        .reliability(policy::Reliability::Reliable {
            max_blocking_time: ros2_client::ros2::Duration::from_millis(100),
        })
        .durability(policy::Durability::TransientLocal)
        .history(policy::History::KeepLast { depth: 1 })
        .build()
}

fn service_qos() -> QosPolicies {
    QosPolicyBuilder::new()
        .reliability(policy::Reliability::Reliable {
            max_blocking_time: ros2_client::ros2::Duration::from_millis(100),
        })
        .durability(policy::Durability::Volatile)
        .history(policy::History::KeepLast { depth: 10 })
        .build()
}

type Trigger = AService<TriggerRequest, TriggerResponse>;

/// Everything on the DDS side.
struct Ros {
    node: Node,
    cp: Publisher<PoseStamped>,
    cv: Publisher<TwistStamped>,
    cf: Publisher<WrenchStamped>,
    gravity: Publisher<WrenchStamped>,
    operating_state: Publisher<StringMsg>,
    servo_cf: Subscription<WrenchStamped>,
    calibrate: Server<Trigger>,
    status: Server<Trigger>,
}

fn ros(args: &Args, namespace: &str, domain: u16) -> anyhow::Result<Ros> {
    let name = |base: &str| {
        Name::new(namespace, base).map_err(|e| {
            anyhow!(
                "--namespace {namespace:?} is not a ROS 2 namespace ({e:?}): it starts with /, \
                 and its tokens are letters, digits and single underscores, none starting with \
                 a digit"
            )
        })
    };
    let node_name = NodeName::new(namespace, &args.node_name).map_err(|e| {
        anyhow!(
            "--node-name {:?} is not a ROS 2 node name ({e:?})",
            args.node_name
        )
    })?;
    let context = Context::with_options(ContextOptions::new().domain_id(domain))
        .context("cannot start DDS")?;
    // No rosout, no spinner (its parameter services): RustDDS 0.11 holds its discovery database
    // locked while it queues a new writer for its event loop on a channel of 10, so a process
    // that creates more than 10 writers can deadlock with discovery (seen here: the spinner's
    // six more, as a peer appeared). The context, the node and the bridge make 9 in all, once.
    let mut node = context
        .new_node(node_name, NodeOptions::new().enable_rosout(false))
        .context("cannot create the ROS 2 node")?;
    let geometry = |t: &str| MessageTypeName::new("geometry_msgs", t);
    let streams = best_effort();
    let topic = |node: &Node, base: &str, t: MessageTypeName, qos: &QosPolicies| {
        node.create_topic(&name(base)?, t, qos)
            .with_context(|| format!("cannot create the topic {base}"))
    };
    let t_cp = topic(&node, "measured_cp", geometry("PoseStamped"), &streams)?;
    let t_cv = topic(&node, "measured_cv", geometry("TwistStamped"), &streams)?;
    let t_cf = topic(&node, "measured_cf", geometry("WrenchStamped"), &streams)?;
    let t_g = topic(&node, "gravity_cf", geometry("WrenchStamped"), &streams)?;
    let t_servo = topic(&node, "servo_cf", geometry("WrenchStamped"), &streams)?;
    let t_state = topic(
        &node,
        "operating_state",
        MessageTypeName::new("std_msgs", "String"),
        &latched(),
    )?;
    let servo_qos = QosPolicyBuilder::new()
        .reliability(policy::Reliability::BestEffort)
        .durability(policy::Durability::Volatile)
        .history(policy::History::KeepLast { depth: 1 })
        .build();
    let trigger = ServiceTypeName::new("std_srvs", "Trigger");
    let mapping = ServiceMapping::from(args.service_mapping);
    let server = |node: &mut Node, base: &str| -> anyhow::Result<Server<Trigger>> {
        node.create_server::<Trigger>(
            mapping,
            &name(base)?,
            &trigger,
            service_qos(),
            service_qos(),
        )
        .with_context(|| format!("cannot create the service {base}"))
    };
    // One writer at a time, each given time to reach RustDDS's event loop (see above).
    let settle = || thread::sleep(WRITER_SETTLE);
    let calibrate = server(&mut node, "calibrate")?;
    settle();
    let status = server(&mut node, "status")?;
    settle();
    Ok(Ros {
        cp: publisher(&mut node, &t_cp)?,
        cv: publisher(&mut node, &t_cv)?,
        cf: publisher(&mut node, &t_cf)?,
        gravity: publisher(&mut node, &t_g)?,
        operating_state: publisher(&mut node, &t_state)?,
        servo_cf: node.create_subscription(&t_servo, Some(servo_qos))?,
        calibrate,
        status,
        node,
    })
}

/// A publisher on `topic`, then the pause that lets RustDDS's event loop take its writer.
fn publisher<M: Serialize>(
    node: &mut Node,
    topic: &ros2_client::rustdds::Topic,
) -> anyhow::Result<Publisher<M>> {
    let p = node.create_publisher(topic, None)?;
    thread::sleep(WRITER_SETTLE);
    Ok(p)
}

/// Why the bridge stopped.
enum Stop {
    Signal,
    Failed(anyhow::Error),
}

fn run(args: Args) -> anyhow::Result<()> {
    if !(args.rate.is_finite() && args.rate > 0.0) {
        bail!("--rate {}: a rate above 0 Hz", args.rate);
    }
    if !(1..=60_000).contains(&args.servo_timeout_ms) {
        bail!(
            "--servo-timeout-ms {}: from 1 to 60000 ms",
            args.servo_timeout_ms
        );
    }
    if !(10..=60_000).contains(&args.status_period_ms) {
        bail!(
            "--status-period-ms {}: from 10 to 60000 ms",
            args.status_period_ms
        );
    }
    let domain = domain_id()?;
    let owner = connect(&args, Role::Control)?;
    if args.rate > owner.rate_hz {
        bail!(
            "--rate {} Hz: the daemon's servo runs at {} Hz, the most it can stream",
            args.rate,
            owner.rate_hz
        );
    }
    let mut observer = connect(&args, Role::Observe)?;
    let device_id = owner.device_id.clone();
    let frame_id = args.frame_id.clone().unwrap_or_else(|| device_id.clone());
    let namespace = args
        .namespace
        .clone()
        .unwrap_or_else(|| logic::default_namespace(&device_id));
    let owns = owner.role == Role::Control;
    let max_force = owner.max_force;
    let ros = ros(&args, &namespace, domain)?;
    info!(
        "bridging {} ({}) to ROS 2 domain {domain}, namespace {namespace}, frame {frame_id:?}",
        owner.device_id, owner.device
    );
    if !owns {
        warn!(
            "another client owns the force: servo_cf will be refused, calibrate too; the state \
             is published"
        );
    }

    let (stop_tx, stop_rx) = mpsc::channel::<Stop>();
    {
        let stop = stop_tx.clone();
        ctrlc::set_handler(move || {
            let _ = stop.send(Stop::Signal);
        })
        .context("cannot install the signal handler")?;
    }
    let owner = Arc::new(Mutex::new(owner));
    let Ros {
        node,
        cp,
        cv,
        cf,
        gravity,
        operating_state,
        servo_cf,
        calibrate,
        status,
    } = ros;

    observer.subscribe(args.rate)?;
    let state_out = StateOut {
        frame_id: frame_id.clone(),
        cp,
        cv,
        cf,
        gravity,
    };
    spawn("hgcd-ros2-state", &stop_tx, move || {
        state_loop(observer, state_out)
    })?;
    {
        let owner = Arc::clone(&owner);
        let timeout = Duration::from_millis(args.servo_timeout_ms);
        let frame_id = frame_id.clone();
        spawn("hgcd-ros2-servo", &stop_tx, move || {
            servo_loop(&owner, servo_cf, &frame_id, max_force, owns, timeout)
        })?;
    }
    {
        let owner = Arc::clone(&owner);
        let period = Duration::from_millis(args.status_period_ms);
        spawn("hgcd-ros2-daemon", &stop_tx, move || {
            daemon_loop(&owner, operating_state, calibrate, status, period, owns)
        })?;
    }
    let outcome = stop_rx
        .recv()
        .expect("a sender lives in the signal handler");
    STOPPING.store(true, Ordering::Relaxed);
    // Zero first; the connections closing as the process ends removes the offset at once too
    // (docs/app-protocol.md §6).
    if owns {
        let _ = lock(&owner).set_force(Vector3::zeros());
    }
    drop(node);
    match outcome {
        Stop::Signal => {
            info!("stopped");
            Ok(())
        }
        Stop::Failed(e) => Err(e),
    }
}

fn spawn(
    name: &str,
    stop: &mpsc::Sender<Stop>,
    body: impl FnOnce() -> anyhow::Result<()> + std::marker::Send + 'static,
) -> anyhow::Result<()> {
    let stop = stop.clone();
    let thread_name = name.to_string();
    thread::Builder::new().name(name.into()).spawn(move || {
        let outcome = match std::panic::catch_unwind(std::panic::AssertUnwindSafe(body)) {
            Ok(Ok(())) => anyhow!("{thread_name} ended"),
            Ok(Err(e)) => e,
            Err(_) => anyhow!("{thread_name} panicked"),
        };
        let _ = stop.send(Stop::Failed(outcome));
    })?;
    Ok(())
}

/// The state topics.
struct StateOut {
    frame_id: String,
    cp: Publisher<PoseStamped>,
    cv: Publisher<TwistStamped>,
    cf: Publisher<WrenchStamped>,
    gravity: Publisher<WrenchStamped>,
}

impl StateOut {
    fn publish(&self, s: &StateSample) {
        let header = Header {
            stamp: Time::now(),
            frame_id: self.frame_id.clone(),
        };
        let wrench = |force: [f64; 3]| Wrench {
            force: V3::from(force),
            torque: V3::default(),
        };
        // Best effort: a write that fails loses this sample, as a lost packet would.
        let _ = [
            self.cp
                .publish(PoseStamped {
                    header: header.clone(),
                    pose: Pose {
                        position: V3::from(s.position),
                        orientation: Quaternion::IDENTITY,
                    },
                })
                .is_ok(),
            self.cv
                .publish(TwistStamped {
                    header: header.clone(),
                    twist: Twist {
                        linear: V3::from(s.velocity),
                        angular: V3::default(),
                    },
                })
                .is_ok(),
            self.cf
                .publish(WrenchStamped {
                    header: header.clone(),
                    wrench: wrench(s.force),
                })
                .is_ok(),
            s.gravity.is_none_or(|g| {
                self.gravity
                    .publish(WrenchStamped {
                        header,
                        wrench: wrench(g),
                    })
                    .is_ok()
            }),
        ];
    }
}

fn state_loop(mut observer: Client, out: StateOut) -> anyhow::Result<()> {
    let mut warned_gravity = false;
    loop {
        let s = match observer.next_state() {
            Ok(s) => s,
            Err(ClientError::Closed) => bail!("the daemon closed the connection"),
            Err(e) => return Err(anyhow!("state stream: {e}")),
        };
        if s.gravity.is_none() && !warned_gravity {
            warned_gravity = true;
            warn!("this daemon does not send the gravity force: gravity_cf is not published");
        }
        out.publish(&s);
    }
}

fn lock(owner: &Mutex<Client>) -> MutexGuard<'_, Client> {
    // A thread that panicked holding it has stopped the bridge already; the client is intact.
    owner.lock().unwrap_or_else(|p| p.into_inner())
}

fn servo_loop(
    owner: &Mutex<Client>,
    servo_cf: Subscription<WrenchStamped>,
    frame_id: &str,
    max_force: f64,
    owns: bool,
    timeout: Duration,
) -> anyhow::Result<()> {
    let poll = Poll::new()?;
    poll.register(&servo_cf, Token(0), Ready::readable(), PollOpt::edge())?;
    let mut events = Events::with_capacity(4);
    let mut hold = Hold::new(timeout, REFRESH.min(timeout));
    let mut refused = [
        Throttle::new(LOG_PERIOD),
        Throttle::new(LOG_PERIOD),
        Throttle::new(LOG_PERIOD),
        Throttle::new(LOG_PERIOD),
    ];
    let mut released_log = Throttle::new(LOG_PERIOD);
    loop {
        let wait = hold
            .next_due()
            .map(|t| t.saturating_duration_since(Instant::now()))
            .unwrap_or(Duration::from_millis(500));
        poll.poll(&mut events, Some(wait))?;
        // Newest wins: take everything waiting, keep the last wrench that passes.
        let mut newest: Option<Vector3<f64>> = None;
        loop {
            match servo_cf.take() {
                Ok(Some((msg, _))) => {
                    let now = Instant::now();
                    if !owns {
                        if let Some(n) = refused[3].allow(now) {
                            warn!("servo_cf refused: another client owns the force{}", more(n));
                        }
                        continue;
                    }
                    match logic::wrench_offset(&msg, frame_id, max_force) {
                        Ok(f) => newest = Some(f),
                        Err(r) => {
                            if let Some(n) = refused[r.kind()].allow(now) {
                                warn!("{r}{}", more(n));
                            }
                        }
                    }
                }
                Ok(None) => break,
                Err(e) => {
                    if let Some(n) = refused[1].allow(Instant::now()) {
                        warn!("servo_cf: a message that does not decode: {e:?}{}", more(n));
                    }
                }
            }
        }
        let now = Instant::now();
        let send = match newest {
            Some(f) => Some(hold.received(f, now)),
            None => hold.due(now),
        };
        let force = match send {
            None => continue,
            Some(Send::Offset(f)) => f,
            Some(Send::Release) => {
                if released_log.allow(now).is_some() {
                    info!(
                        "servo_cf silent for {} ms: offset released",
                        timeout.as_millis()
                    );
                }
                Vector3::zeros()
            }
        };
        lock(owner)
            .set_force(force)
            .context("cannot send the offset to the daemon")?;
    }
}

fn more(n: u64) -> String {
    if n == 0 {
        String::new()
    } else {
        format!(" ({n} more since the last such line)")
    }
}

/// What operating_state carries, as JSON: the daemon's mode, model and calibration state.
#[derive(Serialize, PartialEq, Clone, Debug)]
struct OperatingState {
    device: String,
    device_id: String,
    /// The compensation applied: none, scalar, vector, arm, arm_residual.
    mode: hgcd::client::Compensating,
    /// The grid file in use (the calibrated model), if any.
    grid: Option<String>,
    held_out_pct: Option<f64>,
    calibrating: bool,
    /// The last calibration event the bridge asked for saw (started, finished, failed …).
    calibration: Option<String>,
    owner: Option<String>,
    /// Whether this bridge owns the force (servo_cf is taken).
    bridge_owns_force: bool,
}

fn operating_state(s: &Status, calibration: &Option<String>, owns: bool) -> OperatingState {
    OperatingState {
        device: s.device.clone(),
        device_id: s.device_id.clone(),
        mode: s.mode,
        grid: s.grid.clone(),
        held_out_pct: s.held_out_pct,
        calibrating: s.calibrating,
        calibration: calibration.clone(),
        owner: s.owner.clone(),
        bridge_owns_force: owns,
    }
}

type RequestId = ros2_client::service::RmwRequestId;

/// The next request waiting for `server`, if any; one that does not decode is logged and
/// skipped.
fn request(
    server: &Server<Trigger>,
    name: &str,
    log: &mut Throttle,
) -> Option<(RequestId, TriggerRequest)> {
    loop {
        match server.receive_request() {
            Ok(request) => {
                if let Some((id, _)) = &request {
                    debug!("{name}: request {id:?}");
                }
                return request;
            }
            Err(e) => {
                if let Some(n) = log.allow(Instant::now()) {
                    warn!("{name}: a request that does not decode: {e:?}{}", more(n));
                }
            }
        }
    }
}

fn daemon_loop(
    owner: &Mutex<Client>,
    publisher: Publisher<StringMsg>,
    calibrate: Server<Trigger>,
    status: Server<Trigger>,
    period: Duration,
    owns: bool,
) -> anyhow::Result<()> {
    let mut last_poll: Option<Instant> = None;
    let mut published: Option<OperatingState> = None;
    let mut calibration_event: Option<String> = None;
    let mut calibrating: Option<RequestId> = None;
    let mut status_waiting: Vec<RequestId> = Vec::new();
    let mut daemon_errors = Throttle::new(LOG_PERIOD);
    let mut bad_requests = Throttle::new(LOG_PERIOD);
    let respond = |server: &Server<Trigger>, id: RequestId, success: bool, message: String| {
        debug!("response to {id:?}: {success}");
        if let Err(e) = server.send_response(id, TriggerResponse { success, message }) {
            warn!("cannot send a service response: {e:?}");
        }
    };
    loop {
        let now = Instant::now();
        // Service requests.
        while let Some((id, _)) = request(&calibrate, "calibrate", &mut bad_requests) {
            if calibrating.is_some() {
                respond(
                    &calibrate,
                    id,
                    false,
                    "a calibration asked through this bridge is running".into(),
                );
            } else if !owns {
                respond(
                    &calibrate,
                    id,
                    false,
                    "another client owns the force: only it may start a calibration".into(),
                );
            } else {
                info!("calibrate: asking the daemon");
                lock(owner).request_calibration()?;
                calibrating = Some(id);
            }
        }
        while let Some((id, _)) = request(&status, "status", &mut bad_requests) {
            if status_waiting.is_empty() {
                lock(owner).request_status()?;
            }
            status_waiting.push(id);
        }
        if last_poll.is_none_or(|t| now.duration_since(t) >= period) {
            last_poll = Some(now);
            lock(owner).request_status()?;
        }
        // Replies.
        loop {
            let reply = lock(owner).next_reply_within(Duration::ZERO);
            let reply = match reply {
                Ok(Some(r)) => r,
                Ok(None) => break,
                Err(ClientError::Refused(m)) => bail!("the daemon closed the connection: {m}"),
                Err(ClientError::Closed) => bail!("the daemon closed the connection"),
                Err(e) => bail!("the daemon's connection: {e}"),
            };
            match reply {
                Reply::Status(s) => {
                    let state = operating_state(&s, &calibration_event, owns);
                    if published.as_ref() != Some(&state) {
                        let data = serde_json::to_string(&state)?;
                        if publisher.publish(StringMsg { data }).is_ok() {
                            published = Some(state);
                        }
                    }
                    let text = serde_json::to_string(&s)?;
                    for id in status_waiting.drain(..) {
                        respond(&status, id, true, text.clone());
                    }
                }
                Reply::Calibration { event, message, .. } => {
                    let name = serde_json::to_value(event)?
                        .as_str()
                        .unwrap_or("?")
                        .to_string();
                    info!("calibration: {name} {message}");
                    calibration_event = Some(name);
                    let done = match event {
                        CalibrationStage::Finished => Some(true),
                        CalibrationStage::Failed => Some(false),
                        _ => None,
                    };
                    if let Some(success) = done {
                        if let Some(id) = calibrating.take() {
                            respond(&calibrate, id, success, message);
                        }
                        lock(owner).request_status()?;
                    }
                }
                Reply::Error { message, .. } => {
                    if let Some(n) = daemon_errors.allow(now) {
                        warn!("the daemon says: {message}{}", more(n));
                    }
                }
                Reply::Welcome { .. }
                | Reply::State(_)
                | Reply::Checked(_)
                | Reply::Reverted(_) => {}
            }
        }
        thread::sleep(Duration::from_millis(5));
    }
}
