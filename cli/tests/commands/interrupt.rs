//! SIGINT (Ctrl-C) and SIGTERM stop the commands that hold a device armed
//! through their cleanup (no force, disarmed), say so, and exit 130 or 143;
//! `monitor` without `--seconds` ends normally on either.
//!
//! Nothing here depends on timing: each command is signalled once it said
//! on standard error that it holds (or collects, or monitors), and runs
//! that cannot end by themselves before the signal (a 10-minute hold, a
//! lattice of 2197 cells, a home tolerance no hand holds). The deadlines
//! only keep a hung command from hanging the test.

use std::io::{BufRead, BufReader, Read};
use std::process::{Child, Command, ExitStatus, Stdio};
use std::sync::mpsc::{channel, Receiver};
use std::time::{Duration, Instant};

use nix::libc;
use spidar::sim::virtual_device::Trajectory;
use spidar_core::correction::CorrectionModel;
use spidar_tests::{blob, patient_virtual_device, sim_device};

/// How long a step may take before the test gives up (a guard, not a wait).
const GUARD: Duration = Duration::from_secs(300);

/// A running `spidar` whose standard error is read line by line.
struct Running {
    child: Child,
    stderr: Receiver<String>,
    /// Standard error so far.
    err: String,
}

impl Running {
    /// Starts `spidar args` (stdout and stderr piped).
    fn start(args: &[&str]) -> Running {
        let mut child = Command::new(env!("CARGO_BIN_EXE_spidar"))
            .args(args)
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .expect("run spidar");
        let (tx, rx) = channel();
        let stderr = child.stderr.take().expect("stderr piped");
        std::thread::spawn(move || {
            for line in BufReader::new(stderr).lines() {
                let Ok(line) = line else { return };
                if tx.send(line).is_err() {
                    return;
                }
            }
        });
        Running {
            child,
            stderr: rx,
            err: String::new(),
        }
    }

    /// Waits for a line of standard error that `is_it` accepts.
    fn wait_for_line(&mut self, is_it: impl Fn(&str) -> bool) {
        let deadline = Instant::now() + GUARD;
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            match self.stderr.recv_timeout(left) {
                Ok(line) => {
                    let found = is_it(&line);
                    self.err.push_str(&line);
                    self.err.push('\n');
                    if found {
                        return;
                    }
                }
                Err(_) => {
                    let _ = self.child.kill();
                    panic!("the expected line never came; stderr:\n{}", self.err);
                }
            }
        }
    }

    /// Sends `signal`, waits for the exit: (status, stdout, stderr).
    fn signal_and_wait(mut self, signal: libc::c_int) -> (ExitStatus, String, String) {
        let pid = libc::pid_t::try_from(self.child.id()).expect("a pid");
        // SAFETY: kill(2) on our own child, which has not been waited for.
        assert_eq!(unsafe { libc::kill(pid, signal) }, 0, "kill");
        let mut stdout = self.child.stdout.take().expect("stdout piped");
        let reader = std::thread::spawn(move || {
            let mut text = String::new();
            let _ = stdout.read_to_string(&mut text);
            text
        });
        let deadline = Instant::now() + GUARD;
        let status = loop {
            if let Some(status) = self.child.try_wait().expect("wait") {
                break status;
            }
            if Instant::now() > deadline {
                let _ = self.child.kill();
                panic!("no exit after the signal; stderr:\n{}", self.err);
            }
            std::thread::sleep(Duration::from_millis(20));
        };
        let out = reader.join().expect("stdout reader");
        // The rest of standard error (its reader ends at the pipe's end).
        while let Ok(line) = self.stderr.recv_timeout(GUARD) {
            self.err.push_str(&line);
            self.err.push('\n');
        }
        (status, out, self.err)
    }
}

