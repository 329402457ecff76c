//! (image rendering, written next)
