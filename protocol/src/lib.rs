//! The wire protocol between a SPIDAR controller and its host, and the header
//! of the calibration-model blob it carries.
//!
//! `no_std`, no allocation. Decoding arbitrary bytes never panics.
#![cfg_attr(not(test), no_std)]
#![forbid(unsafe_code)]

pub mod blob;
