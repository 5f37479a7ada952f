//! Tracker input: DTrack2/DTrack3 datagrams (real-format examples, ts2,
//! hybrid bodies, the SDK's tolerance, skipped records, typed errors,
//! arbitrary bytes), the UDP receiver over loopback (loss, duplicates,
//! reordering, occlusion, bad datagrams, midnight, restarts), the CSV replay
//! of the shared example session, and the time-shift estimate. Every socket
//! is on 127.0.0.1; every loop is bounded.

mod dtrack_output;
mod fixtures;
mod parsing;
mod receiver;
mod replay;
mod time_shift;
