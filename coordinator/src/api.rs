//! The HTTP/JSON API of `coordinator serve` (to be written).
