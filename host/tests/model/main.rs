//! The host library's model side on recorded and simulated sessions: the
//! dataset reader, the identification, the learned corrections, the loop
//! that finds effects (on both simulators), devices of 3 to 8 strings. One
//! test binary (issue 14, point 7: a few links, not twelve).

mod dataset;
mod identify;
mod learn;
mod loop_closing;
mod n_strings;
mod sim;
mod sim_physics;
