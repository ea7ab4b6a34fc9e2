//! The service's persistent store (to be written).
