//! What verification refuses, said once: the caller tells a client's mistake (an image or camera
//! that cannot be verified) from a stored record that does not decode and from workers that
//! failed, instead of reading a sentence.
use thiserror::Error;

#[derive(Clone, Debug, Error, PartialEq, Eq)]
pub enum VerifyError {
    /// What was sent cannot be verified: an image that does not decode, an empty or oversized
    /// one, a camera or parameters out of range, more features than the limit.
    #[error("{0}")]
    Invalid(String),
    /// A feature record (stored, or handed in) that breaks its format or invariants.
    #[error("{0}")]
    Corrupt(String),
    /// OpenCV or a verification worker failed, or the workers stopped.
    #[error("{0}")]
    Failed(String),
}

impl VerifyError {
    /// The same kind of error with `context` before its message ("query features: ...").
    pub fn context(self, context: &str) -> Self {
        match self {
            Self::Invalid(m) => Self::Invalid(format!("{context}{m}")),
            Self::Corrupt(m) => Self::Corrupt(format!("{context}{m}")),
            Self::Failed(m) => Self::Failed(format!("{context}{m}")),
        }
    }
}
