use super::*;

const CONFIG: SafetyConfig = SafetyConfig {
    t_min: 0.5,
    t_max: 20.0,
    f_max: 10.0,
    pretension_n: 1.0,
    heartbeat_timeout_ms: 100,
    slack_threshold_mm: 5.0,
};

const LENGTHS: [f32; STRINGS] = [1000.0; STRINGS];

fn armed_monitor() -> SafetyMonitor {
    let mut m = SafetyMonitor::new(CONFIG).unwrap();
    m.heartbeat(0);
    m.arm().unwrap();
    m
}

#[test]
fn inactive_channels_are_not_checked_and_get_no_tension() {
    let mut m = armed_monitor();
    m.set_active(0b0000_1111);
    // Channels 4..8: NaN and "slack" lengths are not read.
    let mut measured = LENGTHS;
    measured[5] = f32::NAN;
    measured[6] = 2000.0;
    assert_eq!(m.check(10, &measured, &LENGTHS, true), SafetyFaults::NONE);
    let mut t = [3.0; STRINGS];
    t[7] = f32::NAN;
    let out = m.apply(t);
    assert_eq!(out, [3.0, 3.0, 3.0, 3.0, 0.0, 0.0, 0.0, 0.0]);
    assert!(m.is_armed());
    // Disarmed: pre-tension on the strings, 0 elsewhere.
    m.disarm();
    assert_eq!(m.apply(t), [1.0, 1.0, 1.0, 1.0, 0.0, 0.0, 0.0, 0.0]);
    // A slack active string is still seen.
    measured[2] = 1010.0;
    assert_eq!(m.check(20, &measured, &LENGTHS, true), SafetyFaults::SLACK);
    assert_eq!(m.slack_mask(), 0b100);
}

#[test]
fn heartbeat_timeout_latches_until_clear() {
    let mut m = armed_monitor();
    let t = [5.0; STRINGS];
    assert_eq!(m.check(50, &LENGTHS, &LENGTHS, true), SafetyFaults::NONE);
    assert_eq!(m.apply(t), t);
    m.heartbeat(90);
    assert_eq!(m.check(190, &LENGTHS, &LENGTHS, true), SafetyFaults::NONE); // exactly the timeout
    assert_eq!(
        m.check(191, &LENGTHS, &LENGTHS, true),
        SafetyFaults::HEARTBEAT_LOST
    );
    assert!(!m.is_armed());
    assert_eq!(m.apply(t), [CONFIG.pretension_n; STRINGS]);
    // Heartbeats resume: still latched, still pre-tension only.
    m.heartbeat(200);
    assert_eq!(
        m.check(210, &LENGTHS, &LENGTHS, true),
        SafetyFaults::HEARTBEAT_LOST
    );
    assert_eq!(m.apply(t), [CONFIG.pretension_n; STRINGS]);
    assert_eq!(m.arm(), Err(SafetyFaults::HEARTBEAT_LOST));
    // The host's arm command: clear, then arm.
    assert_eq!(m.clear(), SafetyFaults::NONE);
    assert_eq!(m.apply(t), [CONFIG.pretension_n; STRINGS]); // cleared but not armed
    m.arm().unwrap();
    assert_eq!(m.check(220, &LENGTHS, &LENGTHS, true), SafetyFaults::NONE);
    assert_eq!(m.apply(t), t);
}

#[test]
fn heartbeat_age_wraps_with_the_clock() {
    let mut m = SafetyMonitor::new(CONFIG).unwrap();
    m.heartbeat(u32::MAX - 10);
    m.arm().unwrap();
    assert_eq!(m.check(20, &LENGTHS, &LENGTHS, true), SafetyFaults::NONE); // 31 ms later
    assert_eq!(m.check(89, &LENGTHS, &LENGTHS, true), SafetyFaults::NONE); // 100 ms later
    assert_eq!(
        m.check(90, &LENGTHS, &LENGTHS, true),
        SafetyFaults::HEARTBEAT_LOST
    ); // 101 ms
}

