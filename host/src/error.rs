//! The one error for a setting out of range, shared by the modules' error
//! enums (each wraps it as its `Config` variant, with its own prefix).

use std::borrow::Cow;

/// A setting that cannot be used: which one, and why.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
#[error("`{field}`: {problem}")]
pub struct ConfigError {
    /// The setting, as the user wrote it (a TOML key, a field, a flag).
    pub field: Cow<'static, str>,
    /// What is wrong with its value.
    pub problem: String,
}

impl ConfigError {
    pub fn new(field: impl Into<Cow<'static, str>>, problem: impl Into<String>) -> ConfigError {
        ConfigError {
            field: field.into(),
            problem: problem.into(),
        }
    }
}
