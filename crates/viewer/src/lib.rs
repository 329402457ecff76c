//! What makes StegoNGP's scenes visible: camera paths, video and the local web viewer.
//! It renders through the backend's renderers and opens scenes as the stego layer does;
//! the engine knows nothing of it.

pub mod frame;
pub mod gate;
pub mod path;
pub mod server;
pub mod video;
