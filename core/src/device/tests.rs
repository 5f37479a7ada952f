//! The device's tests, one module for each thing they test; `bench` is the
//! host most of them drive the device through.

mod bench;
mod home;
mod layouts;
mod models;
mod safety;
mod session;
mod stress;
