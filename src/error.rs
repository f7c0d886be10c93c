//! One error type for the crate. Every variant that comes from input data carries where it happened
//! (file and line or byte offset) so that a user can find the bad spot.

use std::fmt;

#[derive(Debug)]
pub enum Error {
    /// An operating-system I/O failure on `path`.
    Io { path: String, source: std::io::Error },
    /// Malformed input: `location` is e.g. "line 17" or "byte offset 4096".
    Format { path: String, location: String, message: String },
    /// A request that cannot be satisfied (bad argument, impossible window size, ...).
    Invalid(String),
}

pub type Result<T> = std::result::Result<T, Error>;

impl Error {
    pub fn format(path: impl Into<String>, location: impl Into<String>, message: impl Into<String>) -> Self {
        Error::Format { path: path.into(), location: location.into(), message: message.into() }
    }

    pub fn io(path: impl Into<String>, source: std::io::Error) -> Self {
        Error::Io { path: path.into(), source }
    }
}

impl fmt::Display for Error {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Error::Io { path, source } => write!(f, "{path}: {source}"),
            Error::Format { path, location, message } => write!(f, "{path}: {location}: {message}"),
            Error::Invalid(message) => f.write_str(message),
        }
    }
}

impl std::error::Error for Error {
    fn source(&self) -> Option<&(dyn std::error::Error + 'static)> {
        match self {
            Error::Io { source, .. } => Some(source),
            _ => None,
        }
    }
}
