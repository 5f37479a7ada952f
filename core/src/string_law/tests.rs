//! The string law's tests: the fixed point against f64, the compiled
//! terms, and arbitrary input.

mod accuracy;
mod arbitrary;
mod compile;
mod effects;
mod fixtures;
mod layers;
