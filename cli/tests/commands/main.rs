//! The `spidar` binary as a user runs it: calibrate (simulated and measured
//! sessions), demo, the report page in a browser, the device commands, help
//! texts and error messages, and what SIGINT and SIGTERM do to the
//! commands that hold a device.

mod bad_rows;
mod calibrate;
mod collect;
mod compile;
mod device;
mod help;
mod interrupt;
mod real_data;
mod report_page;
