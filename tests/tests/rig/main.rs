//! The host against the device's own logic, each side in a thread of its own:
//! the link (host client, protocol, the firmware's `Device` behind the
//! virtual device's pseudo-terminal), the operator procedures on a simulated
//! rig, and the tracker input. One test binary: these are the timing-sensitive
//! tests `scripts/load-test` runs with every core busy.

mod home_epochs;
mod link;
mod operator_collect;
mod operator_init;
mod operator_recalibrate;
mod streaming;
mod tracker;
mod virtual_device;
