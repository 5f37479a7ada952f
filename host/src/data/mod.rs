//! Measured data: sessions, how they are observed, and their error statistic.
//!
//! - [`dataset`]: the one reader and writer of session CSVs and geometry
//!   files, with file/line/column errors;
//! - [`impossible`]: rows no device of a geometry could produce, set aside
//!   by line before a calibration;
//! - [`observe`]: what a tracked row says (the tracker frame, the body's
//!   orientation, the strings' meeting point);
//! - [`stats`]: eq. 7's error statistics, used by every report.

pub mod dataset;
pub mod home;
pub mod impossible;
pub mod observe;
pub mod output;
pub mod stats;