/// The two signals and the exit status each gives.
/// Runs `spidar args`, waits for the line `ready` says the run is under
/// way with, then sends `signal`: how the command ended and what it said.
fn interrupted(
    args: &[&str],
    ready: impl Fn(&str) -> bool,
    signal: libc::c_int,
) -> (ExitStatus, String, String) {
    let mut running = Running::start(args);
    running.wait_for_line(ready);
    running.signal_and_wait(signal)
}

/// A file of this process in the temporary folder (`spidar-interrupt-PID-what`).
fn temp_file(what: &str) -> std::path::PathBuf {
    std::env::temp_dir().join(format!("spidar-interrupt-{}-{what}", std::process::id()))
}

const SIGNALS: [(libc::c_int, &str, i32); 2] = [
    (libc::SIGINT, "SIGINT", 130),
    (libc::SIGTERM, "SIGTERM", 143),
];

/// Runs `spidar` to its end with a patient client: (success, stdout, stderr).
fn spidar(args: &[&str]) -> (bool, String, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_spidar"))
        .args(args)
        .args(["--timeout-ms", "5000"])
        .output()
        .expect("run spidar");
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stdout).to_string(),
        String::from_utf8_lossy(&out.stderr).to_string(),
    )
}

/// SIGINT and SIGTERM during `device force --hold` and `device arm --hold`
/// end the hold with no force and the device disarmed (`device info`:
/// motors off, no HEARTBEAT_LOST), say so and exit 130 and 143 (issue:
/// they used to kill the process with the force on; the device then lost
/// the heartbeat and held pre-tension).
#[test]
fn device_holds_end_on_sigint_and_sigterm_disarmed_with_no_force() {
    let dev = sim_device();
    let vd = patient_virtual_device(Trajectory::Hold);
    let port = vd.port_path().to_string();
    // Flashed by `spidar flash`: a port this process held could be
    // inherited by a `spidar` another test starts (see device.rs).
    let model = temp_file("model.blob");
    std::fs::write(&model, blob(&dev, CorrectionModel::None, 0x51)).unwrap();
    let (ok, _, err) = spidar(&["flash", "--port", &port, model.to_str().unwrap()]);
    let _ = std::fs::remove_file(&model);
    assert!(ok, "{err}");
    for (signal, name, code) in SIGNALS {
        let (status, out, err) = interrupted(
            &[
                "device",
                "force",
                "--port",
                &port,
                "--timeout-ms",
                "5000",
                "--hold",
                "600",
                "2",
                "0",
                "0",
            ],
            |l| l.starts_with("holding [2, 0, 0] N for 600.0 s"),
            signal,
        );
        assert_eq!(status.code(), Some(code), "{name}: {out}{err}");
        assert!(out.is_empty(), "{name}: {out}");
        assert!(
            err.contains(&format!("spidar: {port}: requested [2, 0, 0] N; rendered"))
                && err.contains(&format!("interrupted by {name}"))
                && err.contains("the force is off and the device disarmed"),
            "{name}: {err}"
        );
        let (ok, info, err) = spidar(&["device", "info", "--port", &port]);
        assert!(ok, "{err}");
        assert!(
            info.contains("state: disarmed, motors off, faults ")
                && !info.contains("HEARTBEAT_LOST"),
            "after {name}: {info}"
        );

        let (status, out, err) = interrupted(
            &[
                "device",
                "arm",
                "--port",
                &port,
                "--timeout-ms",
                "5000",
                "--hold",
                "600",
            ],
            |l| l.starts_with("armed, holding 600.0 s"),
            signal,
        );
        assert_eq!(status.code(), Some(code), "{name}: {out}{err}");
        assert!(
            err.contains(&format!("spidar: {port}: armed, held "))
                && err.contains(&format!("interrupted by {name}"))
                && err.contains("the device is disarmed, motors off"),
            "{name}: {err}"
        );
        let (ok, info, err) = spidar(&["device", "info", "--port", &port]);
        assert!(ok, "{err}");
        assert!(
            info.contains("state: disarmed, motors off, faults ")
                && !info.contains("HEARTBEAT_LOST"),
            "after {name}: {info}"
        );
    }
}

