//! The clients of `coordinator serve`: submit, status, cancel, wait.

use crate::cli::{JobArgs, StatusArgs, SubmitArgs};
use crate::jobs::JobView;

/// Why a client call failed.
#[derive(Debug, thiserror::Error)]
pub enum ClientError {
    /// Anything, for now.
    #[error("{0}")]
    Other(String),
}

/// `coordinator submit`: queues the job, returns its id.
pub fn submit(_args: &SubmitArgs) -> Result<u64, ClientError> {
    Err(ClientError::Other("not yet".into()))
}

/// `coordinator status`: the table to print.
pub fn status(_args: &StatusArgs) -> Result<String, ClientError> {
    Err(ClientError::Other("not yet".into()))
}

/// `coordinator cancel`: the job as cancelled.
pub fn cancel(_args: &JobArgs) -> Result<JobView, ClientError> {
    Err(ClientError::Other("not yet".into()))
}

/// `coordinator wait`: the job once it has ended.
pub fn wait(_args: &JobArgs) -> Result<JobView, ClientError> {
    Err(ClientError::Other("not yet".into()))
}
