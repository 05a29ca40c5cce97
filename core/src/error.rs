//! The error type of saver-core: every message names what was wrong.

/// Errors of the core crate.
#[derive(Debug, thiserror::Error)]
pub enum CoreError {
    /// A tensor operation failed (shape mismatch inside a network, device error).
    #[error("tensor operation failed: {0}")]
    Candle(#[from] candle_core::Error),
    /// A configuration value is out of its valid range.
    #[error("invalid configuration: {0}")]
    Config(String),
    /// Data handed to the core does not match the environment's layout.
    #[error("bad data: {0}")]
    Data(String),
    /// Data over a size cap.
    #[error("too large: {0}")]
    TooLarge(String),
    /// A checkpoint or weights file is unreadable or does not match.
    #[error("checkpoint: {0}")]
    Checkpoint(String),
    /// Training produced a non-finite or exploding loss.
    #[error("diverged: {0}")]
    Diverged(String),
    /// One update met a non-finite loss or gradient (a batch with extreme values): it
    /// was skipped and changed nothing; training goes on.
    #[error("non-finite update skipped: {0}")]
    NonFinite(String),
    /// The wire codec failed.
    #[error(transparent)]
    Codec(#[from] saver_proto::CodecError),
}

/// Result with [`CoreError`].
pub type Result<T> = std::result::Result<T, CoreError>;
