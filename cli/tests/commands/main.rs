//! The `spidar` binary as a user runs it: calibrate (simulated and measured
//! sessions), demo, the report page in a browser, the device commands, help
//! texts and error messages.

mod bad_rows;
mod calibrate;
mod collect;
mod compile;
mod device;
mod help;
mod real_data;
mod report_page;