/// SIGINT and SIGTERM stop `collect` between two frames alike: the
/// motors off, every captured cell on disk, the summary with how to
/// resume, then exit 130 and 143, not the 0 of a completed run (SIGTERM
/// used to end it at once with the motors on; SIGINT exited 0).
#[test]
fn collect_stops_on_sigint_and_sigterm_with_the_motors_off_and_exits_non_zero() {
    for (signal, name, code) in SIGNALS {
        let out_csv = temp_file(&format!("collect-{name}.csv"));
        let _ = std::fs::remove_file(&out_csv);
        // The live view's first line: the device is armed, the run under way.
        let (status, out, err) = interrupted(
            &[
                "collect",
                "--simulate",
                "3",
                "--size-mm",
                "300",
                "--audio",
                "off",
                "--out",
                out_csv.to_str().unwrap(),
            ],
            |l| l.starts_with("cell "),
            signal,
        );
        let _ = std::fs::remove_file(&out_csv);
        assert_eq!(status.code(), Some(code), "{name}: {out}{err}");
        assert!(
            out.contains(
                "interrupted; the motors are off and every captured cell is on disk; run the same command again to resume"
            ) && out.contains("/2197 done"),
            "{name}: {out}"
        );
        assert!(
            err.contains(&format!("spidar: collect: interrupted by {name}")),
            "{name}: {err}"
        );
    }
}

/// `init` stopped by a signal before home is declared: the force off, the
/// device disarmed, nothing written, exit 130 or 143 (a tolerance of a
/// micrometre: the simulated hand never holds it).
#[test]
fn init_stops_on_sigint_and_sigterm_before_home_and_writes_nothing() {
    for (signal, name, code) in SIGNALS {
        let record = temp_file(&format!("init-{name}.toml"));
        let _ = std::fs::remove_file(&record);
        // The live view's first line: guidance under way.
        let (status, out, err) = interrupted(
            &[
                "init",
                "--simulate",
                "3",
                "--audio",
                "off",
                "--tolerance-mm",
                "0.001",
                "--timeout-s",
                "3000",
                "--out",
                record.to_str().unwrap(),
            ],
            |l| l.contains("beep "),
            signal,
        );
        assert_eq!(status.code(), Some(code), "{name}: {out}{err}");
        assert!(
            err.contains(&format!("spidar: init: interrupted by {name}"))
                && err.contains("the force is off and the device disarmed"),
            "{name}: {err}"
        );
        assert!(!record.exists(), "{name}: {} written", record.display());
    }
}

/// `monitor` runs until interrupted: without `--seconds` SIGINT or SIGTERM
/// is its normal end (the summary, exit 0); with `--seconds` they cut the
/// run short (the summary, then exit 130 or 143). It used to exit 130 on
/// SIGINT with no summary at all.
#[test]
fn monitor_prints_its_summary_on_sigint_and_sigterm() {
    for (signal, name, code) in SIGNALS {
        for seconds in [None, Some("3000")] {
            let mut args = vec!["monitor", "--simulate", "5", "--refit", "no"];
            args.extend(seconds.map(|s| ["--seconds", s]).into_iter().flatten());
            let (status, out, err) = interrupted(&args, |l| l.starts_with("monitoring "), signal);
            let what = format!("{name}, --seconds {seconds:?}");
            assert!(
                out.contains("monitored ") && out.contains(" tracker frames"),
                "{what}: {out}{err}"
            );
            match seconds {
                None => {
                    assert_eq!(status.code(), Some(0), "{what}: {out}{err}");
                    assert!(err.contains(&format!("stopped by {name}")), "{what}: {err}");
                }
                Some(_) => {
                    assert_eq!(status.code(), Some(code), "{what}: {out}{err}");
                    assert!(
                        err.contains(&format!("spidar: monitor: interrupted by {name}"))
                            && err.contains("before --seconds was up"),
                        "{what}: {err}"
                    );
                }
            }
        }
    }
}
