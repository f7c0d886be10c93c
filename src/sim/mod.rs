//! Event simulation (ESIM semantics) from a stream of log-intensity frames.
