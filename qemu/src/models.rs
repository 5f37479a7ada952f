//! Host only (`build.rs`): the deterministic calibration models whose compiled
//! blobs the device binaries embed: one with an NN 3-20-3 correction, one with
//! an SVR correction of 1,000 support vectors (the benchmark sizes).
//!
//! Empty until `spidar_core::blob::compile` lands on main.

/// The compiled blob with the NN 3-20-3 correction (empty: not yet available).
pub fn nn_blob() -> Vec<u8> {
    Vec::new()
}

/// The compiled blob with the 1,000-SV SVR correction (empty: not yet available).
pub fn svr_blob() -> Vec<u8> {
    Vec::new()
}
