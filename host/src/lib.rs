//! Host side of the SPIDAR stack: datasets, simulation, identification,
//! learned corrections, diagnosis, reports, and the device link.

pub mod calibrate;
pub mod compile;
pub mod dataset;
pub mod device_run;
pub mod diagnose;
pub mod figures;
pub mod identify;
pub mod layers;
pub mod learn;
pub mod link;
pub mod observe;
pub mod operator;
pub mod predict;
pub mod sim;
pub mod stats;
pub mod tracker;
pub mod virtual_device;
