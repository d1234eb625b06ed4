# Print an optspec for argparse to handle cmd's options that are independent of any subcommand.
function __fish_hgcd_global_optspecs
    string join \n config= state-dir= socket= profile= log-level= h/help V/version
end

function __fish_hgcd_needs_command
    # Figure out if the current invocation already has a command.
    set -l cmd (commandline -opc)
    set -e cmd[1]
    argparse -s (__fish_hgcd_global_optspecs) -- $cmd 2>/dev/null
    or return
    if set -q argv[1]
        # Also print the command, so this can be used to figure out what it is.
        echo $argv[1]
        return 1
    end
    return 0
end

function __fish_hgcd_using_subcommand
    set -l cmd (__fish_hgcd_needs_command)
    test -z "$cmd"
    and return 1
    contains -- $cmd[1] $argv
end

complete -c hgcd -n "__fish_hgcd_needs_command" -l config -d 'Configuration file (default: /etc/hgcd/hgcd.toml if it exists, else built-in defaults)' -r -F
complete -c hgcd -n "__fish_hgcd_needs_command" -l state-dir -d 'Directory of calibration grids (default: config `paths.state_dir`, $STATE_DIRECTORY, /var/lib/hgcd if this user may write there, else ~/.local/state/hgcd)' -r -F
complete -c hgcd -n "__fish_hgcd_needs_command" -l socket -d 'Application socket of the daemon (default: config `app.socket`, else the device\'s own, <device-id>.sock in $RUNTIME_DIRECTORY or /run/hgcd, which `status` and `calibrate --via-daemon` find by --device)' -r -F
complete -c hgcd -n "__fish_hgcd_needs_command" -l profile -d 'Device profile: a built-in name (cartesian-v1, woodenhaptics_v2015, polhem_v1), a user profile\'s name or a profile file (default: config `device.profile`, else chosen by the device; docs/devices.md)' -r
complete -c hgcd -n "__fish_hgcd_needs_command" -l log-level -d 'Log level: error, warn, info, debug or trace (RUST_LOG overrides)' -r
complete -c hgcd -n "__fish_hgcd_needs_command" -s h -l help -d 'Print help'
complete -c hgcd -n "__fish_hgcd_needs_command" -s V -l version -d 'Print version'
complete -c hgcd -n "__fish_hgcd_needs_command" -f -a "run" -d 'Run the servo loop on a device until Ctrl-C/SIGTERM or for --duration seconds'
complete -c hgcd -n "__fish_hgcd_needs_command" -f -a "calibrate" -d 'Run the off-line autocalibration (paper Algorithm 1) and save the mass grid'
complete -c hgcd -n "__fish_hgcd_needs_command" -f -a "validate" -d 'The paper\'s validation experiment (Section 5, Fig. 2): a probe mass on a virtual surface at 27 points, without and with compensation; writes a table, CSV, summary.json and figure'
complete -c hgcd -n "__fish_hgcd_needs_command" -f -a "record" -d 'Log an identification run: compensation on, a PD law tracking slow and fast multisines and holds inside the calibrated grid (docs/discrepancy.md). Ctrl-C ends it early with a valid, shorter log'
complete -c hgcd -n "__fish_hgcd_needs_command" -f -a "analyze" -d 'Compare a measured log with a calibrated grid: where they disagree, which physical effect the model misses (or none), and how much adding it shrinks the gap on held-out data'
complete -c hgcd -n "__fish_hgcd_needs_command" -f -a "check" -d 'Is the saved gravity model still right? Two short friction-robust holds compared with it: unchanged (exit 0), a payload and/or a base tilt it can take in (exit 4), or something else: recalibrate (exit 5) (docs/calibration.md §2)'
complete -c hgcd -n "__fish_hgcd_needs_command" -f -a "status" -d 'Show the running daemons\' state: device, grid, mode, clients, loop timing'
complete -c hgcd -n "__fish_hgcd_needs_command" -f -a "sim-device" -d 'Serve the simulated device (config [sim]) on a Unix socket, for `--device socket:PATH`: the device side of the socket transport, as an external simulator or bridge would be. Serves one host after another until Ctrl-C/SIGTERM; each connection is a power-on'
complete -c hgcd -n "__fish_hgcd_needs_command" -f -a "devices" -d 'List the HID devices hgcd can see, with the spec that opens each'
complete -c hgcd -n "__fish_hgcd_needs_command" -f -a "help" -d 'Print this message or the help of the given subcommand(s)'
complete -c hgcd -n "__fish_hgcd_using_subcommand run" -l device -d 'Device: hid:VID:PID[:SERIAL], sim:MODEL or socket:PATH (default: config `device.spec`)' -r
complete -c hgcd -n "__fish_hgcd_using_subcommand run" -l duration -d 'Stop after this many seconds: of device time where the device sets the pace (--virtual-time, or a socket device in lock-step), of wall-clock time otherwise' -r
complete -c hgcd -n "__fish_hgcd_using_subcommand run" -l config -d 'Configuration file (default: /etc/hgcd/hgcd.toml if it exists, else built-in defaults)' -r -F
complete -c hgcd -n "__fish_hgcd_using_subcommand run" -l state-dir -d 'Directory of calibration grids (default: config `paths.state_dir`, $STATE_DIRECTORY, /var/lib/hgcd if this user may write there, else ~/.local/state/hgcd)' -r -F
complete -c hgcd -n "__fish_hgcd_using_subcommand run" -l socket -d 'Application socket of the daemon (default: config `app.socket`, else the device\'s own, <device-id>.sock in $RUNTIME_DIRECTORY or /run/hgcd, which `status` and `calibrate --via-daemon` find by --device)' -r -F
complete -c hgcd -n "__fish_hgcd_using_subcommand run" -l profile -d 'Device profile: a built-in name (cartesian-v1, woodenhaptics_v2015, polhem_v1), a user profile\'s name or a profile file (default: config `device.profile`, else chosen by the device; docs/devices.md)' -r
complete -c hgcd -n "__fish_hgcd_using_subcommand run" -l log-level -d 'Log level: error, warn, info, debug or trace (RUST_LOG overrides)' -r
complete -c hgcd -n "__fish_hgcd_using_subcommand run" -l virtual-time -d 'Run a simulated device in virtual time (as fast as possible) instead of real time'
complete -c hgcd -n "__fish_hgcd_using_subcommand run" -s h -l help -d 'Print help'
complete -c hgcd -n "__fish_hgcd_using_subcommand calibrate" -l device -d 'Device: hid:VID:PID[:SERIAL], sim:MODEL or socket:PATH (default: config `device.spec`); with --via-daemon, which daemon (a device id or spec; default: the only one running)' -r
complete -c hgcd -n "__fish_hgcd_using_subcommand calibrate" -l output -d 'Write the grid to this file instead of <state-dir>/<device-id>.toml' -r -F
complete -c hgcd -n "__fish_hgcd_using_subcommand calibrate" -l workspace -d '`cube`: the paper\'s grid; `explore`: find the reachable workspace first and calibrate the lattice inside it (default: config `calibration.workspace`; docs/calibration.md §12)' -r
complete -c hgcd -n "__fish_hgcd_using_subcommand calibrate" -l config -d 'Configuration file (default: /etc/hgcd/hgcd.toml if it exists, else built-in defaults)' -r -F
complete -c hgcd -n "__fish_hgcd_using_subcommand calibrate" -l state-dir -d 'Directory of calibration grids (default: config `paths.state_dir`, $STATE_DIRECTORY, /var/lib/hgcd if this user may write there, else ~/.local/state/hgcd)' -r -F
complete -c hgcd -n "__fish_hgcd_using_subcommand calibrate" -l socket -d 'Application socket of the daemon (default: config `app.socket`, else the device\'s own, <device-id>.sock in $RUNTIME_DIRECTORY or /run/hgcd, which `status` and `calibrate --via-daemon` find by --device)' -r -F
complete -c hgcd -n "__fish_hgcd_using_subcommand calibrate" -l profile -d 'Device profile: a built-in name (cartesian-v1, woodenhaptics_v2015, polhem_v1), a user profile\'s name or a profile file (default: config `device.profile`, else chosen by the device; docs/devices.md)' -r
complete -c hgcd -n "__fish_hgcd_using_subcommand calibrate" -l log-level -d 'Log level: error, warn, info, debug or trace (RUST_LOG overrides)' -r
complete -c hgcd -n "__fish_hgcd_using_subcommand calibrate" -l real-time -d 'Run a simulated device in real time (default for simulated devices: virtual time)'
complete -c hgcd -n "__fish_hgcd_using_subcommand calibrate" -l yes -d 'Do not ask for confirmation before starting on a real device'
complete -c hgcd -n "__fish_hgcd_using_subcommand calibrate" -l via-daemon -d 'Ask the running daemon to calibrate its device (it switches to the new grid after)'
complete -c hgcd -n "__fish_hgcd_using_subcommand calibrate" -s h -l help -d 'Print help'
complete -c hgcd -n "__fish_hgcd_using_subcommand validate" -l device -d 'Device: hid:VID:PID[:SERIAL], sim:MODEL or socket:PATH (default: config `device.spec`)' -r
complete -c hgcd -n "__fish_hgcd_using_subcommand validate" -l grid -d 'Compensate with this grid (default: the device\'s stored grid; on a simulated device a fresh calibration, written to DIR/grid.toml)' -r -F
complete -c hgcd -n "__fish_hgcd_using_subcommand validate" -l out -d 'Directory for the results (created if needed)' -r -F
complete -c hgcd -n "__fish_hgcd_using_subcommand validate" -l probe-mass-g -d 'Probe mass m_p, g (on a simulated device it is added to the plant; on hardware attach it)' -r
complete -c hgcd -n "__fish_hgcd_using_subcommand validate" -l stiffness-n-per-mm -d 'Stiffness k of the virtual surface, N/mm' -r
complete -c hgcd -n "__fish_hgcd_using_subcommand validate" -l repetitions -d 'Repetitions per contact point and mode' -r
complete -c hgcd -n "__fish_hgcd_using_subcommand validate" -l modes -d 'Compensation modes to run, in order (comma-separated: none, scalar, vector, arm); default: none, scalar, vector, and arm for a device whose profile has an arm' -r
complete -c hgcd -n "__fish_hgcd_using_subcommand validate" -l sweep -d 'Also compare the grid\'s force with the plant\'s own at N random points of a simulated device\'s reachable workspace; writes DIR/sweep.json (docs/calibration.md §11)' -r
complete -c hgcd -n "__fish_hgcd_using_subcommand validate" -l config -d 'Configuration file (default: /etc/hgcd/hgcd.toml if it exists, else built-in defaults)' -r -F
complete -c hgcd -n "__fish_hgcd_using_subcommand validate" -l state-dir -d 'Directory of calibration grids (default: config `paths.state_dir`, $STATE_DIRECTORY, /var/lib/hgcd if this user may write there, else ~/.local/state/hgcd)' -r -F
complete -c hgcd -n "__fish_hgcd_using_subcommand validate" -l socket -d 'Application socket of the daemon (default: config `app.socket`, else the device\'s own, <device-id>.sock in $RUNTIME_DIRECTORY or /run/hgcd, which `status` and `calibrate --via-daemon` find by --device)' -r -F
complete -c hgcd -n "__fish_hgcd_using_subcommand validate" -l profile -d 'Device profile: a built-in name (cartesian-v1, woodenhaptics_v2015, polhem_v1), a user profile\'s name or a profile file (default: config `device.profile`, else chosen by the device; docs/devices.md)' -r
complete -c hgcd -n "__fish_hgcd_using_subcommand validate" -l log-level -d 'Log level: error, warn, info, debug or trace (RUST_LOG overrides)' -r
complete -c hgcd -n "__fish_hgcd_using_subcommand validate" -l real-time -d 'Run a simulated device in real time (default for simulated devices: virtual time)'
complete -c hgcd -n "__fish_hgcd_using_subcommand validate" -l yes -d 'Do not ask for confirmation before starting on a real device'
complete -c hgcd -n "__fish_hgcd_using_subcommand validate" -s h -l help -d 'Print help'
complete -c hgcd -n "__fish_hgcd_using_subcommand record" -l device -d 'Device: hid:VID:PID[:SERIAL], sim:MODEL or socket:PATH (default: config `device.spec`)' -r
complete -c hgcd -n "__fish_hgcd_using_subcommand record" -l grid -d 'Compensate with this grid (default: the device\'s stored grid)' -r -F
complete -c hgcd -n "__fish_hgcd_using_subcommand record" -l out -d 'The log to write (CSV, docs/log-format.md)' -r -F
complete -c hgcd -n "__fish_hgcd_using_subcommand record" -l duration -d 'Seconds of device time to record' -r
complete -c hgcd -n "__fish_hgcd_using_subcommand record" -l config -d 'Configuration file (default: /etc/hgcd/hgcd.toml if it exists, else built-in defaults)' -r -F
complete -c hgcd -n "__fish_hgcd_using_subcommand record" -l state-dir -d 'Directory of calibration grids (default: config `paths.state_dir`, $STATE_DIRECTORY, /var/lib/hgcd if this user may write there, else ~/.local/state/hgcd)' -r -F
complete -c hgcd -n "__fish_hgcd_using_subcommand record" -l socket -d 'Application socket of the daemon (default: config `app.socket`, else the device\'s own, <device-id>.sock in $RUNTIME_DIRECTORY or /run/hgcd, which `status` and `calibrate --via-daemon` find by --device)' -r -F
complete -c hgcd -n "__fish_hgcd_using_subcommand record" -l profile -d 'Device profile: a built-in name (cartesian-v1, woodenhaptics_v2015, polhem_v1), a user profile\'s name or a profile file (default: config `device.profile`, else chosen by the device; docs/devices.md)' -r
complete -c hgcd -n "__fish_hgcd_using_subcommand record" -l log-level -d 'Log level: error, warn, info, debug or trace (RUST_LOG overrides)' -r
complete -c hgcd -n "__fish_hgcd_using_subcommand record" -l real-time -d 'Run a simulated device in real time (default for simulated devices: virtual time)'
complete -c hgcd -n "__fish_hgcd_using_subcommand record" -l yes -d 'Do not ask for confirmation before starting on a real device'
complete -c hgcd -n "__fish_hgcd_using_subcommand record" -s h -l help -d 'Print help'
complete -c hgcd -n "__fish_hgcd_using_subcommand analyze" -l grid -d 'The calibrated model (hgcd-grid/1)' -r -F
complete -c hgcd -n "__fish_hgcd_using_subcommand analyze" -l log -d 'The measured log (CSV, docs/log-format.md)' -r -F
complete -c hgcd -n "__fish_hgcd_using_subcommand analyze" -l out -d 'Directory for the report (created if needed)' -r -F
complete -c hgcd -n "__fish_hgcd_using_subcommand analyze" -l config -d 'Configuration file (default: /etc/hgcd/hgcd.toml if it exists, else built-in defaults)' -r -F
complete -c hgcd -n "__fish_hgcd_using_subcommand analyze" -l state-dir -d 'Directory of calibration grids (default: config `paths.state_dir`, $STATE_DIRECTORY, /var/lib/hgcd if this user may write there, else ~/.local/state/hgcd)' -r -F
complete -c hgcd -n "__fish_hgcd_using_subcommand analyze" -l socket -d 'Application socket of the daemon (default: config `app.socket`, else the device\'s own, <device-id>.sock in $RUNTIME_DIRECTORY or /run/hgcd, which `status` and `calibrate --via-daemon` find by --device)' -r -F
complete -c hgcd -n "__fish_hgcd_using_subcommand analyze" -l profile -d 'Device profile: a built-in name (cartesian-v1, woodenhaptics_v2015, polhem_v1), a user profile\'s name or a profile file (default: config `device.profile`, else chosen by the device; docs/devices.md)' -r
complete -c hgcd -n "__fish_hgcd_using_subcommand analyze" -l log-level -d 'Log level: error, warn, info, debug or trace (RUST_LOG overrides)' -r
complete -c hgcd -n "__fish_hgcd_using_subcommand analyze" -s h -l help -d 'Print help'
complete -c hgcd -n "__fish_hgcd_using_subcommand check" -l device -d 'Device: hid:VID:PID[:SERIAL], sim:MODEL or socket:PATH (default: config `device.spec`); with --via-daemon, which daemon (a device id or spec; default: the only one running)' -r
complete -c hgcd -n "__fish_hgcd_using_subcommand check" -l grid -d 'Check this grid (default: the device\'s stored grid)' -r -F
complete -c hgcd -n "__fish_hgcd_using_subcommand check" -l config -d 'Configuration file (default: /etc/hgcd/hgcd.toml if it exists, else built-in defaults)' -r -F
complete -c hgcd -n "__fish_hgcd_using_subcommand check" -l state-dir -d 'Directory of calibration grids (default: config `paths.state_dir`, $STATE_DIRECTORY, /var/lib/hgcd if this user may write there, else ~/.local/state/hgcd)' -r -F
complete -c hgcd -n "__fish_hgcd_using_subcommand check" -l socket -d 'Application socket of the daemon (default: config `app.socket`, else the device\'s own, <device-id>.sock in $RUNTIME_DIRECTORY or /run/hgcd, which `status` and `calibrate --via-daemon` find by --device)' -r -F
complete -c hgcd -n "__fish_hgcd_using_subcommand check" -l profile -d 'Device profile: a built-in name (cartesian-v1, woodenhaptics_v2015, polhem_v1), a user profile\'s name or a profile file (default: config `device.profile`, else chosen by the device; docs/devices.md)' -r
complete -c hgcd -n "__fish_hgcd_using_subcommand check" -l log-level -d 'Log level: error, warn, info, debug or trace (RUST_LOG overrides)' -r
complete -c hgcd -n "__fish_hgcd_using_subcommand check" -l real-time -d 'Run a simulated device in real time (default for simulated devices: virtual time)'
complete -c hgcd -n "__fish_hgcd_using_subcommand check" -l yes -d 'Do not ask for confirmation before starting on a real device'
complete -c hgcd -n "__fish_hgcd_using_subcommand check" -l json -d 'Print one JSON object (verdict, payload_g, tilt_deg, tilt_axis, device_time_s, holds)'
complete -c hgcd -n "__fish_hgcd_using_subcommand check" -l apply -d 'Take a payload and tilt found into the grid, keeping the model before as GRID.bak'
complete -c hgcd -n "__fish_hgcd_using_subcommand check" -l revert -d 'Put back the model kept as GRID.bak (before the last --apply or calibration); nothing is measured'
complete -c hgcd -n "__fish_hgcd_using_subcommand check" -l via-daemon -d 'Ask the running daemon to check its device against its grid (with --apply it takes the change in and compensates it at once; with --revert it puts the kept model back and compensates with it); --device then names the daemon'
complete -c hgcd -n "__fish_hgcd_using_subcommand check" -s h -l help -d 'Print help'
complete -c hgcd -n "__fish_hgcd_using_subcommand status" -l device -d 'Only the daemon of this device (a device id or spec; default: every daemon running)' -r
complete -c hgcd -n "__fish_hgcd_using_subcommand status" -l state-dir -d 'Directory of calibration grids (default: config `paths.state_dir`, $STATE_DIRECTORY, /var/lib/hgcd if this user may write there, else ~/.local/state/hgcd)' -r -F
complete -c hgcd -n "__fish_hgcd_using_subcommand status" -l profile -d 'Device profile: a built-in name (cartesian-v1, woodenhaptics_v2015, polhem_v1), a user profile\'s name or a profile file (default: config `device.profile`, else chosen by the device; docs/devices.md)' -r
complete -c hgcd -n "__fish_hgcd_using_subcommand status" -l config -d 'Configuration file (default: /etc/hgcd/hgcd.toml if it exists, else built-in defaults)' -r -F
complete -c hgcd -n "__fish_hgcd_using_subcommand status" -l socket -d 'Application socket of the daemon (default: config `app.socket`, else the device\'s own, <device-id>.sock in $RUNTIME_DIRECTORY or /run/hgcd, which `status` and `calibrate --via-daemon` find by --device)' -r -F
complete -c hgcd -n "__fish_hgcd_using_subcommand status" -l log-level -d 'Log level: error, warn, info, debug or trace (RUST_LOG overrides)' -r
complete -c hgcd -n "__fish_hgcd_using_subcommand status" -s h -l help -d 'Print help'
complete -c hgcd -n "__fish_hgcd_using_subcommand sim-device" -l listen -d 'Socket to listen on' -r -F
complete -c hgcd -n "__fish_hgcd_using_subcommand sim-device" -l model -d 'The simulated model, as in `sim:MODEL` (docs/simulated-devices.md)' -r
complete -c hgcd -n "__fish_hgcd_using_subcommand sim-device" -l state-dir -d 'Directory of calibration grids (default: config `paths.state_dir`, $STATE_DIRECTORY, /var/lib/hgcd if this user may write there, else ~/.local/state/hgcd)' -r -F
complete -c hgcd -n "__fish_hgcd_using_subcommand sim-device" -l socket -d 'Application socket of the daemon (default: config `app.socket`, else the device\'s own, <device-id>.sock in $RUNTIME_DIRECTORY or /run/hgcd, which `status` and `calibrate --via-daemon` find by --device)' -r -F
complete -c hgcd -n "__fish_hgcd_using_subcommand sim-device" -l config -d 'Configuration file (default: /etc/hgcd/hgcd.toml if it exists, else built-in defaults)' -r -F
complete -c hgcd -n "__fish_hgcd_using_subcommand sim-device" -l profile -d 'Device profile: a built-in name (cartesian-v1, woodenhaptics_v2015, polhem_v1), a user profile\'s name or a profile file (default: config `device.profile`, else chosen by the device; docs/devices.md)' -r
complete -c hgcd -n "__fish_hgcd_using_subcommand sim-device" -l log-level -d 'Log level: error, warn, info, debug or trace (RUST_LOG overrides)' -r
complete -c hgcd -n "__fish_hgcd_using_subcommand sim-device" -l lockstep -d 'Wait for the host\'s output report after each input report (deterministic, as fast as both sides allow) instead of reporting in real time'
complete -c hgcd -n "__fish_hgcd_using_subcommand sim-device" -s h -l help -d 'Print help'
complete -c hgcd -n "__fish_hgcd_using_subcommand devices" -l state-dir -d 'Directory of calibration grids (default: config `paths.state_dir`, $STATE_DIRECTORY, /var/lib/hgcd if this user may write there, else ~/.local/state/hgcd)' -r -F
complete -c hgcd -n "__fish_hgcd_using_subcommand devices" -l socket -d 'Application socket of the daemon (default: config `app.socket`, else the device\'s own, <device-id>.sock in $RUNTIME_DIRECTORY or /run/hgcd, which `status` and `calibrate --via-daemon` find by --device)' -r -F
complete -c hgcd -n "__fish_hgcd_using_subcommand devices" -l config -d 'Configuration file (default: /etc/hgcd/hgcd.toml if it exists, else built-in defaults)' -r -F
complete -c hgcd -n "__fish_hgcd_using_subcommand devices" -l profile -d 'Device profile: a built-in name (cartesian-v1, woodenhaptics_v2015, polhem_v1), a user profile\'s name or a profile file (default: config `device.profile`, else chosen by the device; docs/devices.md)' -r
complete -c hgcd -n "__fish_hgcd_using_subcommand devices" -l log-level -d 'Log level: error, warn, info, debug or trace (RUST_LOG overrides)' -r
complete -c hgcd -n "__fish_hgcd_using_subcommand devices" -s h -l help -d 'Print help'
complete -c hgcd -n "__fish_hgcd_using_subcommand help; and not __fish_seen_subcommand_from run calibrate validate record analyze check status sim-device devices help" -f -a "run" -d 'Run the servo loop on a device until Ctrl-C/SIGTERM or for --duration seconds'
complete -c hgcd -n "__fish_hgcd_using_subcommand help; and not __fish_seen_subcommand_from run calibrate validate record analyze check status sim-device devices help" -f -a "calibrate" -d 'Run the off-line autocalibration (paper Algorithm 1) and save the mass grid'
complete -c hgcd -n "__fish_hgcd_using_subcommand help; and not __fish_seen_subcommand_from run calibrate validate record analyze check status sim-device devices help" -f -a "validate" -d 'The paper\'s validation experiment (Section 5, Fig. 2): a probe mass on a virtual surface at 27 points, without and with compensation; writes a table, CSV, summary.json and figure'
complete -c hgcd -n "__fish_hgcd_using_subcommand help; and not __fish_seen_subcommand_from run calibrate validate record analyze check status sim-device devices help" -f -a "record" -d 'Log an identification run: compensation on, a PD law tracking slow and fast multisines and holds inside the calibrated grid (docs/discrepancy.md). Ctrl-C ends it early with a valid, shorter log'
complete -c hgcd -n "__fish_hgcd_using_subcommand help; and not __fish_seen_subcommand_from run calibrate validate record analyze check status sim-device devices help" -f -a "analyze" -d 'Compare a measured log with a calibrated grid: where they disagree, which physical effect the model misses (or none), and how much adding it shrinks the gap on held-out data'
complete -c hgcd -n "__fish_hgcd_using_subcommand help; and not __fish_seen_subcommand_from run calibrate validate record analyze check status sim-device devices help" -f -a "check" -d 'Is the saved gravity model still right? Two short friction-robust holds compared with it: unchanged (exit 0), a payload and/or a base tilt it can take in (exit 4), or something else: recalibrate (exit 5) (docs/calibration.md §2)'
complete -c hgcd -n "__fish_hgcd_using_subcommand help; and not __fish_seen_subcommand_from run calibrate validate record analyze check status sim-device devices help" -f -a "status" -d 'Show the running daemons\' state: device, grid, mode, clients, loop timing'
complete -c hgcd -n "__fish_hgcd_using_subcommand help; and not __fish_seen_subcommand_from run calibrate validate record analyze check status sim-device devices help" -f -a "sim-device" -d 'Serve the simulated device (config [sim]) on a Unix socket, for `--device socket:PATH`: the device side of the socket transport, as an external simulator or bridge would be. Serves one host after another until Ctrl-C/SIGTERM; each connection is a power-on'
complete -c hgcd -n "__fish_hgcd_using_subcommand help; and not __fish_seen_subcommand_from run calibrate validate record analyze check status sim-device devices help" -f -a "devices" -d 'List the HID devices hgcd can see, with the spec that opens each'
complete -c hgcd -n "__fish_hgcd_using_subcommand help; and not __fish_seen_subcommand_from run calibrate validate record analyze check status sim-device devices help" -f -a "help" -d 'Print this message or the help of the given subcommand(s)'