#[test]
fn arming_needs_a_heartbeat() {
    let mut m = SafetyMonitor::new(CONFIG).unwrap();
    assert_eq!(m.arm(), Err(SafetyFaults::HEARTBEAT_LOST));
    // Disarmed and never heard from the host: idle, no fault.
    assert_eq!(
        m.check(10_000, &LENGTHS, &LENGTHS, true),
        SafetyFaults::NONE
    );
    assert_eq!(m.apply([5.0; STRINGS]), [CONFIG.pretension_n; STRINGS]);
}

#[test]
fn slack_is_detected_on_the_right_string() {
    let mut m = armed_monitor();
    let mut measured = LENGTHS;
    measured[5] = 1006.0; // 6 mm longer than geometric: slack
    measured[3] = 1004.0; // 4 mm: within threshold
    measured[1] = 980.0; // shorter (stretched estimate): not slack
    assert_eq!(m.check(10, &measured, &LENGTHS, true), SafetyFaults::SLACK);
    assert_eq!(m.slack_mask(), 0b0010_0000);
    assert_eq!(m.apply([5.0; STRINGS]), [CONFIG.pretension_n; STRINGS]);
    // Taut again: still latched, mask kept.
    assert_eq!(m.check(20, &LENGTHS, &LENGTHS, true), SafetyFaults::SLACK);
    assert_eq!(m.slack_mask(), 0b0010_0000);
    m.clear();
    assert_eq!(m.slack_mask(), 0);
    // Without a consistent position the slack test is skipped; FK_FAULT latches.
    assert_eq!(
        m.check(30, &measured, &LENGTHS, false),
        SafetyFaults::FK_FAULT
    );
    assert_eq!(m.slack_mask(), 0);
}

#[test]
fn tensions_and_force_are_clamped() {
    let mut m = armed_monitor();
    let t = [-1.0, 0.1, 0.5, 10.0, 20.0, 25.0, 1e9, 3.0];
    assert_eq!(m.apply(t), [0.5, 0.5, 0.5, 10.0, 20.0, 20.0, 20.0, 3.0]);
    // |(30, 40, 0)| = 50 N > 10 N: scaled to (6, 8, 0).
    let f = m.limit_force([30.0, 40.0, 0.0]);
    assert!((f[0] - 6.0).abs() < 1e-6 && (f[1] - 8.0).abs() < 1e-6 && f[2] == 0.0);
    assert!(m.warnings().contains(SafetyFaults::OVERFORCE));
    assert!(m.faults().is_empty() && m.is_armed()); // a warning, not a fault
    assert_eq!(m.limit_force([1.0, -2.0, 2.0]), [1.0, -2.0, 2.0]);
    assert!(m.warnings().is_empty());
    assert_eq!(m.limit_force([0.0; 3]), [0.0; 3]);
    let f = m.limit_force([f32::MAX, f32::MAX, 0.0]);
    assert!(f.iter().all(|x| x.is_finite()));
    assert!((f[0] - 10.0 / 2.0f32.sqrt()).abs() < 1e-5);
}

#[test]
fn nan_gives_pretension_and_latches() {
    let mut m = armed_monitor();
    let mut t = [5.0; STRINGS];
    t[2] = f32::NAN;
    assert_eq!(m.apply(t), [CONFIG.pretension_n; STRINGS]);
    assert_eq!(m.faults(), SafetyFaults::NON_FINITE);
    assert_eq!(m.apply([5.0; STRINGS]), [CONFIG.pretension_n; STRINGS]);
    m.clear();
    m.arm().unwrap();
    assert_eq!(m.limit_force([f32::NAN, 0.0, 0.0]), [0.0; 3]);
    assert_eq!(m.faults(), SafetyFaults::NON_FINITE);
    m.clear();
    m.arm().unwrap();
    let mut measured = LENGTHS;
    measured[7] = f32::INFINITY;
    assert_eq!(
        m.check(10, &measured, &LENGTHS, true),
        SafetyFaults::NON_FINITE
    );
    assert_eq!(m.slack_mask(), 0);
}

