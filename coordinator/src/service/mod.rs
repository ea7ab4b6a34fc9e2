//! `coordinator serve`: the farm kept running (to be written).

use crate::CoordinatorError;
use crate::cli::ServeArgs;

/// Runs the service until SIGTERM or Ctrl-C.
pub fn run(_args: ServeArgs) -> Result<(), CoordinatorError> {
    Err(CoordinatorError::Expression("not yet".into()))
}
