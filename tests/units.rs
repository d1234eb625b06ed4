//! The systemd unit and udev rules: checked with `systemd-analyze` when the machine has it.

use std::process::{Command, Output};

/// `systemd-analyze ARGS UNIT` on the unit as installed, with ExecStart pointing at the binary
/// under test (verify checks that the command exists); `None`, and the test is skipped, where
/// the machine has no systemd-analyze.
fn analyze_unit(args: &[&str]) -> Option<Output> {
    let installed = Command::new("systemd-analyze")
        .arg("--version")
        .output()
        .is_ok_and(|o| o.status.success());
    if !installed {
        eprintln!("systemd-analyze not installed: skipped");
        return None;
    }
    let dir = tempfile::tempdir().unwrap();
    let text = std::fs::read_to_string("systemd/hgcd@.service").unwrap();
    let unit = dir.path().join("hgcd@test.service");
    std::fs::write(
        &unit,
        text.replace("/usr/bin/hgcd", env!("CARGO_BIN_EXE_hgcd")),
    )
    .unwrap();
    Some(
        Command::new("systemd-analyze")
            .args(args)
            .arg(&unit)
            .output()
            .unwrap(),
    )
}

#[test]
fn unit_passes_systemd_analyze_verify() {
    let Some(out) = analyze_unit(&["verify"]) else {
        return;
    };
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{stderr}");
    assert!(
        !stderr.contains("hgcd@test.service"),
        "warnings about the unit: {stderr}"
    );
}

#[test]
fn unit_exposure_is_at_most_0_7() {
    let Some(out) = analyze_unit(&["security", "--offline=true", "--no-pager"]) else {
        return;
    };
    let stdout = String::from_utf8_lossy(&out.stdout);
    let line = stdout
        .lines()
        .find(|l| l.contains("Overall exposure level"))
        .unwrap_or_else(|| panic!("no exposure line: {stdout}"));
    let score: f64 = line
        .split(':')
        .nth(1)
        .and_then(|r| r.split_whitespace().next())
        .and_then(|n| n.parse().ok())
        .unwrap_or_else(|| panic!("unparsable: {line}"));
    assert!(score <= 0.7, "{line}");
}

#[test]
fn the_instance_name_reaches_hgcd_unescaped() {
    // %I would unescape "-" to "/" and turn sim:point-mass into sim:point/mass.
    let unit = std::fs::read_to_string("systemd/hgcd@.service").unwrap();
    let exec = unit.lines().find(|l| l.starts_with("ExecStart=")).unwrap();
    assert_eq!(exec, "ExecStart=/usr/bin/hgcd run --device %i");
    for instance in ["sim:point-mass", "hid:1209:4847"] {
        assert!(instance.parse::<hgcd::config::DeviceSpec>().is_ok());
    }
}

#[test]
fn udev_rule_grants_group_access_and_starts_the_unit() {
    let rules = std::fs::read_to_string("udev/70-hgcd.rules").unwrap();
    let rule = rules
        .lines()
        .find(|l| l.starts_with("SUBSYSTEM==\"hidraw\""))
        .expect("a hidraw rule");
    for needle in [
        "GROUP=\"hgcd\"",
        "MODE=\"0660\"",
        "TAG+=\"uaccess\"",
        "TAG+=\"systemd\"",
        "ENV{SYSTEMD_WANTS}+=\"hgcd@hid:1209:4847:$attr{serial}.service\"",
    ] {
        assert!(rule.contains(needle), "missing {needle}");
    }
    // Every device a built-in profile claims by its USB IDs has a rule of the same shape.
    for profile in hgcd::profile::Profile::built_ins() {
        for (vid, pid) in &profile.usb_ids {
            let ids =
                format!("ATTRS{{idVendor}}==\"{vid:04x}\", ATTRS{{idProduct}}==\"{pid:04x}\"");
            let rule = rules
                .lines()
                .find(|l| l.starts_with("SUBSYSTEM==\"hidraw\"") && l.contains(&ids))
                .unwrap_or_else(|| panic!("no rule for {} ({ids})", profile.name));
            let wants = format!(
                "ENV{{SYSTEMD_WANTS}}+=\"hgcd@hid:{vid:04x}:{pid:04x}:$attr{{serial}}.service\""
            );
            for needle in ["GROUP=\"hgcd\"", "MODE=\"0660\"", &wants] {
                assert!(rule.contains(needle), "{}: missing {needle}", profile.name);
            }
        }
    }
    // The instance name is a device spec hgcd accepts, with the USB serial number or without.
    let spec: hgcd::config::DeviceSpec = "hid:1209:4847:SN0042".parse().unwrap();
    assert_eq!(spec.device_id(), "hid-1209-4847-SN0042");
    let spec: hgcd::config::DeviceSpec = "hid:1209:4847:".parse().unwrap();
    assert_eq!(spec, "hid:1209:4847".parse().unwrap());
}

#[test]
fn instances_share_a_runtime_directory_none_of_them_removes() {
    // systemd removes a unit's RuntimeDirectory= when it stops, even when other units use it;
    // each instance removes only its own socket.
    let unit = std::fs::read_to_string("systemd/hgcd@.service").unwrap();
    let lines: Vec<&str> = unit.lines().collect();
    assert!(lines.contains(&"RuntimeDirectory=hgcd"), "{unit}");
    assert!(lines.contains(&"RuntimeDirectoryPreserve=yes"), "{unit}");
    let exec = lines.iter().find(|l| l.starts_with("ExecStart=")).unwrap();
    assert!(
        !exec.contains("--socket"),
        "the socket is derived per device: {exec}"
    );
}