#[test]
fn estop_and_model_survive_clear_while_active() {
    let mut m = armed_monitor();
    m.set_estop(true);
    assert!(!m.is_armed());
    assert_eq!(m.clear(), SafetyFaults::ESTOP);
    assert_eq!(m.arm(), Err(SafetyFaults::ESTOP));
    m.set_estop(false);
    assert_eq!(m.faults(), SafetyFaults::ESTOP); // still latched
    assert_eq!(m.clear(), SafetyFaults::NONE);
    m.set_model_valid(false);
    assert_eq!(m.clear(), SafetyFaults::MODEL_INVALID);
    assert_eq!(
        m.check(10, &LENGTHS, &LENGTHS, true),
        SafetyFaults::MODEL_INVALID
    );
    m.set_model_valid(true);
    assert_eq!(m.clear(), SafetyFaults::NONE);
    m.arm().unwrap();
    assert!(m.is_armed());
    m.disarm();
    assert_eq!(m.apply([5.0; STRINGS]), [CONFIG.pretension_n; STRINGS]);
}

#[test]
fn faults_bit_set() {
    let mut f = SafetyFaults::SLACK | SafetyFaults::ESTOP;
    assert!(
        f.contains(SafetyFaults::SLACK)
            && f.intersects(SafetyFaults::ESTOP | SafetyFaults::FK_FAULT)
    );
    assert!(!f.contains(SafetyFaults::SLACK | SafetyFaults::FK_FAULT));
    f.remove(SafetyFaults::SLACK);
    assert_eq!(f, SafetyFaults::ESTOP);
    f |= SafetyFaults::NON_FINITE;
    assert_eq!(f.bits(), (1 << 7) | (1 << 11));
    assert_eq!(SafetyFaults::from_bits_truncate(0xffff), SafetyFaults::ALL);
}

#[test]
fn invalid_config_is_rejected() {
    let bad = |f: fn(&mut SafetyConfig)| {
        let mut c = CONFIG;
        f(&mut c);
        SafetyMonitor::new(c).err()
    };
    assert_eq!(
        bad(|c| c.t_max = f32::NAN),
        Some(SafetyConfigError::NonFinite)
    );
    assert_eq!(
        bad(|c| c.t_min = 30.0),
        Some(SafetyConfigError::TensionLimits)
    );
    assert_eq!(bad(|c| c.f_max = -1.0), Some(SafetyConfigError::ForceLimit));
    assert_eq!(
        bad(|c| c.pretension_n = 25.0),
        Some(SafetyConfigError::Pretension)
    );
    assert_eq!(
        bad(|c| c.heartbeat_timeout_ms = 0),
        Some(SafetyConfigError::HeartbeatTimeout)
    );
    assert_eq!(
        bad(|c| c.slack_threshold_mm = -1.0),
        Some(SafetyConfigError::SlackThreshold)
    );
    assert_eq!(bad(|_| ()), None);
}

/// A host that sent a command and went away leaves a disarmed device
/// without a fault (the wire's `HEARTBEAT_LOST` is "no request while
/// armed": a flash, then `info` 3 s later, showed it on a device never
/// armed); armed, the same silence latches it.
#[test]
fn a_silent_host_is_a_fault_only_while_armed() {
    let mut m = SafetyMonitor::new(CONFIG).unwrap();
    m.heartbeat(10);
    assert_eq!(m.check(5_000, &LENGTHS, &LENGTHS, true), SafetyFaults::NONE);
    m.heartbeat(5_000);
    m.arm().unwrap();
    assert_eq!(m.check(5_100, &LENGTHS, &LENGTHS, true), SafetyFaults::NONE);
    assert_eq!(
        m.check(5_101, &LENGTHS, &LENGTHS, true),
        SafetyFaults::HEARTBEAT_LOST
    );
    assert!(!m.is_armed());
}
