//! Images, below the farm and its users: the frame a farm collects tile by
//! tile ([`canvas`]) and the PNG and EXR files it becomes ([`output`]).

pub mod canvas;
pub mod output;
